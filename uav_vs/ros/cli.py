"""Command-line tools that take arguments of their own beside `--ros-args ...`."""


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """Split the tool's own arguments from the `--ros-args ... [--]` section.

    rclpy must not see the own arguments: it would take `--remap old:=new` items for
    (deprecated) ROS remapping rules.
    """
    if '--ros-args' not in argv:
        return argv, []
    i = argv.index('--ros-args')
    end = argv.index('--', i) if '--' in argv[i:] else len(argv)
    return argv[:i] + argv[end + 1:], argv[i:end]

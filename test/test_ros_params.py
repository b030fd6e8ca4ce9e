"""Parameters: typed, ranged, documented, and one clear line when wrong."""
import pytest
import rclpy
from rclpy.node import Node

from uav_vs.ros.params import Param, ParameterError, T, declare
from uav_vs.ros.params_file import check_params_file, params_files


@pytest.fixture
def make_node():
    made = []

    def make(*overrides: str) -> Node:
        ctx = rclpy.Context()
        args = ['--ros-args'] + [a for o in overrides for a in ('-p', o)]
        rclpy.init(args=args, context=ctx)
        node = Node('params_test', context=ctx)
        made.append((node, ctx))
        return node

    yield make
    for node, ctx in made:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


SPECS = [Param('gain', T.DOUBLE, 1.0, 'a gain', 0.0, 10.0),
         Param('K', T.DOUBLE_ARRAY, description='intrinsics', size=9),
         Param('mode', T.STRING, 'lsq', 'method', choices=('lsq', 'opencv')),
         Param('count', T.INTEGER, 3, 'how many', 1, 5)]


def test_defaults_and_int_written_for_double(make_node):
    node = make_node('K:=[500, 0, 320, 0, 500, 240, 0, 0, 1]')
    values = declare(node, SPECS)
    assert values == {'gain': 1.0, 'K': [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0],
                      'mode': 'lsq', 'count': 3}
    assert node.get_parameter('K').type_ == T.DOUBLE_ARRAY
    desc = node.describe_parameter('gain')
    assert desc.description == 'a gain'
    assert desc.floating_point_range[0].to_value == 10.0


GOOD_K = 'K:=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]'


@pytest.mark.parametrize('overrides, message', [
    ([], 'K: missing, expected 9 numbers'),
    (['K:=[1.0, 2.0]'], 'K: expected 9 numbers, got [1.0, 2.0]'),
    (["K:=['a', 'b', 'c', 'd', 'e', 'f', 'g', 'h', 'i']"], 'K: expected 9 numbers'),
    ([GOOD_K, 'gain:=11.0'], 'gain: expected a number in [0, 10], got 11.0'),
    ([GOOD_K, 'gain:=fast'], "gain: expected a number in [0, 10], got 'fast'"),
    ([GOOD_K, 'mode:=svd'], 'mode: expected a string (one of lsq, opencv)'),
    ([GOOD_K, 'count:=2.5'], 'count: expected an integer in [1, 5], got 2.5'),
])
def test_errors_name_the_parameter_in_one_line(make_node, overrides, message):
    with pytest.raises(ParameterError) as err:
        declare(make_node(*overrides), SPECS)
    assert str(err.value).startswith(message)
    assert '\n' not in str(err.value)


@pytest.mark.parametrize('items', [
    '[598, 0.0, 1.0]', '[598.0, abc]', '[1, "2"]', '[y, true, off]', '[y, 1]', '[1e3, 2.0]',
    '[0x10, 017, 3]', '[08, 1.5]', '[.inf, -.INF, nan, 1.0]', '[99999999999999999999, 1.5]',
    '[1e400, abc]', '[1e400, 1.0]', '[0x1p3, 2.5]', "['1', '2.0']", '[1_000, 1]',
])
def test_params_file_check_agrees_with_rcl(tmp_path, items):
    """check_params_file refuses exactly the lists that rcl itself refuses."""
    path = tmp_path / 'params.yaml'
    path.write_text(f'/**:\n  ros__parameters:\n    group:\n      values: {items}\n')
    ctx = rclpy.Context()
    try:
        rclpy.init(args=['--ros-args', '--params-file', str(path)], context=ctx)
    except RuntimeError:
        rcl_accepts = False
    else:
        rcl_accepts = True
        rclpy.shutdown(context=ctx)
    problem = check_params_file(str(path))
    assert (problem is None) == rcl_accepts, problem
    if problem is not None:
        assert problem.startswith('group.values: list mixes ') and '\n' not in problem


def test_params_files_are_read_from_the_ros_args_sections_only():
    args = ['node', '--params-file', 'not_ros.yaml', '--ros-args', '-r', '__ns:=/a',
            '--params-file', 'a.yaml', '--', '--params-file', 'app.yaml',
            '--ros-args', '--params-file', 'b.yaml']
    assert params_files(args) == ['a.yaml', 'b.yaml']

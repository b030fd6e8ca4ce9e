"""ground_station: the whole ground station (chapter section 3) as one process.

The trinocular_pose_node and one camshift_node per camera of `cameras.names`, each
the same node with the same names, namespaces, parameters and topics as when it runs
as a process of its own (`/cam1/camshift_node`, ..., `/trinocular_pose_node`), all
spun by one executor, as a component container would hold them. Every `--ros-args`
argument applies to every node, as `ros2 launch` gives the separate processes the
same arguments; a station namespace (`-r __ns:=/uav1`) puts the cameras below it
(`/uav1/cam1/camshift_node`).

Each camera node hands its landmarks to the pose node by a call, on the executor's
thread, as soon as it has published them on `camK/landmarks` for anyone else: rclpy
has no intra-process transport, and a message through DDS costs a publish, a wake-up
and a take. With `--landmark-topics` the pose node subscribes to the cameras' topics
instead, as in separate processes (then remapping them works as there). One process
wakes once per image instead of a process per node woken together: the shorter path
from image to `ground/pose` (docs/latency.md).

    ground_station [--landmark-topics] --ros-args --params-file config/ground_trinocular.yaml
"""
import sys
from typing import Callable

from geometry_msgs.msg import PolygonStamped
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.publisher import Publisher
from rclpy.utilities import remove_ros_args

from uav_vs.nodes.camshift_node import CamshiftNode
from uav_vs.nodes.trinocular_pose_node import TrinocularPoseNode
from uav_vs.ros.node_main import run


class HandOff:
    """A camera node's landmarks publisher that also hands each message to the pose node."""

    def __init__(self, publisher: Publisher, deliver: Callable[[PolygonStamped], None]) -> None:
        self._publisher, self._deliver = publisher, deliver

    def publish(self, msg: PolygonStamped) -> None:
        self._publisher.publish(msg)
        self._deliver(msg)


def ground_station(landmark_topics: bool = False) -> list[Node]:
    """The trinocular_pose_node, then a camshift_node per camera in its namespace."""
    pose = TrinocularPoseNode(subscribe=landmark_topics)
    base = pose.get_namespace().rstrip('/')
    nodes: list[Node] = [pose]
    for k, cam in enumerate(pose.cfg.cameras):
        node = CamshiftNode(cli_args=['--ros-args', '-r', f'__ns:={base}/{cam.name}'],
                            parameter_overrides=[Parameter('camera', value=cam.name)])
        if not landmark_topics:
            node.pub = HandOff(node.pub, lambda msg, k=k: pose.on_landmarks(k, msg))
        nodes.append(node)
    return nodes


def main(args: list[str] | None = None) -> None:
    own = remove_ros_args(sys.argv)[1:] if args is None else remove_ros_args(args)
    unknown = [a for a in own if a != '--landmark-topics']
    if unknown:
        sys.exit(f'ground_station: unknown argument(s) {" ".join(unknown)} '
                 '(usage: ground_station [--landmark-topics] --ros-args ...)')
    run(lambda: ground_station('--landmark-topics' in own), 'ground_station', args)


if __name__ == '__main__':
    main()

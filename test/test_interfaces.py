"""The interface packages that `make install` builds from their Jazzy definitions."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

from rosbags.typesys import Stores, get_typestore

from conftest import ROS2, wait_for

PREFIX = Path(sys.prefix)
JAZZY = get_typestore(Stores.ROS2_JAZZY)

# Publishes two known transforms on /tf until stopped (run as a separate process).
TF_PUBLISHER = textwrap.dedent('''
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    rclpy.init()
    node = rclpy.create_node('tf_publisher')
    pub = node.create_publisher(TFMessage, 'tf', 10)
    msg = TFMessage()
    for k, child in enumerate(['base_link', 'camera']):
        t = TransformStamped()
        t.header.stamp.sec = 40 + k
        t.header.frame_id = 'map'
        t.child_frame_id = child
        t.transform.translation.x = 1.5 + k
        t.transform.rotation.z = 0.6
        t.transform.rotation.w = 0.8
        msg.transforms.append(t)
    node.create_timer(0.1, lambda: pub.publish(msg))
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
''')


def transform(parent: str, child: str, sec: int, x: float, z: float):
    from geometry_msgs.msg import TransformStamped

    t = TransformStamped()
    t.header.stamp.sec = sec
    t.header.frame_id = parent
    t.child_frame_id = child
    t.transform.translation.x = x
    t.transform.translation.z = z
    t.transform.rotation.x = 0.5
    t.transform.rotation.w = 0.5
    return t


def test_tf_message_serializes_to_the_cdr_of_jazzy():
    """rclpy's CDR of a TFMessage is what an independent Jazzy decoder reads."""
    from rclpy.serialization import deserialize_message, serialize_message
    from tf2_msgs.msg import TFMessage

    msg = TFMessage(transforms=[transform('map', 'base_link', 7, 1.25, -3.0),
                                transform('base_link', 'camera', 8, 0.0, 0.1)])
    cdr = serialize_message(msg)
    assert deserialize_message(cdr, TFMessage) == msg
    decoded = JAZZY.deserialize_cdr(cdr, 'tf2_msgs/msg/TFMessage')
    assert [(t.header.frame_id, t.child_frame_id, t.header.stamp.sec,
             t.transform.translation.x, t.transform.translation.z, t.transform.rotation.x)
            for t in decoded.transforms] == [('map', 'base_link', 7, 1.25, -3.0, 0.5),
                                             ('base_link', 'camera', 8, 0.0, 0.1, 0.5)]


def test_tf_message_from_another_process_is_received(ros_node):
    """A /tf publisher in its own process reaches this one, under Jazzy's type hash."""
    from tf2_msgs.msg import TFMessage

    received = []
    ros_node.create_subscription(TFMessage, 'tf', received.append, 10)
    publisher = subprocess.Popen([sys.executable, '-c', TF_PUBLISHER], env=os.environ.copy())
    try:
        assert wait_for(lambda: received, timeout=30), 'no TFMessage received on /tf'
        [info] = ros_node.get_publishers_info_by_topic('/tf')
    finally:
        publisher.terminate()
        publisher.wait(timeout=10)
    assert str(info.topic_type_hash) == JAZZY.hash_rihs01('tf2_msgs/msg/TFMessage')
    transforms = received[0].transforms
    assert [(t.header.frame_id, t.child_frame_id, t.header.stamp.sec) for t in transforms] \
        == [('map', 'base_link', 40), ('map', 'camera', 41)]
    assert [t.transform.translation.x for t in transforms] == [1.5, 2.5]
    assert all((t.transform.rotation.z, t.transform.rotation.w) == (0.6, 0.8)
               for t in transforms)


def test_type_descriptions_installed_carry_jazzy_hashes():
    """The type description files in share/ (what `ros2 interface` reads) hash as Jazzy's."""
    import json

    for name in ('TFMessage', 'TF2Error'):
        description = json.loads((PREFIX / 'share/tf2_msgs/msg' / f'{name}.json').read_text())
        hashes = {h['type_name']: h['hash_string'] for h in description['type_hashes']}
        assert hashes[f'tf2_msgs/msg/{name}'] == JAZZY.hash_rihs01(f'tf2_msgs/msg/{name}')


def test_load_node_service_answers(ros_node):
    """composition_interfaces (which launch_ros imports) carries a LoadNode call both ways."""
    from composition_interfaces.srv import LoadNode
    from rcl_interfaces.msg import Parameter

    def load(request, response):
        response.success = True
        response.full_node_name = f'/{request.node_namespace}/{request.node_name}'
        response.unique_id = len(request.parameters) + 40
        return response

    ros_node.create_service(LoadNode, 'load_node', load)
    client = ros_node.create_client(LoadNode, 'load_node')
    assert client.wait_for_service(timeout_sec=10)
    request = LoadNode.Request(package_name='uav_vs', node_name='tracker', node_namespace='uav',
                               parameters=[Parameter(name='a'), Parameter(name='b')])
    future = client.call_async(request)
    assert wait_for(future.done, timeout=10)
    response = future.result()
    assert (response.success, response.full_node_name, response.unique_id) == \
        (True, '/uav/tracker', 42)


def test_ros2_interface_show_prints_tf_message(ros2_env):
    """With the ROS 2 command line wheels, `ros2 interface show` finds the built package."""
    shown = subprocess.run([*ROS2, 'interface', 'show', 'tf2_msgs/msg/TFMessage'],
                           env=ros2_env, capture_output=True, text=True,
                           stdin=subprocess.DEVNULL, timeout=60)
    assert shown.returncode == 0, shown.stderr
    lines = shown.stdout.splitlines()
    assert lines[0] == 'geometry_msgs/TransformStamped[] transforms'
    assert '\tstring child_frame_id' in lines

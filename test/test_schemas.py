"""uav_vs.bag.schemas: the ros2msg schemas built from the installed definitions describe
the types exactly as rosbags' own ROS 2 Jazzy type store does (an independent parse of
the same definitions), each used type given once; a service's halves likewise."""
import re

import pytest
from rosbags.typesys import Stores, get_typestore

from ros2msg import schema_types
from uav_vs.bag.schemas import SchemaError, message_schema, service_schemas

JAZZY = get_typestore(Stores.ROS2_JAZZY)


def parsed(name: str, schema: str) -> dict:
    """Every type a schema defines, each used type given once."""
    headers = re.findall(r'^MSG: .*$', schema, re.M)
    assert len(headers) == len(set(headers)), headers
    return schema_types(name, schema)


@pytest.mark.parametrize('msgtype', ['geometry_msgs/msg/PoseStamped', 'sensor_msgs/msg/Image',
                                     'sensor_msgs/msg/CameraInfo', 'nav_msgs/msg/Odometry',
                                     'tf2_msgs/msg/TFMessage',
                                     'diagnostic_msgs/msg/DiagnosticArray',
                                     'geometry_msgs/msg/PolygonStamped'])
def test_a_message_schema_describes_the_type_and_every_type_it_uses(msgtype):
    types = parsed(msgtype, message_schema(msgtype))
    assert msgtype in types
    for name, fields in types.items():
        assert fields == JAZZY.fielddefs[name], name


def test_a_service_schema_is_its_request_and_its_response():
    request, response = service_schemas('std_srvs/srv/SetBool')
    assert parsed('std_srvs/srv/SetBool_Request', request) == {
        'std_srvs/msg/SetBool_Request': ([], [('data', JAZZY.fielddefs[
            'std_msgs/msg/Bool'][1][0][1])])}
    [(_, fields)] = parsed('std_srvs/srv/SetBool_Response', response).values()
    assert [name for name, _ in fields] == ['success', 'message']
    request, response = service_schemas('std_srvs/srv/Trigger')       # an empty request
    assert request == '' and 'bool success' in response


def test_an_unknown_type_is_named():
    with pytest.raises(SchemaError, match='no_such_msgs/msg/Nothing'):
        message_schema('no_such_msgs/msg/Nothing')

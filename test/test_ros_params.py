"""Parameters: typed, ranged, documented, and one clear line when wrong."""
import pytest
import rclpy
from rclpy.node import Node

from uav_vs.ros.params import Param, ParameterError, T, declare


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

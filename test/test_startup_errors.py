"""A bad start-up configuration stops a node with one FATAL line and exit status 2.

Bad params files, malformed `-p` rules and `-p` values of another type than the
params file's (which rcl would silently drop) are all named in that one line; never
a traceback, never a value silently ignored.
"""
import subprocess

import pytest
import rclpy
from rclpy.node import Node

from conftest import REPO
from uav_vs.graph import executable
from uav_vs.nodes.camshift_node import CamshiftNode
from uav_vs.nodes.fuzzy_controller_node import FuzzyControllerNode
from uav_vs.ros import node_main
from uav_vs.ros.params_file import check_args

GROUND = REPO / 'config' / 'ground_trinocular.yaml'
FUZZY = REPO / 'config' / 'fuzzy_controller.yaml'
CAMSHIFT = (CamshiftNode, GROUND, ['-p', 'camera:=cam1'])
CONTROLLER = (FuzzyControllerNode, FUZZY, [])

FILES = {
    'list': '- a\n- b\n',
    'scalar': '42\n',
    'no_ros_parameters': 'camshift_node:\n  camera: cam1\n',
    'node_holds_a_list': '/**:\n  - a\n',
    'node_holds_nothing': '/**:\n',
    'ros_parameters_empty': '/**:\n  ros__parameters:\n',
    'ros_parameters_list': '/**:\n  ros__parameters:\n    - a\n',
    'ros_parameters_beside_a_value': '/**:\n  ros__parameters:\n    a: 1\n  b: 2\n',
    'alias': '/**:\n  ros__parameters:\n    a: &x 1\n    b: *x\n',
    'empty_mapping': '/**:\n  ros__parameters:\n    camshift: {}\n',
    'nested_list': '/**:\n  ros__parameters:\n    landmarks:\n      radius: [[0.1]]\n',
}


class Started(Exception):
    """The node was built: the configuration was accepted."""


def start(capfd, node_type, config, args):
    """node_main.run in this process; (exit status, output). Raises Started if it starts."""
    def factory() -> Node:
        node = node_type()
        node.destroy_node()
        raise Started

    argv = ['--ros-args', '--params-file', str(config), *args]
    try:
        with pytest.raises(SystemExit) as stop:
            node_main.run(factory, 'startup_test', argv)
    finally:
        rclpy.try_shutdown()
    out, err = capfd.readouterr()
    return stop.value.code, out + err


def assert_one_fatal(status, output, expected):
    fatal = [line for line in output.splitlines() if 'FATAL' in line]
    assert status == 2, output
    assert len(fatal) == 1 and expected in fatal[0], output
    assert 'Traceback' not in output


@pytest.mark.parametrize('case', sorted(FILES))
def test_bad_params_file_stops_with_one_line_naming_it(tmp_path, capfd, case):
    bad = tmp_path / f'{case}.yaml'
    bad.write_text(FILES[case])
    node_type, config, args = CAMSHIFT
    status, output = start(capfd, node_type, config, [*args, '--params-file', str(bad)])
    expected = {'empty_mapping': 'camshift: empty mapping',
                'nested_list': 'landmarks.radius: expected a list of values'}.get(case,
                                                                               f'{case}.yaml')
    assert_one_fatal(status, output, expected)


@pytest.mark.parametrize('rule', [
    'foo', ':=1', 'a.:=1', 'a b:=1', '/camshift_node:a:=1', 'a:=', 'a:=  ',
    'a:=[1, x', 'a:={', 'a:=[', 'a:=]', 'a:="x', 'a:=*x', 'a:={b: 1}',
    'a:=[1, 2.0]', 'a:=[[1]]', 'a:=[1, [2]]', 'a:=|',
])
def test_malformed_rule_stops_with_one_line_naming_it(capfd, rule):
    node_type, config, args = CAMSHIFT
    status, output = start(capfd, node_type, config, [*args, '-p', rule])
    assert_one_fatal(status, output, f'-p {rule}')


# (node, -p rule, the line names: parameter, expected type as the params file gives it)
CLASHES = [
    (CAMSHIFT, 'camshift.debug_image:=1', 'camshift.debug_image: expected a bool', 'false'),
    (CAMSHIFT, 'camshift.max_iterations:=fast', 'camshift.max_iterations: expected an integer',
     '10'),
    (CAMSHIFT, 'cameras.cam1.width:=640.0', 'cameras.cam1.width: expected an integer', '640'),
    (CAMSHIFT, 'landmarks.red.position:=[]',
     'landmarks.red.position: expected a list of doubles', '[0.3, 0.0, 0.0]'),
    (CONTROLLER, 'controller.max_horizontal_speed:=fast',
     'controller.max_horizontal_speed: expected a double', '1.0'),
    (CONTROLLER, 'controller.enabled:=1', 'controller.enabled: expected a bool', 'false'),
    (CONTROLLER, 'controller.rate:=[1.0]', 'controller.rate: expected a double', '20.0'),
    (CONTROLLER, 'fuzzy.axes.x.rate_filter:=fast', 'fuzzy.axes.x.rate_filter: expected a double',
     '0.05'),
]


@pytest.mark.parametrize('node, rule, expected, kept', CLASHES,
                         ids=[rule for _, rule, _, _ in CLASHES])
def test_rule_of_another_type_than_the_params_file_stops_with_one_line(capfd, node, rule,
                                                                       expected, kept):
    """rcl would keep the params file's value and drop the rule's without a word."""
    node_type, config, args = node
    status, output = start(capfd, node_type, config, [*args, '-p', rule])
    assert_one_fatal(status, output, expected)
    given = rule.split(':=', 1)[1]
    assert f'({given}) from -p {rule}' in output and f'({kept})' in output


@pytest.mark.parametrize('rule', ['controller.rate:=30', 'controller.rate:=30.0',
                                  'controller.enabled:=true', 'fuzzy.axes.x.rate_filter:=0.1'])
def test_rule_rcl_takes_as_given_still_starts_the_node(capfd, rule):
    node_type, config, args = CONTROLLER
    with pytest.raises(Started):
        start(capfd, node_type, config, [*args, '-p', rule])


TYPED = {'bool': 'true', 'integer': '7', 'double': '2.5', 'string': 'fast',
         'bool list': '[true]', 'integer list': '[7]', 'double list': '[2.5]',
         'string list': '[fast]', 'empty list': '[]'}


@pytest.mark.parametrize('first', sorted(TYPED))
def test_dropped_rule_agrees_with_rcl(tmp_path, first):
    """check_args refuses `-p a:=<second>` after a params file's `a: <first>` exactly
    when rclpy's value for `a` is not the rule's."""
    path = tmp_path / 'params.yaml'
    path.write_text(f'/**:\n  ros__parameters:\n    a: {TYPED[first]}\n')
    for second, text in TYPED.items():
        args = ['--ros-args', '--params-file', str(path), '-p', f'a:={text}']
        ctx = rclpy.Context()
        rclpy.init(args=args, context=ctx)
        node = Node('clash_test', context=ctx)
        value = node._parameter_overrides['a'].value     # None when rcl holds no value
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        taken = value if value is None or isinstance(value, (bool, int, float, str)) else list(value)
        given = {'true': True, '7': 7, '2.5': 2.5, 'fast': 'fast', '[true]': [True],
                 '[7]': [7], '[2.5]': [2.5], '[fast]': ['fast'], '[]': None}[text]
        problem = check_args(args)
        assert (problem is None) == (taken == given), (first, second, taken, problem)


@pytest.mark.parametrize('rule', ['x:a:=1', 'a/b:=1', 'a:=1:=2', 'a:=- 1', 'a:=1 #c', 'a:=~',
                                  'a:=[]'])
def test_rules_rcl_accepts_pass_the_check(rule):
    args = ['--ros-args', '-p', rule]
    ctx = rclpy.Context()
    rclpy.init(args=args, context=ctx)
    rclpy.shutdown(context=ctx)
    assert check_args(args) is None


@pytest.mark.parametrize('text', [
    '', '# only a comment\n', '/**:\n  ros__parameters: {}\n',
    'ns:\n  camshift_node:\n    ros__parameters:\n      a: 1\n',
    '/**:\n  ros__parameters:\n    geofence:\n      min: []\n',
    '/**:\n  ros__parameters:\n    a: ~\n    b: "1"\n    c: [x, "y"]\n',
])
def test_params_files_rcl_reads_as_written_pass_the_check(tmp_path, text):
    path = tmp_path / 'params.yaml'
    path.write_text(text)
    args = ['--ros-args', '--params-file', str(path)]
    ctx = rclpy.Context()
    rclpy.init(args=args, context=ctx)
    rclpy.shutdown(context=ctx)
    assert check_args(args) is None


@pytest.mark.parametrize('args, expected', [
    (['-p', 'foo'], '-p foo: Expected lexeme type (22) not found, search ended at index 3'),
    (['-p', 'a:=[1, x'],
     "-p a:=[1, x: Sequence should be of same type. Value type 'string' do not belong at line_num 1"),
])
def test_rcl_refusal_left_to_rcl_is_one_line_naming_the_argument(args, expected):
    """Whatever rcl refuses past the checks still gives one line, from rcl's message."""
    with pytest.raises(RuntimeError) as err:
        rclpy.init(args=['--ros-args', *args], context=rclpy.Context())
    assert node_main._rcl_refusal(str(err.value)) == expected


@pytest.mark.parametrize('args, expected', [
    (['--params-file', 'FILE'], 'list.yaml: expected a mapping of node names'),
    (['-p', 'a:={'], '-p a:={'),
    (['-p', 'controller.enabled:=1'], 'controller.enabled: expected a bool'),
])
def test_node_process_stops_with_one_fatal_line(tmp_path, args, expected):
    bad = tmp_path / 'list.yaml'
    bad.write_text(FILES['list'])
    cmd = [executable('fuzzy_controller_node'), '--ros-args', '--params-file', str(FUZZY),
           *[str(bad) if a == 'FILE' else a for a in args]]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail('the node started')
    output = run.stdout + run.stderr
    assert_one_fatal(run.returncode, output, expected)
    assert len(output.strip().splitlines()) == 1, output

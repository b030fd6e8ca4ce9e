"""Pre-check of the `--params-file` and `-p` arguments, before rcl parses them.

rcl refuses, with its own traceback from rclpy.init, a params file that is missing, is
not YAML, is not a mapping of node names to `ros__parameters`, or has a list whose items
are not all of one type (`[598, 0.0]` is an integer then a double), and a `-p` rule
that is not `[node:]name:=value`. It silently misreads others: a scalar file, an empty
mapping, a nested list, or a `-p` value whose type differs from the params file's (one
of the two is dropped). `check_args` finds those cases first and returns one line naming
the file, the rule or the parameter, so a node can stop with a FATAL line and exit 2.
Scalars are typed as rcl's parser types them (rcl_yaml_param_parser get_value).
"""
import math
import re
from pathlib import Path
from typing import Sequence

import yaml

_TRUE_FALSE = {'Y', 'y', 'yes', 'Yes', 'YES', 'true', 'True', 'TRUE', 'on', 'On', 'ON',
               'N', 'n', 'no', 'No', 'NO', 'false', 'False', 'FALSE', 'off', 'Off', 'OFF'}
_YAML_INF_NAN = {'.nan', '.NaN', '.NAN', '.inf', '.Inf', '.INF', '+.inf', '+.Inf', '+.INF',
                 '-.inf', '-.Inf', '-.INF'}
_C_INT = re.compile(r'[+-]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)')   # strtol, base 0
_C_DECIMAL = re.compile(r'[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?')          # strtod
_C_HEX_FLOAT = re.compile(r'[+-]?0[xX]([0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)([pP][+-]?\d+)?')
_C_INF_NAN = re.compile(r'[+-]?(inf(inity)?|nan)', re.IGNORECASE)
_RULE = re.compile(r'(?:([A-Za-z_]\w*):)?([A-Za-z_]\w*(?:[./][A-Za-z_]\w*)*):=(.*)',
                   re.ASCII | re.DOTALL)                        # [node:]name:=value
# The value rclpy takes when a parameter's rcl entry holds several types: the first here.
_RCLPY_ORDER = ('bool', 'integer', 'double', 'string',
                'bool list', 'integer list', 'double list', 'string list', 'empty list')
_ARTICLE = {'bool': 'a bool', 'integer': 'an integer', 'double': 'a double', 'string': 'a string',
            'bool list': 'a list of bools', 'integer list': 'a list of integers',
            'double list': 'a list of doubles', 'string list': 'a list of strings',
            'empty list': 'an empty list'}


def ros_args(args: Sequence[str], flags: Sequence[str]) -> list[tuple[str, str]]:
    """(flag, value) of every `flags` option inside the `--ros-args` sections of `args`."""
    found, in_ros, items = [], False, iter(args)
    for arg in items:
        if arg == '--ros-args':
            in_ros = True
        elif arg == '--':
            in_ros = False
        elif in_ros and arg in flags:
            found.append((arg, next(items, '')))
    return found


def params_files(args: Sequence[str]) -> list[str]:
    """The files given with `--params-file` inside the `--ros-args` sections of `args`."""
    return [path for _, path in ros_args(args, ('--params-file',))]


def check_args(args: Sequence[str]) -> str | None:
    """One line describing the first params file, `-p` rule or clash of both rcl would
    refuse or silently misread, or None."""
    return check_params_files(args) or check_param_rules(args) or check_override_types(args)


def check_params_files(args: Sequence[str]) -> str | None:
    """One line describing the first unusable params file in `args`, or None."""
    for path in params_files(args):
        problem = check_params_file(path)
        if problem is not None:
            return problem
    return None


def check_param_rules(args: Sequence[str]) -> str | None:
    """One line describing the first `-p [node:]name:=value` rule rcl would refuse, or None."""
    for flag, rule in ros_args(args, ('-p', '--param')):
        try:
            _parse_rule(flag, rule)
        except _Refused as err:
            return str(err)
    return None


def check_override_types(args: Sequence[str]) -> str | None:
    """One line naming a parameter whose last value given would be dropped, or None.

    rcl merges the params files and `-p` rules into one entry per node section and
    parameter, in order; a later value of the same type replaces the earlier, but one of
    another type is stored beside it, and rclpy takes the first type in _RCLPY_ORDER
    (an empty list stores nothing).
    """
    given: dict[tuple[str, str], list[tuple[str, str, str]]] = {}
    for flag, value in ros_args(args, ('--params-file', '-p', '--param')):
        if flag == '--params-file':
            items = _file_values(value)
        else:
            section, name, node = _parse_rule(flag, value)
            items = [(section, name, node, f'{flag} {value}')]
        for section, name, node, origin in items:
            section = section if section.startswith('/') else '/' + section
            given.setdefault((section, name), []).append((_value_type(node), _text(node), origin))
    for (_, name), values in given.items():
        kept_type = min((kind for kind, _, _ in values), key=_RCLPY_ORDER.index)
        kind, text, origin = values[-1]
        if kind != kept_type:
            _, kept, kept_origin = [v for v in values if v[0] == kept_type][-1]
            return (f'{name}: expected {_ARTICLE[kept_type]} as in '
                    f'{kept_origin} ({kept}), got {_ARTICLE[kind]} ({text}) '
                    f'from {origin}; rcl would keep {kept} and drop {text}')
    return None


def _parse_rule(flag: str, rule: str) -> tuple[str, str, yaml.Node]:
    """(node section, name, value node) of a `-p` rule; raises _Refused."""
    match = _RULE.fullmatch(rule)
    if match is None:
        raise _Refused(f'{flag} {rule}: expected [node:]name:=value, e.g. {flag} camera:=cam1')
    node_name, name, text = match.groups()
    try:
        value = yaml.compose(text)
        alias = any(isinstance(e, yaml.AliasEvent) for e in yaml.parse(text))
    except yaml.YAMLError as err:
        raise _Refused(f'{flag} {rule}: the value is not valid YAML '
                       f'({getattr(err, "problem", None) or err})') from None
    if value is None:
        raise _Refused(f'{name}: no value ({flag} {rule})')
    if alias:
        raise _Refused(f'{flag} {rule}: rcl does not support YAML aliases')
    _check_value(name, value, f'{flag} {rule}')
    return ('/' + node_name if node_name else '/**'), name, value


def _file_values(path: str) -> list[tuple[str, str, yaml.Node, str]]:
    """(node section, name, value node, 'file line N') of every parameter in a checked file."""
    root = yaml.compose(Path(path).read_text())
    if root is None:
        return []
    return [(section, name, node, f'{path} line {node.start_mark.line + 1}')
            for section, name, node in _parameters(root, path, '')]


def _value_type(node: yaml.Node) -> str:
    if isinstance(node, yaml.SequenceNode):
        return _rcl_type(node.value[0]) + ' list' if node.value else 'empty list'
    return _rcl_type(node)


def _text(node: yaml.Node) -> str:
    if isinstance(node, yaml.SequenceNode):
        return '[' + ', '.join(item.value for item in node.value) + ']'
    return node.value


def check_params_file(path: str) -> str | None:
    """One line saying why rcl would refuse (or silently misread) the params file at `path`."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as err:
        return f'--params-file {path}: cannot read it ({getattr(err, "strerror", None) or err})'
    try:
        root = yaml.compose(text)
        alias = next((e for e in yaml.parse(text) if isinstance(e, yaml.AliasEvent)), None)
    except yaml.YAMLError as err:
        mark = getattr(err, 'problem_mark', None)
        where = '' if mark is None else f' at line {mark.line + 1}, column {mark.column + 1}'
        return (f'--params-file {path}: not valid YAML '
                f'({getattr(err, "problem", None) or err}{where})')
    if alias is not None:
        return (f'--params-file {path} line {alias.start_mark.line + 1}: '
                f'rcl does not support YAML aliases (*{alias.anchor})')
    if root is None:
        return None
    if not isinstance(root, yaml.MappingNode):
        return (f'--params-file {path}: expected a mapping of node names to ros__parameters '
                f'(e.g. "/**:" then "  ros__parameters:"), got {_kind(root)}')
    try:
        _parameters(root, path, '')
    except _Refused as err:
        return str(err)
    return None


class _Refused(ValueError):
    """A params file or -p value that rcl refuses or would misread; str() is one line."""


def _kind(node: yaml.Node) -> str:
    return {yaml.MappingNode: 'a mapping', yaml.SequenceNode: 'a list'}.get(
        type(node), f'the value {node.value!r}')


def _parameters(node: yaml.MappingNode, path: str,
                section: str) -> list[tuple[str, str, yaml.Node]]:
    """(node section, parameter name, value node) of every parameter in the file's tree.

    Above `ros__parameters` every key is a node name (or namespace) holding a mapping.
    """
    found = []
    for key, value in node.value:
        line = key.start_mark.line + 1
        if key.value == 'ros__parameters':
            if len(node.value) > 1 or not section:
                raise _Refused(f'--params-file {path} line {line}: expected ros__parameters '
                               'alone under a node name (e.g. "/**:")')
            if not isinstance(value, yaml.MappingNode):
                raise _Refused(f'--params-file {path} line {line}: {section}: expected '
                               'ros__parameters to map parameter names to values, '
                               f'got {_kind(value)}')
            found += [(section, name, item) for name, item in _values(value, path, '')]
        elif isinstance(value, yaml.MappingNode):
            name = str(key.value)
            found += _parameters(value, path, f'{section}/{name}' if section else name)
        else:
            where = f'{section}/{key.value}' if section else str(key.value)
            raise _Refused(f'--params-file {path} line {line}: {where}: expected a node name '
                           f'holding ros__parameters, got {_kind(value)}')
    return found


def _values(node: yaml.MappingNode, path: str, prefix: str) -> list[tuple[str, yaml.Node]]:
    """(dotted name, value node) under `ros__parameters`, each value checked."""
    found = []
    for key, value in node.value:
        name = f'{prefix}.{key.value}' if prefix else str(key.value)
        if isinstance(value, yaml.MappingNode):
            if not value.value:
                raise _Refused(f'{name}: empty mapping ({path} line {key.start_mark.line + 1}); '
                               'rcl gives it no value')
            found += _values(value, path, name)
        else:
            _check_value(name, value, f'{path} line {value.start_mark.line + 1}')
            found.append((name, value))
    return found


def _check_value(name: str, node: yaml.Node, where: str) -> None:
    """Refuse a value rcl refuses or misreads: none, a mapping, an empty, nested or mixed list."""
    if isinstance(node, yaml.MappingNode):
        raise _Refused(f'{name}: expected a value or a list, got a mapping ({where})')
    if isinstance(node, yaml.ScalarNode):
        if node.value == '' and node.style not in ("'", '"'):
            raise _Refused(f'{name}: no value ({where})')
        return
    if not all(isinstance(item, yaml.ScalarNode) for item in node.value):
        raise _Refused(f'{name}: expected a list of values, got a list holding lists or '
                       f'mappings ({where})')
    seen: dict[str, str] = {}
    for item in node.value:
        seen.setdefault(_rcl_type(item), item.value)
    if len(seen) > 1:
        kinds = ' and '.join(f'{kind} ({value})' for kind, value in seen.items())
        hint = (' (write every number as a float, e.g. 598.0)'
                if seen.keys() == {'integer', 'double'} else '')
        raise _Refused(f'{name}: list mixes {kinds} ({where}); '
                       f'rcl needs one type per list{hint}')


def _rcl_type(item: yaml.ScalarNode) -> str:
    """bool, integer, double or string, as rcl types the scalar (strtol, then strtod)."""
    text = item.value
    if item.style in ("'", '"'):
        return 'string'
    if text in _TRUE_FALSE:
        return 'bool'
    if _C_INT.fullmatch(text):
        digits = text.lstrip('+-')
        base = 16 if digits[:2] in ('0x', '0X') else 8 if digits[:1] == '0' else 10
        if -2**63 <= int(text, base) < 2**63:
            return 'integer'
    if text in _YAML_INF_NAN or _C_INF_NAN.fullmatch(text):
        return 'double'
    if _C_DECIMAL.fullmatch(text):
        return 'double' if math.isfinite(float(text)) else 'string'
    if _C_HEX_FLOAT.fullmatch(text):
        return 'double' if math.isfinite(float.fromhex(text)) else 'string'
    return 'string'

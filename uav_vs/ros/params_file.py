"""Pre-check of the `--params-file` arguments, before rcl parses them.

rcl refuses a params file that is missing, is not YAML, or has a list whose items are
not all of one type (`[598, 0.0]` is an integer then a double) with its own traceback
from rclpy.init. `check_params_files` finds those cases first and returns one line
naming the file and the parameter, so a node can stop with a FATAL line and exit 2.
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


def params_files(args: Sequence[str]) -> list[str]:
    """The files given with `--params-file` inside the `--ros-args` sections of `args`."""
    files, in_ros, items = [], False, iter(args)
    for arg in items:
        if arg == '--ros-args':
            in_ros = True
        elif arg == '--':
            in_ros = False
        elif in_ros and arg == '--params-file':
            files.append(next(items, ''))
    return files


def check_params_files(args: Sequence[str]) -> str | None:
    """One line describing the first unusable params file in `args`, or None."""
    for path in params_files(args):
        problem = check_params_file(path)
        if problem is not None:
            return problem
    return None


def check_params_file(path: str) -> str | None:
    """One line saying why rcl would refuse the params file at `path`, or None."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as err:
        return f'--params-file {path}: cannot read it ({getattr(err, "strerror", None) or err})'
    try:
        root = yaml.compose(text)
    except yaml.YAMLError as err:
        mark = getattr(err, 'problem_mark', None)
        where = '' if mark is None else f' at line {mark.line + 1}, column {mark.column + 1}'
        return (f'--params-file {path}: not valid YAML '
                f'({getattr(err, "problem", None) or err}{where})')
    return None if root is None else _check_node(root, None, path)


def _check_node(node: yaml.Node, name: str | None, path: str) -> str | None:
    """Walk the tree; `name` is the dotted parameter name once under `ros__parameters`."""
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            key_text = str(key.value)
            if name is None:
                child = '' if key_text == 'ros__parameters' else None
            else:
                child = f'{name}.{key_text}' if name else key_text
            problem = _check_node(value, child, path)
            if problem is not None:
                return problem
    elif isinstance(node, yaml.SequenceNode) and name:
        seen: dict[str, str] = {}
        for item in node.value:
            if isinstance(item, yaml.ScalarNode):
                seen.setdefault(_rcl_type(item), item.value)
        if len(seen) > 1:
            kinds = ' and '.join(f'{kind} ({value})' for kind, value in seen.items())
            hint = (' (write every number as a float, e.g. 598.0)'
                    if seen.keys() == {'integer', 'double'} else '')
            return (f'{name}: list mixes {kinds} ({path} line {node.start_mark.line + 1}); '
                    f'rcl needs one type per list{hint}')
    return None


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

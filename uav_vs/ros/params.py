"""Typed, documented ROS parameters that fail at start-up with one line naming the culprit.

Every parameter goes through `declare`: its raw value (from a params file or `-p`)
is read, checked and coerced here (an integer is accepted where a double is
expected, as YAML writes `500` for `500.0`), then the parameter is declared with its
ROS type, description and range so `ros2 param describe` shows them.
"""
import array
from dataclasses import dataclass, field
from typing import Any, Sequence

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

T = Parameter.Type
REQUIRED = object()

_WHAT = {T.DOUBLE: 'a number', T.INTEGER: 'an integer', T.BOOL: 'true or false',
         T.STRING: 'a string', T.DOUBLE_ARRAY: 'a list of numbers',
         T.INTEGER_ARRAY: 'a list of integers', T.STRING_ARRAY: 'a list of strings',
         T.BOOL_ARRAY: 'a list of booleans'}


class ParameterError(ValueError):
    """A parameter is missing or malformed; str() is one line naming it."""


@dataclass(frozen=True)
class Param:
    """One parameter: name, ROS type, default (REQUIRED if none), description, limits."""

    name: str
    type: T
    default: Any = REQUIRED
    description: str = ''
    low: float | None = None
    high: float | None = None
    choices: Sequence[str] = field(default_factory=tuple)
    size: int | None = None          # exact length, for arrays

    def expected(self) -> str:
        what = _WHAT[self.type]
        if self.size is not None:
            what = f'{self.size} ' + what.removeprefix('a list of ')
        if self.low is not None or self.high is not None:
            lo = '-inf' if self.low is None else f'{self.low:g}'
            hi = 'inf' if self.high is None else f'{self.high:g}'
            what += f' in [{lo}, {hi}]'
        if self.choices:
            what += ' (one of ' + ', '.join(self.choices) + ')'
        return what


def declare(node: Node, specs: Sequence[Param]) -> dict[str, Any]:
    """Declare every spec on `node`; return {name: value}. Raises ParameterError."""
    return {spec.name: _declare_one(node, spec) for spec in specs}


def _declare_one(node: Node, spec: Param) -> Any:
    if node.has_parameter(spec.name):    # declared from the overrides already
        raw = node.get_parameter(spec.name).value
        raw = list(raw) if isinstance(raw, array.array) else raw
    else:
        raw = node.declare_parameter(spec.name, None, ParameterDescriptor(dynamic_typing=True)).value
    node.undeclare_parameter(spec.name)
    if raw is None:
        if spec.default is REQUIRED:
            raise ParameterError(f'{spec.name}: missing, expected {spec.expected()}')
        raw = spec.default
    value = _coerce(spec, raw)
    node.declare_parameter(spec.name, value, _descriptor(spec), ignore_override=True)
    return value


def _coerce(spec: Param, raw: Any) -> Any:
    def bad() -> ParameterError:
        text = repr(raw)
        return ParameterError(f'{spec.name}: expected {spec.expected()}, got '
                              f'{text if len(text) < 80 else text[:77] + "..."}')

    scalar = {T.DOUBLE: float, T.INTEGER: int, T.BOOL: bool, T.STRING: str,
              T.DOUBLE_ARRAY: float, T.INTEGER_ARRAY: int, T.BOOL_ARRAY: bool,
              T.STRING_ARRAY: str}[spec.type]
    is_array = spec.type in (T.DOUBLE_ARRAY, T.INTEGER_ARRAY, T.STRING_ARRAY, T.BOOL_ARRAY)
    items = list(raw) if is_array and isinstance(raw, (list, tuple)) else [raw]
    if is_array != isinstance(raw, (list, tuple)):
        raise bad()
    out = []
    for item in items:
        if scalar is float and isinstance(item, (int, float)) and not isinstance(item, bool):
            item = float(item)
        if type(item) is not scalar:
            raise bad()
        if scalar in (int, float) and ((spec.low is not None and item < spec.low)
                                       or (spec.high is not None and item > spec.high)
                                       or item != item):
            raise bad()
        if spec.choices and item not in spec.choices:
            raise bad()
        out.append(item)
    if spec.size is not None and len(out) != spec.size:
        raise bad()
    return out if is_array else out[0]


def _descriptor(spec: Param) -> ParameterDescriptor:
    desc = ParameterDescriptor(type=spec.type.value, description=spec.description,
                               additional_constraints=f'expected {spec.expected()}')
    if spec.low is not None and spec.high is not None:
        if spec.type == T.DOUBLE:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
        elif spec.type == T.INTEGER:
            desc.integer_range = [IntegerRange(
                from_value=int(spec.low), to_value=int(spec.high), step=1)]
    return desc

"""Typed, documented ROS parameters that fail at start-up with one line naming the culprit.

Every parameter goes through `declare`: its raw value (from a params file or `-p`)
is read, checked and coerced here (an integer is accepted where a double is
expected, as YAML writes `500` for `500.0`), then the parameter is declared with its
ROS type, description and range so `ros2 param describe` shows them.

At run time (`ros2 param set`, the SetParameters services) a parameter declared
`live` is checked by the same rules, then by the node's own `prepare` hook (see
`LiveParams`), which builds the new core objects or refuses the change; every other
parameter is declared read-only, so rclpy refuses to set it.
"""
import array
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
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
    live: bool = False               # takes effect when set at run time (else read-only)

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
    if value == [] and spec.live:      # rclpy would type an empty list as bytes: type it first
        node.declare_parameter(spec.name, spec.type, _descriptor(spec), ignore_override=True)
        node.set_parameters([Parameter(spec.name, spec.type, [])])
    else:
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
                               additional_constraints=f'expected {spec.expected()}',
                               read_only=not spec.live)
    if spec.low is not None and spec.high is not None:
        if spec.type == T.DOUBLE:
            desc.floating_point_range = [FloatingPointRange(
                from_value=float(spec.low), to_value=float(spec.high), step=0.0)]
        elif spec.type == T.INTEGER:
            desc.integer_range = [IntegerRange(
                from_value=int(spec.low), to_value=int(spec.high), step=1)]
    return desc


# A node's hook: the full set of values with the changes in, and the changed names;
# it raises ParameterError (or ValueError) to refuse, or returns what makes them take effect.
Prepare = Callable[[dict[str, Any], set[str]], Callable[[], None]]
_ARRAYS = (T.DOUBLE_ARRAY, T.INTEGER_ARRAY, T.STRING_ARRAY, T.BOOL_ARRAY)


class LiveParams:
    """Run-time changes of a node's live parameters, checked as at start-up, then applied.

    A change (one parameter, or several set atomically) is checked against its spec,
    then `prepare(values, changed)` gets every value with the change in: it checks what
    must hold together (a fence's corners, two rates) and builds the new core objects,
    raising ParameterError to refuse; the reason goes back in SetParametersResult. The
    function it returns runs once rclpy has stored the values, so what the node uses
    and what `ros2 param get` shows never differ.
    An integer is taken where a double is declared (`ros2 param set ... max_speed 1`).
    """

    def __init__(self, node: Node, specs: Sequence[Param], values: dict[str, Any],
                 prepare: Prepare) -> None:
        self._node, self._prepare = node, prepare
        self._specs = {spec.name: spec for spec in specs}
        self.values = dict(values)
        self._pending: tuple[dict[str, Any], Callable[[], None]] | None = None
        node.add_pre_set_parameters_callback(self._widen)
        node.add_on_set_parameters_callback(self._check)
        node.add_post_set_parameters_callback(self._commit)

    def _widen(self, params: list[Parameter]) -> list[Parameter]:
        """Integers where doubles are declared become doubles, an empty list the declared type."""
        return [self._widened(p) for p in params]

    def _widened(self, p: Parameter) -> Parameter:
        if not self._node.has_parameter(p.name):
            return p
        want = T(self._node.describe_parameter(p.name).type)
        value = list(p.value) if isinstance(p.value, (list, tuple, array.array)) else p.value
        if want == T.DOUBLE and p.type_ == T.INTEGER:
            return Parameter(p.name, T.DOUBLE, float(value))
        if want == T.DOUBLE_ARRAY and p.type_ == T.INTEGER_ARRAY:
            return Parameter(p.name, T.DOUBLE_ARRAY, [float(v) for v in value])
        if want in _ARRAYS and p.type_ in (*_ARRAYS, T.BYTE_ARRAY) and not value:
            return Parameter(p.name, want, [])
        return p

    def _check(self, params: list[Parameter]) -> SetParametersResult:
        changes = {}
        try:
            for p in params:
                value = list(p.value) if isinstance(p.value, array.array) else p.value
                if p.name in self._specs:
                    changes[p.name] = _coerce(self._specs[p.name], value)
                elif not self._node.has_parameter(p.name):
                    raise ParameterError(f'{p.name}: unknown parameter')
            values = {**self.values, **changes}
            commit = self._prepare(values, set(changes)) if changes else None
        except ValueError as err:          # ParameterError, or a core object's own check
            return SetParametersResult(successful=False, reason=str(err))
        self._pending = (values, commit) if commit else None
        return SetParametersResult(successful=True)

    def _commit(self, params: list[Parameter]) -> None:
        if self._pending is not None:
            self.values, commit = self._pending
            self._pending = None
            commit()

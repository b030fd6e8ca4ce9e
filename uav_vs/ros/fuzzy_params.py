"""Types, ranges and descriptions of the fuzzy controller's `fuzzy.*` parameters.

The rule bases are data (uav_vs.control.fuzzy, chapter section 6): which parameters
exist depends on the params file (its axes, variables and sets), so each one is
described by the pattern of its name. All of them are live: a change rebuilds the
controller, which replaces the old one only if it is valid.
"""
import re
from typing import Iterable

from uav_vs.control.fuzzy import AGGREGATIONS, AND_OPS, DEFUZZIFIERS, IMPLICATIONS
from uav_vs.ros.params import Param, ParameterError, T

_AXIS = r'(?:axes\.(?P<axis>\w+)|tracking)'
_VAR = r'(?P<var>error|rate|integral|command)'
# Units of an axis's error and command: pose axes in m and m/s, yaw in rad, tracking in px.
_ERROR_UNIT = {'x': 'm', 'y': 'm', 'z': 'm', 'yaw': 'rad', None: 'px'}
_COMMAND_UNIT = {'x': 'm/s', 'y': 'm/s', 'z': 'm/s', 'yaw': 'rad/s', None: 'rad/s'}
_GAIN = {'error': 'universe units per {e}', 'rate': 'universe units per {e}/s',
         'integral': 'universe units per {e} s', 'command': '{c} per universe unit'}

# (name pattern after 'fuzzy.', type, description, low, high, choices)
_PATTERNS = [
    (r'inference\.and', T.STRING, "AND of a rule's antecedents", None, None, AND_OPS),
    (r'inference\.implication', T.STRING,
     "each output set clipped (min) or scaled (product) by its rule's strength",
     None, None, IMPLICATIONS),
    (r'inference\.aggregation', T.STRING, 'how the shaped output sets combine',
     None, None, AGGREGATIONS),
    (r'inference\.defuzzification', T.STRING, 'fuzzy output set -> crisp command',
     None, None, DEFUZZIFIERS),
    (r'inference\.resolution', T.INTEGER, 'points of each output universe', 2, 100000, ()),
    (r'inference\.default', T.DOUBLE, 'output when an input is not finite or no rule fires',
     -1e9, 1e9, ()),
    (_AXIS + r'\.limit', T.DOUBLE, '|command| saturation after the output gain, {c}',
     1e-9, 1e3, ()),
    (_AXIS + r'\.rate_filter', T.DOUBLE,
     'time constant of the low-pass on the error rate (0: raw difference), s', 0.0, 100.0, ()),
    (_AXIS + r'\.integral_limit', T.DOUBLE, 'the error integral is clamped to +-this, {e} s',
     1e-9, 1e9, ()),
    (_AXIS + r'\.rules', T.STRING_ARRAY,
     "rule base: 'IF error IS <set> AND rate IS <set> THEN command IS <set> [WITH weight]'",
     None, None, ()),
    (_AXIS + r'\.' + _VAR + r'\.gain', T.DOUBLE, '{gain} (non-zero)', -1e9, 1e9, ()),
    (_AXIS + r'\.' + _VAR + r'\.sets', T.STRING_ARRAY, 'fuzzy set names, in apex order',
     None, None, ()),
    (_AXIS + r'\.' + _VAR + r'\.apexes', T.DOUBLE_ARRAY,
     'apexes of 50 %-overlap triangles, ascending; the end sets are shoulders',
     None, None, ()),
    (_AXIS + r'\.' + _VAR + r'\.range', T.DOUBLE_ARRAY, 'universe [lo, hi], lo < hi',
     None, None, ()),
    (_AXIS + r'\.' + _VAR + r'\.mf\.(?P<set>\w+)', T.DOUBLE_ARRAY,
     'set {set}: Gaussian [mean, sigma], triangle [a, b, c] or trapezoid [a, b, c, d]',
     None, None, ()),
]
_COMPILED = [(re.compile(pattern + '$'), *rest) for pattern, *rest in _PATTERNS]


def fuzzy_param(name: str) -> Param:
    """The spec of one `fuzzy.<...>` parameter; ParameterError if no pattern matches."""
    for regex, kind, text, low, high, choices in _COMPILED:
        if match := regex.match(name.removeprefix('fuzzy.')):
            groups = match.groupdict()
            axis, var = groups.get('axis'), groups.get('var')
            units = dict(e=_ERROR_UNIT.get(axis, 'input units'),
                         c=_COMMAND_UNIT.get(axis, 'command units'))
            text = text.format(gain=_GAIN.get(var, '').format(**units), set=groups.get('set'),
                               **units)
            return Param(name, kind, description=text, low=low, high=high, choices=choices,
                         live=True)
    raise ParameterError(f'{name}: unknown parameter (see config/fuzzy_controller.yaml)')


def fuzzy_params(names: Iterable[str]) -> list[Param]:
    """The specs of the given `fuzzy.*` parameters, in order."""
    return [fuzzy_param(name) for name in names]

"""Mamdani fuzzy inference defined entirely by data (chapter section 6).

The fuzzy controllers of section 6 (Olivares-Méndez et al.) are Mamdani systems:
crisp inputs are fuzzified by membership functions, rules "IF a IS A AND b IS B
THEN u IS U" fire with the AND of their antecedent memberships, each fired rule
shapes its output set (implication), the shaped sets are aggregated into one
output fuzzy set, and a defuzzifier turns that set into one crisp command.

A system is a dict (usually loaded from YAML)::

    {'inputs': {'error': VAR, 'rate': VAR},      # order = input vector order
     'output': {'command': VAR},                 # exactly one output
     'rules': ['IF error IS NB AND rate IS ZE THEN command IS NM',
               'IF error IS ZE THEN command IS ZE WITH 0.5', ...],
     'and': 'min',              # min | product       (AND of antecedents)
     'implication': 'min',      # min | product       (clip or scale the output set)
     'aggregation': 'max',      # max | sum
     'defuzzification': 'centroid',   # centroid | bisector | mom | height
     'resolution': 201,         # points of the discretised output universe
     'default': 0.0}            # output when the inputs are not finite or no rule fires

and a variable VAR is either a 50 %-overlap triangular partition
``{'sets': ['NB', 'NS', 'ZE', 'PS', 'PB'], 'apexes': [-1, -0.3, 0, 0.3, 1]}``
(`partition`; apexes may be denser near zero, range defaults to the end apexes)
or explicit sets ``{'range': [lo, hi], 'mf': {'NB': [a, b, c], ...}}`` where a
parameter list of length 2 is a Gaussian [mean, sigma], 3 a triangle [a, b, c]
and 4 a trapezoid [a, b, c, d]. Rules are ``IF <in> IS <set> [AND <in> IS <set>]...
THEN <out> IS <set> [WITH <weight in [0, 1]>]`` (keywords in any case); the
weight multiplies the rule's firing strength.

Semantics (vectorised; everything shape-dependent is precomputed at load):
- inputs are clipped to their variable's range, so the end sets act as
  saturating shoulders; a row with any non-finite input gives `default` and
  ok=False, as does a row where no rule fires;
- the output universe is `resolution` even points plus every breakpoint and centre
  of the output sets. A unit (an output set under max aggregation, a rule under sum
  aggregation with min implication) is shaped by its level; with min implication the
  two points where each unit reaches its level are added, and the aggregated set is
  linear between points. Centroid and bisector are exact for that piecewise-linear
  set, which is scikit-fuzzy's ControlSystem definition (the tests check equality);
  mom is the mean of the flat top(s) at maximum membership (or of the points at the
  maximum when there is no flat top); height is the level-weighted mean of the set
  centres (apex, core middle or Gaussian mean).
FuzzyBank computes the common cases by exact shortcuts (linear firing, closed-form
centroid over an output partition); see there.
"""
from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

AND_OPS = ('min', 'product')
IMPLICATIONS = ('min', 'product')
AGGREGATIONS = ('max', 'sum')
DEFUZZIFIERS = ('centroid', 'bisector', 'mom', 'height')
SYSTEM_KEYS = {'inputs', 'output', 'rules', 'and', 'implication', 'aggregation',
               'defuzzification', 'resolution', 'default'}
VARIABLE_KEYS = {'range', 'sets', 'apexes', 'mf'}

_RULE = re.compile(r'^\s*IF\s+(?P<ante>.+?)\s+THEN\s+(?P<out>.+?)'
                   r'(?:\s+WITH\s+(?P<weight>\S+))?\s*$', re.IGNORECASE)
_CLAUSE = re.compile(r'^\s*(\w+)\s+IS\s+(\w+)\s*$', re.IGNORECASE)
_AND = re.compile(r'\s+AND\s+', re.IGNORECASE)


def _einsum_vecdot(x1: np.ndarray, x2: np.ndarray, axis: int = -1) -> np.ndarray:
    """np.vecdot for real arrays on NumPy 1.x (Ubuntu 24.04's 1.26), which lacks it."""
    x1, x2 = np.broadcast_arrays(x1, x2)
    return np.einsum('...i,...i->...', np.moveaxis(x1, axis, -1), np.moveaxis(x2, axis, -1))


# NumPy >= 2's own ufunc where there is one: the closed-form centroid's inner product.
_vecdot = getattr(np, 'vecdot', _einsum_vecdot)


def trapezoid(x: np.ndarray, a: float, b: float, c: float, d: float) -> np.ndarray:
    """Trapezoidal membership [a, b, c, d] (a <= b <= c <= d); a == b or c == d is a vertical edge."""
    x = np.asarray(x, dtype=float)
    y = np.ones_like(x)
    y = np.where(x < b, (x - a) / (b - a) if b > a else 0.0, y)
    y = np.where(x > c, (d - x) / (d - c) if d > c else 0.0, y)
    return np.clip(y, 0.0, 1.0)


def triangle(x: np.ndarray, a: float, b: float, c: float) -> np.ndarray:
    """Triangular membership [a, b, c]: 0 at a and c, 1 at the apex b."""
    return trapezoid(x, a, b, b, c)


def gaussian(x: np.ndarray, mean: float, sigma: float) -> np.ndarray:
    """Gaussian membership exp(-(x - mean)^2 / (2 sigma^2))."""
    return np.exp(-0.5 * ((np.asarray(x, dtype=float) - mean) / sigma) ** 2)


def membership(x: np.ndarray, params: Sequence[float]) -> np.ndarray:
    """Evaluate one set given as [mean, sigma], [a, b, c] or [a, b, c, d]."""
    return (gaussian, triangle, trapezoid)[len(params) - 2](x, *params)


def partition(names: Sequence[str], apexes: Sequence[float],
              lo: float | None = None, hi: float | None = None) -> dict[str, list[float]]:
    """50 %-overlap triangular partition: set k peaks at apexes[k], its feet are the
    neighbouring apexes, the end sets are shoulders reaching lo / hi. Memberships sum
    to 1 everywhere in [lo, hi]; apexes may be spaced non-uniformly (denser near zero)."""
    a = [float(v) for v in apexes]
    lo = a[0] if lo is None else float(lo)
    hi = a[-1] if hi is None else float(hi)
    if len(names) != len(a) or len(a) < 2:
        raise ValueError(f'partition needs as many set names as apexes, at least 2 '
                         f'(got {len(names)} names, {len(a)} apexes)')
    if any(q <= p for p, q in zip(a, a[1:])) or lo > a[0] or hi < a[-1]:
        raise ValueError(f'partition apexes must increase strictly within [{lo}, {hi}]: {a}')
    ext = [lo] + a + [hi]
    sets = {}
    for k, name in enumerate(names):
        left, apex, right = ext[k], ext[k + 1], ext[k + 2]
        if k == 0 and lo < apex:
            sets[name] = [lo, lo, apex, right]
        elif k == len(a) - 1 and apex < hi:
            sets[name] = [left, apex, hi, hi]
        else:
            sets[name] = [apex if k == 0 else left, apex, apex if k == len(a) - 1 else right]
    return sets


def _core(params: Sequence[float]) -> float:
    """Centre used by the height method: Gaussian mean, triangle apex, trapezoid core middle."""
    return params[0] if len(params) == 2 else 0.5 * (params[1] + params[-2])


def _as_trapezoid(params: Sequence[float]) -> tuple[float, float, float, float]:
    return (params[0], params[1], params[1], params[2]) if len(params) == 3 else tuple(params)


def _edges(a, b, c, d, width):
    """Trapezoid as min((x - a) * rise, (d - x) * fall) clipped to [0, 1]; a vertical edge
    becomes a ramp 1e-12 * width wide, so the set is still exactly 1 at b and c."""
    a, b, c, d = (np.asarray(v, dtype=float) for v in (a, b, c, d))
    a = np.where(b > a, a, b - 1e-12 * width)
    d = np.where(d > c, d, c + 1e-12 * width)
    return a, 1.0 / (b - a), d, 1.0 / (d - c)


@dataclass(frozen=True)
class Variable:
    """A linguistic variable: crisp range and named sets (parameter lists)."""
    name: str
    lo: float
    hi: float
    sets: dict[str, tuple[float, ...]]

    @classmethod
    def from_config(cls, name: str, cfg: Mapping) -> Variable:
        """Build from {'sets': [...], 'apexes': [...], 'range'?} or {'range': [lo, hi], 'mf': {...}}."""
        if not isinstance(cfg, Mapping):
            raise ValueError(f'variable {name!r}: expected a mapping, got {type(cfg).__name__}')
        unknown = set(cfg) - VARIABLE_KEYS
        if unknown:
            raise ValueError(f'variable {name!r}: unknown key(s) {sorted(unknown)}')
        rng = cfg.get('range')
        if rng is not None and (len(rng) != 2 or not float(rng[0]) < float(rng[1])):
            raise ValueError(f'variable {name!r}: range must be [lo, hi] with lo < hi, got {list(rng)}')
        if 'apexes' in cfg:
            if 'mf' in cfg or 'sets' not in cfg:
                raise ValueError(f"variable {name!r}: give either 'sets' + 'apexes' or 'mf'")
            lo, hi = (None, None) if rng is None else rng
            try:
                sets = partition(list(cfg['sets']), cfg['apexes'], lo, hi)
            except ValueError as err:
                raise ValueError(f'variable {name!r}: {err}') from None
        elif 'mf' in cfg:
            if rng is None:
                raise ValueError(f"variable {name!r}: 'mf' sets need a 'range'")
            sets = {str(k): [float(v) for v in p] for k, p in cfg['mf'].items()}
        else:
            raise ValueError(f"variable {name!r}: needs 'sets' + 'apexes' or 'range' + 'mf'")
        for set_name, p in sets.items():
            bad = (len(p) not in (2, 3, 4) or not np.all(np.isfinite(p))
                   or (len(p) == 2 and p[1] <= 0) or (len(p) > 2 and np.any(np.diff(p) < 0)))
            if bad:
                raise ValueError(f'variable {name!r}: set {set_name!r} needs [mean, sigma>0], '
                                 f'[a<=b<=c] or [a<=b<=c<=d], got {list(p)}')
        first = next(iter(sets.values()))
        lo, hi = (first[0], list(sets.values())[-1][-1]) if rng is None else rng
        return cls(name, float(lo), float(hi), {k: tuple(v) for k, v in sets.items()})


def universe(var: Variable, points: int) -> np.ndarray:
    """`points` even samples of var's range plus every breakpoint of its sets (a Gaussian's
    mean), each moved onto the grid where one lies within 1e-9 of the range."""
    lo, hi = var.lo, var.hi
    grid = np.linspace(lo, hi, points)
    tol = 1e-9 * (hi - lo)
    extra = []
    for p in var.sets.values():
        for v in (p[:1] if len(p) == 2 else p):
            k = int(np.abs(grid - v).argmin())
            if abs(grid[k] - v) <= tol:
                grid[k] = v
            elif lo < v < hi:
                extra.append(v)
    return np.union1d(grid, extra)


@dataclass(frozen=True)
class Rule:
    """A parsed rule: antecedent (input index, set index) pairs, consequent set index, weight."""
    antecedent: tuple[tuple[int, int], ...]
    consequent: int
    weight: float


def parse_rule(text: str, inputs: Sequence[Variable], output: Variable, number: int = 0) -> Rule:
    """Parse 'IF a IS A [AND b IS B]... THEN out IS U [WITH w]'; ValueError names the fault."""
    where = f'rule {number} {text!r}'
    m = _RULE.match(str(text))
    if m is None:
        raise ValueError(f"{where}: expected 'IF <input> IS <set> [AND ...] THEN <output> IS <set> [WITH <weight>]'")
    names = [v.name for v in inputs]
    ante = []
    for clause in _AND.split(m['ante']):
        c = _CLAUSE.match(clause)
        if c is None:
            raise ValueError(f"{where}: cannot read {clause.strip()!r}, expected '<input> IS <set>'")
        var, set_name = c[1], c[2]
        if var not in names:
            raise ValueError(f'{where}: unknown input variable {var!r} (inputs: {", ".join(names)})')
        k = names.index(var)
        if set_name not in inputs[k].sets:
            raise ValueError(f'{where}: unknown set {set_name!r} of {var!r} '
                             f'(sets: {", ".join(inputs[k].sets)})')
        if any(k == j for j, _ in ante):
            raise ValueError(f'{where}: input {var!r} appears twice')
        ante.append((k, list(inputs[k].sets).index(set_name)))
    c = _CLAUSE.match(m['out'])
    if c is None:
        raise ValueError(f"{where}: cannot read consequent {m['out']!r}, expected '<output> IS <set>'")
    if c[1] != output.name:
        raise ValueError(f'{where}: unknown output variable {c[1]!r} (output: {output.name})')
    if c[2] not in output.sets:
        raise ValueError(f'{where}: unknown set {c[2]!r} of {output.name!r} '
                         f'(sets: {", ".join(output.sets)})')
    weight = 1.0
    if m['weight'] is not None:
        try:
            weight = float(m['weight'])
        except ValueError:
            weight = float('nan')
        if not 0.0 <= weight <= 1.0:
            raise ValueError(f"{where}: weight must be a number in [0, 1], got {m['weight']!r}")
    return Rule(tuple(ante), list(output.sets).index(c[2]), weight)


def _choice(cfg: Mapping, key: str, options: tuple[str, ...], default: str) -> str:
    value = str(cfg.get(key, default)).lower()
    if value not in options:
        raise ValueError(f"{key!r} must be one of {'|'.join(options)}, got {cfg.get(key)!r}")
    return value


class FuzzySystem:
    """One Mamdani system (several inputs, one output) built from a config dict."""

    def __init__(self, inputs: list[Variable], output: Variable, rules: list[Rule],
                 and_op: str = 'min', implication: str = 'min', aggregation: str = 'max',
                 defuzzification: str = 'centroid', resolution: int = 201, default: float = 0.0):
        self.inputs, self.output, self.rules = inputs, output, rules
        self.and_op, self.implication, self.aggregation = and_op, implication, aggregation
        self.defuzzification, self.resolution, self.default = defuzzification, resolution, default
        self.universe = self._grid()
        self._bank: FuzzyBank | None = None

    @classmethod
    def from_config(cls, cfg: Mapping) -> FuzzySystem:
        """Validate and build; every error is a one-line ValueError naming the culprit."""
        unknown = set(cfg) - SYSTEM_KEYS
        if unknown:
            raise ValueError(f'fuzzy system: unknown key(s) {sorted(unknown)}')
        for key in ('inputs', 'output', 'rules'):
            if not cfg.get(key):
                raise ValueError(f'fuzzy system: missing or empty {key!r}')
        if not isinstance(cfg['output'], Mapping) or len(cfg['output']) != 1:
            raise ValueError("fuzzy system: 'output' must map exactly one name to a variable")
        inputs = [Variable.from_config(str(n), v) for n, v in cfg['inputs'].items()]
        (out_name, out_cfg), = cfg['output'].items()
        output = Variable.from_config(str(out_name), out_cfg)
        if isinstance(cfg['rules'], str):
            raise ValueError("fuzzy system: 'rules' must be a list of rule strings")
        rules = [parse_rule(t, inputs, output, k) for k, t in enumerate(cfg['rules'])]
        resolution = int(cfg.get('resolution', 201))
        if resolution < 3:
            raise ValueError(f"'resolution' must be at least 3, got {resolution}")
        default = float(cfg.get('default', 0.0))
        if not output.lo <= default <= output.hi:
            raise ValueError(f"'default' {default} lies outside the output range [{output.lo}, {output.hi}]")
        return cls(inputs, output, rules,
                   _choice(cfg, 'and', AND_OPS, 'min'),
                   _choice(cfg, 'implication', IMPLICATIONS, 'min'),
                   _choice(cfg, 'aggregation', AGGREGATIONS, 'max'),
                   _choice(cfg, 'defuzzification', DEFUZZIFIERS, 'centroid'),
                   resolution, default)

    def _grid(self) -> np.ndarray:
        """Output universe: `resolution` even points plus every breakpoint and centre of the
        output sets, so each set is exactly piecewise linear between grid points."""
        return universe(self.output, self.resolution)

    def evaluate(self, x: Sequence[float]) -> tuple[float, bool]:
        """Crisp output for one input vector (in `inputs` order) and whether it is valid."""
        if self._bank is None:
            self._bank = FuzzyBank([self])
        y, ok = self._bank.evaluate(np.asarray(x, dtype=float)[None, :])
        return float(y[0]), bool(ok[0])


# Closed-form centroid over an output partition (FuzzyBank._partition_centroid): per interval
# between neighbouring apexes the features [A, C, C, A, m, m, A^2, C^2, C^2, A^2, m^2, m^2,
# A^3, C^3, D1, D2, D1 l1, D2 l2, D1 r1, D2 r2, D1 m, D2 m, 1] (repeats keep every step free
# of broadcasting and reversed views); area and first moment (in t) are their dot products
# with these weights. The constant feature adds the smallest positive double to the area (of
# no consequence to any other area), so that where no rule fired the centroid is 0 / _TINY.
_AREA = np.array([1, 1, 0, 0, -1, 0, -1 / 2, -1 / 2, 0, 0, 1, 0,
                  0, 0, 1 / 2, 1 / 2, 0, 0, 0, 0, 0, 0, 0])
_MOMENT = np.array([1 / 2, 1 / 2, 0, 0, -1 / 2, 0, -1 / 2, 0, 0, 0, 1 / 2, 0,
                    1 / 6, -1 / 6, 0, 1 / 2, -1 / 6, 1 / 6, 1 / 6, -1 / 6, 1 / 2, -1 / 2, 0])
_TINY = 5e-324
_HUGE = 1e150        # inputs at least this large (or not finite) are sanitised before use


def _rule_forms(system: FuzzySystem, n_forms: int) -> np.ndarray | None:
    """Firing strengths under min AND as minima of linear forms of the inputs (section 6).

    weight * min(memberships, clipped to [0, 1]) = max(0, min(weight, weight * each edge
    of each antecedent set)), every edge being linear in its input; the max with 0 is
    left to the caller. Inputs are clipped to their range, so an edge beyond a range end
    is constant there and dropped. Returns coefficients (inputs + 1, n_forms, rules),
    the last row the constant term, or None when a set is not of that kind (Gaussian,
    vertical edge inside the range, an edge across a range end).
    """
    V = len(system.inputs)
    coef = np.zeros((V + 1, n_forms, len(system.rules)))
    for r, rule in enumerate(system.rules):
        w = rule.weight
        coef[V, :, r] = w
        for k, (i, j) in enumerate(rule.antecedent):
            var = system.inputs[i]
            p = list(var.sets.values())[j]
            if len(p) == 2:
                return None
            a, b, c, d = _as_trapezoid(p)
            if b > var.lo:                      # rising edge (x - a) / (b - a)
                if not var.lo <= a < b <= var.hi:
                    return None
                coef[i, 2 * k + 1, r], coef[V, 2 * k + 1, r] = w / (b - a), -w * a / (b - a)
            if c < var.hi:                      # falling edge (d - x) / (d - c)
                if not var.lo <= c < d <= var.hi:
                    return None
                coef[i, 2 * k + 2, r], coef[V, 2 * k + 2, r] = -w / (d - c), w * d / (d - c)
    return coef


def _output_partition(system: FuzzySystem) -> tuple[list[int], list[float]] | None:
    """Output sets in order of position and their apexes when they form a 50 %-overlap
    triangular partition of the output range (end sets may be shoulders) whose apexes lie
    on the even grid (the universe has no extra points); otherwise None."""
    out = system.output
    if len(system.universe) != system.resolution or any(len(p) == 2 for p in out.sets.values()):
        return None
    shapes = [_as_trapezoid(p) for p in out.sets.values()]
    order = sorted(range(len(shapes)), key=lambda t: shapes[t][1] + shapes[t][2])
    sets = [shapes[t] for t in order]
    apex = [sets[0][2]] + [p[1] for p in sets[1:]]
    ok = (len(sets) >= 2 and sets[0][:2] == (out.lo, out.lo) and sets[-1][2:] == (out.hi, out.hi)
          and all(p[1] == p[2] for p in sets[1:-1])
          and all(p[3] == q and s[0] == a and a < q
                  for p, s, a, q in zip(sets, sets[1:], apex, apex[1:])))
    return (order, apex) if ok else None


class FuzzyBank:
    """Several systems with the same operators, evaluated in one vectorised call.

    Row b of the (B, V) input goes to system b (V = most inputs of any system; extra
    columns are ignored). Systems are padded to common sizes at load time: padded
    rules never fire, padded antecedents are neutral, padded output sets are empty,
    shorter output grids repeat their last point. A bank of one system repeated P
    times evaluates P input vectors at once. A bank reuses its work buffers, so one
    bank must not be evaluated from two threads at once.

    Where they apply (and `specialise` is true) two stages are replaced by exact
    shortcuts that give the same numbers as the general ones (the tests check it):
    `linear_firing`, rule firing under min AND over triangular/trapezoidal input sets
    as one matrix product and one minimum (`_rule_forms`); `closed_form`, min
    implication + max aggregation + centroid over an output partition computed in
    closed form (`_partition_centroid`) instead of merging and sorting the clip points
    into the output grid. Both flags tell which apply.
    """

    def __init__(self, systems: Sequence[FuzzySystem], specialise: bool = True):
        s0 = systems[0]
        ops = (s0.and_op, s0.implication, s0.aggregation, s0.defuzzification)
        for s in systems:
            if (s.and_op, s.implication, s.aggregation, s.defuzzification) != ops:
                raise ValueError('FuzzyBank: systems must share and/implication/aggregation/'
                                 f'defuzzification, got {ops} and '
                                 f'{(s.and_op, s.implication, s.aggregation, s.defuzzification)}')
        self.and_op, self.implication, self.aggregation, self.defuzzification = ops
        B = len(systems)
        V = max(len(s.inputs) for s in systems)
        R = max(len(s.rules) for s in systems)
        self.n_inputs = V
        self.default = np.array([s.default for s in systems])
        self._nonzero_default = bool(self.default.any())
        self._lo, self._hi = np.zeros((B, V)), np.zeros((B, V))
        for bi, s in enumerate(systems):
            for i, v in enumerate(s.inputs):
                self._lo[bi, i], self._hi[bi, i] = v.lo, v.hi
        self._fire = np.zeros(B * R + 1)           # last entry stays 0
        self._fire_br = self._fire[:-1].reshape(B, R)

        n_forms = 1 + 2 * max(len(r.antecedent) for s in systems for r in s.rules)
        # Mean of maxima hinges on exact ties between levels, which the forms' rounding
        # need not reproduce, so it keeps the general fuzzification.
        linear = specialise and self.and_op == 'min' and self.defuzzification != 'mom'
        forms = [_rule_forms(s, n_forms) for s in systems] if linear else [None]
        self.linear_firing = all(f is not None for f in forms)
        if self.linear_firing:
            self._init_linear_firing(forms, V, R, n_forms)
        else:
            self._init_memberships(systems, V, R)
        closed_form = specialise and ops[1:] == ('min', 'max', 'centroid')
        parts = [_output_partition(s) for s in systems] if closed_form else [None]
        self.closed_form = all(p is not None for p in parts)
        if self.closed_form:
            self._init_partition(systems, parts, R)
        else:
            self._init_aggregation(systems, R)

    def _init_linear_firing(self, forms: list[np.ndarray], V: int, R: int, n_forms: int) -> None:
        """Inputs (B, 1, V + 1) with a trailing 1 times coefficients (B, V + 1, n_forms * R)
        give the forms (B, n_forms, R); their minimum over axis 1 is the firing strength."""
        B = len(forms)
        self._x1 = np.ones((B, 1, V + 1))
        self._x1_in = self._x1[:, 0, :V]
        coef = np.zeros((B, V + 1, n_forms, R))
        for bi, f in enumerate(forms):
            coef[bi, :len(f) - 1, :, :f.shape[2]] = f[:-1]
            coef[bi, V, :, :f.shape[2]] = f[-1]
        self._form_coef = coef.reshape(B, V + 1, -1)
        self._forms = np.empty((B, 1, n_forms * R))
        self._forms_fr = self._forms.reshape(B, n_forms, R)
        self._clip_fire = self.aggregation == 'sum'     # max aggregation reduces with a 0 entry

    def _init_memberships(self, systems: Sequence[FuzzySystem], V: int, R: int) -> None:
        """General fuzzification: each input set reads x.ravel()[set_input] and is a trapezoid
        (see _edges) or a Gaussian exp(-((x - mean) / sigma)^2 / 2); rules combine K arrays
        (B, R) of indices into the memberships buffer (B * S + 2,) whose entry B * S is 1
        (absent antecedent) and entry B * S + 1 is 0 (padded rule)."""
        B = len(systems)
        S = max(sum(len(v.sets) for v in s.inputs) for s in systems)
        K = max(len(r.antecedent) for s in systems for r in s.rules)
        self._set_input = np.zeros((B, S), dtype=np.intp)
        trap = np.zeros((4, B, S))
        self._is_gauss = np.zeros((B, S), dtype=bool)
        self._mean, self._inv_sigma = np.zeros((B, S)), np.ones((B, S))
        ante = np.empty((K, B, R), dtype=np.intp)
        self._weight = np.zeros((B, R))
        for bi, s in enumerate(systems):
            base = bi * S
            self._set_input[bi] = bi * V
            col, set_col = 0, []
            for i, v in enumerate(s.inputs):
                set_col.append(col)
                for p in v.sets.values():
                    self._set_input[bi, col] = bi * V + i
                    if len(p) == 2:
                        self._is_gauss[bi, col] = True
                        self._mean[bi, col], self._inv_sigma[bi, col] = p[0], 1.0 / p[1]
                    else:
                        trap[:, bi, col] = _as_trapezoid(p)
                    col += 1
            trap[:, bi, col:] = v.lo
            ante[:, bi] = B * S
            ante[:, bi, len(s.rules):] = B * S + 1
            for r, rule in enumerate(s.rules):
                for k, (i, j) in enumerate(rule.antecedent):
                    ante[k, bi, r] = base + set_col[i] + j
                self._weight[bi, r] = rule.weight
        self._ante = list(ante)
        width = (self._hi - self._lo).ravel()[self._set_input]
        self._a, self._rise, self._d, self._fall = _edges(*trap, width)
        self._any_gauss = bool(self._is_gauss.any())
        self._weighted = bool((self._weight[self._weight > 0] != 1.0).any())
        self._memberships = np.zeros(B * S + 2)
        self._memberships[B * S] = 1.0

    def _init_partition(self, systems: Sequence[FuzzySystem], parts: list, R: int) -> None:
        """Buffers and coefficients of `_partition_centroid`, all (..., J, B) with the row last
        so that every step works on contiguous blocks. Interval u of row b lies between
        apexes u and u + 1 (width w, left apex p, n grid cells); its area and moment are
        w * area_t and w * p * area_t + w^2 * moment_t, plus the end plateaus of shoulders."""
        B = len(systems)
        J = max(len(apex) for _, apex in parts) - 1
        members = [[[bi * R + r for r, rule in enumerate(s.rules) if rule.consequent == t] for t in order]
                   for bi, (s, (order, _)) in enumerate(zip(systems, parts))]
        depth = max(len(rs) for m in members for rs in m) + 1
        level = np.full((depth, 4, J, B), B * R)            # B * R: the 0 after the firings
        coef = np.zeros((2, len(_AREA), J, B))
        self._cell = np.ones((2, J, B))                        # grid period in t
        for bi, (s, (_, apex)) in enumerate(zip(systems, parts)):
            p = np.array(apex)
            w = np.diff(p)
            cells = np.round(w * (s.resolution - 1) / (s.output.hi - s.output.lo))
            for u in range(len(w)):
                for row, side in enumerate((0, 1, 1, 0)):      # A, C, C, A
                    rs = members[bi][u + side]
                    level[:len(rs), row, u, bi] = rs
            self._cell[:, :len(w), bi] = 1.0 / cells
            coef[0, :, :len(w), bi] = _AREA[:, None] * w
            coef[1, :, :len(w), bi] = _AREA[:, None] * (w * p[:-1]) + _MOMENT[:, None] * w ** 2
            lo, hi = s.output.lo, s.output.hi
            coef[:, 0, 0, bi] += (p[0] - lo, (p[0] ** 2 - lo ** 2) / 2)
            coef[:, 1, len(w) - 1, bi] += (hi - p[-1], (hi ** 2 - p[-1] ** 2) / 2)
            coef[0, -1, 0, bi] = _TINY
        self._level_idx = level
        self._coef = coef.reshape(2, -1, B)
        self._phi = np.ones((len(_AREA), J, B))
        phi = self._phi
        self._levels, self._ac, self._ca, self._m = phi[0:4], phi[0:2], phi[2:4], phi[4:6]
        self._lm, self._squares, self._ac2, self._cubes = phi[0:6], phi[6:12], phi[6:8], phi[12:14]
        self._delta, self._delta_l = phi[14:16], phi[16:18]
        self._delta_r, self._delta_m = phi[18:20], phi[20:22]
        self._phi_flat = phi.reshape(-1, B)
        self._half, self._one = np.full((2, J, B), 0.5), np.ones((2, J, B))
        self._two = np.full((2, 2, J, B), 2.0)
        self._one_minus_m, self._right_clip = np.empty((2, J, B)), np.empty((2, J, B))
        self._clip_dist, self._grid_dist = np.empty((2, 2, J, B)), np.empty((2, 2, J, B))
        self._near = np.empty((2, 2, J, B))
        self._s, self._minus_s = self._clip_dist[1], self._clip_dist[0]
        self._grid_l, self._grid_r = self._grid_dist
        self._near_l, self._near_r = self._near

    def _init_aggregation(self, systems: Sequence[FuzzySystem], R: int) -> None:
        """General aggregation and defuzzification on the output grid plus clip points."""
        B = len(systems)
        T = max(len(s.output.sets) for s in systems)
        N = max(len(s.universe) for s in systems)
        consequent = np.full((B, R), -1)
        for bi, s in enumerate(systems):
            for r, rule in enumerate(s.rules):
                consequent[bi, r] = rule.consequent
        # Output: grid and sets (a, b, c, d), or Gaussian as (sigma, mean, mean, mean).
        self._x = np.empty((B, N))
        out = np.zeros((B, T, 4))
        out_gauss = np.zeros((B, T), dtype=bool)
        for bi, s in enumerate(systems):
            grid = s.universe
            self._x[bi, :len(grid)], self._x[bi, len(grid):] = grid, grid[-1]
            out[bi] = s.output.lo
            for t, p in enumerate(s.output.sets.values()):
                out_gauss[bi, t] = len(p) == 2
                out[bi, t] = (p[1], p[0], p[0], p[0]) if len(p) == 2 else _as_trapezoid(p)

        # Units: what gets clipped/scaled and aggregated. Under sum aggregation with min
        # implication every rule is its own unit; otherwise one unit per output set, its
        # level reduced over its rules by reduceat over groups [0-entry, rules...].
        self._per_rule = self.aggregation == 'sum' and self.implication == 'min'
        if self._per_rule:
            out = np.take_along_axis(out, np.maximum(consequent, 0)[:, :, None], axis=1)
            out_gauss = np.take_along_axis(out_gauss, np.maximum(consequent, 0), axis=1)
        else:
            perm, starts = [], []
            for bi in range(B):
                for t in range(T):
                    starts.append(len(perm))
                    perm += [B * R] + [bi * R + r for r in np.flatnonzero(consequent[bi] == t)]
            self._perm, self._starts = np.array(perm), np.array(starts)
            self._level_reduce = np.maximum.reduceat if self.aggregation == 'max' else np.add.reduceat
        U = out.shape[1]
        mu = np.stack([[membership(self._x[bi], (p[1], p[0]) if g else p)
                        for p, g in zip(out[bi], out_gauss[bi])] for bi in range(B)])
        # On the grid only the units with non-zero membership matter: at most Q per point.
        # (Q, B, N) unit index into level.ravel() and membership (0 where padded).
        Q = int((mu > 0).sum(axis=1).max())
        rank = np.argsort(mu <= 0, axis=1, kind='stable')[:, :Q]        # non-zero units first
        self._grid_unit = (np.arange(B)[:, None, None] * U + rank).transpose(1, 0, 2).copy()
        self._grid_mu = np.take_along_axis(mu, rank, axis=1).transpose(1, 0, 2).copy()
        a, b, c, d = np.moveaxis(out, 2, 0)
        self._centre = np.where(out_gauss, b, 0.5 * (b + c))
        # Clip points of every unit at level L, rising then falling side, (B, 2U):
        # p = a + L (b - a) and p = d - L (d - c), or mean -/+ sigma sqrt(-2 ln L).
        self._unit2 = (np.arange(B)[:, None] * U + np.tile(np.arange(U), 2)).ravel()
        self._p_base = np.concatenate([a, d], axis=1)
        self._p_span = np.concatenate([b - a, c - d], axis=1)
        self._gauss2 = np.tile(out_gauss, 2) if out_gauss.any() else None
        self._g_mean, self._g_sigma = np.tile(b, 2), np.concatenate([-a, a], axis=1)
        self._check_range = self._gauss2 is not None or bool(
            ((a < self._x[:, :1]) | (d > self._x[:, -1:])).any())
        self._olo, self._ohi = self._x[:, :1].copy(), self._x[:, -1:].copy()
        # Every unit at every clip point, flattened to (B * U * 2U,): which point, which
        # unit level, and the unit's shape (trapezoid edges as for the inputs, or Gaussian).
        bb, uu, kk = np.meshgrid(np.arange(B), np.arange(U), np.arange(2 * U), indexing='ij')
        self._pair_point = (bb * 2 * U + kk).ravel()
        self._pair_level = (bb * U + uu).ravel()
        edges = _edges(a, b, c, d, self._x[:, -1:] - self._x[:, :1])
        self._pa, self._prise, self._pd, self._pfall = (e[bb, uu].ravel() for e in edges)
        self._pgauss = out_gauss[bb, uu].ravel()
        self._pmean = b[bb, uu].ravel()
        self._pinv = 1.0 / np.where(out_gauss, a, 1.0)[bb, uu].ravel()
        self._pair_shape = (B, U, 2 * U)
        M = N + 2 * U if self.implication == 'min' else N   # grid + clip points
        self._xa, self._fa = np.empty((B, M)), np.empty((B, M))
        self._xa[:, :N] = self._x
        self._row = np.arange(B)[:, None] * M
        self._row_start = np.arange(B) * M
        self._piece_in_row = np.ones(B * M - 1)
        self._piece_in_row[M - 1::M] = 0.0

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Crisp outputs (B,) for inputs (B, V), and a validity mask (finite inputs, a rule fired)."""
        x = np.asarray(x, dtype=float)
        bad = None
        if not math.hypot(*x.ravel().tolist()) < _HUGE:
            finite = np.isfinite(x)
            bad = ~finite.all(axis=1)
            x = np.minimum(np.maximum(np.where(finite, x, 0.0), self._lo), self._hi)
        if self.linear_firing:
            np.copyto(self._x1_in, x)
            np.matmul(self._x1, self._form_coef, out=self._forms)
            np.minimum.reduce(self._forms_fr, axis=1, out=self._fire_br)
            if self._clip_fire:
                np.maximum(self._fire_br, 0.0, out=self._fire_br)
        else:
            self._fire_memberships(x)
        y, ok = self._partition_centroid() if self.closed_form else self._defuzzify()
        if bad is not None:
            ok &= ~bad
            y[bad] = self.default[bad]
        return y, ok

    def _fire_memberships(self, x: np.ndarray) -> None:
        """Firing strengths (into self._fire) from the memberships of every input set."""
        xs = np.minimum(np.maximum(x, self._lo), self._hi).ravel()[self._set_input]
        mu = self._memberships[:-2].reshape(len(x), -1)
        np.minimum((xs - self._a) * self._rise, (self._d - xs) * self._fall, out=mu)
        if self._any_gauss:
            mu[...] = np.where(self._is_gauss, np.exp(-0.5 * ((xs - self._mean) * self._inv_sigma) ** 2), mu)
        np.minimum(np.maximum(mu, 0.0, out=mu), 1.0, out=mu)
        flat, fire = self._memberships, self._fire_br
        combine = np.minimum if self.and_op == 'min' else np.multiply
        if len(self._ante) == 1:
            fire[...] = flat[self._ante[0]]
        else:
            combine(flat[self._ante[0]], flat[self._ante[1]], out=fire)
            for idx in self._ante[2:]:
                combine(fire, flat[idx], out=fire)
        if self._weighted:
            fire *= self._weight

    def _partition_centroid(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact centroid for min implication, max aggregation and an output partition
        (section 6), without building the aggregated set.

        Between apexes u and u + 1, in t = (x - apex_u) / width, only those two sets are
        non-zero: F(t) = max(f1, f2), f1 = min(A, 1 - t), f2 = min(C, t), A and C their
        levels. The reference set samples F at the grid (t = i / n) and at the clip points
        1 - A and C and is linear in between. Such sampling is linear in F, f1 and f2 bend
        only at clip points, and F = f1 + f2 - g with g = min(m, t, 1 - t), m = min(A, C, 1/2);
        so the area is (A - A^2/2) + (C - C^2/2) - (m - m^2) plus, at each kink of g, the
        triangle D / 2 = dl dr / 2 cut off by the chord between the nearest samples, dl to
        the left and dr to the right (0 when the kink is a sample). Kink 1 is at m; kink 2,
        at 1 - m, is handled mirrored to m (the grid is symmetric) with A and C swapped.
        The grid lies m mod cell to the left and the rest of the cell to the right; clip
        point C lies right of m; clip point 1 - A lies s = 1 - A - m away, s mod 2 to the
        right and -s mod 2 to the left, >= 1 (never nearest) on its wrong side. First
        moments follow likewise, each triangle's at its centroid m + (dr - dl) / 3.
        """
        np.maximum.reduce(self._fire[self._level_idx], axis=0, out=self._levels)
        ac, m, near_l, near_r = self._ac, self._m, self._near_l, self._near_r
        np.minimum(ac, self._ca, out=m)                          # m, once per kink
        np.minimum(m, self._half, out=m)
        np.multiply(self._lm, self._lm, out=self._squares)
        np.multiply(self._ac2, ac, out=self._cubes)
        np.subtract(self._one, m, out=self._one_minus_m)
        np.subtract(self._one_minus_m, ac, out=self._s)         # s, with 1 - C for kink 2
        np.negative(self._s, out=self._minus_s)
        np.mod(self._clip_dist, self._two, out=self._clip_dist)  # [left, right] distances
        np.mod(m, self._cell, out=self._grid_l)
        np.subtract(self._cell, self._grid_l, out=self._grid_r)
        np.minimum(self._clip_dist, self._grid_dist, out=self._near)
        np.subtract(self._ca, m, out=self._right_clip)          # C (kink 1), A (kink 2): right of m
        np.minimum(near_r, self._right_clip, out=near_r)
        np.multiply(near_l, near_r, out=self._delta)
        np.multiply(self._delta, near_l, out=self._delta_l)
        np.multiply(self._delta, near_r, out=self._delta_r)
        np.multiply(self._delta, m, out=self._delta_m)
        area, moment = _vecdot(self._phi_flat, self._coef, axis=-2)
        y, ok = moment / area, area > _TINY
        return (np.where(ok, y, self.default) if self._nonzero_default else y), ok

    def _defuzzify(self) -> tuple[np.ndarray, np.ndarray]:
        """Levels, aggregated output set and crisp value by the general route."""
        B = len(self.default)
        ok = np.ones(B, dtype=bool)
        if self._per_rule:
            level = self._fire_br
        else:
            level = self._level_reduce(self._fire[self._perm], self._starts).reshape(B, -1)
        if self.defuzzification == 'height':
            den = np.add.reduce(level, axis=1)
            ok &= den > 0
            y = _vecdot(level, self._centre) / np.where(ok, den, 1.0)
            return np.where(ok, y, self.default), ok
        xa, fa = self._aggregate(level)
        if self.defuzzification == 'centroid':
            return self._centroid(xa.ravel(), fa.ravel(), ok)
        h = xa[:, 1:] - xa[:, :-1]
        f0, f1 = fa[:, :-1], fa[:, 1:]
        if self.defuzzification == 'mom':
            return self._mean_of_maxima(xa, fa, h, f0, f1, ok)
        return self._bisector(xa, f0, f1, 0.5 * h * (f0 + f1), ok)

    def _centroid(self, x: np.ndarray, f: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exact centroid of the piecewise-linear set, all rows at once on the flat arrays:
        per piece, area h (f0 + f1) / 2 and moment h ((x0 + x1)(f0 + f1) + x0 f0 + x1 f1) / 6;
        the pieces joining one row to the next get h = 0."""
        h = x[1:] - x[:-1]
        h *= self._piece_in_row
        f01 = f[1:] + f[:-1]
        xf = x * f
        moment = x[1:] + x[:-1]
        moment *= f01
        moment += xf[1:]
        moment += xf[:-1]
        moment *= h
        h *= f01
        total = np.add.reduceat(h, self._row_start)
        ok &= total > 0
        y = np.add.reduceat(moment, self._row_start) / (3.0 * np.where(ok, total, 1.0))
        return np.where(ok, y, self.default), ok

    def _aggregate(self, level: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Aggregated output set as sorted points (B, M) and memberships (B, M)."""
        reduce = np.maximum.reduce if self.aggregation == 'max' else np.add.reduce
        lq = level.ravel()[self._grid_unit]
        if self.implication == 'product':
            return self._x, reduce(np.multiply(lq, self._grid_mu, out=lq), axis=0)
        N = self._x.shape[1]
        reduce(np.minimum(lq, self._grid_mu, out=lq), axis=0, out=self._fa[:, :N])
        # Where each unit reaches its level on its rising and falling side; the
        # aggregated set is evaluated exactly there and merged into the grid.
        lev2 = level.ravel()[self._unit2].reshape(len(level), -1)
        p = self._xa[:, N:]
        np.add(self._p_base, lev2 * self._p_span, out=p)
        own = lev2
        if self._check_range:
            if self._gauss2 is not None:
                with np.errstate(divide='ignore'):
                    spread = self._g_sigma * np.sqrt(-2.0 * np.log(lev2))
                p[...] = np.where(self._gauss2, self._g_mean + spread, p)
            own = np.where((lev2 > 0) & (p >= self._olo) & (p <= self._ohi), lev2, 0.0)
            np.clip(p, self._olo, self._ohi, out=p)
        pp = p.ravel()[self._pair_point]
        m = np.minimum((pp - self._pa) * self._prise, (self._pd - pp) * self._pfall)
        if self._gauss2 is not None:
            m = np.where(self._pgauss, np.exp(-0.5 * ((pp - self._pmean) * self._pinv) ** 2), m)
        np.minimum(np.maximum(m, 0.0, out=m), level.ravel()[self._pair_level], out=m)
        fp = self._fa[:, N:]
        reduce(m.reshape(self._pair_shape), axis=1, out=fp)
        if self.aggregation == 'max':   # a unit is exactly at its level at its own points
            np.maximum(fp, own, out=fp)
        order = self._xa.argsort(axis=1, kind='stable')
        order += self._row
        return self._xa.ravel()[order].reshape(order.shape), self._fa.ravel()[order].reshape(order.shape)

    def _mean_of_maxima(self, xa, fa, h, f0, f1, ok):
        """Mean of the set where membership is maximal: length-weighted over flat tops,
        or the mean of the distinct points at the maximum when there is no flat top."""
        top = fa.max(axis=1)[:, None]
        flat = (f0 == top) & (f1 == top)
        length = (h * flat).sum(axis=1)
        mid = (h * flat * (xa[:, :-1] + xa[:, 1:])).sum(axis=1) * 0.5
        at = fa == top
        at[:, 1:] &= h != 0
        points = (xa * at).sum(axis=1) / at.sum(axis=1)
        ok &= top[:, 0] > 0
        y = np.where(length > 0, mid / np.where(length > 0, length, 1.0), points)
        return np.where(ok, y, self.default), ok

    def _bisector(self, xa, f0, f1, area, ok):
        """Point splitting the area of the piecewise-linear set into two equal halves."""
        cum = np.cumsum(area, axis=1)
        total = cum[:, -1]
        ok &= total > 0
        half = 0.5 * total[:, None]
        idx = np.minimum((cum < half).sum(axis=1, keepdims=True), area.shape[1] - 1)
        sub = half[:, 0] - np.take_along_axis(cum - area, idx, axis=1)[:, 0]
        x1 = np.take_along_axis(xa[:, :-1], idx, axis=1)[:, 0]
        x2 = np.take_along_axis(xa[:, 1:], idx, axis=1)[:, 0]
        y1 = np.take_along_axis(f0, idx, axis=1)[:, 0]
        y2 = np.take_along_axis(f1, idx, axis=1)[:, 0]
        # Root u of y1*u + m*u^2/2 = sub, in a form that stays accurate as m -> 0.
        m = (y2 - y1) / np.where(x2 > x1, x2 - x1, 1.0)
        with np.errstate(divide='ignore', invalid='ignore'):
            y = x1 + 2.0 * sub / (y1 + np.sqrt(np.maximum(y1 * y1 + 2.0 * m * sub, 0.0)))
        ok &= np.isfinite(y)
        return np.where(ok, y, self.default), ok

"""The same fuzzy system built in scikit-fuzzy and simpful, for cross-checks and benchmarks.

Both libraries are test/bench dependencies only, imported when these functions run.
scikit-fuzzy fuzzifies by interpolating sampled input sets, so each input universe is
`input_points` even samples plus every breakpoint of its triangular and trapezoidal
sets (on which linear interpolation is then exact) and the mean of each Gaussian set;
with Gaussian sets the samples are dense enough that the interpolation error
h^2 / (8 sigma^2) stays below `GAUSSIAN_TOL`. Its output universe is the system's own grid.
"""
from __future__ import annotations

import math

import numpy as np

from uav_vs.control.fuzzy import FuzzySystem, Variable, membership, universe


GAUSSIAN_TOL = 1e-9       # bound on scikit-fuzzy's interpolation error of a Gaussian input set


def input_universe(var: Variable, points: int | None = None) -> np.ndarray:
    """Samples of an input range for scikit-fuzzy: `points` even ones (default 2001, more
    with Gaussian sets, see the module docstring) plus the sets' breakpoints and means."""
    sigmas = [p[1] for p in var.sets.values() if len(p) == 2]
    if points is None:
        points = 2001
        if sigmas:       # |mu''| <= 1 / sigma^2, so h = sigma sqrt(8 tol) bounds the error by tol
            step = min(sigmas) * math.sqrt(8 * GAUSSIAN_TOL)
            points = max(points, math.ceil((var.hi - var.lo) / step) + 1)
    return universe(var, points)


def to_skfuzzy(system: FuzzySystem, input_points: int | None = None):
    """ControlSystemSimulation equivalent to `system` (min implication, max aggregation only);
    `input_points`: even samples per input universe (see `input_universe`)."""
    from skfuzzy import control as ctrl
    if system.implication != 'min' or system.aggregation != 'max':
        raise ValueError('scikit-fuzzy only implements min implication with max aggregation')
    if system.defuzzification == 'height':
        raise ValueError('scikit-fuzzy has no height defuzzification')
    antecedents = []
    for v in system.inputs:
        universe = input_universe(v, input_points)
        a = ctrl.Antecedent(universe, v.name)
        for name, p in v.sets.items():
            a[name] = membership(universe, p)
        antecedents.append(a)
    out = ctrl.Consequent(system.universe, system.output.name,
                          defuzzify_method=system.defuzzification)
    for name, p in system.output.sets.items():
        out[name] = membership(system.universe, p)
    out_names = list(system.output.sets)
    and_func = np.fmin if system.and_op == 'min' else np.multiply
    rules = []
    for rule in system.rules:
        terms = [antecedents[i][list(system.inputs[i].sets)[j]] for i, j in rule.antecedent]
        ante = terms[0]
        for term in terms[1:]:
            ante = ante & term
        consequent = out[out_names[rule.consequent]]
        if rule.weight != 1.0:
            consequent = consequent % rule.weight
        rules.append(ctrl.Rule(ante, consequent, and_func=and_func))
    return ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules), cache=False)


def skfuzzy_evaluate(sim, system: FuzzySystem, x) -> float:
    """Run a scikit-fuzzy simulation on one input vector (in `system.inputs` order)."""
    for v, value in zip(system.inputs, x):
        sim.input[v.name] = float(value)
    sim.compute()
    return float(sim.output[system.output.name])


def skfuzzy_evaluate_many(sim, system: FuzzySystem, x: np.ndarray) -> np.ndarray:
    """Run a scikit-fuzzy simulation on many input vectors (rows of x) in one call, with
    its array inputs: the same computation as one `skfuzzy_evaluate` per row (its rules
    run on arrays, its defuzzification row by row), tens of times faster. Use a simulation
    built for this (one that has only seen array inputs)."""
    x = np.asarray(x, dtype=float)
    for v, column in zip(system.inputs, x.T):
        sim.input[v.name] = np.ascontiguousarray(column)
    sim.compute()
    return np.asarray(sim.output[system.output.name], dtype=float).reshape(len(x))


def to_simpful(system: FuzzySystem):
    """simpful FuzzySystem with the same sets and rules (its own output discretisation)."""
    import simpful as sf

    def fuzzy_set(name, p):
        if len(p) == 2:
            return sf.FuzzySet(function=sf.Gaussian_MF(p[0], p[1]), term=name)
        if len(p) == 3:
            return sf.FuzzySet(function=sf.Triangular_MF(*p), term=name)
        return sf.FuzzySet(function=sf.Trapezoidal_MF(*p), term=name)

    fs = sf.FuzzySystem(show_banner=False, operators=['AND_PRODUCT'] if system.and_op == 'product' else None)
    for v in [*system.inputs, system.output]:
        sets = [fuzzy_set(name, p) for name, p in v.sets.items()]
        fs.add_linguistic_variable(v.name, sf.LinguisticVariable(sets, universe_of_discourse=[v.lo, v.hi]))
    out_names, rules = list(system.output.sets), []
    for rule in system.rules:
        ante = ' AND '.join(f'({system.inputs[i].name} IS {list(system.inputs[i].sets)[j]})'
                            for i, j in rule.antecedent)
        text = f'IF {ante} THEN ({system.output.name} IS {out_names[rule.consequent]})'
        rules.append(text + (f' WEIGHT {rule.weight}' if rule.weight != 1.0 else ''))
    fs.add_rules(rules)
    return fs


def simpful_evaluate(fs, system: FuzzySystem, x, subdivisions: int = 1000) -> float:
    """Run a simpful system on one input vector (in `system.inputs` order)."""
    for v, value in zip(system.inputs, x):
        fs.set_variable(v.name, float(value), verbose=False)
    name = system.output.name
    return float(fs.Mamdani_inference([name], subdivisions=subdivisions, ignore_warnings=True)[name])

"""Mamdani engine: equivalence with scikit-fuzzy, analytic membership and defuzzification
checks, brute-force integration for the operators scikit-fuzzy lacks, and error handling."""
import warnings

import numpy as np
import pytest

from uav_vs.control.fuzzy import FuzzyBank, FuzzySystem, gaussian, partition, trapezoid, triangle
from uav_vs.control.fuzzy_reference import skfuzzy_evaluate, to_skfuzzy

E7 = ['NB', 'NM', 'NS', 'ZE', 'PS', 'PM', 'PB']
R5 = ['NB', 'NS', 'ZE', 'PS', 'PB']


def pd_config(**ops):
    rules = [f'IF error IS {e} AND rate IS {r} THEN command IS {E7[min(6, max(0, i + j - 2))]}'
             for i, e in enumerate(E7) for j, r in enumerate(R5)]
    return {'inputs': {'error': {'sets': E7, 'apexes': [-1, -0.5, -0.2, 0, 0.2, 0.5, 1]},
                       'rate': {'sets': R5, 'apexes': [-1, -0.35, 0, 0.35, 1]}},
            'output': {'command': {'sets': E7, 'apexes': [-1, -0.6, -0.3, 0, 0.3, 0.6, 1]}},
            'rules': rules, 'resolution': 101, **ops}


def input_grid(n):
    """n x n inputs over and beyond both ranges (inputs saturate at the range ends)."""
    g = np.linspace(-1.2, 1.2, n)
    return np.array([(a, b) for a in g for b in g])


def engine_and_reference(cfg, inputs):
    system = FuzzySystem.from_config(cfg)
    y, ok = FuzzyBank([system] * len(inputs)).evaluate(inputs)
    sim = to_skfuzzy(system)
    with warnings.catch_warnings():      # scikit-fuzzy's own numpy deprecation warnings
        warnings.simplefilter('ignore', DeprecationWarning)
        ref = np.array([skfuzzy_evaluate(sim, system, x) for x in inputs])
    return system, y, ok, ref


# scikit-fuzzy takes ~40 ms per evaluation of this 35-rule system here, so the grids are
# 21 x 21 (441 points) and 11 x 11 to keep the file well under a minute.
@pytest.mark.parametrize('ops,n', [({'and': 'min'}, 21), ({'and': 'product'}, 11)])
def test_centroid_equals_skfuzzy_on_dense_grid(ops, n):
    cfg = pd_config(**ops)
    cfg['rules'][17] += ' WITH 0.6'          # (ZE, ZE) -> ZE, weighted
    _, y, ok, ref = engine_and_reference(cfg, input_grid(n))
    assert ok.all()
    assert np.abs(y - ref).max() < 1e-6


def brute_force(system, x, points=200001, what='centroid'):
    """Independent Mamdani on a very fine grid, straight from the definitions."""
    u = np.linspace(system.output.lo, system.output.hi, points)
    xs = [np.clip(v, var.lo, var.hi) for v, var in zip(x, system.inputs)]
    mus = [{n: float(triangle(v, *p) if len(p) == 3 else trapezoid(v, *p) if len(p) == 4 else gaussian(v, *p))
            for n, p in var.sets.items()} for v, var in zip(xs, system.inputs)]
    out_sets = list(system.output.sets.values())
    agg = np.zeros_like(u)
    for r in system.rules:
        vals = [list(mus[i].values())[j] for i, j in r.antecedent]
        fire = (min(vals) if system.and_op == 'min' else np.prod(vals)) * r.weight
        p = out_sets[r.consequent]
        shape = gaussian(u, *p) if len(p) == 2 else trapezoid(u, *(p if len(p) == 4 else (p[0], p[1], p[1], p[2])))
        shaped = np.minimum(fire, shape) if system.implication == 'min' else fire * shape
        agg = np.maximum(agg, shaped) if system.aggregation == 'max' else agg + shaped
    if what == 'bisector':
        cum = np.concatenate([[0], np.cumsum(0.5 * (agg[1:] + agg[:-1]) * np.diff(u))])
        return float(np.interp(cum[-1] / 2, cum, u))
    return float(np.trapezoid(u * agg, u) / np.trapezoid(agg, u))


def test_bisector_matches_skfuzzy_and_brute_force():
    inputs = input_grid(11)
    system, y, ok, ref = engine_and_reference(pd_config(defuzzification='bisector', resolution=1001), inputs)
    agree = np.abs(y - ref) < 1e-6
    # scikit-fuzzy's bisector loses accuracy on nearly flat pieces (it solves a quadratic
    # whose leading coefficient vanishes); where it disagrees, brute force decides.
    assert agree.mean() > 0.9
    for k in np.flatnonzero(~agree):
        assert abs(y[k] - brute_force(system, inputs[k], what='bisector')) < 2e-5


@pytest.mark.parametrize('ops,tol', [
    ({'implication': 'product', 'aggregation': 'max', 'resolution': 1001}, 2e-5),
    ({'implication': 'min', 'aggregation': 'sum'}, 1e-6),
    ({'implication': 'product', 'aggregation': 'sum'}, 1e-6),
])
def test_other_operators_match_brute_force(ops, tol):
    system = FuzzySystem.from_config(pd_config(**ops))
    rng = np.random.default_rng(4)
    for x in rng.uniform(-1.1, 1.1, (40, 2)):
        y, ok = system.evaluate(x)
        assert ok and abs(y - brute_force(system, x)) < tol


def test_gaussian_output_sets_match_brute_force():
    cfg = pd_config()
    cfg['output'] = {'command': {'range': [-1, 1], 'mf': {n: [c, 0.15] for n, c in
                                                           zip(E7, [-0.9, -0.6, -0.3, 0, 0.3, 0.6, 0.9])}}}
    cfg['resolution'] = 2001
    system = FuzzySystem.from_config(cfg)
    for x in np.random.default_rng(5).uniform(-1, 1, (20, 2)):
        assert abs(system.evaluate(x)[0] - brute_force(system, x)) < 1e-5


def test_mean_of_maxima_and_height_analytic():
    # error 0.1 is half ZE, half PS; rate 0 is ZE: rules (ZE,ZE)->ZE and (PS,ZE)->PS fire
    # at 0.5. Both clipped sets form one plateau at 0.5 from -0.15 (ZE rising) to 0.45
    # (PS falling): mean of maxima 0.15; height: (0 * 0.5 + 0.3 * 0.5) / 1 = 0.15.
    for method in ('mom', 'height'):
        y, ok = FuzzySystem.from_config(pd_config(defuzzification=method)).evaluate([0.1, 0.0])
        assert ok and y == pytest.approx(0.15, abs=1e-12)
    # A single unclipped triangle: its apex.
    y, _ = FuzzySystem.from_config(pd_config(defuzzification='mom')).evaluate([0.2, 0.0])
    assert y == pytest.approx(0.3, abs=1e-12)


def test_membership_shapes():
    x = np.array([-1.0, 0.0, 0.5, 1.0, 1.5, 2.0, 3.0])
    assert triangle(x, 0, 1, 2).tolist() == [0, 0, 0.5, 1, 0.5, 0, 0]
    assert trapezoid(x, 0, 1, 2, 3).tolist() == [0, 0, 0.5, 1, 1, 1, 0]
    assert trapezoid(x, 0, 0, 1, 2).tolist() == [0, 1, 1, 1, 0.5, 0, 0]      # vertical left edge
    assert gaussian(np.array([1.0, 1.5]), 1.0, 0.5) == pytest.approx([1.0, np.exp(-0.5)])


def test_partition_sums_to_one_with_dense_apexes_and_shoulders():
    apexes = [-0.8, -0.3, -0.08, 0.0, 0.08, 0.3, 0.8]
    sets = partition(E7, apexes, lo=-1.0, hi=1.0)
    x = np.linspace(-1, 1, 20001)
    mu = np.array([trapezoid(x, *p) if len(p) == 4 else triangle(x, *p) for p in sets.values()])
    assert np.abs(mu.sum(axis=0) - 1).max() < 1e-12
    assert mu[0, 0] == 1 and mu[-1, -1] == 1                # shoulders reach the range ends
    for p, a in zip(sets.values(), apexes):                 # each set peaks at its apex
        assert (trapezoid(a, *p) if len(p) == 4 else triangle(a, *p)) == 1.0


def test_non_finite_inputs_give_the_default_and_a_flag():
    bank = FuzzyBank([FuzzySystem.from_config(pd_config(default=0.0))] * 5)
    x = np.array([[np.nan, 0.1], [0.3, np.inf], [-np.inf, 0], [0.5, 0.2], [1e300, -1e300]])
    y, ok = bank.evaluate(x)
    assert np.isfinite(y).all()
    assert ok.tolist() == [False, False, False, True, True]
    assert y[:3].tolist() == [0.0, 0.0, 0.0] and y[3] > 0


@pytest.mark.parametrize('rule,named', [
    ('IF error IS NX AND rate IS ZE THEN command IS ZE', "'NX'"),
    ('IF eror IS NB THEN command IS ZE', "'eror'"),
    ('IF error IS NB THEN speed IS ZE', "'speed'"),
    ('IF error IS NB THEN command IS QQ', "'QQ'"),
    ('IF error NB THEN command IS ZE', "'error NB'"),
    ('error IS NB THEN command IS ZE', 'expected'),
    ('IF error IS NB THEN command IS ZE WITH 2', 'weight'),
])
def test_bad_rules_fail_with_one_line_naming_the_fault(rule, named):
    cfg = pd_config()
    cfg['rules'] = cfg['rules'][:3] + [rule]
    with pytest.raises(ValueError) as err:
        FuzzySystem.from_config(cfg)
    msg = str(err.value)
    assert '\n' not in msg and named in msg and 'rule 3' in msg


@pytest.mark.parametrize('key,value', [('and', 'max'), ('implication', 'lukasiewicz'),
                                       ('aggregation', 'min'), ('defuzzification', 'lom')])
def test_bad_operator_names_fail(key, value):
    with pytest.raises(ValueError, match=f'{key}.*{value}'):
        FuzzySystem.from_config(pd_config(**{key: value}))

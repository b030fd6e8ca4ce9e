"""Mamdani engine: equivalence with scikit-fuzzy, analytic membership and defuzzification
checks, brute-force integration for the operators scikit-fuzzy lacks, and error handling."""
import copy
import warnings
from pathlib import Path

import numpy as np
import pytest

from uav_vs.control.controllers import PoseController, TrackingController, load_config
from uav_vs.control.fuzzy import (FuzzyBank, FuzzySystem, _einsum_vecdot, gaussian, partition,
                                  trapezoid, triangle)
from uav_vs.control.fuzzy_reference import skfuzzy_evaluate, skfuzzy_evaluate_many, to_skfuzzy

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'fuzzy_controller.yaml'

E7 = ['NB', 'NM', 'NS', 'ZE', 'PS', 'PM', 'PB']
R5 = ['NB', 'NS', 'ZE', 'PS', 'PB']


def pd_config(**ops):
    rules = [f'IF error IS {e} AND rate IS {r} THEN command IS {E7[min(6, max(0, i + j - 2))]}'
             for i, e in enumerate(E7) for j, r in enumerate(R5)]
    return {'inputs': {'error': {'sets': E7, 'apexes': [-1, -0.5, -0.2, 0, 0.2, 0.5, 1]},
                       'rate': {'sets': R5, 'apexes': [-1, -0.35, 0, 0.35, 1]}},
            'output': {'command': {'sets': E7, 'apexes': [-1, -0.6, -0.3, 0, 0.3, 0.6, 1]}},
            'rules': rules, 'resolution': 101, **ops}


def input_grid(n, dims=2):
    """n ** dims inputs over and beyond every range (inputs saturate at the range ends)."""
    g = np.linspace(-1.2, 1.2, n)
    return np.stack(np.meshgrid(*[g] * dims, indexing='ij'), axis=-1).reshape(-1, dims)


def skfuzzy_outputs(system, inputs):
    """scikit-fuzzy's ControlSystemSimulation on every row of inputs (one array-input run)."""
    with warnings.catch_warnings():      # scikit-fuzzy's own numpy deprecation warnings
        warnings.simplefilter('ignore', DeprecationWarning)
        return skfuzzy_evaluate_many(to_skfuzzy(system), system, inputs)


def engine_and_reference(cfg, inputs):
    system = FuzzySystem.from_config(cfg)
    y, ok = FuzzyBank([system] * len(inputs)).evaluate(inputs)
    return system, y, ok, skfuzzy_outputs(system, inputs)


def config_systems():
    """The distinct fuzzy systems of config/fuzzy_controller.yaml (the x, y, z, yaw and
    tracking axes) and of its PID-like layer config/fuzzy_controller_pid.yaml (z)."""
    cfg = load_config(CONFIG)
    pid = copy.deepcopy(cfg)
    pid['axes']['z'].update(load_config(CONFIG.with_name('fuzzy_controller_pid.yaml'))['axes']['z'])
    axes = [*PoseController.from_config(cfg).axes, *TrackingController.from_config(cfg).axes,
            PoseController.from_config(pid).axes[2]]
    distinct = {}
    for axis in axes:
        s = axis.system
        key = repr(([(v.name, v.lo, v.hi, v.sets) for v in [*s.inputs, s.output]], s.rules))
        distinct.setdefault(key, s)
    return list(distinct.values())


def gaussian_inputs_config(**ops):
    """Gaussian input sets between trapezoid shoulders (one vertical at the range end, one
    whose top runs past it) and a Gaussian centred on a range end; output partition."""
    cfg = pd_config(**ops)
    cfg['inputs']['error'] = {'range': [-1, 1], 'mf': {
        'NB': [-1.0, -1.0, -0.75, -0.4], 'NM': [-0.5, 0.15], 'NS': [-0.2, 0.1], 'ZE': [0.0, 0.08],
        'PS': [0.2, 0.1], 'PM': [0.5, 0.15], 'PB': [0.4, 0.75, 1.0, 1.0]}}
    cfg['inputs']['rate'] = {'range': [-1, 1], 'mf': {
        'NB': [-1.0, 0.3], 'NS': [-0.35, 0.2], 'ZE': [0.0, 0.15], 'PS': [0.35, 0.2],
        'PB': [0.6, 0.85, 1.2, 1.4]}}
    cfg['rules'][17] += ' WITH 0.6'          # (ZE, ZE) -> ZE, weighted
    return cfg


# scikit-fuzzy takes ~40-70 ms per scalar evaluation of a 35-rule system here, but its
# array inputs run a 41 x 41 grid in about a second with the same arithmetic
# (test_skfuzzy_array_inputs_equal_scalar_runs), so the grids are 41 x 41 (1681 points,
# step 0.06 over and beyond [-1, 1]) and 13 x 13 x 13 for the 45-rule PID-like system.
@pytest.mark.parametrize('system', config_systems(),
                         ids=lambda s: f'config-{len(s.inputs)}in-{len(s.rules)}rules')
def test_config_systems_equal_skfuzzy_on_dense_grid(system):
    inputs = input_grid(41) if len(system.inputs) == 2 else input_grid(13, 3)
    y, ok = FuzzyBank([system] * len(inputs)).evaluate(inputs)
    assert ok.all()
    assert np.abs(y - skfuzzy_outputs(system, inputs)).max() < 1e-6


@pytest.mark.parametrize('ops', [{'and': 'min'}, {'and': 'product'}], ids=['min', 'product'])
def test_centroid_equals_skfuzzy_on_dense_grid(ops):
    cfg = pd_config(**ops)
    cfg['rules'][17] += ' WITH 0.6'          # (ZE, ZE) -> ZE, weighted
    _, y, ok, ref = engine_and_reference(cfg, input_grid(41))
    assert ok.all()
    assert np.abs(y - ref).max() < 1e-6


@pytest.mark.parametrize('ops', [{'and': 'min'}, {'and': 'product'}], ids=['min', 'product'])
def test_gaussian_input_sets_equal_skfuzzy(ops):
    # The grid plus random points: the grid's inputs lie on scikit-fuzzy's even input
    # samples, random ones between them, where its interpolated Gaussians differ from
    # the exact ones unless the samples are dense (fuzzy_reference.input_universe).
    inputs = np.vstack([input_grid(41), np.random.default_rng(9).uniform(-1.1, 1.1, (400, 2))])
    system, y, ok, ref = engine_and_reference(gaussian_inputs_config(**ops), inputs)
    assert not FuzzyBank([system]).linear_firing          # the general fuzzification path
    assert ok.all()
    assert np.abs(y - ref).max() < 1e-6


def test_skfuzzy_array_inputs_equal_scalar_runs():
    # The reference's one-call array run is scikit-fuzzy's own scalar computation.
    system = FuzzySystem.from_config(gaussian_inputs_config())
    x = np.random.default_rng(10).uniform(-1.1, 1.1, (6, 2))
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', DeprecationWarning)
        sim = to_skfuzzy(system)
        scalar = [skfuzzy_evaluate(sim, system, xi) for xi in x]
    assert skfuzzy_outputs(system, x).tolist() == scalar


def trapezoid_rule(y, u):
    """Integral of samples y at points u, linear in between."""
    return np.sum(0.5 * (y[1:] + y[:-1]) * np.diff(u))


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
    return float(trapezoid_rule(u * agg, u) / trapezoid_rule(agg, u))


def test_bisector_matches_skfuzzy_and_brute_force():
    inputs = input_grid(41)
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


@pytest.mark.parametrize('shapes, axis', [(((138, 4), (2, 138, 4)), -2), (((4, 7), (7,)), -1)])
def test_numpy1_vecdot_is_the_sum_of_products(shapes, axis):
    rng = np.random.default_rng(3)
    x1, x2 = (rng.normal(size=s) for s in shapes)
    expected = np.sum(x1 * x2, axis=axis)
    assert np.allclose(_einsum_vecdot(x1, x2, axis=axis), expected, rtol=1e-12, atol=1e-12)


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


@pytest.mark.parametrize('specialise', [True, False])
def test_non_finite_inputs_give_the_default_and_a_flag(specialise):
    bank = FuzzyBank([FuzzySystem.from_config(pd_config(default=0.0))] * 6, specialise=specialise)
    x = np.array([[np.nan, 0.1], [0.3, np.inf], [-np.inf, 0], [0.5, 0.2], [1e300, -1e300], [1e308, 1e308]])
    with warnings.catch_warnings():
        warnings.simplefilter('error')              # no overflow or invalid-value warnings either
        y, ok = bank.evaluate(x)
    assert np.isfinite(y).all()
    assert ok.tolist() == [False, False, False, True, True, True]
    assert y[:3].tolist() == [0.0, 0.0, 0.0] and y[3] > 0
    assert y[5] == pytest.approx(FuzzySystem.from_config(pd_config()).evaluate([1, 1])[0], abs=1e-12)


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


def pid_config():
    """Three inputs, 45 rules (error x rate x integral), the shape of the PID-like axes."""
    e5, r3 = ['NB', 'NS', 'ZE', 'PS', 'PB'], ['N', 'ZE', 'P']
    rules = [f'IF error IS {e} AND rate IS {r} AND integral IS {i} '
             f'THEN command IS {E7[min(6, max(0, 3 + a + b + c))]}'
             for a, e in zip(range(-2, 3), e5) for b, r in zip(range(-1, 2), r3)
             for c, i in zip(range(-1, 2), r3)]
    return {'inputs': {'error': {'sets': e5, 'apexes': [-1, -0.2, 0, 0.2, 1]},
                       'rate': {'sets': r3, 'apexes': [-1, 0, 1]},
                       'integral': {'sets': r3, 'apexes': [-1, 0, 1]}},
            'output': {'command': {'sets': E7, 'apexes': [-1, -0.6, -0.3, 0, 0.3, 0.6, 1]}},
            'rules': rules, 'resolution': 101}


def shortcut_cases():
    """(name, config, linear firing expected, closed form expected)."""
    weighted = pd_config()
    weighted['rules'][17] += ' WITH 0.6'
    weighted['rules'][3] += ' WITH 0.3'
    plateaus = pd_config(resolution=116)                # output step 0.02 over [-1.2, 1.1]
    plateaus['output']['command']['range'] = [-1.2, 1.1]
    plateaus['inputs']['error']['range'] = [-1.5, 1.5]
    uneven = pd_config()                                # 21, 12, 18, 14, 16, 19 grid cells
    uneven['output']['command']['apexes'] = [-1, -0.58, -0.34, 0.02, 0.3, 0.62, 1]
    off_grid = pd_config()
    off_grid['output']['command']['apexes'] = [-1, -0.55, -0.33, 0.01, 0.3, 0.6, 1]
    sparse = pd_config()
    sparse['rules'] = [r.split(' AND ')[0] + ' THEN' + r.split(' THEN')[1] for r in sparse['rules'][::5]] \
        + sparse['rules'][1::4]
    beyond = pd_config()
    beyond['inputs']['error'] = {'range': [-1, 1], 'mf': {n: [c - 0.3, c, c + 0.3]
                                                          for n, c in zip(E7, np.linspace(-0.9, 0.9, 7))}}
    return [('pd', pd_config(), True, True), ('weighted', weighted, True, True),
            ('product and', pd_config(**{'and': 'product'}), False, True),
            ('shoulder plateaus', plateaus, True, True), ('uneven cells', uneven, True, True),
            ('sparse, one-antecedent rules', sparse, True, True),
            ('input sets across the range', beyond, False, True),
            ('apexes off the grid', off_grid, True, False),
            ('bisector', pd_config(defuzzification='bisector'), True, False),
            ('height', pd_config(defuzzification='height'), True, False),
            ('sum aggregation', pd_config(aggregation='sum'), True, False),
            ('product implication', pd_config(implication='product'), True, False)]


@pytest.mark.parametrize('name,cfg,linear,closed', shortcut_cases(), ids=[c[0] for c in shortcut_cases()])
def test_shortcuts_give_the_general_result(name, cfg, linear, closed):
    # A dense grid, random points, and every pair of input apexes and midpoints between
    # them (exact ties between memberships and between levels).
    special = [sorted({*a, *((p + q) / 2 for p, q in zip(a, a[1:])), -1.5, 1.5})
               for a in ([-1, -0.5, -0.2, 0, 0.2, 0.5, 1], [-1, -0.35, 0, 0.35, 1])]
    x = np.vstack([input_grid(31), np.random.default_rng(6).uniform(-1.3, 1.3, (400, 2)),
                   [(a, b) for a in special[0] for b in special[1]]])
    system = FuzzySystem.from_config(cfg)
    fast = FuzzyBank([system] * len(x))
    assert (fast.linear_firing, fast.closed_form) == (linear, closed)
    general = FuzzyBank([system] * len(x), specialise=False)
    assert not general.linear_firing and not general.closed_form
    (y, ok), (y_ref, ok_ref) = fast.evaluate(x), general.evaluate(x)
    assert (ok == ok_ref).all()
    assert np.abs(y - y_ref).max() < 1e-12


def test_shortcuts_in_a_bank_of_different_systems():
    three = pd_config(resolution=51)
    three['output']['command'] = {'sets': ['N', 'Z', 'P'], 'apexes': [-1, 0, 1]}
    three['rules'] = [f'IF error IS {e} THEN command IS {"NZP"[min(2, i // 2)]}' for i, e in enumerate(E7)]
    systems = [FuzzySystem.from_config(c) for c in (pid_config(), pd_config(), three)] * 300
    x = np.random.default_rng(7).uniform(-1.3, 1.3, (len(systems), 3))
    fast, general = FuzzyBank(systems), FuzzyBank(systems, specialise=False)
    assert fast.linear_firing and fast.closed_form
    (y, ok), (y_ref, ok_ref) = fast.evaluate(x), general.evaluate(x)
    assert (ok == ok_ref).all() and np.abs(y - y_ref).max() < 1e-12


def levels_config(apexes, resolution=101, output_range=None):
    """Seven inputs in [0, 1], rule k: input k drives output set k, so an input vector
    sets the seven output levels directly."""
    out = {'sets': E7, 'apexes': apexes, **({'range': output_range} if output_range else {})}
    return {'inputs': {f'in{k}': {'range': [0, 1], 'mf': {'HI': [0, 1, 1]}} for k in range(7)},
            'output': {'command': out},
            'rules': [f'IF in{k} IS HI THEN command IS {E7[k]}' for k in range(7)],
            'resolution': resolution}


@pytest.mark.parametrize('apexes,resolution,output_range', [
    ([-1, -0.6, -0.3, 0, 0.3, 0.6, 1], 101, None),
    ([-1, -0.58, -0.34, 0.02, 0.3, 0.62, 1], 101, None),       # uneven cells, odd and even
    ([-1, -0.6, -0.3, 0, 0.3, 0.6, 1], 116, [-1.2, 1.1]),      # shoulder plateaus
    ([-1, -0.9, -0.3, 0, 0.1, 0.6, 1], 21, None),              # one- and two-cell intervals
])
def test_closed_form_centroid_over_all_level_patterns(apexes, resolution, output_range):
    # Random levels, levels from a small set (ties, 1/2, 0, 1, clip points on grid points,
    # clip points sharing a cell with the kink) and sparse ones, against the general route
    # everywhere and against scikit-fuzzy on a sample.
    system = FuzzySystem.from_config(levels_config(apexes, resolution, output_range))
    rng = np.random.default_rng(8)
    values = np.array([0, 0.5, 1, 0.25, 0.75, 1 / 3, 2 / 3, 0.2, 0.8, 0.4, 0.6, 0.1, 0.9, 0.45, 0.55, 0.05])
    levels = np.vstack([rng.uniform(0, 1, (500, 7)), rng.choice(values, (1000, 7)),
                        np.where(rng.uniform(size=(500, 7)) < 0.6, 0, rng.choice(values, (500, 7))),
                        rng.integers(0, 21, (500, 7)) / 20, np.zeros((1, 7))])
    fast, general = FuzzyBank([system] * len(levels)), FuzzyBank([system] * len(levels), specialise=False)
    assert fast.linear_firing and fast.closed_form
    (y, ok), (y_ref, ok_ref) = fast.evaluate(levels), general.evaluate(levels)
    assert (ok == ok_ref).all() and not ok[-1] and y[-1] == 0.0
    assert np.abs(y - y_ref).max() < 1e-12
    sample = rng.choice(np.flatnonzero(ok), 300, replace=False)
    assert np.abs(y[sample] - skfuzzy_outputs(system, levels[sample])).max() < 1e-6


def test_general_centroid_equals_skfuzzy_for_overlapping_trapezoids():
    cfg = pd_config()
    cfg['output']['command'] = {'range': [-1, 1], 'mf': {
        'NB': [-1, -1, -0.8, -0.4], 'NM': [-0.9, -0.55, -0.25], 'NS': [-0.5, -0.3, -0.2, 0.05],
        'ZE': [-0.25, 0, 0.25], 'PS': [-0.05, 0.2, 0.3, 0.5], 'PM': [0.25, 0.55, 0.9],
        'PB': [0.4, 0.8, 1, 1]}}
    cfg['rules'][17] += ' WITH 0.6'
    system, y, ok, ref = engine_and_reference(cfg, input_grid(41))
    assert not FuzzyBank([system]).closed_form
    assert ok.all() and np.abs(y - ref).max() < 1e-6

"""Fuzzy control step: the 4-axis PoseController (config/fuzzy_controller.yaml, centroid)
next to scikit-fuzzy's ControlSystemSimulation and simpful on the same rule bases, and the
engine's exact shortcuts (linear firing, closed-form centroid) next to its general route."""
import warnings
from pathlib import Path

import numpy as np

from bench.common import report, timeit
from uav_vs.control.controllers import PoseController, load_config
from uav_vs.control.fuzzy import FuzzyBank
from uav_vs.control.fuzzy_reference import simpful_evaluate, skfuzzy_evaluate, to_simpful, to_skfuzzy

CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'fuzzy_controller.yaml'


def main() -> None:
    ctl = PoseController.from_config(load_config(CONFIG))
    systems = [a.system for a in ctl.axes]
    rng = np.random.default_rng(0)
    errors = rng.uniform(-2.5, 2.5, (64, 4))
    inputs = np.clip(rng.uniform(-1.2, 1.2, (64, 4, 2)), -1, 1)
    k = iter(range(10 ** 9))

    def ours():
        ctl.step(errors[next(k) % 64], 0.02)

    def engine():
        ctl.bank.evaluate(inputs[next(k) % 64])

    general = FuzzyBank(systems, specialise=False)

    def engine_general():
        general.evaluate(inputs[next(k) % 64])

    sims = [to_skfuzzy(s) for s in systems]
    fss = [to_simpful(s) for s in systems]

    def skfuzzy_step():
        x = inputs[next(k) % 64]
        for sim, s, xi in zip(sims, systems, x):
            skfuzzy_evaluate(sim, s, xi)

    def simpful_step():
        x = inputs[next(k) % 64]
        for fs, s, xi in zip(fss, systems, x):
            simpful_evaluate(fs, s, xi)

    x = inputs[0]
    y, _ = ctl.bank.evaluate(x)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', DeprecationWarning)
        sk = np.array([skfuzzy_evaluate(sim, s, xi) for sim, s, xi in zip(sims, systems, x)])
        ms = timeit(ours, repeat=2000, warmup=50)
        eng = timeit(engine, repeat=2000, warmup=50)
        gen = timeit(engine_general, repeat=2000, warmup=50)
        ref = timeit(skfuzzy_step, repeat=20, warmup=2)
    sp = np.array([simpful_evaluate(fs, s, xi) for fs, s, xi in zip(fss, systems, x)])
    ref_sp = timeit(simpful_step, repeat=20, warmup=2)
    report('fuzzy', 'fuzzy/step_4axis', ms, 'scikit-fuzzy ControlSystemSimulation x4', ref,
           speedup=round(float(np.median(ref) / np.median(ms)), 1),
           max_abs_diff_vs_skfuzzy=float(np.abs(y - sk).max()))
    report('fuzzy', 'fuzzy/engine_4axis', eng, 'simpful Mamdani x4', ref_sp,
           speedup=round(float(np.median(ref_sp) / np.median(eng)), 1),
           max_abs_diff_vs_simpful=round(float(np.abs(y - sp).max()), 4))
    y_all, y_general = (np.array([b.evaluate(x)[0] for x in inputs]) for b in (ctl.bank, general))
    report('fuzzy', 'fuzzy/engine_4axis_general', gen, 'shortcuts (linear firing, closed form)', eng,
           shortcuts=bool(ctl.bank.linear_firing and ctl.bank.closed_form),
           max_abs_diff_vs_shortcuts=float(np.abs(y_all - y_general).max()))

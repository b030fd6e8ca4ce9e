"""The simulated world's slow random quantities have the statistics they are said to
have (uav_vs.sim.random_processes), whatever the step they are sampled at."""
import numpy as np
import pytest

from uav_vs.sim.camera_effects import Exposure
from uav_vs.sim.random_processes import OrnsteinUhlenbeck, RandomWalk


@pytest.mark.parametrize('dt', [0.02, 0.2])
def test_ornstein_uhlenbeck_has_the_stated_spread_and_time_constant(dt):
    sigma, tau = np.array([0.1, 5.0, 0.0]), 2.0
    process = OrnsteinUhlenbeck(sigma, tau, np.random.default_rng(8))
    states = np.array([process.step(dt).copy() for _ in range(int(4000 / dt))])   # 2000 tau
    np.testing.assert_allclose(states.std(axis=0)[:2], sigma[:2], rtol=0.1)
    assert np.all(states[:, 2] == 0.0)                       # sigma 0: stays still
    assert np.all(np.abs(states.mean(axis=0)[:2]) < 0.15 * sigma[:2])
    lag = int(round(tau / dt))                               # one time constant later
    corr = [np.corrcoef(states[:-lag, i], states[lag:, i])[0, 1] for i in range(2)]
    np.testing.assert_allclose(corr, np.exp(-1.0), atol=0.06)


def test_exposure_drifts_as_its_ornstein_uhlenbeck_process():
    exposure = Exposure(0.1, 5.0, 2.0, np.random.default_rng(8))
    exposure.step(0.1)
    assert exposure.gain == 1.0 + exposure.drift.state[0]
    assert exposure.offset == exposure.drift.state[1]
    np.testing.assert_allclose(exposure.drift.sigma, [0.1, 5.0])


@pytest.mark.parametrize('dt', [0.02, 0.5])
def test_random_walk_spreads_as_the_square_root_of_time(dt):
    rate, horizon, runs = 0.01, 20.0, 400
    rng = np.random.default_rng(7)
    finals = []
    for _ in range(runs):
        walk = RandomWalk(rate, 3, rng)
        for _ in range(int(horizon / dt)):
            walk.step(dt)
        finals.append(walk.state)
    spread = np.array(finals).std(axis=0)
    # the sample std of 400 normals is within 10 % of the truth with overwhelming odds
    np.testing.assert_allclose(spread, rate * np.sqrt(horizon), rtol=0.12)

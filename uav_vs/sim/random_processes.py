"""Slowly drifting random quantities of the simulated world: wind gusts, an estimate's
drift, exposure that hunts. Each is stepped by the interval since its last step, so
its statistics do not depend on the rate it is sampled at."""
import numpy as np


class OrnsteinUhlenbeck:
    """A zero-mean Ornstein-Uhlenbeck process of stationary standard deviation `sigma`
    (per component) and time constant `tau` s, started in its stationary law:
    x(t + dt) = a x(t) + sqrt(1 - a^2) sigma n, a = exp(-dt / tau), n ~ N(0, 1),
    the exact discretisation at any dt."""

    def __init__(self, sigma: np.ndarray, tau: float, rng: np.random.Generator) -> None:
        self.sigma = np.asarray(sigma, np.float64)
        self.tau = tau
        self._rng = rng
        self.state = self.sigma * rng.standard_normal(self.sigma.shape)

    def step(self, dt: float) -> np.ndarray:
        a = np.exp(-dt / self.tau)
        self.state = a * self.state + np.sqrt(1 - a * a) * self.sigma * \
            self._rng.standard_normal(self.sigma.shape)
        return self.state


class RandomWalk:
    """A Wiener process of `rate` per sqrt(s) per component, from zero: after t s each
    component has standard deviation rate * sqrt(t)."""

    def __init__(self, rate: float, size: int, rng: np.random.Generator) -> None:
        self.rate = rate
        self._rng = rng
        self.state = np.zeros(size)

    def step(self, dt: float) -> np.ndarray:
        self.state = self.state + self._rng.normal(0.0, self.rate * np.sqrt(dt),
                                                   self.state.shape)
        return self.state

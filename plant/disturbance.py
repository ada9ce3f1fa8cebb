"""Lumped disturbances of the plant: d_p of eq. (1) and d_a of eq. (5), for N UAVs.

Pure numerics: numpy and ``math`` only; randomness comes from an injected, seeded
``numpy.random.Generator`` (same seed and same call sequence -> the same samples).

Model (``zenswarm.schema.DisturbanceConfig``), all as accelerations::

    d_p(t) = wind + sine_amplitude * sin(2 pi sine_freq_hz t) + gust(t)       m/s^2, ENU, (N, 3)
    d_a(t) = attitude_std * n(t)                                              rad/s^2, body, (N, 3)

wind and the sine are common to all UAVs; gust is a first-order Gauss-Markov process per UAV
and axis, time constant ``gust_tau_s``, stationary std ``gust_std``, started from 0 and
discretised exactly over each sample interval dt::

    g_{k+1} = a g_k + gust_std sqrt(1 - a^2) n_k,   a = exp(-dt / gust_tau_s),  n_k ~ N(0, I)

n(t) is white: a fresh standard normal (N, 3) draw per sample.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import DisturbanceConfig

__all__ = ["DisturbanceModel"]


_add = np.add
_mul = np.multiply


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


class DisturbanceModel:
    """Sampler of (d_p, d_a) for N UAVs.

    Parameters
    ----------
    cfg : zenswarm.schema.DisturbanceConfig
    n : int
        Number of UAVs N (>= 1).
    rng : numpy.random.Generator
        Seeded generator; drawn from only when ``gust_std > 0`` (one (N, 3) draw per sample,
        first) and when ``attitude_std > 0`` (one (N, 3) draw per sample, second).
    """

    def __init__(self, cfg: DisturbanceConfig, n: int, rng: np.random.Generator) -> None:
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        self.cfg = cfg
        self.n = int(n)
        self.rng = rng
        self.active = bool(cfg.active)
        self._zero_p = _frozen(np.zeros((self.n, 3)))
        self._zero_a = _frozen(np.zeros((self.n, 3)))
        # (N, 3) copies: numpy broadcasting a (1, 3) operand costs ~3x a same-shape operation
        self._wind = np.tile(np.asarray(cfg.wind, dtype=float), (self.n, 1))
        self._sine = np.tile(np.asarray(cfg.sine_amplitude, dtype=float), (self.n, 1))
        self._has_sine = bool(np.any(self._sine)) and cfg.sine_freq_hz > 0
        self._omega = 2.0 * math.pi * float(cfg.sine_freq_hz)
        self._gust_std = float(cfg.gust_std)
        self._tau = float(cfg.gust_tau_s)
        self._att_std = float(cfg.attitude_std)
        self._att_std_0d = np.array(self._att_std)
        self._gust = np.zeros((self.n, 3))
        self._noise = np.zeros((self.n, 3))
        self._tmp = np.zeros((self.n, 3))
        self._dt: float | None = None
        self._a = np.array(0.0)
        self._b = np.array(0.0)

    @property
    def gust(self) -> np.ndarray:
        """Current Gauss-Markov gust state, (N, 3) m/s^2 (a copy)."""
        return self._gust.copy()

    def reset(self) -> None:
        """Gust state back to 0 (the generator is not rewound)."""
        self._gust[...] = 0.0

    def sampler(self, t: float, dt: float) -> Callable[[int], tuple[np.ndarray, np.ndarray]] | None:
        """The disturbance argument of :func:`zenswarm.plant.quadrotor.step_held` for the sub-steps of dt
        from t: ``j -> self.sample(t + j * dt, dt)``; None when the configuration is inactive
        (no disturbance, and the generator is not touched, as with :meth:`sample`)."""
        if not self.active:
            return None
        return lambda j: self.sample(t + j * dt, dt)

    def sample(self, t: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Disturbances to hold over [t, t + dt), then advance the gust by dt.

        Parameters
        ----------
        t : float
            Sim time at the start of the interval, s.
        dt : float
            Interval to the next call, s (> 0); the gust is discretised exactly over it.

        Returns
        -------
        d_p : (N, 3) ndarray
            Translational disturbance, m/s^2, ENU; eq. (1).
        d_a : (N, 3) ndarray
            Attitude disturbance as an angular acceleration, rad/s^2, body; eq. (5).

        When the configuration is inactive, both are the same cached read-only zero arrays on
        every call and the generator is not touched. ``d_a`` is likewise a cached read-only
        zero array when ``attitude_std == 0``.
        """
        if not self.active:
            return self._zero_p, self._zero_a
        d_p = _add(self._wind, self._gust)  # value at t (the gust starts from 0)
        if self._has_sine:
            _add(d_p, _mul(self._sine, math.sin(self._omega * t), self._tmp), d_p)
        if self._gust_std > 0.0:
            if dt != self._dt:
                if not (dt > 0 and math.isfinite(dt)):
                    raise ValueError(f"dt must be a positive finite number of seconds, got {dt!r}")
                self._dt = dt
                a = math.exp(-dt / self._tau)
                self._a = np.array(a)
                self._b = np.array(self._gust_std * math.sqrt(-math.expm1(-2.0 * dt / self._tau)))  # std sqrt(1 - a^2)
            g = self._gust
            _mul(g, self._a, g)
            noise = self.rng.standard_normal(out=self._noise)
            _add(g, _mul(noise, self._b, noise), g)
        if self._att_std > 0.0:
            d_a = self.rng.standard_normal((self.n, 3))
            _mul(d_a, self._att_std_0d, d_a)
        else:
            d_a = self._zero_a
        return d_p, d_a

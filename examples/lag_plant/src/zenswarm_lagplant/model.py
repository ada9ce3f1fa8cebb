"""A point-mass quadrotor whose attitude follows its setpoint with a first-order lag.

A different, simpler vehicle than zenswarm's own (rigid body + onboard attitude PID), written
against zenswarm's plant model interface (:class:`zenswarm.plant.api.PlantModel`) only.

Vehicle i, per physics sub-step of h = ctx.h seconds (semi-implicit Euler), with the held command
(F_i N, Theta_d,i = [phi_d, theta_d, psi_d] rad) and the scenario's disturbance d_p (m/s^2, ENU)::

    Theta' = wrap(Theta_d - Theta) / tau                   attitude lag, rad/s (roll, pitch clamped to +-max_tilt)
    Theta <- Theta + h Theta'                              (wrapped to (-pi, pi])
    v'    = R(Theta) [0, 0, F / m] - [0, 0, g] - c v + d_p   m/s^2, ENU; R = Rz Ry Rx (ZYX)
    v     <- v + h v';  q <- q + h v

and the reported body rate w is the Euler-angle rate Theta' (exact for small angles). The thrust is
clamped to [0, max_thrust]; the vehicle (mass, g, max_thrust, max_tilt) is zenswarm's Crazyflie 2.1
with the scenario's ``[vehicle]`` overrides (the default :meth:`PlantModel.vehicle`).

It records one internal signal with the flight (``records``: ``plant.rpy_target`` in
``timeseries.npz`` and in each state message of the recording): the attitude the lag follows,
the setpoint after the tilt clamp, rad.

Pure and deterministic: numpy only, no clock, no I/O, no randomness.
"""

from __future__ import annotations

from typing import Annotated, Any

import msgspec
import numpy as np

from zenswarm.plant.api import Disturbance, PlantContext, PlantModel, Signal

__all__ = ["LagPlant", "LagParams", "LagStates"]

Positive = Annotated[float, msgspec.Meta(gt=0)]
NonNegative = Annotated[float, msgspec.Meta(ge=0)]


class LagParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``[plant.params]`` of the lag model (every key optional): ``tau_s`` the attitude time
    constant, s; ``drag`` the linear drag coefficient c, 1/s."""

    tau_s: Positive = 0.05
    drag: NonNegative = 0.0


class LagStates:
    """q, v, rpy, w: (N, 3) each (m, m/s, rad, rad/s)."""

    def __init__(self, q0: np.ndarray) -> None:
        self.q = np.array(q0, dtype=float)
        self.v = np.zeros_like(self.q)
        self.rpy = np.zeros_like(self.q)
        self.w = np.zeros_like(self.q)


def _wrap(a: np.ndarray) -> np.ndarray:
    out: np.ndarray = a - 2.0 * np.pi * np.ceil(a / (2.0 * np.pi) - 0.5)
    return out


class LagPlant(PlantModel):
    """Example plant: point mass, first-order attitude lag, linear drag."""

    name = "lag"
    description = "example plug-in: point-mass quadrotor, first-order attitude lag (tau_s), linear drag"
    Params = LagParams
    records = {"rpy_target": Signal((3,), "rad", "the attitude the lag follows: the setpoint with roll and pitch clamped")}

    def __init__(self, ctx: PlantContext, params: Any) -> None:
        super().__init__(ctx, params)
        self._st = LagStates(ctx.initial_positions)
        tilt = ctx.vehicle.max_tilt
        self._lo = np.array([-tilt, -tilt, -1e6])
        self._hi = np.array([tilt, tilt, 1e6])
        self._target = np.zeros((ctx.n, 3))  # level before the first command
        self._target[:, 2] = ctx.yaw

    def record(self) -> dict[str, np.ndarray]:
        return {"rpy_target": self._target}

    @property
    def state(self) -> LagStates:
        return self._st

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Disturbance | None) -> None:
        c, p, st = self.ctx, self.ctx.vehicle, self._st
        h, tau, drag = c.h, self.params.tau_s, self.params.drag
        F = np.fmin(np.fmax(np.asarray(thrust, dtype=float), 0.0), p.max_thrust)
        target = self._target = np.fmin(np.fmax(np.asarray(rpy, dtype=float), self._lo), self._hi)
        for j in range(c.substeps):
            d_p = disturbance(j)[0] if disturbance is not None else None
            rate = _wrap(target - st.rpy) / tau
            st.rpy[...] = _wrap(st.rpy + h * rate)
            st.w[...] = rate
            sf, st_, sp = np.sin(st.rpy).T
            cf, ct, cp = np.cos(st.rpy).T
            a = (F / p.mass)[:, None] * np.stack([cp * st_ * cf + sp * sf, sp * st_ * cf - cp * sf, cf * ct], axis=1)
            a[:, 2] -= p.g
            a -= drag * st.v
            if d_p is not None:
                a += d_p
            st.v += h * a
            st.q += h * st.v

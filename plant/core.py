"""The plant's tick (numpy only): THE plant step of the plant process and the in-process
simulator alike.

:class:`PlantCore` holds every UAV's rigid-body state, the commands it holds (zero-order hold,
with the tick each was sent at), the failsafe and the disturbance model. Step 7 of a control tick
(see :mod:`zenswarm.compose.sim`) is :meth:`PlantCore.step`: the failsafe decides, from each
command's age, what is applied (:mod:`zenswarm.plant.failsafe`), then ``timing.substeps`` physics
sub-steps run with it held (:func:`zenswarm.plant.quadrotor.step_held`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from zenswarm.params import QuadParams
from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.failsafe import FailsafeState, failsafe_config
from zenswarm.plant.quadrotor import PlantState, initial_state, step_held

__all__ = ["PlantCore"]


class PlantCore:
    """N simulated quadrotors and the commands they hold.

    ``thrust`` (N,) N and ``rpy_cmd`` (N, 3) rad: the held commands (hover thrust, level, yaw =
    controller.yaw before the first); ``last_cmd_tick`` (N,): the tick each was sent at.
    ``state``: :class:`zenswarm.plant.quadrotor.PlantState` (q, v, rpy, w: (N, 3) each).
    """

    def __init__(self, scenario: Any) -> None:
        n = scenario.n
        tm = scenario.timing
        self.n = n
        self.params = QuadParams.from_vehicle(scenario.vehicle)
        self.dt = tm.dt
        self.nsub = tm.substeps
        self.h = tm.dt / tm.substeps
        self.yaw = scenario.controller.yaw
        self.dist = DisturbanceModel(scenario.disturbance, n, np.random.default_rng(scenario.seed))
        self.state: PlantState = initial_state(np.asarray(scenario.initial_positions, dtype=float))
        self.failsafe = FailsafeState(n, failsafe_config(scenario.failsafe))
        self.thrust = np.full(n, self.params.mass * self.params.g)
        self.rpy_cmd = np.zeros((n, 3))
        self.rpy_cmd[:, 2] = self.yaw
        self.last_cmd_tick = [0] * n

    def hold(self, i: int, thrust: float, rpy: np.ndarray, k_cmd: int) -> None:
        """UAV i (0-based) holds this command (thrust N, rpy (3,) rad), sent at tick ``k_cmd``."""
        self.thrust[i] = thrust
        self.rpy_cmd[i] = rpy
        self.last_cmd_tick[i] = k_cmd

    def hold_all(self, thrust: np.ndarray, rpy: np.ndarray, k_cmd: int) -> None:
        """Every UAV holds its command of tick ``k_cmd``: thrust (N,) N, rpy (N, 3) rad."""
        self.thrust = thrust
        self.rpy_cmd = rpy
        self.last_cmd_tick = [k_cmd] * self.n

    def step(self, k: int) -> list[tuple[int, int, str, str]]:
        """Step 7 of tick k: failsafe on the commands' ages, then the physics sub-steps to tick
        k + 1 (in place). Returns the failsafe events of this tick (tick, UAV 1-based, from, to)."""
        p = self.params
        fs = self.failsafe
        before = len(fs.events)
        ages = [(k - self.last_cmd_tick[i]) * self.dt for i in range(self.n)]
        f_app, r_app = fs.apply(k, ages, self.state.q, self.state.v, self.thrust, self.rpy_cmd, p.mass, p.g, self.yaw)
        step_held(self.state, f_app, r_app, p, self.h, self.nsub, self.dist.sampler(k * self.dt, self.h))
        return fs.events[before:]

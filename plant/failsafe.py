"""Per-UAV command-loss failsafe of the simulated vehicle (pure: numpy only).

Like PX4's offboard-loss handling: when a UAV's commands stop (its newest command is older than
``hover_after_s``) the vehicle holds its position (hover) with an onboard position loop; after
``land_after_s`` it descends at ``land_speed`` m/s and cuts the motors on the ground. Unlike PX4,
control returns to the agent as soon as its commands are fresh again (a restarted agent rejoins).
The timeouts are the scenario's ``[failsafe]`` fields.
"""

from __future__ import annotations

import numpy as np

from zenswarm.scenario.config import FailsafeConfig, failsafe_config  # re-exported: the [failsafe] table
from zenswarm.vehicle.inversion import invert_thrust_attitude

__all__ = ["FailsafeConfig", "FailsafeMode", "failsafe_config", "mode_for_age", "hold_command"]

NOMINAL, HOVER, LAND, LANDED = 0, 1, 2, 3
FailsafeMode = int
MODE_NAMES = {NOMINAL: "nominal", HOVER: "hover", LAND: "land", LANDED: "landed"}


def mode_for_age(age_s: float, current: FailsafeMode, cfg: FailsafeConfig) -> FailsafeMode:
    """Failsafe mode for a command age (s). LANDED stays LANDED until commands are fresh."""
    if age_s <= cfg.hover_after_s:
        return NOMINAL
    if current == LANDED:
        return LANDED
    return LAND if age_s > cfg.land_after_s else HOVER


def hold_command(
    mode: FailsafeMode,
    q: np.ndarray,
    v: np.ndarray,
    hold: np.ndarray,
    mass: float,
    g: float,
    yaw: float,
    cfg: FailsafeConfig,
) -> tuple[float, np.ndarray]:
    """Onboard (thrust N, rpy (3,) rad) for HOVER (hold position ``hold``) or LAND (descend at
    land_speed above ``hold``'s x, y). LANDED: zero thrust, level."""
    if mode == LANDED:
        return 0.0, np.array([0.0, 0.0, yaw])
    v_ref = np.zeros(3)
    target = np.array(hold, dtype=float)
    if mode == LAND:
        target[2] = q[2]
        v_ref[2] = -cfg.land_speed
    u = cfg.kp * (target - q) + cfg.kd * (v_ref - v)
    u[2] += g
    F, phi, theta = invert_thrust_attitude(u, mass, yaw)
    return float(F), np.array([float(phi), float(theta), yaw])


class FailsafeState:
    """Failsafe modes of N UAVs; :meth:`apply` turns the held commands into applied ones.

    Used identically by the plant process and the in-process simulator (faulty runs), so both
    agree. ``events`` lists (tick, uav index 1-based, old mode name, new mode name).
    """

    def __init__(self, n: int, cfg: FailsafeConfig) -> None:
        self.cfg = cfg
        self.modes = [NOMINAL] * n
        self.hold = np.zeros((n, 3))
        self.events: list[tuple[int, int, str, str]] = []

    def apply(
        self,
        k: int,
        ages_s: list[float],
        q: np.ndarray,
        v: np.ndarray,
        thrust: np.ndarray,
        rpy: np.ndarray,
        mass: float,
        g: float,
        yaw: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Applied (thrust (N,), rpy (N, 3)) for tick k given each UAV's command age (s)."""
        out_t, out_r = thrust, rpy
        if not any(self.modes):  # all NOMINAL: nothing changes while every command is fresh
            h = self.cfg.hover_after_s
            for age in ages_s:
                if not age <= h:
                    break
            else:
                return out_t, out_r
        for i, age in enumerate(ages_s):
            old = self.modes[i]
            new = mode_for_age(age, old, self.cfg)
            if new == LAND and q[i][2] <= self.cfg.ground_z and old in (LAND, LANDED):
                new = LANDED
            if new != old:
                if old == NOMINAL:
                    self.hold[i] = q[i]
                self.events.append((k, i + 1, MODE_NAMES[old], MODE_NAMES[new]))
                self.modes[i] = new
            if new != NOMINAL:
                if out_t is thrust:
                    out_t, out_r = thrust.copy(), rpy.copy()
                out_t[i], out_r[i] = hold_command(new, q[i], v[i], self.hold[i], mass, g, yaw, self.cfg)
        return out_t, out_r

    def summary(self) -> str:
        """``"2:hover,3:nominal"`` for UAVs not in NOMINAL mode ('' when all are nominal)."""
        return ",".join(f"{i + 1}:{MODE_NAMES[m]}" for i, m in enumerate(self.modes) if m != NOMINAL)

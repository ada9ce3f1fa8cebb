"""Mission metrics from a flight's time series: the fields of ``results.json``.

Pure (numpy only). The in-process simulator, the distributed swarm and the flight report all
compute their results with :func:`compute_results`, so the same flight gives the same JSON.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from leader.aapf import obstacle_clearance_many

__all__ = ["TimeSeries", "compute_results", "UAV_COLLISION_DISTANCE_M", "RESULT_FIELDS"]

UAV_COLLISION_DISTANCE_M = 0.05
"""Two UAV centres closer than this count as a collision (a Crazyflie 2.1 is 92 mm motor to motor;
rotor discs of neighbours may overlap down to about this distance without the frames touching)."""

RESULT_FIELDS = (
    "goal_reached",
    "time_to_goal_s",
    "min_obstacle_clearance_m",
    "min_inter_uav_distance_m",
    "max_formation_error_m",
    "rms_tracking_error_m",
    "sim_time_s",
)


@dataclass
class TimeSeries:
    """One flight sampled at every control tick k (T samples, N UAVs).

    t: (T,) s. q0, v0: (T, 3) leader. qref, vref: (T, N, 3) generator output q*, v*.
    q, v, rpy: (T, N, 3) measured UAV state (m, m/s, rad). u: (T, N, 3) virtual control, m/s^2.
    thrust: (T, N) N. d_hat: (T, N, 3) ESO disturbance estimate, m/s^2.
    """

    t: np.ndarray
    q0: np.ndarray
    v0: np.ndarray
    qref: np.ndarray
    vref: np.ndarray
    q: np.ndarray
    v: np.ndarray
    rpy: np.ndarray
    u: np.ndarray
    thrust: np.ndarray
    d_hat: np.ndarray

    FIELDS = ("t", "q0", "v0", "qref", "vref", "q", "v", "rpy", "u", "thrust", "d_hat")

    @classmethod
    def allocate(cls, T: int, n: int) -> "TimeSeries":
        nan3 = lambda: np.full((T, n, 3), np.nan)  # noqa: E731
        return cls(
            t=np.full(T, np.nan),
            q0=np.full((T, 3), np.nan),
            v0=np.full((T, 3), np.nan),
            qref=nan3(),
            vref=nan3(),
            q=nan3(),
            v=nan3(),
            rpy=nan3(),
            u=nan3(),
            thrust=np.full((T, n), np.nan),
            d_hat=nan3(),
        )

    def truncated(self, T: int) -> "TimeSeries":
        return TimeSeries(**{f: getattr(self, f)[:T] for f in self.FIELDS})

    def save(self, path: str) -> None:
        """Write a compressed ``.npz`` (one array per field)."""
        np.savez_compressed(path, **{f: getattr(self, f) for f in self.FIELDS})

    @classmethod
    def load(cls, path: str) -> "TimeSeries":
        with np.load(path) as z:
            return cls(**{f: np.array(z[f]) for f in cls.FIELDS})


def _num(x: float) -> float | None:
    """JSON-safe float: None for NaN/inf."""
    return float(x) if math.isfinite(x) else None


def compute_results(ts: TimeSeries, scenario: Any, wall_time_s: float | None = None) -> dict[str, Any]:
    """The mission results of a flight.

    Fields: goal_reached (leader within timing.goal_tolerance_m of the goal at some tick),
    time_to_goal_s (first such time, None if never), min_obstacle_clearance_m (every UAV position
    against the real cylinder and cap surfaces), min_inter_uav_distance_m,
    max_formation_error_m (max_i ||q*_i - q0 - h_i|| for t >= timing.settle_time_s),
    rms_tracking_error_m (RMS over ticks and UAVs of ||q*_i - q_i||), sim_time_s, wall_time_s,
    plus collision flags, ``finite`` (no NaN/inf anywhere) and ``success``.
    """
    goal = np.asarray(scenario.leader.goal, dtype=float)
    h = np.asarray(scenario.offsets, dtype=float)
    tol = scenario.timing.goal_tolerance_m
    T = len(ts.t)
    finite = bool(all(np.all(np.isfinite(getattr(ts, f))) for f in TimeSeries.FIELDS))

    dist = np.linalg.norm(ts.q0 - goal, axis=1)
    reached = np.flatnonzero(dist <= tol)
    goal_reached = bool(len(reached))
    time_to_goal = float(ts.t[reached[0]]) if goal_reached else None

    clear = math.inf
    for ob in scenario.obstacles:
        if T:
            clear = min(clear, float(np.nanmin(obstacle_clearance_many(ts.q, ob))))
    n = ts.q.shape[1] if T else scenario.n
    if n > 1 and T:
        diff = ts.q[:, :, None, :] - ts.q[:, None, :, :]
        d = np.linalg.norm(diff, axis=-1)
        iu = np.triu_indices(n, 1)
        inter = float(np.nanmin(d[:, iu[0], iu[1]]))
    else:
        inter = math.inf

    settle = ts.t >= scenario.timing.settle_time_s
    if T and np.any(settle):
        ferr = np.linalg.norm(ts.qref[settle] - ts.q0[settle][:, None, :] - h[None], axis=-1)
        max_ferr = float(np.max(ferr))
    else:
        max_ferr = math.nan
    if T:
        terr = np.linalg.norm(ts.qref - ts.q, axis=-1)
        rms = float(np.sqrt(np.mean(terr**2)))
    else:
        rms = math.nan
    dt = 1.0 / scenario.timing.control_rate_hz
    sim_time = float(ts.t[-1] + dt) if T else 0.0

    obstacle_collision = clear <= 0.0
    uav_collision = inter < UAV_COLLISION_DISTANCE_M
    res: dict[str, Any] = {
        "scenario": scenario.name,
        "n_uav": int(n),
        "goal_reached": goal_reached,
        "time_to_goal_s": time_to_goal,
        "min_obstacle_clearance_m": _num(clear),
        "min_inter_uav_distance_m": _num(inter),
        "max_formation_error_m": _num(max_ferr),
        "rms_tracking_error_m": _num(rms),
        "final_leader_goal_distance_m": _num(float(dist[-1])) if T else None,
        "obstacle_collision": bool(obstacle_collision),
        "uav_collision": bool(uav_collision),
        "finite": finite,
        "sim_time_s": sim_time,
        "wall_time_s": wall_time_s,
    }
    res["success"] = bool(goal_reached and not obstacle_collision and not uav_collision and finite)
    return res

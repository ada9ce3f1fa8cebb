"""The simulated Crazyflie's high-level commander planner (``planner.c``): one minimum-jerk
segment at a time (take off, land, go to). Positions m in the positioning system's frame (the
swarm's ENU here), yaw rad, times s (monotonic).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class HlPlan:
    """The high-level commander's plan: a minimum-jerk segment from ``p0`` to ``p1`` (m, ENU)
    and yaw ``yaw0`` -> ``yaw1`` (rad) over ``duration`` s from ``t0``; ``state`` idle, flying,
    landing (the planner's TRAJECTORY_STATE_*)."""

    state: str = "idle"
    p0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw0: float = 0.0
    yaw1: float = 0.0
    t0: float = 0.0
    duration: float = 1.0

    def sample(self, now: float) -> tuple[np.ndarray, np.ndarray, float, bool]:
        """Position, velocity, yaw at ``now`` and whether the segment is finished."""
        tau = min(max((now - self.t0) / self.duration, 0.0), 1.0)
        s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)
        ds = 30.0 * tau * tau * (1.0 - tau) ** 2 / self.duration
        d = self.p1 - self.p0
        dyaw = (self.yaw1 - self.yaw0 + math.pi) % (2 * math.pi) - math.pi
        return self.p0 + s * d, ds * d, self.yaw0 + s * dyaw, tau >= 1.0

"""The virtual leader's tick (numpy only): THE leader step of the leader process and the
in-process simulator alike.

:class:`LeaderCore` holds what the leader process holds: the leader's position q0 (3,) m and the
tick it belongs to. Step 1 of a control tick (see :mod:`zenswarm.compose.sim`) is :meth:`ref`,
v0 = Gamma*_total(q0) (eq. 15); step 8 is :meth:`advance`, q0 to the next tick by
:func:`zenswarm.leader.aapf.integrate_leader`.
"""

from __future__ import annotations

import numpy as np

from zenswarm.leader.aapf import AapfParams, integrate_leader, total_force

__all__ = ["LeaderCore"]


class LeaderCore:
    """q0 (3,) m at tick ``k``; ``capped``: ticks whose integration hit the sub-step cap."""

    def __init__(self, start: np.ndarray, params: AapfParams, dt: float, substeps: int) -> None:
        self.q0 = np.asarray(start, dtype=float).copy()
        self.k = 0
        self.capped = 0
        self.params = params
        self.dt = dt
        self.substeps = substeps

    @classmethod
    def from_scenario(cls, scenario) -> LeaderCore:
        tm = scenario.timing
        return cls(np.asarray(scenario.leader.start, dtype=float), AapfParams.from_scenario(scenario), tm.dt, tm.substeps)

    def ref(self) -> tuple[np.ndarray, np.ndarray]:
        """Step 1: (q0, v0) of tick ``k``, each (3,): m, m/s (v0 by eq. 15). q0 is the core's
        own array: copy it to keep it past :meth:`advance` (which replaces, never mutates, it)."""
        return self.q0, total_force(self.q0, self.params)

    def advance(self) -> None:
        """Step 8: q0 to tick k + 1 (explicit Euler sub-steps, adaptively refined)."""
        self.q0, info = integrate_leader(self.q0, self.dt, self.params, self.substeps)
        self.capped += int(info.capped)
        self.k += 1

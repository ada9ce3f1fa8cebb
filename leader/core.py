"""The virtual leader's tick: THE leader step of the leader process and the in-process simulator
alike, a shell around the scenario's planner plug-in (:class:`zenswarm.leader.planner.Planner`).

:class:`LeaderCore` holds what the leader process holds: its planner and the tick k it is at.
Step 1 of a control tick (see :mod:`zenswarm.compose.sim`) is :meth:`LeaderCore.ref`, (q0, v0)
of tick k (for the paper's planner v0 = Gamma*_total(q0), eq. 15); step 8 is
:meth:`LeaderCore.advance`, to tick k + 1.

Which planner: :func:`zenswarm.plugins.planner_name` (``[leader] planner``; without it ``aapf``,
the paper's, or ``apf``, fixed gain, when ``[leader] adaptive = false``, the older spelling).
Its parameters: ``[leader.params]``. Its random stream: :func:`zenswarm.plugins.plugin_rng` with
role 0.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from zenswarm.leader.planner import Planner, PlannerContext
from zenswarm.plugins import decode_params, planner_name, plugin_rng, resolve

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.config import Scenario

__all__ = ["LeaderCore", "make_planner"]


def make_planner(scenario: Scenario) -> Planner:
    """The scenario's planner, built (bad name or params: ScenarioError naming them, exit 2)."""
    cls = resolve("planner", planner_name(scenario))
    params = decode_params(cls, scenario.leader.params, "leader.params")
    tm = scenario.timing
    ctx = PlannerContext(
        start=np.asarray(scenario.leader.start, dtype=float),
        goal=np.asarray(scenario.leader.goal, dtype=float),
        obstacles=tuple(scenario.obstacles),
        r_f=scenario.r_f,
        dt=tm.dt,
        substeps=tm.substeps,
        rng=plugin_rng(scenario.seed, 0),
        leader=scenario.leader,
    )
    planner: Planner = cls(ctx, params)
    return planner


class LeaderCore:
    """The planner at tick ``k`` (0 at the start)."""

    def __init__(self, planner: Planner) -> None:
        self.planner = planner
        self.k = 0

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> LeaderCore:
        return cls(make_planner(scenario))

    @property
    def q0(self) -> np.ndarray:
        """The leader's position of tick k, (3,) m."""
        return self.planner.ref()[0]

    @property
    def capped(self) -> int:
        """Ticks whose integration hit the sub-step cap (the paper's planners; 0 otherwise)."""
        return self.planner.counters().get("substep_cap_hits", 0)

    def ref(self) -> tuple[np.ndarray, np.ndarray]:
        """Step 1: (q0, v0) of tick ``k``, each (3,): m, m/s. q0 may be the planner's own array:
        copy it to keep it past :meth:`advance` (which replaces, never mutates, it)."""
        return self.planner.ref()

    def advance(self) -> None:
        """Step 8: to tick k + 1."""
        self.planner.advance()
        self.k += 1

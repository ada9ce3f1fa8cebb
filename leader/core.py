"""The virtual leader's tick: THE leader step of the leader process and the in-process simulator
alike, a shell around the scenario's planner plug-in (:class:`zenswarm.leader.planner.Planner`).

:class:`LeaderCore` holds what the leader process holds: its planner and the tick k it is at.
Step 1 of a control tick (see :mod:`zenswarm.compose.sim`) is :meth:`LeaderCore.ref`, (q0, v0)
of tick k (for the paper's planner v0 = Gamma*_total(q0), eq. 15); step 8 is
:meth:`LeaderCore.advance`, to tick k + 1.

Which planner: :func:`zenswarm.scenario.plugins.planner_name` (``[leader] planner``; without it ``aapf``,
the paper's, or ``apf``, fixed gain, when ``[leader] adaptive = false``, the older spelling).
Its parameters: ``[leader.params]``. Its random stream: :func:`zenswarm.scenario.plugins.plugin_rng` with
role 0.

The planner is called at its boundary (:class:`zenswarm.scenario.plugins.Boundary`): an exception of its
constructor, :meth:`~zenswarm.leader.planner.Planner.advance` or
:meth:`~zenswarm.leader.planner.Planner.ref`, or a reference that is not two finite (3,) vectors,
is a :class:`zenswarm.errors.PluginFailure` of the tick whose reference it failed to give, in
the simulator and the leader process alike.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from zenswarm.leader.planner import Planner, PlannerContext
from zenswarm.scenario.plugins import STAGE_BUILD, STAGE_PLANNER, Boundary, bad_vector, decode_params, planner_name, plugin_rng, resolve

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = ["LeaderCore", "make_planner", "planner_boundary"]


def planner_boundary(scenario: Scenario) -> Boundary:
    """The boundary of the scenario's planner (process ``leader``)."""
    return Boundary("planner", planner_name(scenario), "leader")


def make_planner(scenario: Scenario) -> Planner:
    """The scenario's planner, built (bad name or params: ScenarioError naming them, exit 2; an
    exception of its constructor: :class:`zenswarm.errors.PluginFailure` at tick 0)."""
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
    planner: Planner = planner_boundary(scenario).call(0, STAGE_BUILD, "__init__", cls, ctx, params)
    return planner


class LeaderCore:
    """The planner at tick ``k`` (0 at the start), called at ``boundary`` (default: process
    ``leader``, the planner's class name)."""

    def __init__(self, planner: Planner, boundary: Boundary | None = None) -> None:
        self.planner = planner
        self.boundary = boundary or Boundary("planner", type(planner).name or type(planner).__qualname__, "leader")
        self.k = 0
        self._ref: tuple[np.ndarray, np.ndarray] | None = None  # ref() of tick k, once asked for

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> LeaderCore:
        return cls(make_planner(scenario), planner_boundary(scenario))

    @property
    def q0(self) -> np.ndarray:
        """The leader's position of tick k, (3,) m."""
        return self.ref()[0]

    @property
    def capped(self) -> int:
        """Ticks whose integration hit the sub-step cap (the paper's planners; 0 otherwise)."""
        return self.planner.counters().get("substep_cap_hits", 0)

    def ref(self) -> tuple[np.ndarray, np.ndarray]:
        """Step 1: (q0, v0) of tick ``k``, each (3,): m, m/s. q0 may be the planner's own array:
        copy it to keep it past :meth:`advance` (which replaces, never mutates, it). The
        planner's :meth:`~zenswarm.leader.planner.Planner.ref` is called once per tick, checked."""
        if self._ref is None:
            b, k = self.boundary, self.k
            got = b.call(k, STAGE_PLANNER, "ref", self.planner.ref)
            if not (isinstance(got, tuple) and len(got) == 2):
                raise b.fail(k, STAGE_PLANNER, "ref", "ref", f"expected a pair (q0, v0), got {type(got).__name__}")
            problems = [(name, bad) if (bad := bad_vector(x, (3,))) else None for name, x in zip(("q0", "v0"), got, strict=True)]
            b.check(k, STAGE_PLANNER, "ref", problems)
            self._ref = (got[0], got[1])
        return self._ref

    def advance(self) -> None:
        """Step 8: to tick k + 1 (a failure of the planner's advance is one of tick k + 1: the
        reference it did not give)."""
        self.boundary.call(self.k + 1, STAGE_PLANNER, "advance", self.planner.advance)
        self.k += 1
        self._ref = None

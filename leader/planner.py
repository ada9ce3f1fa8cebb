"""The leader planner interface, and the paper's planners as its built-in implementations.

A planner is the virtual leader's trajectory: from the start, the goal and the obstacles it gives
the leader's reference (q0, v0) of each control tick. It is pure and deterministic: no clock, no
I/O; randomness only from the seeded :class:`numpy.random.Generator` of its context. The
in-process simulator, the leader process and ``zenswarm verify`` call it through
:class:`zenswarm.leader.core.LeaderCore`, so any such planner flies the same in all of them.

Frames and units: positions (3,) float64 m, velocities (3,) m/s, inertial ENU (z up); times s.

Write one by subclassing :class:`Planner` (set ``name``, ``description``, ``Params``; implement
:meth:`Planner.ref` and :meth:`Planner.advance`) and name it in the scenario
(``[leader] planner = "my_pkg.plan:MyPlanner"``) with its parameters in ``[leader.params]``
(see :mod:`zenswarm.scenario.plugins`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, ClassVar

import msgspec
import numpy as np

from zenswarm.leader.aapf import AapfParams, ObstacleLike, integrate_leader, total_force
from zenswarm.leader.escape import DEFAULT_LOOKAHEAD, DEFAULT_MARGIN, DEFAULT_SIDES, EscapeParams, escape_velocity, integrate_escape

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import LeaderConfig

__all__ = ["PlannerContext", "Planner", "NoParams", "AapfPlanner", "ApfPlanner", "EscapePlanner"]


class NoParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A plug-in without parameters: its ``params`` table must be empty."""


@dataclass(frozen=True)
class PlannerContext:
    """What a planner is built from (the scenario, typed).

    start, goal: (3,) m ENU (``[leader]``). obstacles: the scenario's capped cylinders
    (:class:`zenswarm.leader.aapf.ObstacleLike`). r_f: formation-enclosing sphere radius, m.
    dt: control tick, s. substeps: physics sub-steps per tick (a floor for integration sub-steps).
    rng: the planner's seeded stream (:func:`zenswarm.scenario.plugins.plugin_rng` with role 0).
    leader: the whole ``[leader]`` table (the built-ins read the paper's gains from it).
    """

    start: np.ndarray
    goal: np.ndarray
    obstacles: Sequence[ObstacleLike]
    r_f: float
    dt: float
    substeps: int
    rng: np.random.Generator
    leader: LeaderConfig


class Planner(ABC):
    """The virtual leader's planner: its state is at control tick k (k = 0 after construction).

    Class attributes: ``name`` (the name it is listed under), ``description`` (one line),
    ``Params`` (a frozen :class:`msgspec.Struct` with ``forbid_unknown_fields=True``: the
    scenario's ``[leader.params]`` table decoded, unknown keys rejected naming the field).
    """

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    Params: ClassVar[type[msgspec.Struct]] = NoParams

    def __init__(self, ctx: PlannerContext, params: Any) -> None:
        self.ctx = ctx
        self.params = params

    @abstractmethod
    def ref(self) -> tuple[np.ndarray, np.ndarray]:
        """(q0, v0) of the current tick: (3,) m and (3,) m/s, ENU. May return internal arrays:
        the caller copies what it keeps past :meth:`advance`, which must replace, not mutate, them.
        Called once or more per tick; must not change the state."""

    @abstractmethod
    def advance(self) -> None:
        """Move to the next tick (dt = ``ctx.dt`` later)."""

    def counters(self) -> dict[str, int]:
        """Diagnostic counters (published in the leader's diag); default none."""
        return {}


class AapfPlanner(Planner):
    """The paper's adaptive APF (eqs 8-15, adaptive gain eq. 12): v0 = Gamma*_total(q0)
    (eq. 15), q0 integrated by explicit Euler sub-steps (:func:`zenswarm.leader.aapf.integrate_leader`).
    Gains from ``[leader]`` (k_att, k_rep_min, k_rep_max, d0, speed_limit)."""

    name = "aapf"
    description = "the paper's adaptive artificial potential field (eqs 8-15, adaptive gain eq. 12); the default"
    adaptive: ClassVar[bool] = True

    def __init__(self, ctx: PlannerContext, params: Any) -> None:
        super().__init__(ctx, params)
        ld = ctx.leader
        self.aapf = AapfParams(
            goal=tuple(float(x) for x in ctx.goal), k_att=ld.k_att, k_rep_min=ld.k_rep_min, k_rep_max=ld.k_rep_max, d0=ld.d0, r_f=ctx.r_f,
            obstacles=ctx.obstacles, adaptive=self.adaptive, k_rep_fixed=ld.k_rep_fixed, speed_limit=ld.speed_limit,
        )
        self.q0 = np.asarray(ctx.start, dtype=float).copy()
        self.capped = 0

    def ref(self) -> tuple[np.ndarray, np.ndarray]:
        return self.q0, total_force(self.q0, self.aapf)

    def advance(self) -> None:
        self.q0, info = integrate_leader(self.q0, self.ctx.dt, self.aapf, self.ctx.substeps)
        self.capped += int(info.capped)

    def counters(self) -> dict[str, int]:
        return {"substep_cap_hits": self.capped}


class ApfPlanner(AapfPlanner):
    """The fixed-gain APF: :class:`AapfPlanner` with K_rep = ``[leader] k_rep_fixed`` instead of eq. (12)."""

    name = "apf"
    description = "fixed-gain artificial potential field (K_rep = leader.k_rep_fixed instead of eq. 12), for comparison"
    adaptive = False


class EscapePlanner(Planner):
    """The AAPF steered along a global path around the known obstacles, so it does not stall in
    the AAPF's local minima (:mod:`zenswarm.leader.escape`): a shortest path over the obstacles
    inflated by r_f + d0 + ``margin`` (visibility graph, planned once at construction), the
    attraction of eq. (9) aimed at a carrot ``lookahead`` m ahead on it, the repulsion of
    eqs (10)-(13) unchanged; explicit Euler sub-steps as the AAPF's. Where the straight
    start-goal segment is clear it is the AAPF bit for bit. Gains from ``[leader]``."""

    name = "escape"
    description = "the AAPF steered along a path round the inflated obstacles (visibility graph): escapes the AAPF's local minima"

    class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
        """``[leader.params]`` of the escape planner. margin: m, how far outside the repulsion band
        (d_obs = d0) the path keeps the formation sphere; lookahead: m, carrot arc length ahead
        of the leader's nearest path point; sides: polygon sides per inflated obstacle disc."""

        margin: Annotated[float, msgspec.Meta(ge=0)] = DEFAULT_MARGIN
        lookahead: Annotated[float, msgspec.Meta(gt=0)] = DEFAULT_LOOKAHEAD
        sides: Annotated[int, msgspec.Meta(ge=3, le=360)] = DEFAULT_SIDES

    def __init__(self, ctx: PlannerContext, params: Any) -> None:
        super().__init__(ctx, params)
        ld = ctx.leader
        aapf = AapfParams(
            goal=tuple(float(x) for x in ctx.goal), k_att=ld.k_att, k_rep_min=ld.k_rep_min, k_rep_max=ld.k_rep_max, d0=ld.d0, r_f=ctx.r_f,
            obstacles=ctx.obstacles, adaptive=ld.adaptive, k_rep_fixed=ld.k_rep_fixed, speed_limit=ld.speed_limit,
        )
        self.escape = EscapeParams(aapf, tuple(float(x) for x in ctx.start), params.margin, params.lookahead, params.sides)
        self.q0 = np.asarray(ctx.start, dtype=float).copy()
        self.capped = 0

    @property
    def path(self) -> np.ndarray:
        """The planned path's waypoints (M, 3), m ENU, start first and goal last."""
        return self.escape.path

    def ref(self) -> tuple[np.ndarray, np.ndarray]:
        return self.q0, escape_velocity(self.q0, self.escape)

    def advance(self) -> None:
        self.q0, info = integrate_escape(self.q0, self.ctx.dt, self.escape, self.ctx.substeps)
        self.capped += int(info.capped)

    def counters(self) -> dict[str, int]:
        return {"substep_cap_hits": self.capped}

"""The paper's controller as the built-in plug-in ``paper`` (the default): distributed reference
generator (eqs 16-17) + ESO (eq. 27) + composite control (eq. 28) and the thrust/attitude
inversion after it, i.e. :class:`zenswarm.agents.core.AgentCore` behind
:class:`zenswarm.agents.api.Controller`. Its gains come from the scenario's ``[generator]``,
``[eso]`` and ``[controller]`` tables; it has no ``[agents.params]``.

It shares its reference (q*_i, v*_i) and nothing else. It also offers the two-phase tick the
agent process uses (:meth:`PaperController.prepare` before the state arrives: the generator
rates need the references only; :meth:`PaperController.finish` when it is in), and the
simulator flies it as one :class:`zenswarm.agents.core.StackedAgents` when there are no link
faults (the same numpy functions, bit for bit).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from zenswarm.agents.api import Command, Controller, ControllerContext, Shared
from zenswarm.agents.core import AgentCore, AgentRow, Rates

__all__ = ["PaperController"]


class PaperController(Controller):
    """Generator (16-17) + ESO (27) + composite controller (28) of one UAV."""

    name = "paper"
    description = "the paper's distributed generator (eqs 16-17) + ESO (27) + composite control (28); the default"
    two_phase: ClassVar[bool] = True

    def __init__(self, ctx: ControllerContext, params: Any) -> None:
        super().__init__(ctx, params)
        self.row = AgentRow.from_scenario(ctx.scenario, ctx.i, ctx.mass, ctx.g)
        self.core = AgentCore(self.row)

    @property
    def initialised(self) -> bool:
        return self.core.initialised

    def reset(self, q: np.ndarray, v: np.ndarray) -> None:
        self.core.reset(q, v)

    def share(self) -> Shared:
        c = self.core
        assert c.q_ref is not None and c.v_ref is not None, "reset() first"
        return Shared(c.q_ref, c.v_ref)

    def prepare(self, neighbours: Sequence[Any], leader: Any) -> Rates:
        """Phase 1: the generator rates (16-17) of this tick from the references only."""
        return self.core.rates_from(neighbours, leader)

    def finish(self, q: np.ndarray, v: np.ndarray, rates: Rates, dt: float) -> Command:
        """Phase 2: control (28), inversion, then ESO and generator to the next tick."""
        cmd = self.core.finish(q, v, rates, dt)
        return Command(cmd.thrust, cmd.rpy, cmd.u, cmd.d_hat)

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        return self.finish(q, v, self.prepare(neighbours, leader), dt)

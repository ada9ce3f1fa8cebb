"""Test-only plug-ins (named ``plugin_fixtures:ConsensusController`` / ``plugin_fixtures:LinePlanner``
/ ``plugin_fixtures:CrashingController`` / ``plugin_fixtures:SlowController``
with ``tests/`` on PYTHONPATH): a controller that shares an EXTRA quantity with its neighbours and
draws from its seeded stream, and a planner; tests/test_plugins.py flies them in sim and lockstep up."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import replace as _replace
from typing import Any

import msgspec
import numpy as np

from zenswarm.agents.api import Command, Controller, ControllerContext, Shared
from zenswarm.agents.paper import PaperController
from zenswarm.leader.planner import AapfPlanner, Planner, PlannerContext
from zenswarm.vehicle.inversion import invert_thrust_attitude


class ConsensusController(Controller):
    """First-order consensus on the formation reference, PD tracking, no ESO; shares its
    measured (q, v) as the extra quantity ``meas`` (2, 3) and damps with the neighbours' velocities."""

    name = "test-consensus"
    description = "test-only: first-order consensus + PD, shares an extra quantity"
    shares = {"meas": (2, 3)}

    class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
        k_c: float = 1.0
        kp: float = 6.0
        kd: float = 4.0

    def __init__(self, ctx: ControllerContext, params: Any) -> None:
        super().__init__(ctx, params)
        self.jitter = 1.0 + 0.01 * float(ctx.rng.random())  # the seeded stream: sim and swarm agree
        self.qs: np.ndarray | None = None

    @property
    def initialised(self) -> bool:
        return self.qs is not None

    def reset(self, q: np.ndarray, v: np.ndarray) -> None:
        self.qs = np.array(q, dtype=float)
        self.vs = np.zeros(3)
        self.meas = np.stack([np.asarray(q, float), np.asarray(v, float)])

    def share(self) -> Shared:
        assert self.qs is not None
        return Shared(self.qs, self.vs, {"meas": self.meas})

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        assert self.qs is not None
        ctx, p = self.ctx, self.params
        vel = np.zeros(3)
        for nb, m in zip(ctx.neighbours, neighbours):
            if m is not None:
                vel -= p.k_c * nb.weight * ((self.qs - ctx.offset) - (m.q - nb.offset))
                vel += 0.1 * nb.weight * (m.extra["meas"][1] - self.vs)
        if leader is not None:
            vel -= p.k_c * ctx.pinning * (self.qs - ctx.offset - leader.q)
            vel += leader.v
        vel *= self.jitter
        u = p.kp * (self.qs - q) + p.kd * (vel - v)
        u[2] += ctx.g
        F, phi, theta = invert_thrust_attitude(u, ctx.mass, 0.0)
        self.qs = self.qs + dt * vel
        self.vs = vel
        self.meas = np.stack([np.asarray(q, float), np.asarray(v, float)])
        return Command(float(F), np.array([float(phi), float(theta), 0.0]), u)


class LinePlanner(Planner):
    """Straight line to the goal at ``speed`` m/s (no obstacle avoidance)."""

    name = "test-line"
    description = "test-only: straight line to the goal"

    class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
        speed: float = 0.2

    def __init__(self, ctx: PlannerContext, params: Any) -> None:
        super().__init__(ctx, params)
        self.q0 = np.asarray(ctx.start, float).copy()

    def ref(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.ctx.goal - self.q0
        n = float(np.linalg.norm(d))
        return self.q0, (d / n * min(self.params.speed, n / self.ctx.dt) if n > 0 else np.zeros(3))

    def advance(self) -> None:
        self.q0 = self.q0 + self.ctx.dt * self.ref()[1]


class CrashingController(ConsensusController):
    """Raises on its first step (tests/test_sweep.py: a crashing run is recorded with its error)."""

    name = "test-crash"
    description = "test-only: raises RuntimeError on its first step"

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        raise RuntimeError("test-crash controller: deliberate failure")


# ----------------------------------------------------------------------------- plug-ins that misbehave
# (tests/test_plugin_failures.py: the same named failure in sim, up and api.fly)


class PluginAbort(BaseException):
    """A plug-in's own BaseException (not an Exception): what some libraries raise to unwind."""


class MisbehavingController(PaperController):
    """The paper's controller that misbehaves from tick ``tick`` on UAV ``uav`` (0: every UAV):
    ``how`` = ``raise`` (its finish raises), ``nan`` (a NaN thrust), ``shape`` (a (2,) attitude),
    ``share`` (an infinite shared velocity), ``init`` (its constructor raises), ``exit`` (its
    finish calls ``sys.exit(3)``), ``generator-exit`` (raises ``GeneratorExit``), ``base`` (raises
    :class:`PluginAbort`, a ``BaseException`` of its own)."""

    name = "test-misbehaving"
    description = "test-only: the paper's controller, misbehaving as its params say"

    class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
        how: str = "raise"
        tick: int = 50
        uav: int = 2

    def __init__(self, ctx: ControllerContext, params: Any) -> None:
        self.mine = params.uav in (0, ctx.i + 1)
        if params.how == "init" and self.mine:
            raise ValueError(f"misbehaving controller of UAV {ctx.i + 1}: refused to start")
        super().__init__(ctx, params)
        self.k = 0  # the tick this controller is at

    def _now(self) -> bool:
        return self.mine and self.k >= self.params.tick

    def share(self) -> Shared:
        sh = super().share()
        if self.params.how == "share" and self._now():
            return Shared(sh.q, np.array([0.0, np.inf, 0.0]))
        return sh

    def finish(self, q: np.ndarray, v: np.ndarray, rates: Any, dt: float) -> Command:
        now, how = self._now(), self.params.how
        cmd = super().finish(q, v, rates, dt)
        self.k += 1
        if now and how == "raise":
            raise RuntimeError(f"misbehaving controller: deliberate error at tick {self.k - 1}")
        if now and how == "exit":
            sys.exit(3)
        if now and how == "generator-exit":
            raise GeneratorExit(f"misbehaving controller: leaving at tick {self.k - 1}")
        if now and how == "base":
            raise PluginAbort(f"misbehaving controller: aborting at tick {self.k - 1}")
        if now and how == "nan":
            return _replace(cmd, thrust=float("nan"))
        if now and how == "shape":
            return _replace(cmd, rpy=cmd.rpy[:2])
        return cmd


class SlowController(PaperController):
    """The paper's controller, slow on UAV ``uav`` (0: every UAV): each tick takes ``sleep_s``
    more wall time (a loaded or slow computer; the values are the paper controller's)."""

    name = "test-slow"
    description = "test-only: the paper's controller, sleep_s of wall time per tick"

    class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
        uav: int = 1
        sleep_s: float = 0.04

    def __init__(self, ctx: ControllerContext, params: Any) -> None:
        super().__init__(ctx, params)
        self.mine = params.uav in (0, ctx.i + 1)

    def finish(self, q: np.ndarray, v: np.ndarray, rates: Any, dt: float) -> Command:
        if self.mine:
            import time

            time.sleep(self.params.sleep_s)
        return super().finish(q, v, rates, dt)


class MisbehavingPlanner(AapfPlanner):
    """The AAPF that misbehaves from tick ``tick``: ``how`` = ``nan`` (its position goes NaN),
    ``raise`` (its advance raises)."""

    name = "test-misbehaving-planner"
    description = "test-only: the AAPF, misbehaving as its params say"

    class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
        how: str = "nan"
        tick: int = 40

    def __init__(self, ctx: PlannerContext, params: Any) -> None:
        super().__init__(ctx, params)
        self.k = 0

    def advance(self) -> None:
        self.k += 1
        if self.k >= self.params.tick and self.params.how == "raise":
            raise ZeroDivisionError("misbehaving planner: deliberate error")
        super().advance()
        if self.k >= self.params.tick and self.params.how == "nan":
            self.q0 = self.q0 * np.nan

"""The agent controller interface: what one UAV holds and does per control tick.

A controller is pure and deterministic: no clock, no I/O; randomness only from the seeded
:class:`numpy.random.Generator` of its context. The in-process simulator
(:mod:`zenswarm.compose.sim`), the agent process (:mod:`zenswarm.agents.process`) and
``zenswarm verify`` (:mod:`zenswarm.bridge.replay.verify`) call it the same way, so any such controller
flies bit for bit the same in ``zenswarm sim`` and in the lockstep swarm, with and without link
faults. The paper's generator + ESO + composite controller is the built-in
:class:`zenswarm.agents.paper.PaperController` (name ``paper``, the default).

Frames and units: positions (3,) float64 m, velocities (3,) m/s, accelerations m/s^2, inertial
ENU (z up); attitude roll, pitch, yaw in rad (ZYX); thrust N; times s.

One tick k of agent i, in every runner:

1. the agent publishes :meth:`Controller.share` (its :class:`Shared` of tick k) to its neighbours
   (on the first tick after :meth:`Controller.reset` from the measured state);
2. it receives its neighbours' :class:`Shared` of tick k (in ``ctx.neighbours`` order; None = not
   heard from yet: with link faults the newest value a link delivered is held) and, if pinned
   (b_i > 0), the leader's (q0, v0) (a :class:`Shared` without extras; None before the first);
3. :meth:`Controller.step` with the measured (q, v) of tick k and ``dt`` (seconds since the
   previous step: the nominal dt in lockstep and in the simulator) returns the :class:`Command`
   and moves the controller to tick k + 1.

Sharing more than (q*, v*): declare ``shares = {"name": shape, ...}`` and return the values in
``Shared.extra``; they travel in the reference message (:attr:`zenswarm.bus.wire.Ref.extra`), are
recorded and fault-injected with it, and arrive reshaped to the declared shape (a message
without them counts as not heard).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar

import msgspec
import numpy as np

from zenswarm.scenario.plugins import STAGE_BUILD, STAGE_SHARE, STAGE_STEP, Boundary, bad_scalar, bad_vector

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = [
    "Neighbour", "ControllerContext", "Shared", "Command", "Controller", "NoParams", "received", "context_of",
    "make_controller", "inputs_of", "prepare", "finish",
    "boundary_of", "build_controller", "check_shared", "check_command", "checked_reset", "checked_share", "checked_prepare",
    "checked_finish",
]

_EMPTY: Mapping[str, np.ndarray] = MappingProxyType({})


class NoParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A plug-in without parameters: its ``params`` table must be empty."""


@dataclass(frozen=True)
class Neighbour:
    """Neighbour j of agent i: ``index`` j (0-based; UAV number j + 1), ``weight`` a_ij > 0,
    ``offset`` h_j (3,) m (its formation offset)."""

    index: int
    weight: float
    offset: np.ndarray


@dataclass(frozen=True)
class ControllerContext:
    """What agent i's controller is built from (its row of the scenario, typed).

    i: 0-based index (UAV number i + 1). offset: h_i (3,) m. neighbours: its graph row (a_ij > 0,
    in increasing j: the order :meth:`Controller.step` gets their messages in). pinning: b_i
    (0: never hears the leader). mass: kg. g: m/s^2. dt: nominal control tick, s.
    rng: its seeded stream (:func:`zenswarm.scenario.plugins.plugin_rng` with role i + 1).
    scenario: the whole scenario (the built-in reads the paper's gains from it).
    """

    i: int
    offset: np.ndarray
    neighbours: tuple[Neighbour, ...]
    pinning: float
    mass: float
    g: float
    dt: float
    rng: np.random.Generator
    scenario: Scenario

    @property
    def pinned(self) -> bool:
        return self.pinning > 0.0


@dataclass(frozen=True)
class Shared:
    """What an agent publishes to its neighbours each tick: q (3,) m and v (3,) m/s (the paper:
    its reference q*_i, v*_i) and ``extra``: the controller's declared quantities, name -> array
    of the declared shape."""

    q: np.ndarray
    v: np.ndarray
    extra: Mapping[str, np.ndarray] = field(default_factory=lambda: _EMPTY)


@dataclass(frozen=True)
class Command:
    """What a tick sends to the vehicle: ``thrust`` F (N), ``rpy`` (3,) rad attitude setpoint;
    optional diagnostics (recorded, in the command message): ``u`` (3,) m/s^2 the virtual control
    (commanded acceleration incl. gravity compensation), ``d_hat`` (3,) m/s^2 a disturbance
    estimate (zeros when the controller has none)."""

    thrust: float
    rpy: np.ndarray
    u: np.ndarray = field(default_factory=lambda: np.zeros(3))
    d_hat: np.ndarray = field(default_factory=lambda: np.zeros(3))


class Controller(ABC):
    """One UAV's controller. Class attributes: ``name`` (listed under), ``description`` (one
    line), ``Params`` (a frozen :class:`msgspec.Struct` with ``forbid_unknown_fields=True``: the
    scenario's ``[agents.params]`` decoded, unknown keys rejected naming the field), ``shares``
    (extra quantities published to neighbours: name -> shape)."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    Params: ClassVar[type[msgspec.Struct]] = NoParams
    shares: ClassVar[Mapping[str, tuple[int, ...]]] = MappingProxyType({})

    def __init__(self, ctx: ControllerContext, params: Any) -> None:
        self.ctx = ctx
        self.params = params

    @property
    @abstractmethod
    def initialised(self) -> bool:
        """:meth:`reset` has been called (since the last restart)."""

    @abstractmethod
    def reset(self, q: np.ndarray, v: np.ndarray) -> None:
        """(Re)start from the measured state q (3,) m, v (3,) m/s (first tick, or rejoining)."""

    @abstractmethod
    def share(self) -> Shared:
        """What this agent publishes to its neighbours for the current tick (after :meth:`reset`).
        The runner copies nothing: return arrays that :meth:`step` replaces, never mutates."""

    @abstractmethod
    def step(
        self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float
    ) -> Command:
        """One tick: measured q (3,) m and v (3,) m/s; the neighbours' shared values of this tick
        in ``ctx.neighbours`` order (None: not heard from); the leader's (q0, v0) if pinned and
        heard (else None); dt s since the previous step. Returns the command; the controller is
        then at the next tick (its :meth:`share` is the next tick's)."""


def received(msg: Any, shares: Mapping[str, tuple[int, ...]]) -> Shared | None:
    """A neighbour's message as the controller gets it. Without declared extras the message
    itself (anything with ``q``, ``v``: a :class:`Shared` or a :class:`zenswarm.bus.wire.Ref`);
    with them a :class:`Shared` whose extras are float64 arrays of the declared shapes, or None
    if one is missing or has the wrong size (counted as not heard)."""
    if msg is None or not shares:
        return msg  # type: ignore[no-any-return]
    got = msg.extra
    extra: dict[str, np.ndarray] = {}
    for name, shape in shares.items():
        x = got.get(name)
        if x is None:
            return None
        a = np.asarray(x, dtype=float)
        if a.size != int(np.prod(shape)):
            return None
        extra[name] = a.reshape(shape)
    return Shared(msg.q, msg.v, MappingProxyType(extra))


def context_of(scenario: Scenario, i: int, mass: float, g: float, rng: np.random.Generator) -> ControllerContext:
    """Agent i's (0-based) :class:`ControllerContext` from the scenario."""
    graph = scenario.comm_graph  # built once per scenario: O(k_i) per agent
    h = scenario.offsets_array
    nbrs = tuple(Neighbour(int(j), float(a), h[j].copy()) for j, a in zip(graph.nbr[i], graph.w[i], strict=True))
    return ControllerContext(
        i=i, offset=h[i].copy(), neighbours=nbrs, pinning=float(graph.b[i]), mass=mass, g=g,
        dt=scenario.timing.dt, rng=rng, scenario=scenario,
    )


def make_controller(scenario: Scenario, i: int, mass: float, g: float) -> Controller:
    """Agent i's (0-based) controller: the scenario's ``[agents] controller`` with its
    ``[agents.params]`` and the random stream :func:`zenswarm.scenario.plugins.plugin_rng` (seed, i + 1).
    A bad name or parameter raises :class:`zenswarm.errors.ScenarioError` naming it."""
    from zenswarm.scenario.plugins import decode_params, plugin_rng, resolve

    cls = resolve("controller", scenario.agents.controller)
    params = decode_params(cls, scenario.agents.params, "agents.params")
    ctrl: Controller = cls(context_of(scenario, i, mass, g, plugin_rng(scenario.seed, i + 1)), params)
    return ctrl


def inputs_of(ctrl: Controller, nbr: Sequence[Any], lead: Any) -> tuple[list[Shared | None], Shared | None]:
    """The neighbours' messages (in ``ctx.neighbours`` order, None: not heard) and the leader's
    as the controller gets them (:func:`received`)."""
    shares = ctrl.shares
    if not shares:
        return list(nbr), lead
    return [received(m, shares) for m in nbr], lead


def prepare(ctrl: Controller, nbr: Sequence[Any], lead: Any) -> Any:
    """Phase 1 of a tick, with the inputs only: a two-phase controller's (``two_phase = True``:
    :meth:`prepare` then :meth:`finish`, e.g. the paper's generator rates) work done ahead;
    for any other controller just the inputs. Hand the result to :func:`finish`."""
    nbrs, leader = inputs_of(ctrl, nbr, lead)
    if getattr(ctrl, "two_phase", False):
        return ctrl.prepare(nbrs, leader)  # type: ignore[attr-defined]
    return nbrs, leader


def finish(ctrl: Controller, q: np.ndarray, v: np.ndarray, prepared: Any, dt: float) -> Command:
    """Phase 2 of a tick with the measured state (q, v) and dt s: the command (the controller is
    then at the next tick). ``finish(c, q, v, prepare(c, nbr, lead), dt)`` IS the tick, in the
    simulator, the agent process and ``zenswarm verify`` alike."""
    if getattr(ctrl, "two_phase", False):
        cmd: Command = ctrl.finish(q, v, prepared, dt)  # type: ignore[attr-defined]
        return cmd
    nbrs, leader = prepared
    return ctrl.step(q, v, nbrs, leader, dt)


# ----------------------------------------------------------------------------- the plug-in boundary
#
# The runners (the simulator, the agent process, ``zenswarm verify``) call a controller through
# these: an exception, a non-finite or a wrongly shaped output becomes a
# :class:`zenswarm.errors.PluginFailure` naming the controller, the UAV, the tick and the call
# or field, the same in every runner (docs/plugins.md, "When a plug-in fails").


def boundary_of(scenario: Scenario, i: int) -> Boundary:
    """The boundary of agent i's (0-based) controller: process ``agent:<i+1>``, UAV i + 1."""
    return Boundary("controller", scenario.agents.controller, f"agent:{i + 1}", (i + 1,))


def build_controller(scenario: Scenario, i: int, mass: float, g: float) -> Controller:
    """:func:`make_controller`, with the plug-in's constructor at the boundary (tick 0, stage
    build): a bad name or parameter is a ScenarioError (exit 2, checked before any work), an
    exception of the constructor a PluginFailure."""
    from zenswarm.scenario.plugins import decode_params, plugin_rng, resolve

    cls = resolve("controller", scenario.agents.controller)
    params = decode_params(cls, scenario.agents.params, "agents.params")
    ctx = context_of(scenario, i, mass, g, plugin_rng(scenario.seed, i + 1))
    ctrl: Controller = boundary_of(scenario, i).call(0, STAGE_BUILD, "__init__", cls, ctx, params)
    return ctrl


def check_shared(sh: Any, shares: Mapping[str, tuple[int, ...]]) -> list[tuple[str, str] | None]:
    """What is wrong with a :meth:`Controller.share` result: (field, problem) pairs (None: fine)."""
    if not (hasattr(sh, "q") and hasattr(sh, "v")):
        return [("share", f"{type(sh).__name__} is not a Shared (q, v, extra)")]
    out: list[tuple[str, str] | None] = []
    for name, x in (("q", sh.q), ("v", sh.v)):
        bad = bad_vector(x, (3,))
        out.append(None if bad is None else (name, bad))
    extra = getattr(sh, "extra", None) or {}
    for name, shape in shares.items():
        x = extra.get(name) if isinstance(extra, Mapping) else None
        size = int(np.prod(shape))
        bad = "missing (declared in shares)" if x is None else bad_vector(np.reshape(np.asarray(x, dtype=float), -1), (size,))
        out.append(None if bad is None else (f"extra.{name}", bad))
    return out


def check_command(cmd: Any) -> list[tuple[str, str] | None]:
    """What is wrong with a :meth:`Controller.step` result: (field, problem) pairs (None: fine)."""
    if not isinstance(cmd, Command):
        return [("command", f"{type(cmd).__name__} is not a zenswarm.agents.api.Command")]
    out: list[tuple[str, str] | None] = []
    bad = bad_scalar(cmd.thrust)
    out.append(None if bad is None else ("thrust", bad))
    for name, x in (("rpy", cmd.rpy), ("u", cmd.u), ("d_hat", cmd.d_hat)):
        bad = bad_vector(x, (3,))
        out.append(None if bad is None else (name, bad))
    return out


def checked_reset(ctrl: Controller, b: Boundary, k: int, q: np.ndarray, v: np.ndarray) -> None:
    """:meth:`Controller.reset` at tick k (stage share: it starts what the tick shares)."""
    b.call(k, STAGE_SHARE, "reset", ctrl.reset, q, v)


def checked_share(ctrl: Controller, b: Boundary, k: int) -> Shared:
    """:meth:`Controller.share` of tick k, checked (finite (3,) q and v, the declared extras)."""
    sh: Shared = b.call(k, STAGE_SHARE, "share", ctrl.share)
    b.check(k, STAGE_SHARE, "share", check_shared(sh, ctrl.shares))
    return sh


def checked_prepare(ctrl: Controller, b: Boundary, k: int, nbr: Sequence[Any], lead: Any) -> Any:
    """:func:`prepare` of tick k at the boundary."""
    two = bool(getattr(ctrl, "two_phase", False))
    return b.call(k, STAGE_STEP, "prepare" if two else "step", prepare, ctrl, nbr, lead)


def checked_finish(ctrl: Controller, b: Boundary, k: int, q: np.ndarray, v: np.ndarray, prepared: Any, dt: float) -> Command:
    """:func:`finish` of tick k at the boundary, its command checked (finite thrust, (3,) rpy, u, d_hat)."""
    what = "finish" if getattr(ctrl, "two_phase", False) else "step"
    cmd: Command = b.call(k, STAGE_STEP, what, finish, ctrl, q, v, prepared, dt)
    b.check(k, STAGE_STEP, what, check_command(cmd))
    return cmd

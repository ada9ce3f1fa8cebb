"""One agent's control tick, composed from the pure pieces (numpy only).

:class:`AgentCore` holds exactly what UAV i holds in the distributed swarm: its generator state
(q*_i, v*_i), its ESO estimate and its row of the graph. It performs steps 2-6 of a control tick
as documented in :mod:`zenswarm.compose.sim`. It is THE agent tick: the agent process
(:mod:`zenswarm.agents.process`), the in-process simulator (:mod:`zenswarm.compose.sim`) and
``zenswarm verify`` (:mod:`zenswarm.bridge.replay.verify`) all run it, so a lockstep swarm reproduces the
simulator and a recording reproduces its agents bit for bit.

:class:`StackedAgents` is the same tick for all N agents at once (the simulator's fast path
without link faults): its state arrays are (N, 3), its rates are :meth:`AgentCore.rates`'s
equations vectorised over agents (the same element-wise operations in the same order per row:
bit for bit), and its :meth:`~AgentCore.command` and :meth:`~AgentCore.advance` ARE
:class:`AgentCore`'s (inherited; the same numpy functions, which work row-wise on (N, 3)).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, cast

import numpy as np

from zenswarm.agents.controller import composite_control, invert_thrust_attitude
from zenswarm.agents.eso import eso_step
from zenswarm.agents.generator import generator_rates, generator_rates_slots, neighbour_slots

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = ["AgentCommand", "AgentCore", "AgentRow", "Rates", "RefLike", "StackedAgents", "elapsed_dt"]


class RefLike(Protocol):
    """A reference (q*, v*) as received: each (3,), m and m/s (:class:`zenswarm.bus.wire.Ref` is one)."""

    q: np.ndarray
    v: np.ndarray


Rates = tuple[np.ndarray, np.ndarray]
"""Generator rates (q*', v*') of one tick: (3,) m/s and m/s^2 for one agent, (N, 3) stacked."""


@dataclass(frozen=True)
class AgentRow:
    """What agent i (0-based index ``i``; UAV number i + 1) knows of the scenario.

    neighbours: 0-based indices j with a_ij > 0; weights: (k,) a_ij; h_nbr: (k, 3) their offsets.
    pinned weight b_i (0 = the agent never needs the leader).
    """

    i: int
    h: np.ndarray
    neighbours: tuple[int, ...]
    weights: np.ndarray
    h_nbr: np.ndarray
    b: float
    mu1: float
    mu2: float
    beta: tuple[float, float, float]
    eso_enabled: bool
    kp: np.ndarray
    kd: np.ndarray
    yaw: float
    mass: float
    g: float
    dt: float

    @classmethod
    def from_scenario(cls, scenario: Scenario, i: int, mass: float, g: float) -> AgentRow:
        graph = scenario.comm_graph  # built once per scenario: this is O(k_i), not O(N^2)
        h = scenario.offsets_array
        idx = graph.nbr[i]
        nbr = tuple(int(j) for j in idx)
        return cls(
            i=i,
            h=h[i].copy(),
            neighbours=nbr,
            weights=graph.w[i].copy(),
            h_nbr=h[idx].copy() if nbr else np.zeros((0, 3)),
            b=float(graph.b[i]),
            mu1=scenario.generator.mu1,
            mu2=scenario.generator.mu2,
            beta=cast("tuple[float, float, float]", tuple(scenario.eso.beta)),
            eso_enabled=scenario.eso.enabled,
            kp=np.asarray(scenario.controller.kp, dtype=float),
            kd=np.asarray(scenario.controller.kd, dtype=float),
            yaw=float(scenario.controller.yaw),
            mass=mass,
            g=g,
            dt=scenario.timing.dt,
        )

    @property
    def pinned(self) -> bool:
        return self.b > 0.0


def elapsed_dt(k: int, k_prev: int | None, dt: float) -> float | None:
    """Time (s) a realtime agent integrates over at tick ``k`` when the previous state it ticked
    on was of tick ``k_prev``: (k - k_prev) control periods of ``dt`` s. None (= one nominal
    period, :meth:`AgentCore.advance`'s default) when no tick was skipped, at the first tick
    (``k_prev`` None) and if the ticks do not advance (a restarted stream)."""
    if k_prev is None or k - k_prev <= 1:
        return None
    return (k - k_prev) * dt


@dataclass(frozen=True)
class AgentCommand:
    """Output of one tick: thrust F (N), attitude setpoint rpy (3,) rad, virtual control u (3,)
    m/s^2, the disturbance estimate used d_hat (3,) m/s^2 and the feed-forward v*' (3,).
    From :class:`StackedAgents`: thrust (N,), the others (N, 3)."""

    thrust: Any
    rpy: np.ndarray
    u: np.ndarray
    d_hat: np.ndarray
    vdot_ref: np.ndarray


class AgentCore:
    """Generator + ESO + composite controller of one UAV."""

    def __init__(self, row: AgentRow) -> None:
        self.row = row
        self.q_ref: np.ndarray | None = None
        self.v_ref: np.ndarray | None = None
        self.q_hat: np.ndarray | None = None
        self.v_hat: np.ndarray | None = None
        self.d_hat: np.ndarray | None = None

    @property
    def initialised(self) -> bool:
        return self.q_ref is not None

    def reset(self, q_meas: np.ndarray, v_meas: np.ndarray) -> None:
        """Start (or restart) from the measured state: q* = q, v* = 0; ESO at (q, v, 0)."""
        self.q_ref = np.array(q_meas, dtype=float)
        self.v_ref = np.zeros(self.q_ref.shape)
        self.q_hat = np.array(q_meas, dtype=float)
        self.v_hat = np.array(v_meas, dtype=float)
        self.d_hat = np.zeros(self.q_ref.shape)

    def rates_from(self, nbr: Sequence[RefLike | None], lead: RefLike | None) -> Rates:
        """Step 3 from the inputs as received: ``nbr`` holds the neighbours' references in
        ``row.neighbours`` order (None: never heard from, left out this tick), ``lead`` the
        leader's (None: no pinning term this tick). See :meth:`rates`."""
        present = [x for x, m in enumerate(nbr) if m is not None]
        qn = np.array([nbr[x].q for x in present]).reshape(-1, 3)  # type: ignore[union-attr]
        vn = np.array([nbr[x].v for x in present]).reshape(-1, 3)  # type: ignore[union-attr]
        return self.rates(qn, vn, lead.q if lead else None, lead.v if lead else None, present)

    def rates(
        self,
        q_nbr: np.ndarray,
        v_nbr: np.ndarray,
        q0: np.ndarray | None,
        v0: np.ndarray | None,
        present: list[int] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Step 3 of a tick: the generator rates (q*_i', v*_i') of eqs (16)-(17), each (3,).

        Depends on the references only (own q*_i, v*_i and the neighbours' / leader's), not on
        the measured state: the agent process computes them as soon as its neighbours'
        references of tick k are in, before the plant's state(k) arrives (see :meth:`tick`)."""
        assert self.q_ref is not None and self.v_ref is not None, "reset() first"
        r = self.row
        weights, h_nbr = r.weights, r.h_nbr
        if present is not None and len(present) != len(r.neighbours):
            weights, h_nbr = weights[present], h_nbr[present]
        b = r.b if q0 is not None else 0.0
        return generator_rates(self.q_ref, self.v_ref, r.h, q_nbr, v_nbr, h_nbr, weights, b, q0, v0, r.mu1, r.mu2)

    def command(self, q_meas: np.ndarray, v_meas: np.ndarray, dv: np.ndarray) -> AgentCommand:
        """Steps 4-5: the composite control (28) from the measured state (q, v: (3,) m, m/s)
        and the generator's v*' = ``dv`` (3,) m/s^2, then thrust/attitude inversion. Changes no
        state: call :meth:`advance` with the result to finish the tick."""
        assert self.q_ref is not None and self.v_ref is not None and self.d_hat is not None, "reset() first"
        r = self.row
        d_used = self.d_hat if r.eso_enabled else np.zeros(np.shape(self.d_hat))
        u = composite_control(self.q_ref, self.v_ref, dv, q_meas, v_meas, d_used, r.kp, r.kd, r.g)
        F, phi, theta = invert_thrust_attitude(u, r.mass, r.yaw)
        return self._command_of(F, phi, theta, u, d_used, dv)

    def _command_of(self, F: Any, phi: Any, theta: Any, u: np.ndarray, d_used: np.ndarray, dv: np.ndarray) -> AgentCommand:
        return AgentCommand(float(F), np.array([float(phi), float(theta), self.row.yaw]), u, d_used.copy(), dv)

    def advance(self, q_meas: np.ndarray, u: np.ndarray, dq: np.ndarray, dv: np.ndarray, dt: float | None = None) -> None:
        """Step 6: ESO (27) and generator to k+1 with the tick's control ``u`` and rates.

        ``dt`` (s): the time to integrate over; None or ``row.dt`` = one control period (lockstep,
        the simulator, replay: always, so they stay bit-identical). A realtime agent that
        skipped ticks passes the time that elapsed since the state it last ticked on
        (:func:`elapsed_dt`); see :meth:`advance_elapsed` for how a long step stays stable."""
        if dt is not None and dt != self.row.dt:
            self.advance_elapsed(q_meas, u, dq, dv, dt)
            return
        assert self.q_hat is not None and self.v_hat is not None and self.d_hat is not None, "reset() first"
        assert self.q_ref is not None and self.v_ref is not None, "reset() first"
        r = self.row
        self.q_hat, self.v_hat, self.d_hat = eso_step(self.q_hat, self.v_hat, self.d_hat, q_meas, u, r.beta, r.dt, r.g)
        self.q_ref = self.q_ref + r.dt * dq
        self.v_ref = self.v_ref + r.dt * dv

    def advance_elapsed(self, q_meas: np.ndarray, u: np.ndarray, dq: np.ndarray, dv: np.ndarray, dt: float) -> None:
        """Step 6 over an elapsed time ``dt`` (s) that may span several control periods.

        ESO (27): ``ceil(dt / row.dt)`` explicit-Euler sub-steps of equal length (at most one
        control period each, so the observer's discretisation is never coarser than nominally
        and stays as stable as at the nominal rate), with the measurement ``q_meas`` and the
        control ``u`` held over the sub-steps. Generator (16)-(17): one explicit-Euler step with
        the tick's rates (the neighbours' references are held anyway), over ``dt`` clamped to
        :meth:`generator_max_step`: for a longer gap the references lag by the excess (as before
        this existed) rather than overshoot. ``dt`` equal to ``row.dt`` computes what
        :meth:`advance` does with ``dt=None``."""
        assert self.q_hat is not None and self.v_hat is not None and self.d_hat is not None, "reset() first"
        assert self.q_ref is not None and self.v_ref is not None, "reset() first"
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError(f"elapsed dt must be positive and finite, got {dt!r} s")
        r = self.row
        n = max(1, math.ceil(dt / r.dt - 1e-9))
        h = dt / n
        q_hat, v_hat, d_hat = self.q_hat, self.v_hat, self.d_hat
        for _ in range(n):
            q_hat, v_hat, d_hat = eso_step(q_hat, v_hat, d_hat, q_meas, u, r.beta, h, r.g)
        self.q_hat, self.v_hat, self.d_hat = q_hat, v_hat, d_hat
        hg = min(dt, self.generator_max_step())
        self.q_ref = self.q_ref + hg * dq
        self.v_ref = self.v_ref + hg * dv

    def generator_max_step(self) -> float:
        """Longest explicit-Euler step (s) of this agent's generator: 1 / (max(mu1, mu2) d_i),
        d_i = sum_j a_ij + b_i. Within it the agent's own feedback terms of (16)-(17)
        (-mu d_i q*_i, -mu d_i v*_i) contract without changing sign (the Euler factor
        1 - mu d_i h stays in [0, 1)). Infinite for an isolated, unpinned agent."""
        r = self.row
        d = float(np.sum(r.weights)) + r.b
        mu = max(r.mu1, r.mu2)
        return 1.0 / (mu * d) if mu * d > 0.0 else math.inf

    def tick(
        self,
        q_meas: np.ndarray,
        v_meas: np.ndarray,
        q_nbr: np.ndarray,
        v_nbr: np.ndarray,
        q0: np.ndarray | None,
        v0: np.ndarray | None,
        present: list[int] | None = None,
    ) -> AgentCommand:
        """Steps 3-6 of a tick: rates (16-17), control (28), inversion, then ESO and generator
        steps to k+1. q_nbr, v_nbr: (k, 3) neighbours' references in ``row.neighbours`` order.
        q0, v0 are needed only if pinned. After the call ``q_ref, v_ref`` hold tick k+1.
        Equal to :meth:`rates`, then :meth:`command`, then :meth:`advance` (the same operations
        in the same order: bit-identical).

        Missing data (a neighbour never heard from, or the leader before its first message):
        ``present`` lists the positions in ``row.neighbours`` that q_nbr/v_nbr hold (default: all),
        and q0 = None drops the pinning term for this tick."""
        return self.finish(q_meas, v_meas, self.rates(q_nbr, v_nbr, q0, v0, present))

    def finish(self, q_meas: np.ndarray, v_meas: np.ndarray, rates: Rates, dt: float | None = None) -> AgentCommand:
        """Steps 4-6 with the tick's generator rates (from :meth:`rates` or :meth:`rates_from`):
        :meth:`command`, then :meth:`advance` over ``dt`` (s; None = ``row.dt``). Returns the command."""
        dq, dv = rates
        cmd = self.command(q_meas, v_meas, dv)
        self.advance(q_meas, cmd.u, dq, dv, dt)
        return cmd


class StackedAgents(AgentCore):
    """All N agents of a scenario as one :class:`AgentCore` with (N, 3) state arrays.

    For the in-process simulator without link faults (every agent hears every input of every
    tick). :meth:`rates_all` computes what :meth:`AgentCore.rates` computes for every row at
    once (:func:`zenswarm.agents.generator.generator_rates_slots`); :meth:`command`, :meth:`advance`
    and :meth:`finish` are :class:`AgentCore`'s. The rows' scenario-wide gains (kp, kd, beta, mass, g, yaw, dt, eso) are those of row 0.
    """

    def __init__(self, rows: Sequence[AgentRow]) -> None:
        super().__init__(rows[0])
        self.rows = list(rows)
        self.h_all = np.array([r.h for r in self.rows])
        self.slots = neighbour_slots([np.asarray(r.neighbours, dtype=np.int64) for r in self.rows],
                                     [r.weights for r in self.rows], np.array([r.b for r in self.rows]))

    def rates_all(self, q0: np.ndarray, v0: np.ndarray) -> Rates:
        """Step 3 for every agent: ((N, 3), (N, 3)), row i as :meth:`AgentCore.rates` of agent i
        with all its neighbours present and the leader's (q0, v0) (3,) given: eqs (16)-(17)
        vectorised over agents (:func:`zenswarm.agents.generator.generator_rates_slots`, the same
        operations in the same order, bit for bit)."""
        q, v = self.q_ref, self.v_ref
        assert q is not None and v is not None, "reset() first"
        r = self.row
        return generator_rates_slots(q, v, self.h_all, self.slots, q0, v0, r.mu1, r.mu2)

    def _command_of(self, F: Any, phi: Any, theta: Any, u: np.ndarray, d_used: np.ndarray, dv: np.ndarray) -> AgentCommand:
        rpy = np.empty((len(F), 3))
        rpy[:, 0], rpy[:, 1], rpy[:, 2] = phi, theta, self.row.yaw
        return AgentCommand(F, rpy, u, d_used.copy(), dv)

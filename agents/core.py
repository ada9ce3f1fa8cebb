"""One agent's control tick, composed from the pure pieces (numpy only).

:class:`AgentCore` holds exactly what UAV i holds in the distributed swarm: its generator state
(q*_i, v*_i), its ESO estimate and its row of the graph. It performs steps 2-6 of a control tick
as documented in :mod:`zenswarm.compose.sim`, in the same order and with the same functions, so a
lockstep swarm reproduces the in-process simulator.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, cast

import numpy as np

from zenswarm.agents.controller import composite_control, invert_thrust_attitude
from zenswarm.agents.eso import eso_step
from zenswarm.agents.generator import generator_rates

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.config import Scenario

__all__ = ["AgentRow", "AgentCommand", "AgentCore"]


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
        A = np.asarray(scenario.graph.adjacency, dtype=float)
        h = np.asarray(scenario.offsets, dtype=float)
        nbr = tuple(int(j) for j in np.flatnonzero(A[i]))
        return cls(
            i=i,
            h=h[i].copy(),
            neighbours=nbr,
            weights=A[i, list(nbr)].copy(),
            h_nbr=h[list(nbr)].copy() if nbr else np.zeros((0, 3)),
            b=float(scenario.graph.pinning[i]),
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


@dataclass(frozen=True)
class AgentCommand:
    """Output of one tick: thrust F (N), attitude setpoint rpy (3,) rad, virtual control u (3,)
    m/s^2, the disturbance estimate used d_hat (3,) m/s^2 and the feed-forward v*' (3,)."""

    thrust: float
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
        self.v_ref = np.zeros(3)
        self.q_hat = np.array(q_meas, dtype=float)
        self.v_hat = np.array(v_meas, dtype=float)
        self.d_hat = np.zeros(3)

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
        d_used = self.d_hat if r.eso_enabled else np.zeros(3)
        u = composite_control(self.q_ref, self.v_ref, dv, q_meas, v_meas, d_used, r.kp, r.kd, r.g)
        F, phi, theta = invert_thrust_attitude(u, r.mass, r.yaw)
        return AgentCommand(float(F), np.array([float(phi), float(theta), r.yaw]), u, d_used.copy(), dv)

    def advance(self, q_meas: np.ndarray, u: np.ndarray, dq: np.ndarray, dv: np.ndarray) -> None:
        """Step 6: ESO (27) and generator to k+1 with the tick's control ``u`` and rates."""
        assert self.q_hat is not None and self.v_hat is not None and self.d_hat is not None, "reset() first"
        assert self.q_ref is not None and self.v_ref is not None, "reset() first"
        r = self.row
        self.q_hat, self.v_hat, self.d_hat = eso_step(self.q_hat, self.v_hat, self.d_hat, q_meas, u, r.beta, r.dt, r.g)
        self.q_ref = self.q_ref + r.dt * dq
        self.v_ref = self.v_ref + r.dt * dv

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
        dq, dv = self.rates(q_nbr, v_nbr, q0, v0, present)
        cmd = self.command(q_meas, v_meas, dv)
        self.advance(q_meas, cmd.u, dq, dv)
        return cmd

"""A first-order consensus formation law with PD tracking and no disturbance observer.

A different, simpler scheme than the paper's (second-order generator + ESO + composite control),
written against zenswarm's controller interface (:class:`zenswarm.agents.api.Controller`) only.

UAV i keeps a reference position r_i (3,) m, ENU. With xi_i = r_i - h_i (its formation-centred
reference; h_i its offset), its neighbours' shared (r_j, w_j) and, if pinned, the leader's
(q0, v0), each tick k:

    e_i  = sum_j a_ij (xi_i - xi_j) + b_i (xi_i - q0)                    consensus error, m
    ff_i = (sum_j a_ij w_j + b_i v0) / (sum_j a_ij + b_i)                 velocity feed-forward, m/s
    w_i  = ff_i - k_c e_i                                                 reference rate, m/s
    u_i  = kp (r_i - q_i) + kd (w_i - v_i) + g e_z                       PD tracking, m/s^2
    r_i <- r_i + dt w_i                                                   explicit Euler

then thrust and attitude from u_i by zenswarm's inversion (F = m ||u||, roll/pitch for the yaw).
Sums run over what has been heard (a neighbour or leader not heard from yet is left out). The
agent shares (r_i, w_i of the previous tick): nothing beyond zenswarm's (q, v) pair.

Pure and deterministic: numpy only, no clock, no I/O, no randomness.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any

import msgspec
import numpy as np

from zenswarm.agents.api import Command, Controller, ControllerContext, Shared
from zenswarm.vehicle.inversion import invert_thrust_attitude

__all__ = ["ConsensusController", "ConsensusParams"]

Positive = Annotated[float, msgspec.Meta(gt=0)]


class ConsensusParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``[agents.params]`` of the consensus controller (every key optional).

    k_consensus: consensus gain k_c, 1/s. kp: position gains (3,), 1/s^2. kd: velocity gains (3,),
    1/s. yaw: desired yaw, rad."""

    k_consensus: Positive = 1.0
    kp: tuple[Positive, Positive, Positive] = (4.5, 4.5, 5.4)
    kd: tuple[Positive, Positive, Positive] = (5.0, 5.0, 3.0)
    yaw: float = 0.0


class ConsensusController(Controller):
    """First-order consensus on formation-centred references + PD tracking (no ESO)."""

    name = "consensus"
    description = "example plug-in: first-order consensus formation law with PD tracking, no ESO"
    Params = ConsensusParams

    def __init__(self, ctx: ControllerContext, params: Any) -> None:
        super().__init__(ctx, params)
        p: ConsensusParams = params
        self.kc = float(p.k_consensus)
        self.kp = np.asarray(p.kp, dtype=float)
        self.kd = np.asarray(p.kd, dtype=float)
        self.gz = np.array([0.0, 0.0, ctx.g])
        self.r: np.ndarray | None = None  # reference position r_i (3,), m
        self.w = np.zeros(3)  # reference rate of the previous tick (3,), m/s

    @property
    def initialised(self) -> bool:
        return self.r is not None

    def reset(self, q: np.ndarray, v: np.ndarray) -> None:
        """Start the reference at the measured position, at rest."""
        self.r = np.array(q, dtype=float)
        self.w = np.zeros(3)

    def share(self) -> Shared:
        assert self.r is not None, "reset() first"
        return Shared(self.r, self.w)

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        assert self.r is not None, "reset() first"
        ctx = self.ctx
        xi = self.r - ctx.offset
        err = np.zeros(3)
        ff = np.zeros(3)
        weight = 0.0
        for nb, msg in zip(ctx.neighbours, neighbours, strict=True):
            if msg is None:
                continue
            err = err + nb.weight * (xi - (np.asarray(msg.q) - nb.offset))
            ff = ff + nb.weight * np.asarray(msg.v)
            weight += nb.weight
        if ctx.pinned and leader is not None:
            err = err + ctx.pinning * (xi - np.asarray(leader.q))
            ff = ff + ctx.pinning * np.asarray(leader.v)
            weight += ctx.pinning
        w = (ff / weight if weight > 0 else ff) - self.kc * err
        u = self.kp * (self.r - q) + self.kd * (w - v) + self.gz
        thrust, roll, pitch = invert_thrust_attitude(u, ctx.mass, self.params.yaw)
        self.r = self.r + dt * w  # replaced, never mutated: a runner may hold the shared arrays
        self.w = w
        return Command(float(thrust), np.array([float(roll), float(pitch), self.params.yaw]), u, np.zeros(3))

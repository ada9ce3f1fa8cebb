"""Distributed second-order reference generator, paper eqs (16)-(17).

Pure numerics (numpy only). Two forms of the same equations:

* :func:`generator_rates` for one agent i, using only what agent i has in the distributed
  swarm: its own generator state (q*_i, v*_i) and offset h_i, its neighbours' (q*_j, v*_j) with
  their offsets h_j and weights a_ij, and, only if pinned (b_i > 0), the leader's (q0, v0).
* :func:`generator_rates_all` for all N agents at once, from the whole graph (analysis and tests).
* :func:`generator_rates_slots` for all N agents at once from neighbour lists, vectorised over
  agents (the in-process simulator, through :class:`zenswarm.agents.core.StackedAgents`): it
  adds the same terms in the same order as :func:`generator_rates` does for each agent (slot s =
  every agent's s-th neighbour), with element-wise numpy operations only, so every row is bit
  for bit agent i's (no reduction whose summation order could differ).

Both return (q*_i', v*_i'); v*_i' is also the feed-forward term v-dot-star of eq. (28).
Discretisation (both simulator and swarm): explicit Euler at the control period dt,
q*(k+1) = q*(k) + dt q*'(k), v*(k+1) = v*(k) + dt v*'(k), see :func:`euler_step`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "generator_rates", "generator_rates_all", "generator_rates_slots", "NeighbourSlots", "neighbour_slots", "euler_step",
    "graph_matrix", "error_matrix",
]


def generator_rates(
    q_i: np.ndarray,
    v_i: np.ndarray,
    h_i: np.ndarray,
    q_nbr: np.ndarray,
    v_nbr: np.ndarray,
    h_nbr: np.ndarray,
    a_nbr: np.ndarray,
    b_i: float,
    q0: np.ndarray | None,
    v0: np.ndarray | None,
    mu1: float,
    mu2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Right-hand sides of eqs (16) and (17) for agent i.

    q_i, v_i, h_i: (3,) m, m/s, m: own generator state and formation offset.
    q_nbr, v_nbr, h_nbr: (k, 3) the k neighbours' q*_j, v*_j and h_j (k may be 0).
    a_nbr: (k,) weights a_ij > 0. b_i: pinning weight (0 = not pinned; q0, v0 are then unused
    and may be None). q0, v0: (3,) leader position and velocity. mu1, mu2 > 0.
    Returns (q*_i' (3,) m/s, v*_i' (3,) m/s^2).
    """
    e_q = np.zeros(3)
    e_v = np.zeros(3)
    base = q_i - h_i
    for k in range(len(a_nbr)):
        a = a_nbr[k]
        e_q += a * (base - (q_nbr[k] - h_nbr[k]))
        e_v += a * (v_i - v_nbr[k])
    if b_i > 0.0:
        e_q += b_i * (q_i - (q0 + h_i))
        e_v += b_i * (v_i - v0)
    return v_i - mu1 * e_q, -mu2 * e_v


def generator_rates_all(
    qs: np.ndarray,
    vs: np.ndarray,
    h: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    q0: np.ndarray,
    v0: np.ndarray,
    mu1: float,
    mu2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs (16)-(17) for all agents. qs, vs, h: (N, 3); A: (N, N) symmetric; b: (N,); q0, v0: (3,).

    Computed per agent in the same order as :func:`generator_rates` so that the in-process
    simulator and the distributed swarm agree to rounding. Returns ((N, 3), (N, 3)).
    """
    n = qs.shape[0]
    dq = np.empty_like(qs)
    dv = np.empty_like(vs)
    for i in range(n):
        nbr = np.flatnonzero(A[i])
        dq[i], dv[i] = generator_rates(
            qs[i], vs[i], h[i], qs[nbr], vs[nbr], h[nbr], A[i, nbr], float(b[i]), q0, v0, mu1, mu2
        )
    return dq, dv


@dataclass(frozen=True)
class NeighbourSlots:
    """The graph as slots for :func:`generator_rates_slots`: ``slots[s]`` = (rows, cols, a) with
    rows (m_s,) the agents that have an s-th neighbour (0-based s, in increasing neighbour
    order), cols (m_s,) that neighbour j, a (m_s, 1) the weight a_ij; ``pin_rows`` (p,) the
    pinned agents and ``pin_b`` (p, 1) their b_i > 0."""

    slots: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]
    pin_rows: np.ndarray
    pin_b: np.ndarray


def neighbour_slots(nbr: Sequence[Any], weights: Sequence[Any], b: Any) -> NeighbourSlots:
    """:class:`NeighbourSlots` of neighbour lists ``nbr[i]`` (k_i,) int (increasing j), their
    weights ``weights[i]`` (k_i,) and the pinning b (N,). O(N + E) memory and time."""
    deg = np.array([len(x) for x in nbr], dtype=np.int64)
    slots = []
    for s in range(int(deg.max()) if len(deg) else 0):
        rows = np.flatnonzero(deg > s)
        cols = np.array([nbr[int(i)][s] for i in rows], dtype=np.int64)
        a = np.array([weights[int(i)][s] for i in rows], dtype=np.float64).reshape(-1, 1)
        slots.append((rows, cols, a))
    bb = np.asarray(b, dtype=float)
    pin = np.flatnonzero(bb > 0.0)
    return NeighbourSlots(tuple(slots), pin, bb[pin].reshape(-1, 1))


def generator_rates_slots(
    q: np.ndarray,
    v: np.ndarray,
    h: np.ndarray,
    graph: NeighbourSlots,
    q0: np.ndarray,
    v0: np.ndarray,
    mu1: float,
    mu2: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs (16)-(17) for all agents: q, v, h (N, 3) generator states and offsets; the graph as
    :func:`neighbour_slots`; q0, v0 (3,) the leader's. Returns (q*' (N, 3) m/s, v*' (N, 3) m/s^2).

    Row i equals :func:`generator_rates` of agent i bit for bit: e_q and e_v start at 0 and get
    a_ij (q*_i - h_i - (q*_j - h_j)) and a_ij (v*_i - v*_j) added neighbour by neighbour in
    increasing j, then the pinning term, with the same element-wise operations."""
    e_q = np.zeros_like(q)
    e_v = np.zeros_like(v)
    base = q - h  # q*_i - h_i, and (the same operation) q*_j - h_j of every neighbour
    for rows, cols, a in graph.slots:
        e_q[rows] += a * (base[rows] - base[cols])
        e_v[rows] += a * (v[rows] - v[cols])
    p, b = graph.pin_rows, graph.pin_b
    if len(p):
        e_q[p] += b * (q[p] - (q0 + h[p]))
        e_v[p] += b * (v[p] - v0)
    return v - mu1 * e_q, -mu2 * e_v


def euler_step(q: np.ndarray, v: np.ndarray, dq: np.ndarray, dv: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Explicit Euler update of the generator state over one control period dt (s)."""
    return q + dt * dq, v + dt * dv


def graph_matrix(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """M = L + B for adjacency A (N, N) and pinning b (N,) (section Graph theory notions)."""
    A = np.asarray(A, dtype=float)
    M: np.ndarray = np.diag(A.sum(axis=1)) - A + np.diag(np.asarray(b, dtype=float))
    return M


def error_matrix(M: np.ndarray, mu1: float, mu2: float) -> np.ndarray:
    """D of eq. (21): [[-mu1 M, I], [0, -mu2 M]], (2N, 2N)."""
    n = M.shape[0]
    return np.block([[-mu1 * M, np.eye(n)], [np.zeros((n, n)), -mu2 * M]])

"""The communication graph among the followers, as neighbour lists (section Graph theory notions).

A scenario's ``[graph]`` gives the undirected weighted graph A (N, N) in one of three forms
(:class:`zenswarm.schema.GraphConfig`), and the pinning b (N,):

* ``adjacency``: the dense matrix (N rows of N weights, a_ij = a_ji >= 0, zero diagonal);
* ``edges``: a list of ``[i, j, a_ij]`` with UAV numbers 1..N and a weight > 0; each undirected
  edge once (listing it in both directions is allowed when both carry the same weight);
* ``topology``: one of the generator's topologies by name (``ring``, ``star``, ``complete``,
  ``knn`` with ``k``), built from the formation offsets by :func:`topology_neighbours` (unit
  weights; :func:`zenswarm.scenario.generate.adjacency_matrix` is its dense form).

:class:`CommGraph` holds it once per scenario as neighbour lists (row i: the 0-based indices j
with a_ij > 0, increasing, and their weights): building and checking it is O(N + E) for the
sparse forms (O(N^2) only to read a dense matrix, and for ``knn`` the distances). Lemma 1's
condition (M = L + B positive definite) is checked as the equivalent graph condition: every
connected component has a pinned UAV (b_i > 0), which needs no eigenvalues.

Errors are :class:`zenswarm.errors.ScenarioError` naming the field and the offending entry
(``graph.edges[3]``, ``graph.adjacency[1][1]``, ``graph.pinning``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError

__all__ = ["TOPOLOGIES", "CommGraph", "components", "topology_neighbours"]

TOPOLOGIES: tuple[str, ...] = ("ring", "star", "complete", "knn")
"""The topologies ``[graph] topology`` names (the generator's, :mod:`zenswarm.scenario.generate`)."""

_KNN_BLOCK = 256
"""Rows of the (rows, N) distance block the knn builder holds at once (memory O(256 N))."""


@dataclass(frozen=True, eq=False)
class CommGraph:
    """The undirected graph A and pinning b of a scenario, as neighbour lists.

    n: N. nbr[i]: (k_i,) int64, the 0-based neighbours j of UAV i (a_ij > 0), increasing.
    w[i]: (k_i,) float64, their weights a_ij. b: (N,) float64 pinning weights b_i >= 0.
    Arrays are read-only (one graph is shared by every agent of a run)."""

    n: int
    nbr: tuple[np.ndarray, ...]
    w: tuple[np.ndarray, ...]
    b: np.ndarray

    # ------------------------------------------------------------------ queries

    def neighbours(self, i: int) -> list[int]:
        """0-based indices j with a_ij > 0 of 0-based UAV i, increasing."""
        return [int(j) for j in self.nbr[i]]

    @property
    def n_edges(self) -> int:
        """Number of undirected edges E."""
        return sum(len(x) for x in self.nbr) // 2

    def dense(self) -> np.ndarray:
        """A as a dense (N, N) float64 matrix (analysis, plots; O(N^2) memory)."""
        A = np.zeros((self.n, self.n))
        for i in range(self.n):
            A[i, self.nbr[i]] = self.w[i]
        return A

    def edge_list(self) -> list[tuple[int, int, float]]:
        """The undirected edges as ``(i, j, a_ij)``, UAV numbers 1..N, i < j, in row order."""
        return [(i + 1, int(j) + 1, float(a)) for i in range(self.n) for j, a in zip(self.nbr[i], self.w[i], strict=True) if j > i]

    # ------------------------------------------------------------------ builders

    @classmethod
    def from_lists(cls, nbr: Sequence[Any], w: Sequence[Any], b: Any) -> CommGraph:
        """From neighbour lists (each increasing) and weights; b (N,)."""
        def ro(a: np.ndarray) -> np.ndarray:
            a.setflags(write=False)
            return a

        return cls(
            n=len(nbr),
            nbr=tuple(ro(np.asarray(x, dtype=np.int64).reshape(-1)) for x in nbr),
            w=tuple(ro(np.asarray(x, dtype=float).reshape(-1)) for x in w),
            b=ro(np.array(b, dtype=float)),
        )

    @classmethod
    def from_dense(cls, adjacency: Any, b: Any, field: str = "graph.adjacency") -> CommGraph:
        """From a dense matrix (N rows of N weights), checked: weights >= 0, zero diagonal, symmetric."""
        A = np.asarray(adjacency, dtype=float).reshape(len(adjacency), -1) if len(adjacency) else np.zeros((0, 0))
        if np.any(A < 0):
            i, j = np.argwhere(A < 0)[0]
            raise ScenarioError(f"{field}[{i}][{j}]", "weights must be >= 0")
        if not np.array_equal(A, A.T):
            i, j = np.argwhere(A != A.T)[0]
            raise ScenarioError(field, f"must be symmetric (undirected graph): a[{i}][{j}]={A[i, j]} but a[{j}][{i}]={A[j, i]}")
        if np.any(np.diag(A) != 0):
            i = int(np.flatnonzero(np.diag(A))[0])
            raise ScenarioError(f"{field}[{i}][{i}]", "diagonal must be 0 (no self loops)")
        nbr = [np.flatnonzero(row) for row in A]
        return cls.from_lists(nbr, [A[i, x] for i, x in enumerate(nbr)], b)

    @classmethod
    def from_edges(cls, edges: Sequence[Sequence[Any]], n: int, b: Any, field: str = "graph.edges") -> CommGraph:
        """From ``[i, j, a_ij]`` entries (UAV numbers 1..n, weight > 0 and finite), checked: the
        UAVs exist, no self loop, and an edge listed twice (either direction) has one weight."""
        seen: dict[tuple[int, int], int] = {}  # (lo, hi) 0-based -> entry index
        rows: list[dict[int, float]] = [{} for _ in range(n)]
        for x, e in enumerate(edges):
            i, j, a = int(e[0]), int(e[1]), float(e[2])
            for pos, u in ((0, i), (1, j)):
                if not 1 <= u <= n:
                    raise ScenarioError(f"{field}[{x}][{pos}]", f"UAV {u} does not exist (the scenario has UAVs 1..{n}), in {list(e)}")
            if i == j:
                raise ScenarioError(f"{field}[{x}]", f"self loop {list(e)}: an edge joins two different UAVs")
            if not (math.isfinite(a) and a > 0.0):
                raise ScenarioError(
                    f"{field}[{x}][2]", f"the weight must be finite and > 0 (leave a missing edge out), got {a!r} in {list(e)}"
                )
            key = (min(i, j) - 1, max(i, j) - 1)
            if key in seen:
                y = seen[key]
                prev = float(edges[y][2])
                if prev != a:
                    raise ScenarioError(
                        f"{field}[{x}]",
                        f"asymmetric: {list(e)} but {field}[{y}] = {list(edges[y])}; an undirected edge has one weight "
                        "(list it once)",
                    )
                continue
            seen[key] = x
            rows[key[0]][key[1]] = a
            rows[key[1]][key[0]] = a
        nbr = [sorted(r) for r in rows]
        return cls.from_lists(nbr, [[r[j] for j in s] for r, s in zip(rows, nbr, strict=True)], b)

    @classmethod
    def from_topology(cls, topology: str, k: int | None, offsets: Any, b: Any) -> CommGraph:
        """From a topology name (:data:`TOPOLOGIES`; ``k`` for ``knn``) and the offsets (N, 3) m,
        unit weights (:func:`topology_neighbours`)."""
        nbr = topology_neighbours(offsets, topology, 2 if k is None else k)
        return cls.from_lists(nbr, [np.ones(len(x)) for x in nbr], b)

    # ------------------------------------------------------------------ Lemma 1

    def check_pinning(self, field: str = "graph.pinning") -> None:
        """b >= 0, and every connected component has a pinned UAV: then, and only then, the leader
        reaches every UAV through a spanning tree of G-bar and M = L + B is positive definite
        (Lemma 1). Raises ScenarioError naming the first UAV the leader does not reach."""
        if len(self.b) != self.n:
            raise ScenarioError(field, f"expected a list of length {self.n}, got {len(self.b)}")
        if np.any(self.b < 0):
            i = int(np.flatnonzero(self.b < 0)[0])
            raise ScenarioError(field, f"weights must be >= 0, got b[{i}] = {self.b[i]}")
        for comp in components(self.nbr):
            if not np.any(self.b[comp] > 0):
                uavs = ", ".join(str(i + 1) for i in comp[:10]) + (", ..." if len(comp) > 10 else "")
                raise ScenarioError(
                    field,
                    f"the leader reaches no spanning tree: UAV {comp[0] + 1} (pinning[{comp[0]}]) is in a connected "
                    f"component of {len(comp)} UAV{'s' if len(comp) != 1 else ''} ({uavs}) without a pinned UAV, so "
                    "M = L + B is not positive definite; pin at least one UAV in every connected component",
                )


def components(nbr: Sequence[Any]) -> list[list[int]]:
    """Connected components of an undirected graph given by neighbour lists: lists of 0-based
    nodes, each sorted, ordered by their smallest node. O(N + E)."""
    n = len(nbr)
    seen = np.zeros(n, dtype=bool)
    out: list[list[int]] = []
    for root in range(n):
        if seen[root]:
            continue
        seen[root] = True
        stack, comp = [root], []
        while stack:  # bounded: each node is pushed once
            i = stack.pop()
            comp.append(i)
            for j in nbr[i]:
                if not seen[j]:
                    seen[j] = True
                    stack.append(int(j))
        out.append(sorted(comp))
    return out


def topology_neighbours(offsets: Any, topology: str, k: int = 2) -> list[list[int]]:
    """Neighbour lists (increasing) of a named topology over the offsets (N, 3) m, without an
    (N, N) matrix (:func:`zenswarm.scenario.generate.adjacency_matrix` is their dense form).

    ``ring``: i ~ i+1 (mod N); ``star``: UAV 1 ~ every other; ``complete``: all pairs; ``knn``:
    each UAV ~ its k nearest by offset distance (ties by index; k clamped to N - 1), symmetrised,
    then while disconnected the closest pair between UAV 1's component and the rest is joined."""
    h = np.asarray(offsets, dtype=float)
    n = h.shape[0]
    if topology not in TOPOLOGIES:
        raise ValueError(f"unknown topology {topology!r} (choose from {', '.join(TOPOLOGIES)})")
    if topology == "knn" and (isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1):
        raise ValueError(f"k must be an integer >= 1 (neighbours per UAV for knn), got {k!r}")
    adj: list[set[int]] = [set() for _ in range(n)]
    if n == 1:
        return [[]]

    def join(i: int, j: int) -> None:
        adj[i].add(j)
        adj[j].add(i)

    if topology == "ring":
        for i in range(n):
            join(i, (i + 1) % n)
    elif topology == "star":
        for j in range(1, n):
            join(0, j)
    elif topology == "complete":
        return [[j for j in range(n) if j != i] for i in range(n)]
    else:
        kk = min(int(k), n - 1)
        for lo in range(0, n, _KNN_BLOCK):  # the distances a block of rows at a time
            D = np.linalg.norm(h[lo:lo + _KNN_BLOCK, None, :] - h[None, :, :], axis=2)
            for r in range(D.shape[0]):
                D[r, lo + r] = np.inf
                for j in np.argsort(D[r], kind="stable")[:kk]:
                    join(lo + r, int(j))
        for _ in range(n - 1):  # bounded: each join merges two components
            comps = components([sorted(a) for a in adj])
            if len(comps) == 1:
                break
            inside = np.zeros(n, dtype=bool)
            inside[comps[0]] = True
            ins, outs = np.flatnonzero(inside), np.flatnonzero(~inside)
            sub = np.linalg.norm(h[ins][:, None, :] - h[outs][None, :, :], axis=2)
            a, c = np.unravel_index(int(np.argmin(sub)), sub.shape)
            join(int(ins[a]), int(outs[c]))
    return [sorted(a) for a in adj]

"""Obstacle and swarm geometry on arrays: clearances to the capped cylinders, the leader sphere's
d_obs, and the nearest pair of a point set.

Pure (numpy only). Obstacles are any objects with ``center`` (3,) = base centre c, ``radius`` r_o
and ``height`` h_o: a vertical cylinder capped by an upper hemisphere (paper, Remark 1), e.g.
:class:`zenswarm.schema.Obstacle`. Positions are in metres, inertial ENU frame (z up). :func:`obstacle_clearance`
is the scalar form used by the scenario's checks and the planner; the ``_many`` functions are
vectorised twins for judging and plotting whole flights.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["obstacle_clearance", "obstacle_clearance_many", "d_obs_many", "close_pairs"]


def obstacle_clearance(p: np.ndarray, ob: Any) -> float:
    """Signed distance from a point p (3,) to the real capped-cylinder surface, m (negative inside).

    Unlike :func:`d_obs` this measures against the true solid: the cylinder side for
    z_c <= z <= z_c + h_o, the hemispherical cap above, and the base disc's rim below z_c.
    """
    xc: float
    yc: float
    zc: float
    xc, yc, zc = ob.center
    r_o: float = ob.radius
    top: float = zc + ob.height
    rho = math.hypot(p[0] - xc, p[1] - yc)
    z: float = p[2]
    if z > top:
        return math.sqrt(rho * rho + (z - top) ** 2) - r_o
    if z >= zc:
        side: float = rho - r_o
        if side < 0:  # inside the cylinder part: nearest boundary is the side or the base
            return max(side, zc - z)
        return side
    below: float = zc - z
    if rho <= r_o:
        return below
    return math.hypot(rho - r_o, below)


def obstacle_clearance_many(p: np.ndarray, ob: Any) -> np.ndarray:
    """Signed distance from points p (..., 3) to the real capped-cylinder surface, (...,) m.

    Negative inside. The cylinder side for z_c <= z <= z_c + h_o, the hemispherical cap above,
    and the base disc's rim below z_c (the same solid as :func:`obstacle_clearance`).
    """
    p = np.asarray(p, dtype=float)
    xc, yc, zc = ob.center
    top = zc + ob.height
    rho = np.hypot(p[..., 0] - xc, p[..., 1] - yc)
    z = p[..., 2]
    above = np.sqrt(rho * rho + (z - top) ** 2) - ob.radius
    side = rho - ob.radius
    mid = np.where(side < 0, np.maximum(side, zc - z), side)
    below = np.where(rho <= ob.radius, zc - z, np.hypot(rho - ob.radius, zc - z))
    out: np.ndarray = np.where(z > top, above, np.where(z >= zc, mid, below))
    return out


def d_obs_many(q0: np.ndarray, ob: Any, r_f: float) -> np.ndarray:
    """Sphere clearance d_obs(q0) = ||q0 - q_obs(q0)|| - r_o - r_f for q0 of shape (..., 3), m.

    q_obs is the equivalent obstacle centre of eq. (10): [x_c, y_c, z0] beside the cylinder part,
    c + [0, 0, h_o] above it. The AAPF's repulsion (eqs 11-13) acts where d_obs <= d0.
    """
    q0 = np.asarray(q0, dtype=float)
    xc, yc, zc = ob.center
    top = zc + ob.height
    dx = q0[..., 0] - xc
    dy = q0[..., 1] - yc
    dz = np.where(q0[..., 2] <= top, 0.0, q0[..., 2] - top)
    d: np.ndarray = np.sqrt(dx * dx + dy * dy + dz * dz) - ob.radius - r_f
    return d


def close_pairs(p: np.ndarray, cutoff: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pair of points closer than ``cutoff``: (i, j, distance) with i < j.

    p: (N, 3) m, finite. Returns three arrays of equal length (int, int, float), in the order of
    a sweep along the axis of largest spread (points sorted on it, stable; pairs by their gap s
    in that order, then by the first point's rank): the order :func:`_sweep_pairs` finds them in.
    The candidates come from a grid of cells a little wider than ``cutoff`` (a close pair lies in
    the same or adjacent cells), so memory and work are O(N * the points per neighbourhood)
    whatever the swarm's shape (a sweep costs O(N * the points within ``cutoff`` along one axis):
    the whole width of a large ring's ends); where the grid would not fit 63-bit cell keys, or
    ``cutoff`` is infinite, the sweep itself.
    """
    n = len(p)
    empty = (np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp), np.empty(0))
    if n < 2 or not cutoff > 0:
        return empty
    axis = int(np.argmax(np.ptp(p, axis=0)))
    order = np.argsort(p[:, axis], kind="stable")
    cand = _grid_candidates(p, cutoff) if math.isfinite(cutoff) else None
    if cand is None:
        return _sweep_pairs(p, cutoff, order)
    rank = np.empty(n, dtype=np.intp)
    rank[order] = np.arange(n)
    ra, rb = rank[cand[0]], rank[cand[1]]
    lo, hi = np.minimum(ra, rb), np.maximum(ra, rb)
    d = np.linalg.norm(p[order[hi]] - p[order[lo]], axis=1)  # the sweep's operands, in its order
    keep = np.flatnonzero(d < cutoff)
    if len(keep) == 0:
        return empty
    lo, hi, d = lo[keep], hi[keep], d[keep]
    by = np.lexsort((lo, hi - lo))  # gap s first, then the first point's rank: the sweep's order
    a, b = order[lo[by]], order[hi[by]]
    return np.minimum(a, b), np.maximum(a, b), d[by]


def _grid_candidates(p: np.ndarray, cutoff: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Every unordered pair (i, j) of points in the same or adjacent cells (27-neighbourhood) of
    a grid of cells 1.01 ``cutoff`` wide: a superset of the pairs closer than ``cutoff``. None if
    the cell keys would not fit 63 bits."""
    n = len(p)
    w = 1.01 * cutoff
    cell = np.floor((p - p.min(axis=0)) / w).astype(np.int64) + 1  # >= 1: a neighbour's coordinate >= 0
    dims = cell.max(axis=0) + 2
    if float(dims[0]) * float(dims[1]) * float(dims[2]) >= 2.0**62:
        return None
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    srt = np.argsort(key, kind="stable")
    ks = key[srt]
    idx = np.arange(n)
    ii: list[np.ndarray] = []
    jj: list[np.ndarray] = []
    # the cell itself and 13 of its 26 neighbours: each unordered pair of cells once
    offsets = [(0, 0, 0)] + [(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) > (0, 0, 0)]
    for x, y, z in offsets:
        nk = key + (x * dims[1] + y) * dims[2] + z
        first = np.searchsorted(ks, nk, side="left")
        cnt = np.searchsorted(ks, nk, side="right") - first
        total = int(cnt.sum())
        if total == 0:
            continue
        i = np.repeat(idx, cnt)
        j = srt[np.repeat(first, cnt) + (np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt))]
        if (x, y, z) == (0, 0, 0):
            m = i < j
            i, j = i[m], j[m]
        ii.append(i)
        jj.append(j)
    if not ii:
        return np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp)
    return np.concatenate(ii), np.concatenate(jj)


def _sweep_pairs(p: np.ndarray, cutoff: float, order: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`close_pairs` by a sweep along the axis ``order`` sorts the points on: each point
    compared with its s-th successor for s = 1, 2, ... while any such gap is below ``cutoff``."""
    n = len(p)
    axis = int(np.argmax(np.ptp(p, axis=0)))
    ps = p[order]
    xs = ps[:, axis]
    ii, jj, dd = [], [], []
    for s in range(1, n):
        near = np.flatnonzero(xs[s:] - xs[:-s] < cutoff)
        if len(near) == 0:
            break
        d = np.linalg.norm(ps[near + s] - ps[near], axis=1)
        keep = d < cutoff
        if np.any(keep):
            a, b = order[near[keep]], order[near[keep] + s]
            ii.append(np.minimum(a, b))
            jj.append(np.maximum(a, b))
            dd.append(d[keep])
    if not ii:
        return np.empty(0, dtype=np.intp), np.empty(0, dtype=np.intp), np.empty(0)
    return np.concatenate(ii), np.concatenate(jj), np.concatenate(dd)

"""Escape planner: the paper's AAPF steered along a global path around the known obstacles, so the
virtual leader cannot stall in the AAPF's local minima (goal directly behind an obstacle; obstacles
closer together than their repulsion bands let the formation pass).

Pure numerics: imports numpy, the standard library's ``math`` and the AAPF module only; no I/O, no
clock; deterministic (no randomness: ties are broken by index).

Conventions as in :mod:`zenswarm.leader.aapf`: positions are (3,) arrays in metres, inertial ENU
frame (z up); an obstacle is a vertical cylinder with base centre c (3,), radius r_o and height h_o,
capped by an upper hemisphere (Remark 1).

The planner, in two parts:

1. **Global path** (:func:`plan_path`, once, at construction). In the horizontal plane, every
   obstacle that reaches the flight band is a disc of radius R = r_o + r_f + d0 + margin about
   (x_c, y_c): the formation sphere (radius r_f) kept ``margin`` outside the AAPF's repulsion band
   (d_obs <= d0, eq. 11). "Reaches the flight band" means its inflated cap top z_c + h_o + R is
   above the lower of start and goal altitudes; a lower obstacle can never come within d0 + margin
   of a leader flying between those altitudes and is left to the AAPF's repulsion (its cap, eq. 10).
   A disc that contains the start or the goal is shrunk to just exclude it (the scenario keeps both
   outside r_o + r_f). The shortest collision-free polyline from start to goal is found on a
   visibility graph: the vertices of a regular ``sides``-gon circumscribed about each disc (so
   every polygon edge stays outside its disc), vertices inside another disc dropped, an edge
   wherever the straight segment clears every disc; Dijkstra on that graph. The altitude along the
   path is interpolated linearly from start to goal by horizontal arc length. Flying over an
   obstacle is not planned: the mission's altitude band is the start-goal one, and above a cap the
   AAPF's own field already works (eq. 10 makes the cap a sphere, with no minimum beside it).

2. **Path-following AAPF** (:func:`escape_force`, every sub-step). The attraction of eq. (9),
   -K_att (q0 - q_goal), is replaced by K_att * rho * e where e is the unit vector from q0 to a
   carrot point ``lookahead`` m of arc length ahead of q0's nearest point on the path, and rho is
   the distance to the goal *along the path* via the carrot. The repulsion (eqs 10-13, the same
   adaptive gain and clearance floor as the AAPF) is added unchanged, and the speed limit applied as
   in :func:`zenswarm.leader.aapf.total_force`. Once the carrot reaches the goal this is exactly
   eq. (9) again; when the straight start-goal segment clears every disc the path is that segment
   and the field is the AAPF's, bit for bit (:func:`escape_force` calls the AAPF's own scalar
   core). Along the path the repulsion is zero (the path keeps d_obs >= d0 + margin; cutting a
   corner by the carrot costs at most its sagitta, lookahead^2 / (8 R)), so the leader neither
   stalls nor chatters in a repulsion band: the attraction's magnitude is K_att times a remaining
   path length > 0 everywhere away from the goal.

If no collision-free path exists in the plane (the goal enclosed), the path is the straight
segment and the planner is the AAPF.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import numpy as np

from zenswarm.leader.aapf import (
    AapfParams,
    LeaderStepInfo,
    ObstacleLike,
    _add_repulsion,
    _force_and_margin,
    _integrate,
)

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = [
    "EscapeParams",
    "plan_path",
    "inflated_discs",
    "nearest_on_path",
    "escape_force",
    "escape_velocity",
    "integrate_escape",
    "DEFAULT_MARGIN",
    "DEFAULT_LOOKAHEAD",
    "DEFAULT_SIDES",
]

DEFAULT_MARGIN = 0.05
"""m: how far outside the repulsion band (d_obs = d0) the planned path keeps the formation sphere."""

DEFAULT_LOOKAHEAD = 0.10
"""m: arc length from the leader's nearest path point to the carrot it is attracted to."""

DEFAULT_SIDES = 24
"""Sides of the polygon circumscribed about each inflated disc (visibility-graph vertices)."""

_EPS = 1e-9


def inflated_discs(
    start: np.ndarray,
    goal: np.ndarray,
    obstacles: Sequence[ObstacleLike],
    r_f: float,
    d0: float,
    margin: float,
) -> np.ndarray:
    """The obstacles that block the flight band, as horizontal discs (K, 3): [x_c, y_c, R] in m.

    R = r_o + r_f + d0 + margin, shrunk to just exclude start and goal (horizontally) when either
    lies inside; obstacles whose inflated cap top z_c + h_o + R is not above min(start z, goal z),
    or whose disc shrinks to nothing, are left out. start, goal: (3,) m.
    """
    zlow = min(float(start[2]), float(goal[2]))
    rows: list[tuple[float, float, float]] = []
    for ob in obstacles:
        xc, yc, zc = (float(v) for v in ob.center)
        R = float(ob.radius) + r_f + d0 + margin
        if zc + float(ob.height) + R <= zlow:
            continue
        for p in (start, goal):
            R = min(R, math.hypot(float(p[0]) - xc, float(p[1]) - yc) * (1.0 - 1e-6))
        if R > 0.0:
            rows.append((xc, yc, R))
    return np.array(rows, dtype=float).reshape(-1, 3)


def _segments_clear(a: np.ndarray, b: np.ndarray, discs: np.ndarray) -> np.ndarray:
    """Whether each segment a[i] -> b[i] (2D, shapes (M, 2)) keeps outside every disc: (M,) bool.

    A segment touching a disc's boundary counts as clear (relative tolerance 1e-9 on R).
    """
    if len(discs) == 0:
        return np.ones(len(a), dtype=bool)
    d = b - a  # (M, 2)
    L2 = np.einsum("ij,ij->i", d, d)[:, None]  # (M, 1)
    c = discs[None, :, :2]  # (1, K, 2)
    ac = c - a[:, None, :]  # (M, K, 2)
    t = np.einsum("mkj,mj->mk", ac, d) / np.where(L2 > 0.0, L2, 1.0)
    t = np.clip(t, 0.0, 1.0)
    near = a[:, None, :] + t[..., None] * d[:, None, :]
    dist = np.linalg.norm(near - c, axis=2)  # (M, K)
    clear: np.ndarray = np.all(dist >= discs[None, :, 2] * (1.0 - _EPS), axis=1)
    return clear


def _dijkstra(W: np.ndarray, src: int, dst: int) -> list[int] | None:
    """Shortest path src -> dst on a dense weight matrix W (N, N) (inf = no edge); node list or None.

    O(N^2), numpy only; ties go to the lowest node index (deterministic).
    """
    n = len(W)
    dist = np.full(n, np.inf)
    prev = np.full(n, -1, dtype=np.intp)
    done = np.zeros(n, dtype=bool)
    dist[src] = 0.0
    for _ in range(n):
        cand = np.where(done, np.inf, dist)
        u = int(np.argmin(cand))
        if not math.isfinite(float(cand[u])):
            return None
        if u == dst:
            break
        done[u] = True
        alt = dist[u] + W[u]
        better = (alt < dist) & ~done
        dist[better] = alt[better]
        prev[better] = u
    if not math.isfinite(float(dist[dst])):
        return None
    path = [dst]
    while path[-1] != src:
        path.append(int(prev[path[-1]]))
    return path[::-1]


def plan_path(
    start: np.ndarray,
    goal: np.ndarray,
    obstacles: Sequence[ObstacleLike],
    r_f: float,
    d0: float,
    margin: float = DEFAULT_MARGIN,
    sides: int = DEFAULT_SIDES,
) -> np.ndarray:
    """Shortest polyline start -> goal clear of the inflated discs (:func:`inflated_discs`).

    start, goal: (3,) m. Returns waypoints (M, 3), M >= 2, first = start and last = goal exactly;
    z interpolated linearly by horizontal arc length. [start, goal] when that segment is clear or
    when no clear path exists.
    """
    start = np.asarray(start, dtype=float)
    goal = np.asarray(goal, dtype=float)
    straight = np.array([start, goal])
    discs = inflated_discs(start, goal, obstacles, r_f, d0, margin)
    if bool(_segments_clear(start[None, :2], goal[None, :2], discs)[0]):
        return straight
    k = max(3, int(sides))
    ang = 2.0 * math.pi * np.arange(k) / k
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1) / math.cos(math.pi / k) * (1.0 + 1e-7)
    verts = (discs[:, None, :2] + discs[:, None, 2:3] * ring[None]).reshape(-1, 2)
    # drop vertices inside any disc (its own is excluded by construction: they lie outside R)
    inside = np.linalg.norm(verts[:, None, :] - discs[None, :, :2], axis=2) < discs[None, :, 2] * (1.0 - _EPS)
    verts = verts[~np.any(inside, axis=1)]
    nodes = np.vstack([start[:2], goal[:2], verts])  # node 0 = start, 1 = goal
    n = len(nodes)
    iu, ju = np.triu_indices(n, 1)
    ok = _segments_clear(nodes[iu], nodes[ju], discs)
    W = np.full((n, n), np.inf)
    lengths = np.linalg.norm(nodes[ju] - nodes[iu], axis=1)
    W[iu[ok], ju[ok]] = lengths[ok]
    W[ju[ok], iu[ok]] = lengths[ok]
    route = _dijkstra(W, 0, 1)
    if route is None:
        return straight
    xy = nodes[route]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    z = start[2] + (goal[2] - start[2]) * s / s[-1]
    out = np.column_stack([xy, z])
    out[0], out[-1] = start, goal
    return out


class EscapeParams:
    """The escape planner's parameters: the AAPF's (eqs 8-13, :class:`zenswarm.leader.aapf.AapfParams`)
    plus the planned path.

    aapf: the paper's parameters (goal, K_att, gains, d0, r_f, obstacles, speed limit).
    start: (3,) m, the leader's start (the path's first point). margin: m, path clearance outside
    the repulsion band. lookahead: m, carrot arc length. sides: polygon sides per disc.
    ``path`` (M, 3) m is computed here, once (:func:`plan_path`).
    """

    __slots__ = ("aapf", "start", "margin", "lookahead", "sides", "path", "_seg", "_s", "_straight")

    def __init__(
        self,
        aapf: AapfParams,
        start: Sequence[float],
        margin: float = DEFAULT_MARGIN,
        lookahead: float = DEFAULT_LOOKAHEAD,
        sides: int = DEFAULT_SIDES,
    ) -> None:
        if not margin >= 0.0:
            raise ValueError(f"margin must be >= 0 m, got {margin!r}")
        if not lookahead > 0.0:
            raise ValueError(f"lookahead must be > 0 m, got {lookahead!r}")
        if int(sides) < 3:
            raise ValueError(f"sides must be >= 3, got {sides!r}")
        self.aapf = aapf
        self.start = np.asarray(start, dtype=float)
        self.margin = float(margin)
        self.lookahead = float(lookahead)
        self.sides = int(sides)
        self.path = plan_path(self.start, aapf.goal, aapf.obstacles, aapf.r_f, aapf.d0, self.margin, self.sides)
        self._straight = len(self.path) == 2
        # per segment: a (3), direction d (3), 1 / |d|^2 (0 for a zero-length one), s at a, |d|
        P = self.path
        D = np.diff(P, axis=0)
        L = np.linalg.norm(D, axis=1)
        s0 = np.concatenate([[0.0], np.cumsum(L)])
        self._s = tuple(float(v) for v in s0)
        inv_l2 = np.where(L > 0.0, 1.0 / np.where(L > 0.0, L * L, 1.0), 0.0)
        self._seg = tuple(
            (float(a[0]), float(a[1]), float(a[2]), float(d[0]), float(d[1]), float(d[2]), float(w), float(s), float(l))
            for a, d, w, s, l in zip(P[:-1], D, inv_l2, s0[:-1], L, strict=True)
        )

    @property
    def length(self) -> float:
        """Arc length of the planned path, m."""
        return self._s[-1]

    @classmethod
    def from_scenario(
        cls,
        scenario: Scenario,
        margin: float = DEFAULT_MARGIN,
        lookahead: float = DEFAULT_LOOKAHEAD,
        sides: int = DEFAULT_SIDES,
    ) -> EscapeParams:
        """Build from a :class:`zenswarm.scenario.config.Scenario` (its ``[leader]`` table and obstacles)."""
        return cls(AapfParams.from_scenario(scenario), scenario.leader.start, margin, lookahead, sides)


def nearest_on_path(x: float, y: float, z: float, E: EscapeParams) -> float:
    """Arc length s (m) of the path point nearest to q0 = (x, y, z); ties go to the later point."""
    best = math.inf
    s_best = 0.0
    for ax, ay, az, dx, dy, dz, inv_l2, s0, ln in E._seg:
        px = x - ax
        py = y - ay
        pz = z - az
        t = (px * dx + py * dy + pz * dz) * inv_l2
        if t < 0.0:
            t = 0.0
        elif t > 1.0:
            t = 1.0
        ex = px - t * dx
        ey = py - t * dy
        ez = pz - t * dz
        d2 = ex * ex + ey * ey + ez * ez
        if d2 <= best:
            best = d2
            s_best = s0 + t * ln
    return s_best


def _point_at(s: float, E: EscapeParams) -> tuple[float, float, float, float, float, float]:
    """Path point at arc length s (clamped to the path) and the unit tangent there: 6 floats."""
    seg = E._seg
    i = 0
    while i < len(seg) - 1 and s > seg[i + 1][7]:
        i += 1
    ax, ay, az, dx, dy, dz, _inv_l2, s0, ln = seg[i]
    t = (s - s0) / ln if ln > 0.0 else 0.0
    t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    inv = 1.0 / ln if ln > 0.0 else 0.0
    return ax + t * dx, ay + t * dy, az + t * dz, dx * inv, dy * inv, dz * inv


def escape_force(x: float, y: float, z: float, E: EscapeParams) -> tuple[float, float, float, float]:
    """Leader velocity (v_x, v_y, v_z) m/s at q0 = (x, y, z) and the smallest d_obs (m).

    Path-following attraction (module docstring, part 2) plus the AAPF's repulsion, eqs (10)-(13),
    and its speed limit. A straight path gives the AAPF's field, eq. (14), exactly.
    """
    p = E.aapf
    if E._straight:
        return _force_and_margin(x, y, z, p)
    k_att = p.k_att
    S = E._s[-1]
    s_c = nearest_on_path(x, y, z, E) + E.lookahead
    gx, gy, gz = p._goal_t
    if s_c >= S:  # carrot at the goal: eq. (9)
        fx = -k_att * (x - gx)
        fy = -k_att * (y - gy)
        fz = -k_att * (z - gz)
    else:
        cx, cy, cz, tx, ty, tz = _point_at(s_c, E)
        ex, ey, ez = cx - x, cy - y, cz - z
        dist = math.sqrt(ex * ex + ey * ey + ez * ez)
        if dist > 0.0:
            ex, ey, ez = ex / dist, ey / dist, ez / dist
        else:
            ex, ey, ez = tx, ty, tz
        m = k_att * (dist + S - s_c)
        fx, fy, fz = m * ex, m * ey, m * ez
    # repulsion, eqs (10)-(13), and the speed limit: the AAPF's own (bit for bit)
    return _add_repulsion(x, y, z, fx, fy, fz, p)


def escape_velocity(q0: np.ndarray, E: EscapeParams) -> np.ndarray:
    """The leader velocity v0 (3,) m/s at q0 (3,) m (:func:`escape_force` without the margin)."""
    fx, fy, fz, _ = escape_force(float(q0[0]), float(q0[1]), float(q0[2]), E)
    return np.array([fx, fy, fz])


def integrate_escape(
    q0: np.ndarray, dt: float, E: EscapeParams, min_substeps: int = 10
) -> tuple[np.ndarray, LeaderStepInfo]:
    """Advance q0 by dt under q0' = :func:`escape_force` (eq. 15 with this planner's field).

    The sub-stepping of :func:`zenswarm.leader.aapf.integrate_leader`, step for step (at least
    ``min_substeps`` explicit Euler sub-steps, halved near obstacles so no sub-step moves the
    leader further than STEP_FRACTION of its clearance margin, at most MAX_SUBSTEPS); with a
    straight path it gives the AAPF's result bit for bit. q0: (3,) m. dt: s. Returns (q0 at
    t + dt, info).
    """
    return _integrate(q0, dt, escape_force, E, E.aapf.d0, min_substeps)

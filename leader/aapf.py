"""Adaptive artificial potential field (AAPF) for the virtual leader, paper eqs (8)-(15).

Pure numerics: imports numpy and the standard library's ``math`` only; no I/O, no clock.

Conventions: positions are (3,) arrays in metres, inertial ENU frame (z up). An obstacle is any
object with ``center`` (3,) = base centre c, ``radius`` r_o and ``height`` h_o (a vertical cylinder
capped by an upper hemisphere, Remark 1), e.g. :class:`zenswarm.schema.Obstacle`.

Behaviour at and inside the boundary (the paper leaves it open): the repulsion (13) grows like
1/d_obs^3 as d_obs -> 0. For evaluation the clearance is floored at ``d_floor = D_FLOOR_FRACTION *
d0`` so the force stays finite; for d_obs <= d_floor (including d_obs <= 0, the formation sphere
touching or inside the obstacle) the force is the one at d_floor, pointing out of the obstacle
along the same direction as eq. (10). The planner integrates (15) with adaptive sub-steps so that
no step moves the leader by more than ``STEP_FRACTION`` of its current clearance margin; see
:func:`integrate_leader`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable, Protocol, Sequence, TypeVar

import numpy as np

from zenswarm.vehicle.geometry import obstacle_clearance, obstacle_clearance_many  # re-exported: the solid's distance

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = [
    "ObstacleLike",
    "AapfParams",
    "attractive_force",
    "equivalent_center",
    "obstacle_distance",
    "obstacle_clearance",
    "obstacle_clearance_many",
    "d_obs",
    "min_d_obs",
    "clearance_gradient",
    "adaptive_gain",
    "repulsive_potential",
    "repulsive_force",
    "total_force",
    "integrate_leader",
    "LeaderStepInfo",
    "D_FLOOR_FRACTION",
    "STEP_FRACTION",
    "MAX_SUBSTEPS",
]

D_FLOOR_FRACTION = 0.05
"""Clearance floor for force evaluation, as a fraction of d0."""

STEP_FRACTION = 0.25
"""Largest leader displacement per sub-step, as a fraction of max(d_obs, d_floor)."""

MAX_SUBSTEPS = 20_000
"""Bound on sub-steps within one call of :func:`integrate_leader`."""


class ObstacleLike(Protocol):
    """A capped cylinder (read-only): ``center`` (3,) m, ``radius`` r_o m, ``height`` h_o m,
    e.g. :class:`zenswarm.schema.Obstacle`."""

    @property
    def center(self) -> Sequence[float]: ...
    @property
    def radius(self) -> float: ...
    @property
    def height(self) -> float: ...


class AapfParams:
    """AAPF parameters (eqs 8-13) plus the formation radius r_f.

    k_att: K_att > 0, 1/s (eq. 9 read as a velocity field, eq. 15).
    k_rep_min, k_rep_max: K_rep^min <= K_rep^max (eq. 12).
    d0: avoidance threshold, m (eq. 11). r_f: formation-enclosing sphere radius, m.
    adaptive: True for the paper's gain (12); False for the fixed-gain APF (K_rep = k_rep_fixed).
    speed_limit: m/s, 0 = off.
    """

    __slots__ = (
        "goal", "k_att", "k_rep_min", "k_rep_max", "d0", "r_f", "adaptive", "k_rep_fixed", "speed_limit", "obstacles",
        "_goal_t", "_obs_t",
    )

    def __init__(
        self,
        goal: Sequence[float],
        k_att: float,
        k_rep_min: float,
        k_rep_max: float,
        d0: float,
        r_f: float,
        obstacles: Sequence[ObstacleLike] = (),
        adaptive: bool = True,
        k_rep_fixed: float = 1.0,
        speed_limit: float = 0.0,
    ) -> None:
        self.goal = np.asarray(goal, dtype=float)
        self.k_att = float(k_att)
        self.k_rep_min = float(k_rep_min)
        self.k_rep_max = float(k_rep_max)
        self.d0 = float(d0)
        self.r_f = float(r_f)
        self.obstacles = tuple(obstacles)
        self.adaptive = bool(adaptive)
        self.k_rep_fixed = float(k_rep_fixed)
        self.speed_limit = float(speed_limit)
        self._goal_t = tuple(float(g) for g in self.goal)
        self._obs_t = tuple(
            (float(o.center[0]), float(o.center[1]), float(o.center[2]) + float(o.height), float(o.radius)) for o in self.obstacles
        )

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> AapfParams:
        """Build from a :class:`zenswarm.scenario.config.Scenario`."""
        ld = scenario.leader
        return cls(
            goal=ld.goal,
            k_att=ld.k_att,
            k_rep_min=ld.k_rep_min,
            k_rep_max=ld.k_rep_max,
            d0=ld.d0,
            r_f=scenario.r_f,
            obstacles=scenario.obstacles,
            adaptive=ld.adaptive,
            k_rep_fixed=ld.k_rep_fixed,
            speed_limit=ld.speed_limit,
        )


def attractive_force(q0: np.ndarray, goal: np.ndarray, k_att: float) -> np.ndarray:
    """Gamma_att = -K_att (q0 - q_goal), eq. (9). q0, goal: (3,) m. Returns (3,) m/s."""
    f: np.ndarray = -k_att * (np.asarray(q0, dtype=float) - np.asarray(goal, dtype=float))
    return f


def equivalent_center(q0: np.ndarray, ob: ObstacleLike) -> np.ndarray:
    """Equivalent obstacle centre q_obs(q0), eq. (10). Returns (3,) m.

    [x_c, y_c, z0] while z0 <= z_c + h_o (cylinder part), c + [0, 0, h_o] above it (cap).
    """
    xc, yc, zc = ob.center
    top = zc + ob.height
    if q0[2] <= top:
        return np.array([xc, yc, q0[2]], dtype=float)
    return np.array([xc, yc, top], dtype=float)


def obstacle_distance(q0: np.ndarray, ob: ObstacleLike) -> tuple[float, np.ndarray]:
    """Distance ||q0 - q_obs(q0)|| and its unit direction (3,) pointing away from the obstacle.

    Within the cylinder part the direction is horizontal. On the axis (zero distance) the
    direction is taken as +x (cylinder) or +z (cap) so it is always defined.
    """
    xc, yc, zc = ob.center
    top = zc + ob.height
    dx = q0[0] - xc
    dy = q0[1] - yc
    if q0[2] <= top:
        r = math.hypot(dx, dy)
        if r == 0.0:
            return 0.0, np.array([1.0, 0.0, 0.0])
        return r, np.array([dx / r, dy / r, 0.0])
    dz = q0[2] - top
    r = math.sqrt(dx * dx + dy * dy + dz * dz)
    if r == 0.0:
        return 0.0, np.array([0.0, 0.0, 1.0])
    return r, np.array([dx / r, dy / r, dz / r])


def d_obs(q0: np.ndarray, ob: ObstacleLike, r_f: float) -> float:
    """Sphere-to-obstacle clearance d_obs(q0) = ||q0 - q_obs(q0)|| - r_o - r_f, m (section AAPF)."""
    r, _ = obstacle_distance(q0, ob)
    return r - ob.radius - r_f


def clearance_gradient(q0: np.ndarray, ob: ObstacleLike) -> np.ndarray:
    """d d_obs / d q0, (3,): the unit direction of :func:`obstacle_distance` (eq. 13)."""
    return obstacle_distance(q0, ob)[1]


def adaptive_gain(d: float, p: AapfParams) -> float:
    """K_rep^*(d_obs), eq. (12); the fixed K_rep for the APF variant. 0 outside d0."""
    if d > p.d0:
        return 0.0
    if not p.adaptive:
        return p.k_rep_fixed
    frac = 1.0 - max(d, 0.0) / p.d0
    return p.k_rep_min + (p.k_rep_max - p.k_rep_min) * min(frac, 1.0)


def repulsive_potential(d: float, d0: float) -> float:
    """U_rep(d_obs), eq. (11), dimension 1/m^2. Uses the clearance floor for d <= d_floor."""
    if d > d0:
        return 0.0
    dd = max(d, D_FLOOR_FRACTION * d0)
    return 0.5 * (1.0 / dd - 1.0 / d0) ** 2


def repulsive_force(q0: np.ndarray, p: AapfParams) -> np.ndarray:
    """Gamma_rep(q0) summed over all obstacles, eq. (13). Returns (3,) m/s.

    Each obstacle contributes K*(1/d^2)(1/d - 1/d0) dd/dq0 when d = d_obs <= d0, with d floored
    at D_FLOOR_FRACTION * d0 (finite force, see the module docstring).
    """
    f = np.zeros(3)
    d_floor = D_FLOOR_FRACTION * p.d0
    for ob in p.obstacles:
        r, n = obstacle_distance(q0, ob)
        d = r - ob.radius - p.r_f
        if d > p.d0:
            continue
        k = adaptive_gain(d, p)
        dd = d if d > d_floor else d_floor
        f += (k / (dd * dd) * (1.0 / dd - 1.0 / p.d0)) * n
    return f


def _force_and_margin(x: float, y: float, z: float, p: AapfParams) -> tuple[float, float, float, float]:
    """Scalar core of eqs (9)-(14): (v_x, v_y, v_z, min d_obs) at q0 = (x, y, z).

    Plain floats: this runs 10+ times per control tick, where numpy's per-call overhead on
    3-vectors would dominate. Same arithmetic as :func:`repulsive_force`.
    """
    k_att = p.k_att
    gx, gy, gz = p._goal_t
    fx = -k_att * (x - gx)
    fy = -k_att * (y - gy)
    fz = -k_att * (z - gz)
    return _add_repulsion(x, y, z, fx, fy, fz, p)


def _add_repulsion(
    x: float, y: float, z: float, fx: float, fy: float, fz: float, p: AapfParams
) -> tuple[float, float, float, float]:
    """An attraction (fx, fy, fz) at q0 = (x, y, z) plus the repulsion of eqs (10)-(13), then the
    speed limit: (v_x, v_y, v_z, min d_obs). Plain floats (see :func:`_force_and_margin`); the
    escape planner adds the same repulsion to its own attraction
    (:func:`zenswarm.leader.escape.escape_force`).
    """
    d0 = p.d0
    d_floor = D_FLOOR_FRACTION * d0
    inv_d0 = 1.0 / d0
    margin = math.inf
    for xc, yc, top, ro in p._obs_t:
        dx = x - xc
        dy = y - yc
        if z <= top:
            r = math.sqrt(dx * dx + dy * dy)
            if r == 0.0:
                nx, ny, nz = 1.0, 0.0, 0.0
            else:
                nx, ny, nz = dx / r, dy / r, 0.0
        else:
            dz = z - top
            r = math.sqrt(dx * dx + dy * dy + dz * dz)
            if r == 0.0:
                nx, ny, nz = 0.0, 0.0, 1.0
            else:
                nx, ny, nz = dx / r, dy / r, dz / r
        d = r - ro - p.r_f
        if d < margin:
            margin = d
        if d > d0:
            continue
        if p.adaptive:
            frac = 1.0 - (d if d > 0.0 else 0.0) / d0
            k = p.k_rep_min + (p.k_rep_max - p.k_rep_min) * (frac if frac < 1.0 else 1.0)
        else:
            k = p.k_rep_fixed
        dd = d if d > d_floor else d_floor
        c = k / (dd * dd) * (1.0 / dd - inv_d0)
        fx += c * nx
        fy += c * ny
        fz += c * nz
    if p.speed_limit > 0.0:
        s = math.sqrt(fx * fx + fy * fy + fz * fz)
        if s > p.speed_limit:
            f = p.speed_limit / s
            fx, fy, fz = fx * f, fy * f, fz * f
    return fx, fy, fz, margin


def total_force(q0: np.ndarray, p: AapfParams) -> np.ndarray:
    """Gamma*_total = Gamma_att + Gamma_rep, eq. (14); the leader velocity v0 of eq. (15), m/s.

    With ``p.speed_limit > 0`` the result is scaled down to that norm (off by default).
    Returns (3,).
    """
    fx, fy, fz, _ = _force_and_margin(float(q0[0]), float(q0[1]), float(q0[2]), p)
    return np.array([fx, fy, fz])


def min_d_obs(q0: np.ndarray, p: AapfParams) -> float:
    """Smallest d_obs over all obstacles (inf without obstacles), m."""
    best = math.inf
    for ob in p.obstacles:
        r, _ = obstacle_distance(q0, ob)
        best = min(best, r - ob.radius - p.r_f)
    return best


class LeaderStepInfo:
    """What :func:`integrate_leader` did: sub-steps taken and whether the cap stopped it."""

    __slots__ = ("substeps", "capped")

    def __init__(self, substeps: int, capped: bool) -> None:
        self.substeps = substeps
        self.capped = capped


def integrate_leader(
    q0: np.ndarray, dt: float, p: AapfParams, min_substeps: int = 10
) -> tuple[np.ndarray, LeaderStepInfo]:
    """Advance q0 by dt under q0' = Gamma*_total(q0) (eq. 15) with explicit Euler sub-steps.

    At least ``min_substeps`` equal sub-steps are taken (10 = the 1 kHz physics rate at a 100 Hz
    control rate). A sub-step is halved (recursively) while it would move the leader further than
    STEP_FRACTION * max(d_obs, d_floor) near an obstacle, so the stiff repulsion never
    overshoots. At most MAX_SUBSTEPS sub-steps are taken; ``info.capped`` says when that bound
    ended the interval early (the leader is then left where it got to). Deterministic.

    q0: (3,) m. dt: s. Returns (q0 at t + dt, info).
    """
    return _integrate(q0, dt, _force_and_margin, p, p.d0, min_substeps)


_F = TypeVar("_F")


def _integrate(
    q0: np.ndarray, dt: float, field: Callable[[float, float, float, _F], tuple[float, float, float, float]], params: _F,
    d0: float, min_substeps: int,
) -> tuple[np.ndarray, LeaderStepInfo]:
    """The sub-stepping of :func:`integrate_leader` under any leader field ``field(x, y, z, params)
    -> (v_x, v_y, v_z, min d_obs)`` (the AAPF's, or the escape planner's); ``d0``: m, the repulsion
    band that sets the clearance floor and where sub-steps start being limited."""
    x, y, z = float(q0[0]), float(q0[1]), float(q0[2])
    h_nom = dt / max(1, int(min_substeps))
    remaining = dt
    n = 0
    d_floor = D_FLOOR_FRACTION * d0
    near = d0 * 4.0
    while remaining > 1e-15 * dt:
        if n >= MAX_SUBSTEPS:
            return np.array([x, y, z]), LeaderStepInfo(n, True)
        h = h_nom if h_nom < remaining else remaining
        vx, vy, vz, margin = field(x, y, z, params)
        if margin < near:
            lim = STEP_FRACTION * (margin if margin > d_floor else d_floor)
            speed = math.sqrt(vx * vx + vy * vy + vz * vz)
            while speed * h > lim and h > 1e-9 * dt:
                h *= 0.5
        # snap the last sub-step to the interval end to avoid a sliver step
        if remaining - h < 1e-12 * dt:
            h = remaining
        x += h * vx
        y += h * vy
        z += h * vz
        remaining -= h
        n += 1
    return np.array([x, y, z]), LeaderStepInfo(n, False)

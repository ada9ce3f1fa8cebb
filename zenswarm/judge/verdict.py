"""The verdict of a flight, from the vehicles' real states: did every UAV get to its slot without
touching anything, and if not, what went wrong and when.

Pure (numpy only), one pass over the flight in chunks of ticks, so memory is linear in the number
of UAVs N (no (T, N, N) arrays). The in-process simulator, the distributed swarm's supervisor and
the flight report all judge with :func:`judge`, and all decide an early end with
:func:`decide_end`, so one flight gets one verdict wherever it is judged.

Conventions: tick k at t_k = k dt (row r of a series is the tick round(t[r] / dt): a realtime
series starts at the first tick every process had produced a value, not always 0); q (T, N, 3)
the UAVs' measured positions (the plant's states, or the vehicles' telemetry through the MAVLink
bridge), q0 (T, 3) the virtual leader, qref (T, N, 3) the reference generator's q*_i, metres,
inertial ENU frame (z up). UAV numbers in failures are 1-based, like process names (``agent:1``).

Mission success requires all of (:func:`judge`):

* the leader reached the goal (within ``timing.goal_tolerance_m``);
* every UAV ended within ``mission.slot_tolerance_m`` of its slot q0_goal + h_i and stayed there
  for the last ``mission.settle_window_s`` of the flight;
* no contact: a UAV's clearance to an obstacle surface below its radius, two UAV centres closer
  than twice the radius, or a UAV that had taken off (reached z >= radius) below z = 0;
* every state finite.

Each failure is named with its cause and time (:data:`CAUSES`). Two failures end a run early,
since its outcome can no longer change (:func:`decide_end`): the leader stalled in a local minimum
of the AAPF away from the goal (``leader_stalled``), and a UAV that no longer tracks its reference
(farther than ``mission.divergence_m`` from q*_i: it fell or was blown away) or went non-finite
(``uav_diverged``, ``non_finite``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenswarm.vehicle.geometry import close_pairs, d_obs_many, obstacle_clearance_many

__all__ = [
    "CAUSES",
    "Criteria",
    "Failure",
    "Verdict",
    "criteria_from_scenario",
    "decide_end",
    "judge",
    "leader_stall_tick",
    "uav_decided",
    "in_slots",
]

CAUSES = (
    "leader_stalled",
    "uav_diverged",
    "non_finite",
    "collision_obstacle",
    "collision_ground",
    "collision_uav",
    "uav_off_slot",
    "timeout",
    "incomplete",
    "process_died",
    "plugin_error",
    "interrupted",
    "no_data",
)
"""Every cause a failure can have. ``process_died``, ``plugin_error`` and ``interrupted`` are
added by the tools that run the flight (a swarm process died; a plug-in raised or gave a
non-finite or wrongly shaped output, :class:`zenswarm.errors.PluginFailure`; Ctrl-C) in place of
``incomplete`` (a flight that stopped before its time limit, undecided); the rest come from the
UAVs' states."""

TERMINAL = ("leader_stalled", "uav_diverged", "non_finite")
"""Causes that end a run early (unless the whole time limit is asked for)."""

_CHUNK_ELEMENTS = 1 << 20
"""Positions per chunk of ticks (chunk_ticks * N), about 24 MiB of float64 (T, N, 3) data."""

MAX_LISTED_PAIRS = 20
"""UAV-UAV contacts listed one by one in the failures; more are counted in one entry."""


@dataclass(frozen=True)
class Criteria:
    """What a flight is judged against (a scenario's ``[mission]``, ``[vehicle]``, ``[timing]``).

    goal (3,), offsets h (N, 3), m. obstacles: capped cylinders. d0: the AAPF's repulsion range, m;
    r_f: formation radius, m (for the stall report). dt: control period, s. settle_time_s: from
    when the formation error counts. The rest: see ``[mission]`` in :mod:`zenswarm.scenario.config`.
    """

    goal: np.ndarray
    offsets: np.ndarray
    obstacles: tuple[Any, ...]
    dt: float
    goal_tolerance_m: float
    settle_time_s: float
    vehicle_radius_m: float
    slot_tolerance_m: float
    settle_window_s: float
    stall_speed_m_s: float
    stall_window_s: float
    divergence_m: float
    d0: float
    r_f: float

    @property
    def stall_ticks(self) -> int:
        """The stall window in ticks (>= 1)."""
        return max(1, int(round(self.stall_window_s / self.dt)))

    @property
    def settle_ticks(self) -> int:
        """The settle window in ticks (>= 1)."""
        return max(1, int(round(self.settle_window_s / self.dt)))


def criteria_from_scenario(sc: Any) -> Criteria:
    """The :class:`Criteria` of a :class:`zenswarm.scenario.config.Scenario`."""
    m = sc.mission
    return Criteria(
        goal=np.asarray(sc.leader.goal, dtype=float),
        offsets=np.asarray(sc.offsets, dtype=float).reshape(-1, 3),
        obstacles=tuple(sc.obstacles),
        dt=sc.timing.dt,
        goal_tolerance_m=sc.timing.goal_tolerance_m,
        settle_time_s=sc.timing.settle_time_s,
        vehicle_radius_m=sc.vehicle_radius,
        slot_tolerance_m=m.slot_tolerance_m,
        settle_window_s=m.settle_window_s,
        stall_speed_m_s=m.stall_speed_m_s,
        stall_window_s=m.stall_window_s,
        divergence_m=m.divergence_m,
        d0=sc.leader.d0,
        r_f=sc.r_f,
    )


@dataclass
class Failure:
    """One named failure: ``cause`` (one of :data:`CAUSES`), when (s, sim time), which UAVs
    (1-based), which obstacle (0-based index into ``obstacles``), and a sentence."""

    cause: str
    t_s: float | None
    detail: str
    uavs: tuple[int, ...] = ()
    obstacle: int | None = None
    where: tuple[float, float, float] | None = None

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"cause": self.cause, "t_s": self.t_s, "detail": self.detail, "uavs": list(self.uavs)}
        if self.obstacle is not None:
            d["obstacle"] = self.obstacle
        if self.where is not None:
            d["where"] = [float(x) for x in self.where]
        return d


@dataclass
class Verdict:
    """The judged flight. Distances in m, times in s (sim time); None where there was nothing to
    measure (no obstacle, a single UAV, no tick after the settle time)."""

    success: bool
    failures: list[Failure]
    end_tick: int  # ticks judged: up to end_tick - 1 (the last row's tick + 1: a realtime series may start after tick 0)
    ended_early: bool  # the outcome was decided at end_tick - 1 (a terminal failure), the run ended there
    goal_reached: bool
    time_to_goal_s: float | None
    final_leader_goal_distance_m: float | None
    max_formation_error_m: float | None  # vehicles: max ||q_i - q0 - h_i||, t >= settle_time_s
    max_generator_formation_error_m: float | None  # generator: max ||q*_i - q0 - h_i||, t >= settle_time_s
    rms_tracking_error_m: float | None  # RMS over ticks and UAVs of ||q*_i - q_i||
    final_slot_errors_m: list[float | None]  # per UAV, max ||q_i - (goal + h_i)|| over the final window
    min_obstacle_clearance_m: float | None  # UAV centre to the nearest obstacle surface
    min_inter_uav_distance_m: float | None  # between UAV centres
    min_altitude_m: float | None  # lowest z of a UAV after it took off
    vehicle_radius_m: float
    finite: bool
    stall: dict[str, Any] | None = None

    @property
    def min_obstacle_margin_m(self) -> float | None:
        """Clearance minus the vehicle radius (negative: contact)."""
        c = self.min_obstacle_clearance_m
        return None if c is None else c - self.vehicle_radius_m

    @property
    def min_inter_uav_margin_m(self) -> float | None:
        """Centre distance minus twice the vehicle radius (negative: contact)."""
        d = self.min_inter_uav_distance_m
        return None if d is None else d - 2.0 * self.vehicle_radius_m

    @property
    def causes(self) -> list[str]:
        return [f.cause for f in self.failures]


# ============================================================================ early end


def _stalled(q0: np.ndarray, k0: int, k1: int, c: Criteria) -> int | None:
    """First tick k in [k0, k1) at which the leader has moved less than stall_speed * window over
    the window ending at k while away from the goal with an obstacle's repulsion active
    (d_obs <= d0: without repulsion the field (8)-(15) has no minimum but the goal). None if none."""
    W = c.stall_ticks
    a = max(k0, W)
    if a >= k1:
        return None
    now = q0[a:k1]
    moved = np.linalg.norm(now - q0[a - W : k1 - W], axis=1)
    slow = moved < c.stall_speed_m_s * W * c.dt
    slow &= np.linalg.norm(now - c.goal, axis=1) > c.goal_tolerance_m
    if not np.any(slow) or not c.obstacles:
        return None
    near = np.zeros(len(now), dtype=bool)
    for ob in c.obstacles:
        near |= d_obs_many(now, ob, c.r_f) <= c.d0
    hit = np.flatnonzero(slow & near)
    return int(a + hit[0]) if len(hit) else None


def leader_stall_tick(q0: np.ndarray, c: Criteria, k0: int, k1: int) -> int | None:
    """The first tick in [k0, k1) at which the leader counts as stalled (see :func:`decide_end`);
    q0 (T, 3) may hold NaN rows for ticks not known yet (they never count)."""
    with np.errstate(invalid="ignore"):
        return _stalled(q0, k0, min(k1, len(q0)), c)


def uav_decided(q: np.ndarray, qref: np.ndarray, c: Criteria) -> str | None:
    """``non_finite`` or ``uav_diverged`` if the UAVs' positions q (N, 3) against their
    references qref (N, 3) at one tick end the run; else None (see :func:`decide_end`)."""
    if not np.isfinite(q).all():
        return "non_finite"
    with np.errstate(invalid="ignore"):
        return "uav_diverged" if np.any(np.linalg.norm(q - qref, axis=1) > c.divergence_m) else None


def in_slots(q: np.ndarray, c: Criteria) -> bool:
    """Every UAV of q (..., N, 3) within the slot tolerance of its slot goal + h_i."""
    e = np.linalg.norm(q - (c.goal + c.offsets), axis=-1)
    return bool(np.all(np.isfinite(e)) and np.all(e <= c.slot_tolerance_m))


def _point(a: Any) -> tuple[float, float, float]:
    """A (3,) point, m, as a tuple of Python floats."""
    return (float(a[0]), float(a[1]), float(a[2]))


def _diverged(q: np.ndarray, qref: np.ndarray, k0: int, k1: int, c: Criteria) -> tuple[int, int, str] | None:
    """First (tick, uav index, cause) in [k0, k1) where a UAV's state is not finite or it is
    farther than ``divergence_m`` from its reference q*_i (it no longer tracks: it fell, or was
    blown away). A formation that lags its leader while tracking its references does not count:
    that is judged at the end (``uav_off_slot``)."""
    qs = q[k0:k1]
    bad = ~np.isfinite(qs).all(axis=2)
    with np.errstate(invalid="ignore"):
        far = np.linalg.norm(qs - qref[k0:k1], axis=2) > c.divergence_m
    kb = np.flatnonzero(bad.any(axis=1))
    kf = np.flatnonzero(far.any(axis=1))
    first_bad = int(kb[0]) if len(kb) else None
    first_far = int(kf[0]) if len(kf) else None
    if first_bad is None and first_far is None:
        return None
    if first_far is None or (first_bad is not None and first_bad <= first_far):
        assert first_bad is not None
        return k0 + first_bad, int(np.flatnonzero(bad[first_bad])[0]), "non_finite"
    return k0 + first_far, int(np.flatnonzero(far[first_far])[0]), "uav_diverged"


def decide_end(
    q0: np.ndarray, q: np.ndarray, qref: np.ndarray, c: Criteria, k0: int = 0, k1: int | None = None
) -> int | None:
    """The first tick in [k0, k1) at which the outcome can no longer change: the leader stalled
    (``leader_stalled``), its reference went non-finite, or a UAV diverged from its reference or
    went non-finite. The run ends after that tick.

    Causal: the decision at tick k reads ticks <= k only, so a run stopped there holds the same
    ticks as one that flew on. q0 (T, 3), q and qref (T, N, 3); default k1 = T. None if no such
    tick.
    """
    k1 = len(q0) if k1 is None else min(k1, len(q0))
    if k1 <= k0:
        return None
    div = _diverged(q, qref, k0, k1, c)
    lead = np.flatnonzero(~np.isfinite(q0[k0:k1]).all(axis=1))  # the leader's reference went non-finite
    hits = [k for k in (_stalled(q0, k0, k1, c), div[0] if div else None, k0 + int(lead[0]) if len(lead) else None) if k is not None]
    return min(hits) if hits else None


# ============================================================================ judging


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _chunks(T: int, n: int) -> list[tuple[int, int]]:
    step = max(1, _CHUNK_ELEMENTS // max(1, n))
    return [(a, min(T, a + step)) for a in range(0, T, step)]


_PAIRWISE_MAX_N = 48
"""Up to this many UAVs the pair distances of a chunk of ticks are computed all at once."""


def _pairs_chunk(
    qs: np.ndarray, fin: np.ndarray, k0: int, contact: float, best: float, first: dict[tuple[int, int], tuple[int, float]]
) -> float:
    """Update the closest UAV distance ``best`` (returned) and ``first`` (pair -> first contact
    (tick, distance)) with the ticks of qs (t, N, 3) starting at tick k0; fin (t, N) marks finite
    positions. Small swarms: all pairs of all ticks at once; large: :func:`close_pairs` per tick
    with the cutoff max(contact, best), so memory stays linear in N."""
    nt, n = qs.shape[:2]
    if n <= _PAIRWISE_MAX_N:
        iu, ju = np.triu_indices(n, 1)
        step = max(1, _CHUNK_ELEMENTS // (n * n))
        for s in range(0, nt, step):
            d = np.linalg.norm(qs[s : s + step, iu] - qs[s : s + step, ju], axis=2)  # (t, pairs)
            d = np.where(np.isfinite(d), d, np.inf)
            best = min(best, float(d.min()))
            hit = d < contact
            for x in np.flatnonzero(hit.any(axis=0)):
                key = (int(iu[x]), int(ju[x]))
                if key not in first:
                    k = int(np.argmax(hit[:, x]))
                    first[key] = (k0 + s + k, float(d[k, x]))
        return best
    for k in range(nt):
        ok = np.flatnonzero(fin[k])
        if len(ok) < 2:
            continue
        pk = qs[k, ok]
        if not math.isfinite(best):  # a first bound: neighbours in x order are some pair's distance
            order = np.argsort(pk[:, 0], kind="stable")
            best = float(np.min(np.linalg.norm(pk[order[1:]] - pk[order[:-1]], axis=1))) * (1.0 + 1e-9) + 1e-12
        ii, jj, dd = close_pairs(pk, max(contact, best))
        if len(dd) == 0:
            continue
        best = min(best, float(dd.min()))
        for x in np.flatnonzero(dd < contact):
            key = (int(ok[ii[x]]), int(ok[jj[x]]))
            if key not in first:
                first[key] = (k0 + k, float(dd[x]))
    return best


@dataclass
class _Scan:
    """What one pass over a flight's ticks found (:func:`_scan`): the closest obstacle clearance
    and each UAV's first obstacle contact (uav -> (tick, obstacle, clearance)); each UAV's first
    ground contact after take-off (uav -> (tick, z)) and the lowest altitude after it; the closest
    UAV distance and each pair's first contact (pair -> (tick, distance)); the largest vehicle and
    generator formation errors after the settle time; the sum and count of squared tracking
    errors; whether every state was finite. m, 0-based indices."""

    n: int
    clear_min: float = math.inf
    clear_first: dict[int, tuple[int, int, float]] = field(default_factory=dict)
    ground_first: dict[int, tuple[int, float]] = field(default_factory=dict)
    airborne: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    alt_min: float = math.inf
    pair_min: float = math.inf
    pair_first: dict[tuple[int, int], tuple[int, float]] = field(default_factory=dict)
    ferr_max: float = -math.inf
    gerr_max: float = -math.inf
    sq_sum: float = 0.0
    sq_count: int = 0
    finite: bool = True

    def __post_init__(self) -> None:
        self.airborne = np.zeros(self.n, dtype=bool)


def _scan_obstacles(s: _Scan, qs: np.ndarray, a: int, c: Criteria) -> None:
    """Ticks qs (t, N, 3) from tick a: each UAV centre's clearance to each obstacle surface; contact below the radius."""
    r = c.vehicle_radius_m
    for o, ob in enumerate(c.obstacles):
        cl = obstacle_clearance_many(qs, ob)
        with np.errstate(invalid="ignore"):
            if np.any(np.isfinite(cl)):
                s.clear_min = min(s.clear_min, float(np.nanmin(cl)))
            hit = cl < r
        for i in np.flatnonzero(hit.any(axis=0)).tolist():
            k = int(np.argmax(hit[:, i]))
            if int(i) not in s.clear_first or s.clear_first[int(i)][0] > a + k:
                s.clear_first[int(i)] = (a + k, o, float(cl[k, i]))


def _scan_ground(s: _Scan, qs: np.ndarray, fin_q: np.ndarray, a: int, r: float) -> None:
    """Ticks qs (t, N, 3) from tick a (fin_q (t, N): finite positions): a UAV that has reached z >= r and then goes below z = 0."""
    z = qs[..., 2]
    with np.errstate(invalid="ignore"):
        up = np.logical_or.accumulate(z >= r, axis=0) | s.airborne[None]
        if np.any(up & fin_q):
            s.alt_min = min(s.alt_min, float(np.min(z[up & fin_q])))
        below = up & (z < 0.0)
    s.airborne = up[-1] if len(up) else s.airborne
    for i in np.flatnonzero(below.any(axis=0)).tolist():
        if int(i) not in s.ground_first:
            k = int(np.flatnonzero(below[:, i])[0])
            s.ground_first[int(i)] = (a + k, float(z[k, i]))


def _scan_errors(s: _Scan, t: np.ndarray, q0: np.ndarray, qs: np.ndarray, qref: np.ndarray, c: Criteria) -> None:
    """Ticks of one chunk (t (t,), q0 (t, 3), qs and qref (t, N, 3)): the formation errors after the
    settle time (vehicles and generator), the tracking error."""
    late = t >= c.settle_time_s
    if np.any(late):
        lead = q0[late][:, None, :] + c.offsets[None]
        fe = np.linalg.norm(qs[late] - lead, axis=2)
        ge = np.linalg.norm(qref[late] - lead, axis=2)
        if np.any(np.isfinite(fe)):
            s.ferr_max = max(s.ferr_max, float(np.nanmax(fe)))
        if np.any(np.isfinite(ge)):
            s.gerr_max = max(s.gerr_max, float(np.nanmax(ge)))
    te = np.linalg.norm(qref - qs, axis=2)
    te = te[np.isfinite(te)]
    s.sq_sum += float(np.sum(te * te))
    s.sq_count += len(te)


def _scan(t: np.ndarray, q0: np.ndarray, q: np.ndarray, qref: np.ndarray, c: Criteria, n: int) -> _Scan:
    """One pass over the flight in chunks of ticks (memory linear in N): contacts, margins, errors."""
    s = _Scan(n)
    for a, b in _chunks(len(t), n):
        qs = q[a:b]
        fin_q = np.isfinite(qs).all(axis=2)  # (t, N)
        s.finite &= bool(fin_q.all()) and bool(np.isfinite(q0[a:b]).all())
        _scan_obstacles(s, qs, a, c)
        _scan_ground(s, qs, fin_q, a, c.vehicle_radius_m)
        if n > 1:  # UAV pairs: the closest distance, and the first contact of each pair
            s.pair_min = _pairs_chunk(qs, fin_q, a, 2.0 * c.vehicle_radius_m, s.pair_min, s.pair_first)
        _scan_errors(s, t[a:b], q0[a:b], qs, qref[a:b], c)
    return s


def _slot_errors(q: np.ndarray, c: Criteria) -> list[float | None]:
    """Per UAV, the largest distance to its slot goal + h_i over the final window of q (T, N, 3)
    (None: not finite there); [] without ticks."""
    T = len(q)
    if not T:
        return []
    W = min(c.settle_ticks, T)
    e = np.linalg.norm(q[T - W : T] - (c.goal + c.offsets)[None], axis=2)  # (W, N)
    with np.errstate(invalid="ignore"):
        worst = np.where(np.isfinite(e).all(axis=0), np.max(np.where(np.isfinite(e), e, 0.0), axis=0), np.inf)
    return [_num(float(x)) for x in worst]


def _terminal_failures(
    t: np.ndarray, q0: np.ndarray, q: np.ndarray, qref: np.ndarray, stop: int, c: Criteria
) -> tuple[list[Failure], dict[str, Any] | None]:
    """The failures that decided the run at tick ``stop`` (:func:`decide_end`): a UAV diverged or
    went non-finite, the leader stalled (with the stall's report, else None)."""
    T = len(t)
    failures: list[Failure] = []
    qs_stop = q[stop]
    div = _diverged(q, qref, stop, stop + 1, c)
    if div is not None and div[0] == stop:
        k, i, cause = div
        if cause == "non_finite":
            failures.append(Failure("non_finite", float(t[k]) if k < T else None, f"UAV {i + 1}'s state is not finite", (i + 1,)))
        else:
            e_i: float | None = float(np.linalg.norm(qs_stop[i] - qref[stop, i]))
            failures.append(
                Failure(
                    "uav_diverged",
                    float(t[k]) if k < T else None,
                    f"UAV {i + 1} is {e_i:.2f} m from its reference q*_{i + 1} (divergence at {c.divergence_m:g} m)",
                    (i + 1,),
                    where=_point(qs_stop[i]),
                )
            )
    if _stalled(q0, stop, stop + 1, c) != stop:
        return failures, None
    where = q0[stop]
    within = [o for o, ob in enumerate(c.obstacles) if float(d_obs_many(where, ob, c.r_f)) <= c.d0]
    moved = float(np.linalg.norm(q0[stop] - q0[stop - c.stall_ticks]))
    stall_info: dict[str, Any] = {
        "t_s": float(t[stop]) if stop < T else None,
        "where": [float(x) for x in where],
        "goal_distance_m": float(np.linalg.norm(where - c.goal)),
        "moved_m": moved,
        "window_s": c.stall_window_s,
        "obstacles_within_d0": within,
    }
    failures.append(
        Failure(
            "leader_stalled",
            stall_info["t_s"],
            f"the virtual leader moved {moved:.3f} m in {c.stall_window_s:g} s at "
            f"({where[0]:.2f}, {where[1]:.2f}, {where[2]:.2f}), {stall_info['goal_distance_m']:.2f} m from the goal, "
            f"obstacles within d0={c.d0:g} m: {within} (a local minimum of the AAPF)",
            where=_point(where),
        )
    )
    return failures, stall_info


def _non_finite_failure(t: np.ndarray, q0: np.ndarray, q: np.ndarray) -> Failure:
    """The first non-finite state of a flight that has one: a UAV's, else the leader's."""
    bad = ~np.isfinite(q).all(axis=2)
    ks = np.flatnonzero(bad.any(axis=1))
    if len(ks):
        k = int(ks[0])
        i = int(np.flatnonzero(bad[k])[0])
        return Failure("non_finite", float(t[k]), f"UAV {i + 1}'s state is not finite", (i + 1,))
    k = int(np.flatnonzero(~np.isfinite(q0).all(axis=1))[0])
    return Failure("non_finite", float(t[k]), "the virtual leader's state is not finite")


def _contact_failures(t: np.ndarray, q: np.ndarray, s: _Scan, r: float) -> list[Failure]:
    """The contacts :func:`_scan` found: obstacles, the ground, UAV pairs (the first
    :data:`MAX_LISTED_PAIRS` one by one, the rest in one entry), each in time order."""
    failures: list[Failure] = []
    for i, (k, o, cl_k) in sorted(s.clear_first.items(), key=lambda x: x[1][0]):
        failures.append(
            Failure(
                "collision_obstacle",
                float(t[k]),
                f"UAV {i + 1} came within {cl_k:.3f} m of obstacle {o}'s surface (vehicle radius {r:.4f} m)",
                (i + 1,),
                obstacle=o,
                where=_point(q[k, i]),
            )
        )
    for i, (k, zk) in sorted(s.ground_first.items(), key=lambda x: x[1][0]):
        failures.append(
            Failure("collision_ground", float(t[k]), f"UAV {i + 1} went below the ground (z = {zk:.3f} m) after take-off", (i + 1,))
        )
    pairs = sorted(s.pair_first.items(), key=lambda x: x[1][0])
    for (i, j), (k, d) in pairs[:MAX_LISTED_PAIRS]:
        failures.append(
            Failure(
                "collision_uav", float(t[k]), f"UAVs {i + 1} and {j + 1} came {d:.3f} m apart (contact below {2 * r:.4f} m)", (i + 1, j + 1)
            )
        )
    if len(pairs) > MAX_LISTED_PAIRS:
        t_more = float(t[pairs[MAX_LISTED_PAIRS][1][0]])
        failures.append(Failure("collision_uav", t_more, f"{len(pairs) - MAX_LISTED_PAIRS} more UAV pairs came into contact"))
    return failures


def _course_failures(
    t: np.ndarray,
    q: np.ndarray,
    dist_goal: np.ndarray,
    slot_err: list[float | None],
    end_tick: int,
    n_ticks: int,
    stalled: bool,
    c: Criteria,
) -> list[Failure]:
    """A flight that ran its course (not ended by a decided outcome): without the goal, unless the
    leader stalled (named already), ``timeout`` at the time limit or ``incomplete`` before it;
    with the goal, ``uav_off_slot`` for each UAV not settled in its slot (``slot_err``, :func:`_slot_errors`)."""
    T = len(t)
    t_end = float(t[-1])
    if not np.any(dist_goal <= c.goal_tolerance_m):
        if stalled:
            return []
        d_end = float(dist_goal[-1])
        if end_tick >= n_ticks:
            return [Failure("timeout", t_end, f"the virtual leader did not reach the goal by the time limit ({d_end:.3f} m from it)")]
        return [
            Failure(
                "incomplete",
                t_end,
                f"the flight stopped at {t_end:.2f} s, before the time limit, with the leader {d_end:.3f} m from the goal",
            )
        ]
    W = min(c.settle_ticks, T)
    failures = []
    for i, e_i in enumerate(slot_err):
        if e_i is None or e_i > c.slot_tolerance_m:
            how = "not finite" if e_i is None else f"up to {e_i:.3f} m"
            failures.append(
                Failure(
                    "uav_off_slot",
                    t_end,
                    f"UAV {i + 1} was {how} from its slot goal + h_{i + 1} in the last {W * c.dt:g} s "
                    f"(tolerance {c.slot_tolerance_m:g} m)",
                    (i + 1,),
                    where=_point(q[T - 1, i]) if np.isfinite(q[T - 1, i]).all() else None,
                )
            )
    return failures


def judge(
    t: np.ndarray,
    q0: np.ndarray,
    q: np.ndarray,
    qref: np.ndarray,
    c: Criteria,
    early_end: bool = True,
    n_ticks: int | None = None,
) -> Verdict:
    """Judge a flight of T ticks (see the module docstring for what success means).

    t (T,) s; q0 (T, 3), q and qref (T, N, 3) m. With ``early_end`` the flight is judged up to
    and including the tick :func:`decide_end` finds (the tick the run ended at, or would have),
    else over all T ticks (``--full-time``); the terminal failures are named either way.
    ``n_ticks``: the time limit in ticks (default T); whether the flight got there is read from
    the last tick's time, so a series that starts after tick 0 (realtime: the ticks before every
    process had produced a value are not in it) still ran its course. A flight that stopped before it without a
    decided outcome and without the goal is ``incomplete`` (not ``timeout``): the tool that
    stopped it names why (``interrupted``, ``process_died``).
    """
    n_ticks = len(t) if n_ticks is None else n_ticks
    n = q.shape[1] if q.ndim == 3 else len(c.offsets)
    stop = decide_end(q0, q, qref, c)
    ended_early = early_end and stop is not None
    end = stop + 1 if (ended_early and stop is not None) else len(t)
    t, q0, q, qref = t[:end], q0[:end], q[:end], qref[:end]
    T = end
    # the tick the judged series ends at, from its time (not its length: a realtime series may
    # start after tick 0, when every process had produced a value)
    end_tick = int(round(float(t[-1]) / c.dt)) + 1 if T else 0
    dist_goal = np.linalg.norm(q0 - c.goal, axis=1) if T else np.empty(0)
    reached = np.flatnonzero(dist_goal <= c.goal_tolerance_m)
    s = _scan(t, q0, q, qref, c, n)
    slot_err = _slot_errors(q, c)

    # the failures, in time order within each cause
    failures, stall_info = _terminal_failures(t, q0, q, qref, stop, c) if stop is not None else ([], None)
    if T and not s.finite and not any(f.cause == "non_finite" for f in failures):
        failures.append(_non_finite_failure(t, q0, q))
    failures += _contact_failures(t, q, s, c.vehicle_radius_m)
    if T and not ended_early:  # the flight ran its course: did it get there?
        failures += _course_failures(t, q, dist_goal, slot_err, end_tick, n_ticks, stall_info is not None, c)
    if T == 0:
        failures.append(Failure("no_data", None, "no tick of the flight has the UAVs' states"))
    failures.sort(key=lambda f: (f.t_s is None, f.t_s or 0.0))  # in time order (stable within a tick)
    return Verdict(
        success=T > 0 and not failures,
        failures=failures,
        end_tick=end_tick,
        ended_early=ended_early,
        goal_reached=bool(len(reached)),
        time_to_goal_s=float(t[reached[0]]) if len(reached) else None,
        final_leader_goal_distance_m=_num(float(dist_goal[-1])) if T else None,
        max_formation_error_m=_num(s.ferr_max),
        max_generator_formation_error_m=_num(s.gerr_max),
        rms_tracking_error_m=_num(math.sqrt(s.sq_sum / s.sq_count)) if s.sq_count else None,
        final_slot_errors_m=slot_err,
        min_obstacle_clearance_m=_num(s.clear_min),
        min_inter_uav_distance_m=_num(s.pair_min),
        min_altitude_m=_num(s.alt_min),
        vehicle_radius_m=c.vehicle_radius_m,
        finite=s.finite,
        stall=stall_info,
    )

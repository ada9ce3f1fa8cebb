"""What the flight's view shows, one frame at a time, independent of any viewer: the neutral
description of the scene (:func:`describe`: entities made of spheres, cylinders, cubes, arrows,
labels and lines, in ENU world coordinates), the vehicles' poses (:func:`poses`) and the
flight's figures (:func:`metrics`, flattened to time series by :func:`metric_series`). Two
encoders turn it into a viewer's format, so both viewers show the same scene from one code:

* Foxglove (:mod:`zenswarm.bridge.views.foxglove_scene`): ``foxglove.SceneUpdate`` on ``/scene``,
  ``foxglove.FrameTransforms`` on ``/tf``, JSON on ``/metrics`` (:data:`METRICS_SCHEMA`), for
  ``zenswarm export --foxglove`` (a file) and ``zenswarm up/replay --live`` (the WebSocket server);
* Rerun (:mod:`zenswarm.bridge.views.rerun_scene`): Rerun archetypes under ``world/...`` and scalar time
  series under ``metrics/...`` on the ``sim_time`` timeline, for ``zenswarm export --rerun`` (an
  ``.rrd`` file) and ``--live rerun`` (Rerun's own web viewer and gRPC server).

The scene: obstacles (cylinder + sphere for the hemispherical cap), their d0 bands (translucent:
where the leader's centre q0 feels the AAPF repulsion, eqs (10)-(13): d_obs(q0) <= d0, i.e. within
r_o + r_f + d0 of the obstacle's axis or cap centre), the UAVs (spheres, a velocity arrow, a
label, a faint sphere at the reference q*_i), the formation links (the graph's edges a_ij > 0
between UAVs, and the pinned UAVs b_i > 0 to the leader), trails over the last ``trail_s``
seconds, the virtual leader and its enclosing sphere of radius r_f, start and goal. Every frame
holds the whole scene (the entities marked ``static`` are the same in every frame).

The poses: ``world`` -> ``leader`` and ``world`` -> ``uav<i>`` (attitude from the measured
roll/pitch/yaw). The figures (:data:`METRICS_SCHEMA`): formation and tracking errors, obstacle
clearance per UAV and their extremes, the closest UAV pair, the leader's d_obs, the failsafe state
(the plant's diagnostics) and per-link delivery and age (the agents' link counters, present when
link faults are on: without them every link delivers everything).

Coordinates are ENU, z up, m, as in the paper; times are sim time, ns. Pure data: numpy and the
base (no viewer's package is imported here).
"""

from __future__ import annotations

import math
import re
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenswarm.bus import wire
from zenswarm.vehicle.geometry import d_obs_many, obstacle_clearance_many

__all__ = [
    "SCENE_TOPIC",
    "TF_TOPIC",
    "METRICS_TOPIC",
    "WORLD",
    "METRICS_SCHEMA",
    "Frame",
    "Trails",
    "LatestFrames",
    "frame_from_series",
    "Sphere",
    "Cylinder",
    "Cube",
    "Arrow",
    "Label",
    "Polyline",
    "Entity",
    "Pose",
    "static_entities",
    "describe",
    "poses",
    "palette",
    "quat_rpy",
    "quat_x_to",
    "metrics",
    "metric_series",
    "diag_view",
    "failsafe_modes",
]

SCENE_TOPIC = "/scene"
"""The scene's stream (Foxglove topic ``/scene``)."""
TF_TOPIC = "/tf"
"""The poses' stream (Foxglove topic ``/tf``)."""
METRICS_TOPIC = "/metrics"
"""The figures' stream (Foxglove topic ``/metrics``)."""
WORLD = "world"
"""The world frame, ENU, m: the parent of every pose and the frame of every entity."""


@dataclass
class Frame:
    """What one frame shows, at sim time ``t_ns`` (ns). ``q0`` (3,) the virtual leader; ``q``,
    ``v``, ``rpy``, ``qref`` (N, 3) each UAV's measured position (m), velocity (m/s), attitude
    (rad) and reference q*_i (m); NaN where unknown. ``trail0`` (M, 3) and ``trails`` (N arrays
    (M_i, 3)): the recent path of the leader and of each UAV, oldest first, finite points only."""

    t_ns: int
    q0: np.ndarray
    q: np.ndarray
    v: np.ndarray
    rpy: np.ndarray
    qref: np.ndarray
    trail0: np.ndarray
    trails: list[np.ndarray]


def _finite_rows(a: np.ndarray) -> np.ndarray:
    out: np.ndarray = a[np.all(np.isfinite(a), axis=1)]
    return out


def frame_from_series(ts: Any, k: int, trail_ticks: int, stride: int) -> Frame:
    """Frame of tick k of a :class:`zenswarm.judge.metrics.TimeSeries`: trails sampled every ``stride``
    ticks over the last ``trail_ticks`` ticks (and tick k itself)."""
    lo = max(0, k - trail_ticks)
    idx = np.arange(lo, k + 1, stride)
    if idx[-1] != k:
        idx = np.append(idx, k)
    return Frame(
        t_ns=wire.t_ns(float(ts.t[k])),
        q0=ts.q0[k],
        q=ts.q[k],
        v=ts.v[k],
        rpy=ts.rpy[k],
        qref=ts.qref[k],
        trail0=_finite_rows(ts.q0[idx]),
        trails=[_finite_rows(ts.q[idx, i]) for i in range(ts.q.shape[1])],
    )


class Trails:
    """The live view's trails: the leader's and each UAV's positions at the frames shown, kept
    for ``trail_s`` seconds of sim time."""

    def __init__(self, n: int, trail_s: float) -> None:
        self.n = n
        self.trail_ns = wire.t_ns(trail_s)
        self.points: deque[tuple[int, np.ndarray, np.ndarray]] = deque()  # (t ns, q0 (3,), q (N, 3))

    def add(self, t_ns: int, q0: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """Add the positions at ``t_ns``; the trails (leader, UAVs) ending there."""
        if self.points and t_ns < self.points[-1][0]:  # time went back (a replay loop): start over
            self.points.clear()
        self.points.append((t_ns, np.array(q0, dtype=float), np.array(q, dtype=float)))
        while self.points and self.points[0][0] < t_ns - self.trail_ns:
            self.points.popleft()
        q0s = np.array([p[1] for p in self.points])
        qs = np.array([p[2] for p in self.points])  # (M, N, 3)
        return _finite_rows(q0s), [_finite_rows(qs[:, i]) for i in range(self.n)]




class LatestFrames:
    """The newest messages of swarm ``swarm`` flying scenario ``sc`` (:meth:`feed`: an append to
    a short queue per key, cheap enough for the supervisor's bus loop) and the frame they make
    (:meth:`frame`): what both live views (Foxglove's, Rerun's) show.

    A frame shows one instant: the newest tick every UAV's state has reached (the oldest of their
    newest states, leaving out a UAV more than :data:`STALE_S` behind the newest, which is shown
    at its last state), each UAV's state and reference at that tick (the newest not after it, of
    its last :data:`HISTORY`), the leader's likewise. Messages of one tick arrive one by one, so
    taking each key's newest would mix ticks (UAV 1 at tick k, UAV 2 still at k - 1). A UAV
    whose first state has not come yet counts as one at the first state the view received (the
    flight's start, or a replay window's): the first frame waits for every UAV's first state
    until the newest is more than :data:`STALE_S` past that, and a UAV that never came is then
    left out (not drawn)."""

    HISTORY = 8
    STALE_S = 0.25

    def __init__(self, sc: Any, swarm: str, trail_s: float = 10.0) -> None:
        self.sc = sc
        self.keys = wire.Keys(swarm)
        self.trails = Trails(sc.n, trail_s)
        self._last: dict[str, bytes] = {}
        self._shown = -1  # sim time of the last frame, ns
        self._first: int | None = None  # sim time of the first state received, ns
        n = sc.n
        self._state_keys = [self.keys.state(i) for i in range(1, n + 1)]
        self._ref_keys = [self.keys.ref(i) for i in range(1, n + 1)]
        self._hist: dict[str, deque[bytes]] = {
            k: deque(maxlen=self.HISTORY) for k in [*self._state_keys, *self._ref_keys, self.keys.leader_ref]
        }
        self._diag_prefix = self.keys.prefix + "/diag/"
        self._stale_ns = wire.t_ns(self.STALE_S)

    def feed(self, key: str, payload: bytes) -> None:
        """Take one message of the swarm."""
        h = self._hist.get(key)
        if h is not None:
            h.append(payload)
        else:
            self._last[key] = payload

    def _decoded(self, key: str, kind: str, cls: type) -> list[Any]:
        out = []
        for payload in self._hist[key]:
            try:
                m = wire.decode(kind, payload)
            except wire.WireDecodeError:
                continue
            if isinstance(m, cls):
                out.append(m)
        return out

    @staticmethod
    def _at(msgs: list[Any], t_ns: int) -> Any:
        """The newest of ``msgs`` not after ``t_ns`` (else the oldest; None without any)."""
        best = None
        for m in msgs:
            if m.t <= t_ns and (best is None or m.t >= best.t):
                best = m
        return best if best is not None else (min(msgs, key=lambda m: m.t) if msgs else None)

    def frame(self) -> tuple[Frame, dict[str, dict[str, Any]]] | None:
        """The frame of the newest messages and the newest diagnostics per process (None: no state
        yet, or no tick newer than the last frame's)."""
        n = self.sc.n
        states = [self._decoded(k, "state", wire.State) for k in self._state_keys]
        newest = [max(m.t for m in ms) for ms in states if ms]
        if not newest:
            return None
        t_max = max(newest)
        if self._first is None:
            self._first = min(newest)
        if len(newest) < n and t_max - self._first <= self._stale_ns:
            return None  # a UAV's first state is still on the way: no frame with it missing
        t_ns = min(t for t in newest if t >= t_max - self._stale_ns)
        if t_ns == self._shown:
            return None
        self._shown = t_ns
        nan = np.full((n, 3), np.nan)
        q, v, rpy, qref = nan.copy(), nan.copy(), nan.copy(), nan.copy()
        for i in range(n):
            st = self._at(states[i], t_ns)
            if st is not None:
                q[i], v[i], rpy[i] = st.q, st.v, st.rpy
            r = self._at(self._decoded(self._ref_keys[i], "ref", wire.Ref), t_ns)
            if r is not None:
                qref[i] = r.q
        lead = self._at(self._decoded(self.keys.leader_ref, "ref", wire.Ref), t_ns)
        q0 = np.asarray(lead.q, dtype=float) if lead is not None else np.full(3, np.nan)
        diag = {}
        for key in [k for k in self._last if k.startswith(self._diag_prefix)]:
            try:
                d = wire.decode("diag", self._last[key])
            except wire.WireDecodeError:
                continue
            if isinstance(d, wire.Diag):
                diag[d.process] = diag_view(d)
        trail0, trails = self.trails.add(t_ns, q0, q)
        return Frame(t_ns, q0, q, v, rpy, qref, trail0, trails), diag


# =========================================================================== the scene, neutral

Rgba = tuple[float, float, float, float]
"""A colour: red, green, blue, alpha, each 0..1 (alpha 1: opaque)."""


@dataclass(frozen=True)
class Sphere:
    """A sphere of ``diameter`` (m) centred at ``center`` (3,), m, world frame."""

    center: Any
    diameter: float
    color: Rgba


@dataclass(frozen=True)
class Cylinder:
    """An upright cylinder (axis along world z) of ``diameter`` and ``height`` (m) standing on ``base`` (3,), m."""

    base: Any
    diameter: float
    height: float
    color: Rgba


@dataclass(frozen=True)
class Cube:
    """An axis-aligned cube of edge ``size`` (m) centred at ``center`` (3,), m."""

    center: Any
    size: float
    color: Rgba


@dataclass(frozen=True)
class Arrow:
    """An arrow from ``origin`` (3,), m, along the unit vector ``direction`` (3,), ``length`` m of
    shaft (then the head: ``head_length`` m long, ``head_diameter`` m wide); shaft ``shaft_diameter`` m."""

    origin: Any
    direction: Any
    length: float
    shaft_diameter: float
    head_length: float
    head_diameter: float
    color: Rgba


@dataclass(frozen=True)
class Label:
    """A text at ``position`` (3,), m, facing the viewer, ``size`` screen pixels high."""

    position: Any
    text: str
    color: Rgba
    size: float


@dataclass(frozen=True)
class Polyline:
    """Lines through ``points`` (a list of (3,), m), ``width`` screen pixels wide: ``strip`` one
    line through every point in order; ``pairs`` one segment per consecutive pair (0-1, 2-3, ...)."""

    points: list[Any]
    color: Rgba
    width: float
    kind: str  # "strip" | "pairs"


@dataclass
class Entity:
    """One thing of the scene, named ``id`` (``obstacle/1``, ``uav/2``, ``trails``...), made of
    primitives in the world frame. ``static``: the same in every frame of a flight."""

    id: str
    static: bool = False
    spheres: list[Sphere] = field(default_factory=list)
    cylinders: list[Cylinder] = field(default_factory=list)
    cubes: list[Cube] = field(default_factory=list)
    arrows: list[Arrow] = field(default_factory=list)
    labels: list[Label] = field(default_factory=list)
    lines: list[Polyline] = field(default_factory=list)


@dataclass(frozen=True)
class Pose:
    """The frame ``child`` in the world frame: origin at ``position`` (3,), m; orientation the
    quaternion ``rotation`` (x, y, z, w) of body FLU in ENU."""

    child: str
    position: Any
    rotation: tuple[float, float, float, float]


IDENTITY = (0.0, 0.0, 0.0, 1.0)


def _rgba(c: Any, a: float) -> Rgba:
    return (float(c[0]), float(c[1]), float(c[2]), float(a))


def quat_rpy(rpy: Any) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of roll-pitch-yaw (ZYX: R = Rz(yaw) Ry(pitch) Rx(roll)), body FLU in ENU."""
    r, p, y = (0.5 * float(x) for x in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def quat_x_to(d: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) rotating +x onto the unit vector d (arrow orientation)."""
    dx, dy, dz = (float(v) for v in d)
    w = 1.0 + dx
    if w < 1e-9:  # d = -x: half turn about z
        return (0.0, 0.0, 1.0, 0.0)
    y, z = -dz, dy  # cross((1, 0, 0), d)
    nrm = math.sqrt(w * w + y * y + z * z)
    return (0.0, y / nrm, z / nrm, w / nrm)


def palette(n: int) -> list[tuple[float, float, float]]:
    """One RGB colour (each 0..1) per UAV: tab10 up to 10 UAVs, else spread over turbo."""
    from matplotlib import colormaps

    if n <= 10:
        cmap = colormaps["tab10"]
        return [tuple(float(x) for x in cmap(i)[:3]) for i in range(n)]  # type: ignore[misc]
    cmap = colormaps["turbo"]
    return [tuple(float(x) for x in cmap(0.05 + 0.9 * i / max(1, n - 1))[:3]) for i in range(n)]  # type: ignore[misc]


def _finite(p: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(p)))


_GREY = (0.55, 0.57, 0.6)
_BAND = (0.95, 0.55, 0.15)
_DARK = (0.1, 0.1, 0.1)


def static_entities(sc: Any) -> list[Entity]:
    """Obstacles with their caps and d0 bands, goal and start: the same in every frame."""
    ents = []
    band_r = sc.r_f + sc.leader.d0  # beyond r_o: d_obs(q0) <= d0 (eq. 10)
    for j, ob in enumerate(sc.obstacles):
        c = np.asarray(ob.center, dtype=float)
        top = c + (0.0, 0.0, ob.height)
        d = 2.0 * ob.radius
        ents.append(
            Entity(
                f"obstacle/{j + 1}",
                static=True,
                cylinders=[Cylinder(c, d, ob.height, _rgba(_GREY, 0.75))],
                spheres=[Sphere(top, d, _rgba(_GREY, 0.75))],  # the cap; its lower half inside the cylinder
            )
        )
        db = 2.0 * (ob.radius + band_r)
        ents.append(
            Entity(
                f"d0_band/{j + 1}",
                static=True,
                cylinders=[Cylinder(c, db, ob.height, _rgba(_BAND, 0.08))],
                spheres=[Sphere(top, db, _rgba(_BAND, 0.08))],
                labels=[Label(top + (0.0, 0.0, ob.radius + band_r), f"d0 band {j + 1}", _rgba(_BAND, 0.9), 11.0)],
            )
        )
    goal = np.asarray(sc.leader.goal, dtype=float)
    start = np.asarray(sc.leader.start, dtype=float)
    marker = max(0.15, 0.5 * sc.r_f)  # m: seen at the scale of the whole flight, not a dot
    green = (0.1, 0.75, 0.2)
    ents.append(
        Entity(
            "goal",
            static=True,
            spheres=[
                Sphere(goal, marker, _rgba(green, 0.9)),
                Sphere(goal, 2.0 * sc.r_f, _rgba(green, 0.15)),  # where the formation's sphere of radius r_f ends
            ],
            lines=[Polyline([goal * (1, 1, 0), goal], _rgba(green, 0.9), 2.0, "strip")],  # a pole from the ground
            labels=[Label(goal + (0.0, 0.0, sc.r_f + 0.1), "goal", _rgba((0.1, 0.6, 0.2), 1.0), 14.0)],
        )
    )
    ents.append(
        Entity(
            "start",
            static=True,
            cubes=[Cube(start, marker, _rgba(_DARK, 0.9))],
            labels=[Label(start + (0.0, 0.0, marker + 0.1), "start", _rgba(_DARK, 1.0), 14.0)],
        )
    )
    return ents


def _graph_lines(sc: Any, f: Frame) -> list[Polyline]:
    """The formation links: UAV pairs with a_ij > 0 (grey) and pinned UAVs b_i > 0 to the leader (blue)."""
    b = np.asarray(sc.graph.pinning, dtype=float)
    n = len(b)
    pairs = [(i - 1, j - 1) for i, j, _ in sc.comm_graph.edge_list()]  # i < j, in row order
    pts = [p for i, j in pairs if _finite(f.q[i]) and _finite(f.q[j]) for p in (f.q[i], f.q[j])]
    out = []
    if pts:
        out.append(Polyline(pts, _rgba((0.35, 0.35, 0.35), 0.6), 1.0, "pairs"))
    if _finite(f.q0):
        pin = [p for i in range(n) if b[i] > 0 and _finite(f.q[i]) for p in (f.q0, f.q[i])]
        if pin:
            out.append(Polyline(pin, _rgba((0.3, 0.5, 0.95), 0.6), 1.0, "pairs"))
    return out


def describe(f: Frame, sc: Any, colors: list[tuple[float, float, float]]) -> list[Entity]:
    """The whole scene of frame ``f`` of scenario ``sc`` (see the module docstring), in this order:
    :func:`static_entities`, ``leader`` (once q0 is known), ``uav/<i>`` (those whose position is
    known), ``links``, ``trails``; ``colors`` from :func:`palette`."""
    ents = static_entities(sc)
    lines = []
    if len(f.trail0) >= 2:
        lines.append(Polyline(list(f.trail0), _rgba(_DARK, 0.8), 1.5, "strip"))
    if _finite(f.q0):
        ents.append(
            Entity(
                "leader",
                spheres=[Sphere(f.q0, 0.03, _rgba((0.05, 0.05, 0.05), 1.0)), Sphere(f.q0, 2.0 * sc.r_f, _rgba((0.3, 0.5, 0.95), 0.12))],
                labels=[Label(f.q0 + (0, 0, 0.06), "leader", _rgba(_DARK, 1.0), 12.0)],
            )
        )
    for i, col in enumerate(colors):
        qi, vi = f.q[i], f.v[i]
        if len(f.trails[i]) >= 2:
            lines.append(Polyline(list(f.trails[i]), _rgba(col, 0.9), 2.0, "strip"))
        if not _finite(qi):
            continue
        spheres = [Sphere(qi, 0.09, _rgba(col, 1.0))]
        if _finite(f.qref[i]):
            spheres.append(Sphere(f.qref[i], 0.05, _rgba(col, 0.3)))
        arrows = []
        speed = float(np.linalg.norm(vi)) if _finite(vi) else 0.0
        if speed > 0.01:  # 0.5 s of travel
            arrows.append(Arrow(qi, vi / speed, 0.5 * speed, 0.008, 0.03, 0.025, _rgba(col, 0.9)))
        label = Label(qi + (0, 0, 0.08), f"uav {i + 1}", _rgba(col, 1.0), 12.0)
        ents.append(Entity(f"uav/{i + 1}", spheres=spheres, arrows=arrows, labels=[label]))
    ents.append(Entity("links", lines=_graph_lines(sc, f)))
    ents.append(Entity("trails", lines=lines))
    return ents


def poses(f: Frame) -> list[Pose]:
    """The frames of ``f`` in the world frame: ``leader`` (no rotation; once q0 is known) and
    ``uav<i>`` (attitude from the measured roll/pitch/yaw; identity while unknown)."""
    out = []
    if _finite(f.q0):
        out.append(Pose("leader", f.q0, IDENTITY))
    for i in range(len(f.q)):
        if _finite(f.q[i]):
            out.append(Pose(f"uav{i + 1}", f.q[i], quat_rpy(f.rpy[i]) if _finite(f.rpy[i]) else IDENTITY))
    return out


# =========================================================================== time series


def _opt(d: str) -> dict[str, Any]:
    return {"type": ["number", "null"], "description": d}


METRICS_SCHEMA: dict[str, Any] = {
    "title": "zenswarm.Metrics",
    "description": "The flight's figures at one frame (null: unknown at that time); ENU, m, s",
    "type": "object",
    "properties": {
        "t": {"type": "number", "description": "sim time, s"},
        "max_formation_error_m": _opt("max_i ||q_i - q0 - h_i||"),
        "max_tracking_error_m": _opt("max_i ||q*_i - q_i||"),
        "min_clearance_m": _opt("smallest clearance of a UAV centre to an obstacle surface"),
        "min_inter_uav_m": _opt("closest UAV pair, centre to centre"),
        "leader_d_obs_m": _opt("min over obstacles of d_obs(q0) (eq. 10); the AAPF repels where <= d0"),
        "d0_m": {"type": "number", "description": "the AAPF's repulsion range d0"},
        "failsafe": {"type": "string", "description": "the plant's failsafe modes not nominal, e.g. '2:hover' ('none', '' unknown)"},
        "failsafe_uavs": {"type": "integer", "minimum": 0, "description": "UAVs not in nominal mode"},
        "uavs": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "uav": {"type": "integer", "minimum": 1},
                    "formation_error_m": _opt("||q_i - q0 - h_i||"),
                    "tracking_error_m": _opt("||q*_i - q_i||"),
                    "clearance_m": _opt("clearance to the nearest obstacle surface"),
                    "failsafe": {"type": "string", "description": "nominal, hover, land, landed"},
                },
                "required": ["uav", "formation_error_m", "tracking_error_m", "clearance_m", "failsafe"],
                "additionalProperties": False,
            },
        },
        "links": {
            "type": "array",
            "description": "per link src->dst:kind, as its receiver counts (link faults on)",
            "items": {
                "type": "object",
                "properties": {
                    "link": {"type": "string"},
                    "received": {"type": "number", "minimum": 0},
                    "delivered": {"type": "number", "minimum": 0},
                    "delivery": _opt("delivered / received"),
                    "age_s": _opt("age of the value the receiver holds, s (sim)"),
                    "max_age_s": _opt("largest such age so far, s"),
                },
                "required": ["link", "received", "delivered", "delivery", "age_s", "max_age_s"],
                "additionalProperties": False,
            },
        },
    },
    "required": [
        "t", "max_formation_error_m", "max_tracking_error_m", "min_clearance_m", "min_inter_uav_m", "leader_d_obs_m", "d0_m",
        "failsafe", "failsafe_uavs", "uavs", "links",
    ],
    "additionalProperties": False,
}
"""JSON Schema of the ``/metrics`` messages (plot e.g. ``/metrics.uavs[:].formation_error_m``)."""

_LINK_RE = re.compile(r"^(link:.+)\.(received|delivered|age_ticks|max_age_ticks)$")


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _nanmax(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(np.max(a)) if len(a) else None


def _nanmin(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(np.min(a)) if len(a) else None


def _links(diag: dict[str, dict[str, Any]], dt: float) -> list[dict[str, Any]]:
    """Per-link figures from the agents' diagnostics counters ``link:<src>-><dst>:<kind>.<counter>``."""
    found: dict[str, dict[str, float]] = {}
    for proc in sorted(diag):
        for name, v in diag[proc].items():
            m = _LINK_RE.match(name)
            if m is not None and isinstance(v, (int, float)):
                found.setdefault(m.group(1)[len("link:") :], {})[m.group(2)] = float(v)
    out = []
    for link, c in sorted(found.items()):
        rx, dl = c.get("received", 0.0), c.get("delivered", 0.0)
        age, mx = c.get("age_ticks", -1.0), c.get("max_age_ticks", -1.0)
        out.append(
            {
                "link": link,
                "received": rx,
                "delivered": dl,
                "delivery": dl / rx if rx > 0 else None,
                "age_s": age * dt if age >= 0 else None,
                "max_age_s": mx * dt if mx >= 0 else None,
            }
        )
    return out


def diag_view(msg: wire.Diag) -> dict[str, Any]:
    """A process's diagnostics as one flat dict: its counters and its scalar info (what
    :attr:`zenswarm.process.collector.Collector.diag` keeps per process)."""
    return {**msg.counters, **{k: v for k, v in msg.info.items() if isinstance(v, (int, float, bool, str))}}


def failsafe_modes(summary: str, n: int) -> list[str]:
    """Each UAV's mode from the plant's failsafe summary (``"2:hover,3:land"``; ``none``: all nominal)."""
    modes = ["nominal"] * n
    for part in summary.split(","):
        i, _, mode = part.partition(":")
        if i.strip().isdigit() and 1 <= int(i) <= n and mode:
            modes[int(i) - 1] = mode.strip()
    return modes


def metrics(f: Frame, sc: Any, diag: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The ``/metrics`` message of frame ``f`` (:data:`METRICS_SCHEMA`); ``diag``: process ->
    its newest diagnostics (counters and info, as :attr:`zenswarm.process.collector.Collector.diag`)."""
    n = len(f.q)
    h = np.asarray(sc.offsets, dtype=float).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        fe = np.linalg.norm(f.q - f.q0[None] - h, axis=1)
        te = np.linalg.norm(f.qref - f.q, axis=1)
        cl = np.full(n, np.inf)
        for ob in sc.obstacles:
            cl = np.fmin(cl, obstacle_clearance_many(f.q, ob))
        dobs = min((float(d_obs_many(f.q0, ob, sc.r_f)) for ob in sc.obstacles), default=math.inf)
        pair = math.inf
        ok = f.q[np.all(np.isfinite(f.q), axis=1)]
        if len(ok) > 1:
            d = np.linalg.norm(ok[:, None] - ok[None], axis=2)
            pair = float(np.min(d[np.triu_indices(len(ok), 1)]))
    plant = diag.get("plant") or diag.get("bridge") or {}
    fs = str(plant.get("failsafe", ""))
    modes = failsafe_modes(fs, n)
    uavs = [
        {
            "uav": i + 1,
            "formation_error_m": _num(float(fe[i])),
            "tracking_error_m": _num(float(te[i])),
            "clearance_m": _num(float(cl[i])),
            "failsafe": modes[i],
        }
        for i in range(n)
    ]
    return {
        "t": f.t_ns / 1e9,
        "max_formation_error_m": _nanmax(fe),
        "max_tracking_error_m": _nanmax(te),
        "min_clearance_m": _nanmin(cl),
        "min_inter_uav_m": _num(pair),
        "leader_d_obs_m": _num(dobs),
        "d0_m": float(sc.leader.d0),
        "failsafe": fs,
        "failsafe_uavs": sum(m != "nominal" for m in modes),
        "uavs": uavs,
        "links": _links(diag, sc.timing.dt),
    }


_SCALARS = (
    "max_formation_error_m", "max_tracking_error_m", "min_clearance_m", "min_inter_uav_m", "leader_d_obs_m", "d0_m", "failsafe_uavs",
)


def metric_series(m: dict[str, Any]) -> dict[str, float]:
    """The figures of a :func:`metrics` message as named scalars (the unknown ones left out):
    ``max_formation_error_m`` ... ``d0_m``, ``failsafe_uavs``; per UAV
    ``<figure>/uav<i>`` (``formation_error_m/uav1``, ``tracking_error_m/uav1``, ``clearance_m/uav1``);
    per link ``link_<figure>/<src>-><dst>:<kind>`` (``link_delivery/...``, ``link_age_s/...``,
    ``link_max_age_s/...``). Names are ``/``-separated paths: a viewer groups them by their first part."""
    out: dict[str, float] = {}
    for k in _SCALARS:
        if m.get(k) is not None:
            out[k] = float(m[k])
    for u in m["uavs"]:
        for k in ("formation_error_m", "tracking_error_m", "clearance_m"):
            if u[k] is not None:
                out[f"{k}/uav{u['uav']}"] = float(u[k])
    for ln in m["links"]:
        for k in ("delivery", "age_s", "max_age_s"):
            if ln[k] is not None:
                out[f"link_{k}/{ln['link']}"] = float(ln[k])
    return out


class PacedView(ABC):
    """What both live views share (:class:`zenswarm.bridge.views.live.LiveView`,
    :class:`zenswarm.bridge.views.rerun_scene.RerunLiveView`): the swarm's newest messages
    (:class:`LatestFrames`, :meth:`feed`) and a frame published at most ``hz`` per wall second
    (:meth:`maybe_publish`); a view implements :meth:`publish`."""

    def __init__(self, sc: Any, swarm: str, hz: float, trail_s: float) -> None:
        self.sc = sc
        self.latest = LatestFrames(sc, swarm, trail_s)
        self.keys = self.latest.keys
        self.period = 1.0 / hz
        self.frames = 0
        self._next = 0.0

    def feed(self, key: str, payload: bytes) -> None:
        """Take one message of the swarm (the newest of each key is kept)."""
        self.latest.feed(key, payload)

    def maybe_publish(self, now: float) -> bool:
        """Publish a frame if one is due at ``now`` (monotonic s) and something new arrived."""
        if now < self._next:
            return False
        self._next = now + self.period
        return self.publish()

    @abstractmethod
    def publish(self) -> bool:
        """Show a frame of the newest messages (False: no state yet, or none newer than the last frame)."""

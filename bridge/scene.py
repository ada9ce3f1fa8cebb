"""The flight as Foxglove sees it, one frame at a time: the 3D scene, the frame transforms and the
time series. One code for both outputs: ``zenswarm export --foxglove`` writes these frames to an
MCAP file (:mod:`zenswarm.bridge.foxglove`), ``zenswarm up --live`` / ``zenswarm replay --live``
serve them to the Foxglove app over its WebSocket protocol (:mod:`zenswarm.bridge.live`).

Channels (the same in the file and on the live server):

``/scene``    ``foxglove.SceneUpdate`` (protobuf, Foxglove's official schema as the ``foxglove-sdk``
              package ships it): obstacles (cylinder + sphere for the hemispherical cap), their d0
              bands (translucent: where the leader's centre q0 feels the AAPF repulsion, eqs
              (10)-(13): d_obs(q0) <= d0, i.e. within r_o + r_f + d0 of the obstacle's axis or
              cap centre), the UAVs (spheres, a velocity arrow, a label, a faint sphere at the
              reference q*_i), the formation links (the graph's edges a_ij > 0 between UAVs, and
              the pinned UAVs b_i > 0 to the leader), trails over the last ``trail_s`` seconds,
              the virtual leader and its enclosing sphere of radius r_f, start and goal. Every
              message holds the whole scene, so a seek shows it complete.
``/tf``       ``foxglove.FrameTransforms`` (protobuf): ``world`` -> ``leader`` and ``world`` ->
              ``uav<i>`` (attitude from the measured roll/pitch/yaw).
``/metrics``  JSON (:data:`METRICS_SCHEMA`): formation and tracking errors, obstacle clearance per
              UAV and their extremes, the closest UAV pair, the leader's d_obs, the failsafe state
              (the plant's diagnostics) and per-link delivery and age (the agents' link counters,
              present when link faults are on: without them every link delivers everything).

Coordinates are ENU, z up, m, as in the paper; every stamp is the caller's ``stamp_ns``.
"""

from __future__ import annotations

import json
import math
import re
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove import Channel, Context
from foxglove import messages as fm
from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel

from zenswarm import wire
from zenswarm.bridge.foxglove import METRICS_TOPIC, SCENE_TOPIC, TF_TOPIC, WORLD
from zenswarm.geometry import d_obs_many, obstacle_clearance_many

__all__ = [
    "SCENE_TOPIC",
    "TF_TOPIC",
    "METRICS_TOPIC",
    "WORLD",
    "METRICS_SCHEMA",
    "Frame",
    "Trails",
    "frame_from_series",
    "scene_update",
    "frame_transforms",
    "metrics",
    "SceneChannels",
    "diag_view",
]



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
    """Frame of tick k of a :class:`zenswarm.metrics.TimeSeries`: trails sampled every ``stride``
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


# =========================================================================== primitives


def _time(ns: int) -> fm.Timestamp:
    return fm.Timestamp(sec=int(ns // 1_000_000_000), nsec=int(ns % 1_000_000_000))


def _v3(p: Any) -> fm.Vector3:
    return fm.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def _p3(p: Any) -> fm.Point3:
    return fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))


_IDENTITY = (0.0, 0.0, 0.0, 1.0)


def _quat(q: tuple[float, float, float, float]) -> fm.Quaternion:
    return fm.Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])


def _pose(p: Any, q: tuple[float, float, float, float] = _IDENTITY) -> fm.Pose:
    return fm.Pose(position=_v3(p), orientation=_quat(q))


def _color(c: Any, a: float) -> fm.Color:
    return fm.Color(r=float(c[0]), g=float(c[1]), b=float(c[2]), a=float(a))


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


def _entity(eid: str, stamp_ns: int, **prims: Any) -> fm.SceneEntity:
    return fm.SceneEntity(timestamp=_time(stamp_ns), frame_id=WORLD, id=eid, lifetime=fm.Duration(sec=0, nsec=0), **prims)


def _sphere(p: Any, diameter: float, color: fm.Color) -> fm.SpherePrimitive:
    return fm.SpherePrimitive(pose=_pose(p), size=_v3((diameter, diameter, diameter)), color=color)


def _cylinder(base: Any, diameter: float, height: float, color: fm.Color) -> fm.CylinderPrimitive:
    return fm.CylinderPrimitive(
        pose=_pose(np.asarray(base, dtype=float) + (0.0, 0.0, 0.5 * height)),
        size=_v3((diameter, diameter, height)),
        bottom_scale=1.0,
        top_scale=1.0,
        color=color,
    )


def _text(p: Any, text: str, color: fm.Color, size: float = 14.0) -> fm.TextPrimitive:
    return fm.TextPrimitive(pose=_pose(p), billboard=True, font_size=size, scale_invariant=True, color=color, text=text)


def _lines(points: list[Any], color: fm.Color, thickness: float, kind: fm.LinePrimitiveLineType) -> fm.LinePrimitive:
    return fm.LinePrimitive(
        type=kind, pose=_pose((0.0, 0.0, 0.0)), thickness=thickness, scale_invariant=True, points=[_p3(p) for p in points], color=color
    )


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


# =========================================================================== the scene


_GREY = (0.55, 0.57, 0.6)
_BAND = (0.95, 0.55, 0.15)
_DARK = (0.1, 0.1, 0.1)


def _static_entities(sc: Any, stamp_ns: int) -> list[fm.SceneEntity]:
    """Obstacles with their caps and d0 bands, goal and start."""
    ents = []
    band_r = sc.r_f + sc.leader.d0  # beyond r_o: d_obs(q0) <= d0 (eq. 10)
    for j, ob in enumerate(sc.obstacles):
        c = np.asarray(ob.center, dtype=float)
        top = c + (0.0, 0.0, ob.height)
        d = 2.0 * ob.radius
        ents.append(
            _entity(
                f"obstacle/{j + 1}",
                stamp_ns,
                cylinders=[_cylinder(c, d, ob.height, _color(_GREY, 0.75))],
                spheres=[_sphere(top, d, _color(_GREY, 0.75))],  # the cap; its lower half inside the cylinder
            )
        )
        db = 2.0 * (ob.radius + band_r)
        ents.append(
            _entity(
                f"d0_band/{j + 1}",
                stamp_ns,
                cylinders=[_cylinder(c, db, ob.height, _color(_BAND, 0.08))],
                spheres=[_sphere(top, db, _color(_BAND, 0.08))],
                texts=[_text(top + (0.0, 0.0, ob.radius + band_r), f"d0 band {j + 1}", _color(_BAND, 0.9), 11.0)],
            )
        )
    goal = np.asarray(sc.leader.goal, dtype=float)
    ents.append(
        _entity(
            "goal",
            stamp_ns,
            spheres=[_sphere(goal, 0.05, _color((0.1, 0.75, 0.2), 0.9))],
            texts=[_text(goal + (0, 0, 0.08), "goal", _color((0.1, 0.6, 0.2), 1.0))],
        )
    )
    start = fm.CubePrimitive(pose=_pose(sc.leader.start), size=_v3((0.04, 0.04, 0.04)), color=_color((0.2, 0.2, 0.2), 0.9))
    ents.append(_entity("start", stamp_ns, cubes=[start]))
    return ents


def _graph_lines(sc: Any, f: Frame) -> list[fm.LinePrimitive]:
    """The formation links: UAV pairs with a_ij > 0 (grey) and pinned UAVs b_i > 0 to the leader (blue)."""
    A = np.asarray(sc.graph.adjacency, dtype=float)
    b = np.asarray(sc.graph.pinning, dtype=float)
    n = len(A)
    pts = [p for i in range(n) for j in range(i + 1, n) if A[i, j] > 0 and _finite(f.q[i]) and _finite(f.q[j]) for p in (f.q[i], f.q[j])]
    out = []
    if pts:
        out.append(_lines(pts, _color((0.35, 0.35, 0.35), 0.6), 1.0, fm.LinePrimitiveLineType.LineList))
    if _finite(f.q0):
        pin = [p for i in range(n) if b[i] > 0 and _finite(f.q[i]) for p in (f.q0, f.q[i])]
        if pin:
            out.append(_lines(pin, _color((0.3, 0.5, 0.95), 0.6), 1.0, fm.LinePrimitiveLineType.LineList))
    return out


def scene_update(f: Frame, sc: Any, stamp_ns: int, colors: list[tuple[float, float, float]]) -> fm.SceneUpdate:
    """The ``foxglove.SceneUpdate`` of frame ``f`` of scenario ``sc``: the whole scene (see the
    module docstring), every entity stamped ``stamp_ns``; ``colors`` from :func:`palette`."""
    ents = _static_entities(sc, stamp_ns)
    lines = []
    if len(f.trail0) >= 2:
        lines.append(_lines(list(f.trail0), _color(_DARK, 0.8), 1.5, fm.LinePrimitiveLineType.LineStrip))
    if _finite(f.q0):
        ents.append(
            _entity(
                "leader",
                stamp_ns,
                spheres=[_sphere(f.q0, 0.03, _color((0.05, 0.05, 0.05), 1.0)), _sphere(f.q0, 2.0 * sc.r_f, _color((0.3, 0.5, 0.95), 0.12))],
                texts=[_text(f.q0 + (0, 0, 0.06), "leader", _color(_DARK, 1.0), 12.0)],
            )
        )
    for i, col in enumerate(colors):
        qi, vi = f.q[i], f.v[i]
        if len(f.trails[i]) >= 2:
            lines.append(_lines(list(f.trails[i]), _color(col, 0.9), 2.0, fm.LinePrimitiveLineType.LineStrip))
        if not _finite(qi):
            continue
        spheres = [_sphere(qi, 0.09, _color(col, 1.0))]
        if _finite(f.qref[i]):
            spheres.append(_sphere(f.qref[i], 0.05, _color(col, 0.3)))
        arrows = []
        speed = float(np.linalg.norm(vi)) if _finite(vi) else 0.0
        if speed > 0.01:
            arrows.append(
                fm.ArrowPrimitive(
                    pose=_pose(qi, quat_x_to(vi / speed)),
                    shaft_length=0.5 * speed,  # 0.5 s of travel
                    shaft_diameter=0.008,
                    head_length=0.03,
                    head_diameter=0.025,
                    color=_color(col, 0.9),
                )
            )
        label = _text(qi + (0, 0, 0.08), f"uav {i + 1}", _color(col, 1.0), 12.0)
        ents.append(_entity(f"uav/{i + 1}", stamp_ns, spheres=spheres, arrows=arrows, texts=[label]))
    ents.append(_entity("links", stamp_ns, lines=_graph_lines(sc, f)))
    ents.append(_entity("trails", stamp_ns, lines=lines))
    return fm.SceneUpdate(deletions=[], entities=ents)


def _transform(ts: fm.Timestamp, child: str, p: Any, rot: tuple[float, float, float, float]) -> fm.FrameTransform:
    return fm.FrameTransform(timestamp=ts, parent_frame_id=WORLD, child_frame_id=child, translation=_v3(p), rotation=_quat(rot))


def frame_transforms(f: Frame, stamp_ns: int) -> fm.FrameTransforms:
    """``foxglove.FrameTransforms`` of frame ``f``: world -> leader, world -> uav<i>."""
    out = []
    ts = _time(stamp_ns)
    if _finite(f.q0):
        out.append(_transform(ts, "leader", f.q0, _IDENTITY))
    for i in range(len(f.q)):
        if _finite(f.q[i]):
            rot = quat_rpy(f.rpy[i]) if _finite(f.rpy[i]) else _IDENTITY
            out.append(_transform(ts, f"uav{i + 1}", f.q[i], rot))
    return fm.FrameTransforms(transforms=out)


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
    :attr:`zenswarm.collector.Collector.diag` keeps per process)."""
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
    its newest diagnostics (counters and info, as :attr:`zenswarm.collector.Collector.diag`)."""
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


# =========================================================================== the channels


class SceneChannels:
    """``/scene``, ``/tf`` and ``/metrics`` on a Foxglove context (whatever sinks it has: an MCAP
    file, a WebSocket server); :meth:`put` logs one frame on the three."""

    def __init__(self, sc: Any, context: Context, trail_s: float = 10.0) -> None:
        self.sc = sc
        self.colors = palette(sc.n)
        self.trail_s = trail_s
        self.scene = SceneUpdateChannel(SCENE_TOPIC, context=context)
        self.tf = FrameTransformsChannel(TF_TOPIC, context=context)
        self.metrics = Channel(METRICS_TOPIC, schema=METRICS_SCHEMA, context=context)

    def put(self, f: Frame, stamp_ns: int, diag: dict[str, dict[str, Any]]) -> None:
        """Log frame ``f`` at ``stamp_ns`` (ns, the messages' log time and stamps)."""
        self.scene.log(scene_update(f, self.sc, stamp_ns, self.colors), log_time=stamp_ns)
        self.tf.log(frame_transforms(f, stamp_ns), log_time=stamp_ns)
        self.metrics.log(json.dumps(metrics(f, self.sc, diag), separators=(",", ":"), allow_nan=False).encode(), log_time=stamp_ns)

"""The Foxglove encoder of the scene (:mod:`zenswarm.bridge.views.scene`, the neutral description of
what the view shows): ``foxglove.SceneUpdate`` on ``/scene``, ``foxglove.FrameTransforms`` on
``/tf`` (protobuf, Foxglove's official schemas as the ``foxglove-sdk`` package ships them) and
JSON on ``/metrics`` (:data:`zenswarm.bridge.views.scene.METRICS_SCHEMA`). One code for both Foxglove
outputs: ``zenswarm export --foxglove`` writes these frames to an MCAP file
(:mod:`zenswarm.bridge.views.foxglove`), ``zenswarm up --live`` / ``zenswarm replay --live`` serve them
to the Foxglove app over its WebSocket protocol (:mod:`zenswarm.bridge.views.live`).

Every ``/scene`` message holds the whole scene (a seek shows it complete), every entity in the
``world`` frame with lifetime 0 (until replaced); every stamp is the caller's ``stamp_ns``.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from foxglove import Channel, Context
from foxglove import messages as fm
from foxglove.channels import FrameTransformsChannel, SceneUpdateChannel

from zenswarm.bridge.views.scene import (
    METRICS_SCHEMA,
    METRICS_TOPIC,
    SCENE_TOPIC,
    TF_TOPIC,
    WORLD,
    Arrow,
    Cube,
    Cylinder,
    Entity,
    Frame,
    Label,
    Polyline,
    Pose,
    Sphere,
    describe,
    metrics,
    palette,
    poses,
    quat_x_to,
)

__all__ = ["scene_update", "frame_transforms", "SceneChannels"]


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


def _color(c: tuple[float, float, float, float]) -> fm.Color:
    return fm.Color(r=c[0], g=c[1], b=c[2], a=c[3])


def _sphere(s: Sphere) -> fm.SpherePrimitive:
    d = s.diameter
    return fm.SpherePrimitive(pose=_pose(s.center), size=_v3((d, d, d)), color=_color(s.color))


def _cylinder(c: Cylinder) -> fm.CylinderPrimitive:
    return fm.CylinderPrimitive(
        pose=_pose(np.asarray(c.base, dtype=float) + (0.0, 0.0, 0.5 * c.height)),
        size=_v3((c.diameter, c.diameter, c.height)),
        bottom_scale=1.0,
        top_scale=1.0,
        color=_color(c.color),
    )


def _cube(c: Cube) -> fm.CubePrimitive:
    return fm.CubePrimitive(pose=_pose(c.center), size=_v3((c.size, c.size, c.size)), color=_color(c.color))


def _arrow(a: Arrow) -> fm.ArrowPrimitive:
    return fm.ArrowPrimitive(
        pose=_pose(a.origin, quat_x_to(a.direction)),
        shaft_length=a.length,
        shaft_diameter=a.shaft_diameter,
        head_length=a.head_length,
        head_diameter=a.head_diameter,
        color=_color(a.color),
    )


def _text(t: Label) -> fm.TextPrimitive:
    return fm.TextPrimitive(
        pose=_pose(t.position), billboard=True, font_size=t.size, scale_invariant=True, color=_color(t.color), text=t.text
    )


_LINE_KIND = {"strip": fm.LinePrimitiveLineType.LineStrip, "pairs": fm.LinePrimitiveLineType.LineList}


def _lines(ln: Polyline) -> fm.LinePrimitive:
    return fm.LinePrimitive(
        type=_LINE_KIND[ln.kind],
        pose=_pose((0.0, 0.0, 0.0)),
        thickness=ln.width,
        scale_invariant=True,
        points=[_p3(p) for p in ln.points],
        color=_color(ln.color),
    )


def _entity(e: Entity, stamp_ns: int) -> fm.SceneEntity:
    return fm.SceneEntity(
        timestamp=_time(stamp_ns),
        frame_id=WORLD,
        id=e.id,
        lifetime=fm.Duration(sec=0, nsec=0),
        arrows=[_arrow(a) for a in e.arrows],
        cubes=[_cube(c) for c in e.cubes],
        spheres=[_sphere(s) for s in e.spheres],
        cylinders=[_cylinder(c) for c in e.cylinders],
        lines=[_lines(ln) for ln in e.lines],
        texts=[_text(t) for t in e.labels],
    )


def scene_update(f: Frame, sc: Any, stamp_ns: int, colors: list[tuple[float, float, float]]) -> fm.SceneUpdate:
    """The ``foxglove.SceneUpdate`` of frame ``f`` of scenario ``sc``: the whole scene
    (:func:`zenswarm.bridge.views.scene.describe`), every entity stamped ``stamp_ns``; ``colors`` from
    :func:`zenswarm.bridge.views.scene.palette`."""
    return fm.SceneUpdate(deletions=[], entities=[_entity(e, stamp_ns) for e in describe(f, sc, colors)])


def _transform(ts: fm.Timestamp, p: Pose) -> fm.FrameTransform:
    return fm.FrameTransform(
        timestamp=ts, parent_frame_id=WORLD, child_frame_id=p.child, translation=_v3(p.position), rotation=_quat(p.rotation)
    )


def frame_transforms(f: Frame, stamp_ns: int) -> fm.FrameTransforms:
    """``foxglove.FrameTransforms`` of frame ``f`` (:func:`zenswarm.bridge.views.scene.poses`): world -> leader, world -> uav<i>."""
    ts = _time(stamp_ns)
    return fm.FrameTransforms(transforms=[_transform(ts, p) for p in poses(f)])


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

"""``zenswarm export --foxglove FILE --out OUT.mcap``: a recording Foxglove opens without plugins.

Foxglove does not decode msgpack, so the export re-encodes every recorded wire message as JSON
(message encoding ``json``) on a channel with a JSON Schema (schema encoding ``jsonschema``), one
schema per message kind (``zenswarm.State``, ``zenswarm.Ref``, ``zenswarm.Cmd``, ``zenswarm.Clock``,
``zenswarm.Mission``, ``zenswarm.Diag``): the wire fields exactly as :mod:`zenswarm.wire` defines
them (``v``, ``k``, ``t``, ``seq``, ``q``, ``vel``...). Topics are the recorded Zenoh keys.

On top of that it adds, at ``--scene-hz`` (default 20 Hz) of sim time:

``/scene``  ``foxglove.SceneUpdate``: obstacles (cylinder + sphere for the hemispherical cap), the
            UAVs (spheres, a velocity arrow, a label, a faint sphere at the reference q*_i), their
            trails (line strips over the last ``--trail-s`` seconds), the virtual leader and its
            enclosing sphere of radius r_f, start and goal.
``/tf``     ``foxglove.FrameTransforms``: ``world`` -> ``leader`` and ``world`` -> ``uav<i>``
            (attitude from the measured roll/pitch/yaw), so the 3D panel can follow any of them.

Both use Foxglove's published JSON Schemas (``schemas/jsonschema/SceneUpdate.json`` and
``FrameTransforms.json`` of foxglove/foxglove-sdk), rebuilt here from their parts; coordinates
are ENU, z up, as in the paper. The foxglove-sdk Python package encodes its typed messages as
protobuf only, which cannot be validated here without a protobuf runtime, so the file is written
with the ``mcap`` writer the recorder uses.

Time: every message is logged at ``base + t`` where t is its sim time (the wire ``t``) and base
the receive wall time of the recording's first message, so Foxglove plays the flight in sim
time (a lockstep run that computed 25x faster than real time plays at its real speed).
"""

from __future__ import annotations

import argparse
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from zenswarm import wire
from zenswarm.errors import RecordingError, ZenswarmError

__all__ = [
    "SCENE_TOPIC",
    "TF_TOPIC",
    "SCENE_UPDATE_SCHEMA",
    "FRAME_TRANSFORMS_SCHEMA",
    "wire_json_schema",
    "wire_to_json",
    "ExportSummary",
    "export_foxglove",
    "add_parsers",
]

SCENE_TOPIC = "/scene"
TF_TOPIC = "/tf"
WORLD = "world"

# =========================================================================== JSON Schemas: wire

_KIND_TITLES = {
    "clock": "zenswarm.Clock",
    "state": "zenswarm.State",
    "ref": "zenswarm.Ref",
    "cmd": "zenswarm.Cmd",
    "mission": "zenswarm.Mission",
    "diag": "zenswarm.Diag",
}

_KIND_DESCRIPTIONS = {
    "clock": "Lockstep tick published by the plant (swarm/<name>/clock)",
    "state": "Measured state of UAV i, plant -> agent i (swarm/<name>/uav/<i>/state); ENU, SI units",
    "ref": (
        "Reference q*_i, v*_i of UAV i, eqs (16)-(17) (swarm/<name>/uav/<i>/ref), "
        "or the virtual leader's q0, v0 (swarm/<name>/leader/ref)"
    ),
    "cmd": "Command of agent i to the plant, eq. (28) and the attitude inversion (swarm/<name>/uav/<i>/cmd)",
    "mission": "The scenario, published by the leader (swarm/<name>/mission)",
    "diag": "Diagnostics counters of a process (swarm/<name>/diag/<process>)",
}


def _vec3(desc: str) -> dict[str, Any]:
    return {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3, "description": desc}


def wire_json_schema(kind: str) -> dict[str, Any]:
    """JSON Schema of a wire message of ``kind`` (one of :data:`zenswarm.wire.KINDS`) as JSON.

    The exact field set of the wire (no other property), with the decoder's constraints:
    version, kind tag, non-negative integer t (sim time, ns) and seq, 3-vectors of numbers.
    """
    if kind not in _KIND_TITLES:
        raise ValueError(f"unknown message kind {kind!r}; expected one of {wire.KINDS}")
    props: dict[str, Any] = {
        "v": {"const": wire.SCHEMA_VERSION, "description": "wire schema version"},
        "k": {"const": kind, "description": "message kind"},
        "t": {"type": "integer", "minimum": 0, "maximum": wire.MAX_T_NS, "description": "sim time, ns"},
        "seq": {"type": "integer", "minimum": 0, "maximum": wire.MAX_SEQ, "description": "sequence number"},
    }
    if kind == "state":
        props["q"] = _vec3("position, m, ENU")
        props["vel"] = _vec3("velocity, m/s, ENU")
        props["rpy"] = _vec3("roll, pitch, yaw, rad")
        props["w"] = _vec3("body (FLU) angular rate, rad/s")
    elif kind == "ref":
        props["q"] = _vec3("reference position q*_i (or q0), m, ENU")
        props["vel"] = _vec3("reference velocity v*_i (or v0), m/s, ENU")
    elif kind == "cmd":
        props["thrust"] = {"type": "number", "description": "collective thrust F, N"}
        props["rpy"] = _vec3("desired roll, pitch, yaw, rad")
        props["u"] = _vec3("virtual control u_i, m/s^2 (eq. 28)")
        props["d_hat"] = _vec3("ESO disturbance estimate, m/s^2 (eq. 27)")
    elif kind == "mission":
        props["scenario"] = {"type": "object", "description": "the scenario (zenswarm.config.scenario_to_dict)"}
    elif kind == "diag":
        props["process"] = {"type": "string", "description": "process name (plant, leader, agent:<i>, ...)"}
        props["counters"] = {"type": "object", "additionalProperties": {"type": "number"}, "description": "counters"}
        props["info"] = {"type": "object", "description": "free-form information"}
    required = list(props)
    if kind == "state":  # optional: the MAVLink bridge's vehicle time of the measurement
        props["ts"] = {
            "type": "integer",
            "minimum": -wire.MAX_T_NS,
            "maximum": wire.MAX_T_NS,
            "description": "when the vehicle measured q and vel, on the sim-time clock, ns (t - ts: the state's age)",
        }
    return {
        "title": _KIND_TITLES[kind],
        "description": _KIND_DESCRIPTIONS[kind],
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": False,
    }


def wire_to_json(kind: str, payload: bytes) -> bytes:
    """Validate a msgpack wire payload with :func:`zenswarm.wire.decode` and re-encode its wire
    map as compact JSON. Raises :class:`zenswarm.wire.WireDecodeError` when it is rejected."""
    wire.decode(kind, payload)
    obj = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


# =========================================================================== JSON Schemas: Foxglove
# Foxglove's published JSON Schemas (foxglove/foxglove-sdk, schemas/jsonschema/*.json), rebuilt
# from their parts: same titles, properties, types and required lists.


def _fx(title: str, description: str, props: dict[str, Any], required: list[str] | None = None) -> dict[str, Any]:
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": props,
        "required": list(props) if required is None else required,
    }


def _num(d: str) -> dict[str, Any]:
    return {"type": "number", "description": d}


def _arr(items: dict[str, Any], d: str) -> dict[str, Any]:
    return {"type": "array", "items": items, "description": d}


_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_DURATION = {
    "type": "object",
    "title": "duration",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_VECTOR3 = _fx(
    "foxglove.Vector3",
    "A vector in 3D space that represents a direction only",
    {"x": _num("x coordinate length"), "y": _num("y coordinate length"), "z": _num("z coordinate length")},
)
_POINT3 = _fx(
    "foxglove.Point3",
    "A point representing a position in 3D space",
    {"x": _num("x coordinate position"), "y": _num("y coordinate position"), "z": _num("z coordinate position")},
)
_QUATERNION = _fx(
    "foxglove.Quaternion",
    "A [quaternion](https://eater.net/quaternions) representing a rotation in 3D space",
    {"x": _num("x value"), "y": _num("y value"), "z": _num("z value"), "w": _num("w value")},
)
_POSE = _fx(
    "foxglove.Pose",
    "A position and orientation for an object or reference frame in 3D space",
    {"position": _VECTOR3, "orientation": _QUATERNION},
)
_COLOR = _fx(
    "foxglove.Color",
    "A color in RGBA format",
    {
        "r": _num("Red value between 0 and 1"),
        "g": _num("Green value between 0 and 1"),
        "b": _num("Blue value between 0 and 1"),
        "a": _num("Alpha value between 0 and 1"),
    },
)
_KEY_VALUE = _fx(
    "foxglove.KeyValuePair",
    "A key with its associated value",
    {"key": {"type": "string", "description": "Key"}, "value": {"type": "string", "description": "Value"}},
)
_ARROW = _fx(
    "foxglove.ArrowPrimitive",
    "A primitive representing an arrow",
    {
        "pose": _POSE,
        "shaft_length": _num("Length of the arrow shaft"),
        "shaft_diameter": _num("Diameter of the arrow shaft"),
        "head_length": _num("Length of the arrow head"),
        "head_diameter": _num("Diameter of the arrow head"),
        "color": _COLOR,
    },
)
_CUBE = _fx(
    "foxglove.CubePrimitive", "A primitive representing a cube or rectangular prism", {"pose": _POSE, "size": _VECTOR3, "color": _COLOR}
)
_SPHERE = _fx(
    "foxglove.SpherePrimitive", "A primitive representing a sphere or ellipsoid", {"pose": _POSE, "size": _VECTOR3, "color": _COLOR}
)
_CYLINDER = _fx(
    "foxglove.CylinderPrimitive",
    "A primitive representing a cylinder, elliptic cylinder, or truncated cone",
    {
        "pose": _POSE,
        "size": _VECTOR3,
        "bottom_scale": _num("0-1, ratio of the diameter of the cylinder's bottom face (min z) to the bottom of the bounding box"),
        "top_scale": _num("0-1, ratio of the diameter of the cylinder's top face (max z) to the top of the bounding box"),
        "color": _COLOR,
    },
)
_INDICES = _arr({"type": "integer", "minimum": 0}, "Indices into the `points` and `colors` attribute arrays")
_LINE = _fx(
    "foxglove.LinePrimitive",
    "A primitive representing a series of points connected by lines",
    {
        "type": {
            "title": "foxglove.LineType",
            "description": "An enumeration indicating how input points should be interpreted to create lines",
            "oneOf": [
                {"title": "LINE_STRIP", "const": 0, "description": "Connected line segments: 0-1, 1-2, ..., (n-1)-n"},
                {"title": "LINE_LOOP", "const": 1, "description": "Closed polygon: 0-1, 1-2, ..., (n-1)-n, n-0"},
                {"title": "LINE_LIST", "const": 2, "description": "Individual line segments: 0-1, 2-3, 4-5, ..."},
            ],
        },
        "pose": _POSE,
        "thickness": _num("Line thickness"),
        "scale_invariant": {
            "type": "boolean",
            "description": "Indicates whether `thickness` is a fixed size in screen pixels (true), "
            "or specified in world coordinates and scales with distance from the camera (false)",
        },
        "points": _arr(_POINT3, "Points along the line"),
        "color": _COLOR,
        "colors": _arr(_COLOR, "Per-point colors (if non-empty, must have the same length as `points`)."),
        "indices": _INDICES,
    },
)
_TRIANGLES = _fx(
    "foxglove.TriangleListPrimitive",
    "A primitive representing a set of triangles or a surface tiled by triangles",
    {
        "pose": _POSE,
        "points": _arr(_POINT3, "Vertices to use for triangles, interpreted as a list of triples (0-1-2, 3-4-5, ...)"),
        "color": _COLOR,
        "colors": _arr(_COLOR, "Per-vertex colors (if specified, must have the same length as `points`)."),
        "indices": _INDICES,
    },
)
_TEXT = _fx(
    "foxglove.TextPrimitive",
    "A primitive representing a text label",
    {
        "pose": _POSE,
        "billboard": {
            "type": "boolean",
            "description": "Whether the text should respect `pose.orientation` (false) or always face the camera (true)",
        },
        "font_size": _num("Font size (height of one line of text)"),
        "scale_invariant": {
            "type": "boolean",
            "description": "Indicates whether `font_size` is a fixed size in screen pixels (true), "
            "or specified in world coordinates and scales with distance from the camera (false)",
        },
        "color": _COLOR,
        "text": {"type": "string", "description": "Text"},
    },
)
_MODEL = _fx(
    "foxglove.ModelPrimitive",
    "A primitive representing a 3D model file loaded from an external URL or embedded data",
    {
        "pose": _POSE,
        "scale": _VECTOR3,
        "color": _COLOR,
        "override_color": {
            "type": "boolean",
            "description": "Whether to use the color specified in `color` instead of any materials embedded in the original model.",
        },
        "url": {"type": "string", "description": "URL pointing to model file. One of `url` or `data` should be non-empty."},
        "media_type": {"type": "string", "description": "Media type of embedded model (e.g. `model/gltf-binary`)."},
        "data": {
            "type": "string", "contentEncoding": "base64", "description": "Embedded model. One of `url` or `data` should be non-empty."
        },
    },
)
_ENTITY = _fx(
    "foxglove.SceneEntity",
    "A visual element in a 3D scene. An entity may be composed of multiple primitives which all share the same frame of reference.",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string", "description": "Frame of reference"},
        "id": {
            "type": "string",
            "description": "Identifier for the entity. A entity will replace any prior entity on the same topic with the same `id`.",
        },
        "lifetime": _DURATION,
        "frame_locked": {
            "type": "boolean",
            "description": "Whether the entity should keep its location in the fixed frame (false) or follow the frame "
            "specified in `frame_id` as it moves relative to the fixed frame (true)",
        },
        "metadata": _arr(_KEY_VALUE, "Additional user-provided metadata associated with the entity. Keys must be unique."),
        "arrows": _arr(_ARROW, "Arrow primitives"),
        "cubes": _arr(_CUBE, "Cube primitives"),
        "spheres": _arr(_SPHERE, "Sphere primitives"),
        "cylinders": _arr(_CYLINDER, "Cylinder primitives"),
        "lines": _arr(_LINE, "Line primitives"),
        "triangles": _arr(_TRIANGLES, "Triangle list primitives"),
        "texts": _arr(_TEXT, "Text primitives"),
        "models": _arr(_MODEL, "Model primitives"),
    },
)
_DELETION = _fx(
    "foxglove.SceneEntityDeletion",
    "Command to remove previously published entities",
    {
        "timestamp": _TIME,
        "type": {
            "title": "foxglove.SceneEntityDeletionType",
            "description": "An enumeration indicating which entities should match a SceneEntityDeletion command",
            "oneOf": [
                {
                    "title": "MATCHING_ID",
                    "const": 0,
                    "description": "Delete the existing entity on the same topic that has the provided `id`",
                },
                {"title": "ALL", "const": 1, "description": "Delete all existing entities on the same topic"},
            ],
        },
        "id": {"type": "string", "description": "Identifier which must match if `type` is `MATCHING_ID`."},
    },
)
SCENE_UPDATE_SCHEMA: dict[str, Any] = {
    **_fx(
        "foxglove.SceneUpdate",
        "An update to the entities displayed in a 3D scene",
        {"deletions": _arr(_DELETION, "Scene entities to delete"), "entities": _arr(_ENTITY, "Scene entities to add or replace")},
    ),
    "$comment": "Foxglove's published schema (foxglove/foxglove-sdk schemas/jsonschema/SceneUpdate.json)",
}
"""JSON Schema of ``foxglove.SceneUpdate``."""

_FRAME_TRANSFORM = _fx(
    "foxglove.FrameTransform",
    "A transform between two reference frames in 3D space",
    {
        "timestamp": _TIME,
        "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
        "child_frame_id": {"type": "string", "description": "Name of the child frame"},
        "translation": _VECTOR3,
        "rotation": _QUATERNION,
    },
)
FRAME_TRANSFORMS_SCHEMA: dict[str, Any] = {
    **_fx("foxglove.FrameTransforms", "An array of FrameTransform messages", {"transforms": _arr(_FRAME_TRANSFORM, "Array of transforms")}),
    "$comment": "Foxglove's published schema (foxglove/foxglove-sdk schemas/jsonschema/FrameTransforms.json)",
}
"""JSON Schema of ``foxglove.FrameTransforms``."""


# =========================================================================== scene building


def _time(ns: int) -> dict[str, int]:
    return {"sec": int(ns // 1_000_000_000), "nsec": int(ns % 1_000_000_000)}


def _v3(p: Any) -> dict[str, float]:
    return {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}


_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def _pose(p: Any, q: dict[str, float] | None = None) -> dict[str, Any]:
    return {"position": _v3(p), "orientation": dict(q or _IDENTITY)}


def _rgba(c: Any, a: float | None = None) -> dict[str, float]:
    r, g, b = (float(x) for x in c[:3])
    return {"r": r, "g": g, "b": b, "a": float(c[3] if a is None and len(c) > 3 else (1.0 if a is None else a))}


def _quat_rpy(rpy: Any) -> dict[str, float]:
    """Quaternion of roll-pitch-yaw (ZYX: R = Rz(yaw) Ry(pitch) Rx(roll)), body FLU in ENU."""
    r, p, y = (0.5 * float(x) for x in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return {
        "x": sr * cp * cy - cr * sp * sy,
        "y": cr * sp * cy + sr * cp * sy,
        "z": cr * cp * sy - sr * sp * cy,
        "w": cr * cp * cy + sr * sp * sy,
    }


def _quat_x_to(d: np.ndarray) -> dict[str, float]:
    """Quaternion rotating +x onto the unit vector d (arrow orientation)."""
    dx, dy, dz = (float(v) for v in d)
    w = 1.0 + dx
    if w < 1e-9:  # d = -x: half turn about z
        return {"x": 0.0, "y": 0.0, "z": 1.0, "w": 0.0}
    x, y, z = 0.0, -dz, dy  # cross((1, 0, 0), d)
    nrm = math.sqrt(w * w + y * y + z * z)
    return {"x": x / nrm, "y": y / nrm, "z": z / nrm, "w": w / nrm}


def _entity(eid: str, stamp_ns: int, **prims: list) -> dict[str, Any]:
    e: dict[str, Any] = {
        "timestamp": _time(stamp_ns),
        "frame_id": WORLD,
        "id": eid,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [],
    }
    for k in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models"):
        e[k] = prims.get(k, [])
    return e


def _sphere(p: Any, diameter: float, color: dict[str, float]) -> dict[str, Any]:
    return {"pose": _pose(p), "size": _v3((diameter, diameter, diameter)), "color": color}


def _text(p: Any, text: str, color: dict[str, float], size: float = 14.0) -> dict[str, Any]:
    return {"pose": _pose(p), "billboard": True, "font_size": size, "scale_invariant": True, "color": color, "text": text}


def _strip(points: np.ndarray, color: dict[str, float], thickness: float = 2.0) -> dict[str, Any]:
    return {
        "type": 0,
        "pose": _pose((0.0, 0.0, 0.0)),
        "thickness": thickness,
        "scale_invariant": True,
        "points": [_v3(p) for p in points],
        "color": color,
        "colors": [],
        "indices": [],
    }


def _rgb(rgba: tuple[float, float, float, float]) -> tuple[float, float, float]:
    """The colour of an RGBA tuple (each 0..1), without its alpha."""
    return (rgba[0], rgba[1], rgba[2])


def _palette(n: int) -> list[tuple[float, float, float]]:
    from matplotlib import colormaps

    if n <= 10:
        cmap = colormaps["tab10"]
        return [_rgb(cmap(i)) for i in range(n)]
    cmap = colormaps["turbo"]
    return [_rgb(cmap(0.05 + 0.9 * i / max(1, n - 1))) for i in range(n)]


def _finite(p: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(p)))


def scene_update(ts: Any, sc: Any, k: int, stamp_ns: int, trail_ticks: int, stride: int, colors: list) -> dict[str, Any]:
    """The ``foxglove.SceneUpdate`` of tick k: the whole scene (every entity, so a seek in
    Foxglove shows a complete scene from the latest message alone)."""
    ents: list[dict[str, Any]] = []
    grey = {"r": 0.55, "g": 0.57, "b": 0.6, "a": 0.75}
    for j, ob in enumerate(sc.obstacles):
        c = np.asarray(ob.center, dtype=float)
        d = 2.0 * ob.radius
        cyl = {
            "pose": _pose(c + (0.0, 0.0, 0.5 * ob.height)),
            "size": _v3((d, d, ob.height)),
            "bottom_scale": 1.0,
            "top_scale": 1.0,
            "color": grey,
        }
        cap = _sphere(c + (0.0, 0.0, ob.height), d, grey)  # lower half hidden inside the cylinder
        ents.append(_entity(f"obstacle/{j + 1}", stamp_ns, cylinders=[cyl], spheres=[cap]))
    ents.append(
        _entity(
            "goal",
            stamp_ns,
            spheres=[_sphere(sc.leader.goal, 0.05, {"r": 0.1, "g": 0.75, "b": 0.2, "a": 0.9})],
            texts=[_text(np.asarray(sc.leader.goal) + (0, 0, 0.08), "goal", {"r": 0.1, "g": 0.6, "b": 0.2, "a": 1.0})],
        )
    )
    start_cube = {"pose": _pose(sc.leader.start), "size": _v3((0.04, 0.04, 0.04)), "color": {"r": 0.2, "g": 0.2, "b": 0.2, "a": 0.9}}
    ents.append(_entity("start", stamp_ns, cubes=[start_cube]))

    lo = max(0, k - trail_ticks)
    idx = np.arange(lo, k + 1, stride)
    if idx[-1] != k:
        idx = np.append(idx, k)
    lines = []
    q0 = ts.q0[k]
    if _finite(q0):
        tr = ts.q0[idx]
        tr = tr[np.all(np.isfinite(tr), axis=1)]
        if len(tr) >= 2:
            lines.append(_strip(tr, {"r": 0.1, "g": 0.1, "b": 0.1, "a": 0.8}, 1.5))
        ents.append(
            _entity(
                "leader",
                stamp_ns,
                spheres=[
                    _sphere(q0, 0.03, {"r": 0.05, "g": 0.05, "b": 0.05, "a": 1.0}),
                    _sphere(q0, 2.0 * sc.r_f, {"r": 0.3, "g": 0.5, "b": 0.95, "a": 0.12}),
                ],
                texts=[_text(q0 + (0, 0, 0.06), "leader", {"r": 0.1, "g": 0.1, "b": 0.1, "a": 1.0}, 12.0)],
            )
        )
    n = ts.q.shape[1]
    for i in range(n):
        col = colors[i]
        qi, vi = ts.q[k, i], ts.v[k, i]
        tr = ts.q[idx, i]
        tr = tr[np.all(np.isfinite(tr), axis=1)]
        if len(tr) >= 2:
            lines.append(_strip(tr, _rgba(col, 0.9)))
        if not _finite(qi):
            continue
        spheres = [_sphere(qi, 0.09, _rgba(col, 1.0))]
        if _finite(ts.qref[k, i]):
            spheres.append(_sphere(ts.qref[k, i], 0.05, _rgba(col, 0.3)))
        arrows = []
        speed = float(np.linalg.norm(vi)) if _finite(vi) else 0.0
        if speed > 0.01:
            arrows.append(
                {
                    "pose": _pose(qi, _quat_x_to(vi / speed)),
                    "shaft_length": 0.5 * speed,  # 0.5 s of travel
                    "shaft_diameter": 0.008,
                    "head_length": 0.03,
                    "head_diameter": 0.025,
                    "color": _rgba(col, 0.9),
                }
            )
        ents.append(
            _entity(
                f"uav/{i + 1}",
                stamp_ns,
                spheres=spheres,
                arrows=arrows,
                texts=[_text(qi + (0, 0, 0.08), f"uav {i + 1}", _rgba(col, 1.0), 12.0)],
            )
        )
    ents.append(_entity("trails", stamp_ns, lines=lines))
    return {"deletions": [], "entities": ents}


def frame_transforms(ts: Any, k: int, stamp_ns: int) -> dict[str, Any]:
    """``foxglove.FrameTransforms`` of tick k: world -> leader, world -> uav<i>."""
    out = []
    if _finite(ts.q0[k]):
        out.append(
            {
                "timestamp": _time(stamp_ns),
                "parent_frame_id": WORLD,
                "child_frame_id": "leader",
                "translation": _v3(ts.q0[k]),
                "rotation": dict(_IDENTITY),
            }
        )
    for i in range(ts.q.shape[1]):
        if _finite(ts.q[k, i]):
            rot = _quat_rpy(ts.rpy[k, i]) if _finite(ts.rpy[k, i]) else dict(_IDENTITY)
            out.append(
                {
                    "timestamp": _time(stamp_ns),
                    "parent_frame_id": WORLD,
                    "child_frame_id": f"uav{i + 1}",
                    "translation": _v3(ts.q[k, i]),
                    "rotation": rot,
                }
            )
    return {"transforms": out}


# =========================================================================== export


@dataclass
class ExportSummary:
    """What an export wrote: counts per topic, what it skipped and why."""

    out: Path
    messages: int = 0
    scene_frames: int = 0
    topics: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    time_base_ns: int = 0

    def skip(self, why: str) -> None:
        """Count one recorded message not exported, and why."""
        self.skipped[why] = self.skipped.get(why, 0) + 1


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _compression():
    from mcap.writer import CompressionType

    try:
        import zstandard  # noqa: F401

        return CompressionType.ZSTD
    except ImportError:  # pragma: no cover - mcap depends on zstandard
        return CompressionType.LZ4


def _json_items(rec: Any, keys: wire.Keys, summary: ExportSummary) -> tuple[list[tuple[int, int, str, str, bytes]], int]:
    """The recorded messages as JSON: ``(sim t ns, file order, topic, kind, json)`` (what cannot
    be exported is counted in ``summary.skipped``), and the time base, ns: the first received
    message's receive time minus its sim time (0 without messages)."""
    items: list[tuple[int, int, str, str, bytes]] = []  # (sim t, order, topic, kind, json)
    first_rx: tuple[int, int] | None = None  # (receive time, sim t) of the first message received
    for order, m in enumerate(rec.messages):
        if m.encoding != "msgpack":
            summary.skip("not msgpack")
            continue
        try:
            key_kind, _, _ = keys.parse(m.topic)
        except wire.InvalidKeyError:
            summary.skip("not a key of the swarm")
            continue
        kind = wire.message_kind(key_kind)
        if kind is None:
            summary.skip("liveliness token")
            continue
        try:
            data = wire_to_json(kind, m.data)
        except wire.WireDecodeError as e:
            summary.skip(f"rejected by the decoder ({e.reason})")
            continue
        t_sim = int(json.loads(data)["t"])
        items.append((t_sim, order, m.topic, kind, data))
        if first_rx is None or m.log_time < first_rx[0]:
            first_rx = (m.log_time, t_sim)
    base = max(0, first_rx[0] - first_rx[1]) if first_rx is not None else 0
    return items, base


class _JsonOut:
    """The export's MCAP writer: JSON channels registered at first use (one JSON Schema per
    title), per-channel sequence numbers from 0, log time = publish time = ``base`` + sim time."""

    def __init__(self, w: Any, base: int) -> None:
        self.w = w
        self.base = base
        self.schema_ids: dict[str, int] = {}
        self.channel_ids: dict[str, int] = {}
        self.seqs: dict[int, int] = {}

    def schema(self, schema: dict[str, Any]) -> int:
        sid = self.schema_ids.get(schema["title"])
        if sid is None:
            sid = self.w.register_schema(schema["title"], "jsonschema", _dumps(schema))
            self.schema_ids[schema["title"]] = sid
        return sid

    def channel(self, topic: str, schema: dict[str, Any]) -> int:
        cid = self.channel_ids.get(topic)
        if cid is None:
            cid = self.w.register_channel(topic, "json", self.schema(schema))
            self.channel_ids[topic] = cid
        return cid

    def put(self, cid: int, t_sim: int, data: bytes) -> None:
        s = self.seqs.get(cid, 0)
        self.seqs[cid] = s + 1
        self.w.add_message(cid, log_time=self.base + t_sim, data=data, publish_time=self.base + t_sim, sequence=s)


@dataclass
class _Scene:
    """The 3D scene's frames: ``frames`` = (sim t ns, tick) every ``stride`` ticks of ``ts``."""

    ts: Any
    sc: Any
    frames: list[tuple[int, int]]
    stride: int
    trail_ticks: int
    colors: list
    scene_cid: int
    tf_cid: int

    def put(self, out: _JsonOut, j: int) -> None:
        """Write frame j on /scene and /tf."""
        ts_ns, k = self.frames[j]
        stamp = out.base + ts_ns
        out.put(self.scene_cid, ts_ns, _dumps(scene_update(self.ts, self.sc, k, stamp, self.trail_ticks, self.stride, self.colors)))
        out.put(self.tf_cid, ts_ns, _dumps(frame_transforms(self.ts, k, stamp)))


def _scene(ts: Any, sc: Any, out: _JsonOut, scene_hz: float, trail_s: float) -> _Scene | None:
    """The scene of the flight series ``ts`` (None without one); registers /scene and /tf."""
    if ts is None or not len(ts.t):
        return None
    dt = sc.timing.dt
    stride = max(1, int(round(1.0 / (scene_hz * dt))))
    frames = [(wire.t_ns(float(ts.t[k])), k) for k in range(0, len(ts.t), stride)]
    colors = _palette(ts.q.shape[1])
    scene_cid = out.channel(SCENE_TOPIC, SCENE_UPDATE_SCHEMA)
    tf_cid = out.channel(TF_TOPIC, FRAME_TRANSFORMS_SCHEMA)
    return _Scene(ts, sc, frames, stride, int(round(trail_s / dt)), colors, scene_cid, tf_cid)


def _write_messages(out: _JsonOut, items: list[tuple[int, int, str, str, bytes]], scene: _Scene | None, summary: ExportSummary) -> None:
    """The recorded messages in sim-time order (file order among equal times), each scene frame
    before the messages of a later sim time."""
    frames = scene.frames if scene is not None else []
    j = 0
    for t_sim, _, topic, kind, data in items:
        while j < len(frames) and frames[j][0] <= t_sim:
            scene.put(out, j)  # type: ignore[union-attr]
            summary.scene_frames += 1
            j += 1
        out.put(out.channel(topic, wire_json_schema(kind)), t_sim, data)
        summary.topics[topic] = summary.topics.get(topic, 0) + 1
        summary.messages += 1
    for jj in range(j, len(frames)):
        scene.put(out, jj)  # type: ignore[union-attr]
        summary.scene_frames += 1
    if summary.scene_frames:
        summary.topics[SCENE_TOPIC] = summary.topics[TF_TOPIC] = summary.scene_frames


def export_foxglove(recording: str | Path, out: str | Path, *, scene_hz: float = 20.0, trail_s: float = 10.0) -> ExportSummary:
    """Export a recording for Foxglove (see the module docstring). The file is written next to
    ``out`` and renamed into place when complete. Raises RecordingError for an unusable input."""
    from mcap.writer import Writer

    from zenswarm.bridge.report import flight_from_recording, load_recording

    if not scene_hz > 0 or not math.isfinite(scene_hz):
        raise ZenswarmError(f"--scene-hz must be a positive number, got {scene_hz}")
    if not trail_s >= 0 or not math.isfinite(trail_s):
        raise ZenswarmError(f"--trail-s must be >= 0, got {trail_s}")
    rec = load_recording(recording)
    out = Path(out)
    summary = ExportSummary(out)

    # 1. recorded messages -> JSON, each at base + its sim time
    items, base = _json_items(rec, wire.Keys(rec.swarm), summary)
    summary.time_base_ns = base

    # 2. the scene, from the same series the report uses
    try:
        ts = flight_from_recording(rec).series
    except RecordingError:
        ts = None
    tmp = out.with_name(out.name + ".part")
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(tmp, "wb") as f:
        w = Writer(f, compression=_compression(), chunk_size=4 * 1024 * 1024)
        w.start(profile="", library="zenswarm export --foxglove")
        jo = _JsonOut(w, base)
        for kind in wire.KINDS:  # schemas of every kind, even those not in this recording
            jo.schema_ids[_KIND_TITLES[kind]] = w.register_schema(_KIND_TITLES[kind], "jsonschema", _dumps(wire_json_schema(kind)))
        items.sort(key=lambda it: (it[0], it[1]))
        _write_messages(jo, items, _scene(ts, rec.scenario, jo, scene_hz, trail_s), summary)
        w.add_metadata("zenswarm", dict(rec.metadata))
        w.add_metadata(
            "zenswarm_export",
            {"source": str(rec.path), "time_base_ns": str(base), "timeline": "base + sim time", "scene_hz": f"{scene_hz:g}"},
        )
        for name, d in rec.other_metadata:
            if name not in ("zenswarm", "zenswarm_export"):
                w.add_metadata(name, d)
        w.finish()
    os.replace(tmp, out)
    return summary


# =========================================================================== CLI


def _run_export(args: argparse.Namespace) -> int:
    from zenswarm.paths import check_output_file

    check_output_file(args.out, "--out")
    s = export_foxglove(args.foxglove, args.out, scene_hz=args.scene_hz, trail_s=args.trail_s)
    skipped = ", ".join(f"{n} {why}" for why, n in sorted(s.skipped.items())) or "none"
    print(
        f"{s.out}: {s.messages} recorded messages on {len(s.topics) - (2 if s.scene_frames else 0)} JSON channels, "
        f"{s.scene_frames} scene frames on {SCENE_TOPIC} and {TF_TOPIC}; skipped: {skipped}"
    )
    print(s.out)
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``zenswarm export`` on the CLI's subparsers."""
    p = sub.add_parser(
        "export",
        help="export a recording for other tools (--foxglove: JSON channels + 3D scene for Foxglove)",
        description=(
            "Export a recording. --foxglove FILE writes OUT, an MCAP file Foxglove opens without "
            "plugins: every recorded message as JSON with a JSON Schema per message kind (topics "
            "are the Zenoh keys), plus a 3D scene on /scene (foxglove.SceneUpdate: obstacles, "
            "UAVs, trails, the virtual leader and its enclosing sphere) and /tf "
            "(foxglove.FrameTransforms), timed in sim time."
        ),
    )
    p.add_argument("--foxglove", type=Path, required=True, metavar="FILE", help="the MCAP recording to export")
    p.add_argument("--out", type=Path, required=True, metavar="OUT.mcap", help="output MCAP file (replaced if present)")
    p.add_argument("--scene-hz", type=float, default=20.0, help="rate of /scene and /tf in sim time (default 20)")
    p.add_argument("--trail-s", type=float, default=10.0, help="length of the trails, s of sim time (default 10)")
    p.set_defaults(func=_run_export)

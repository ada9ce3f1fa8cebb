"""``zenswarm export --foxglove FILE --out OUT.mcap``: a recording Foxglove opens without plugins.

Foxglove does not decode msgpack, so the export re-encodes every recorded wire message as JSON
(message encoding ``json``) on a channel with a JSON Schema (schema encoding ``jsonschema``), one
schema per message kind (``zenswarm.State``, ``zenswarm.Ref``, ``zenswarm.Cmd``, ``zenswarm.Clock``,
``zenswarm.Mission``, ``zenswarm.Diag``): the wire fields exactly as :mod:`zenswarm.bus.wire` defines
them (``v``, ``k``, ``t``, ``seq``, ``q``, ``vel``...). Topics are the recorded Zenoh keys.

On top of that it adds, at ``--scene-hz`` (default 20 Hz) of sim time, the frames of
:mod:`zenswarm.bridge.views.scene`, encoded by :mod:`zenswarm.bridge.views.foxglove_scene` (the code ``zenswarm up
--live`` serves to the Foxglove app too):

``/scene``    ``foxglove.SceneUpdate``: obstacles with their caps and d0 bands, the UAVs, the
              formation links, trails over the last ``--trail-s`` seconds, the virtual leader and
              its enclosing sphere of radius r_f, start and goal.
``/tf``       ``foxglove.FrameTransforms``: ``world`` -> ``leader`` and ``world`` -> ``uav<i>``.
``/metrics``  JSON: formation and tracking errors, clearances, failsafe state, per-link delivery
              and age (:data:`zenswarm.bridge.views.scene.METRICS_SCHEMA`).

The two Foxglove types are encoded as protobuf with Foxglove's official schemas (the message
types of the ``foxglove-sdk`` package, which embeds their descriptors in the file); the file is
written by that package's MCAP writer (``foxglove.open_mcap``) on a context of its own.

Time: every message is logged at ``base + t`` where t is its sim time (the wire ``t``) and base
the receive wall time of the recording's first message, so Foxglove plays the flight in sim
time (a lockstep run that computed 25x faster than real time plays at its real speed).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from zenswarm.bridge.views.scene import METRICS_TOPIC, SCENE_TOPIC, TF_TOPIC
from zenswarm.bus import wire
from zenswarm.errors import RecordingError, ZenswarmError

__all__ = [
    "SCENE_TOPIC",
    "TF_TOPIC",
    "METRICS_TOPIC",
    "wire_json_schema",
    "wire_to_json",
    "ExportSummary",
    "export_foxglove",
    "interleave",
    "scene_frames",
]

# The Foxglove SDK is imported where it is used (here, and in zenswarm.bridge.views.foxglove_scene): this
# module is imported by the CLI of every zenswarm process.

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
    """JSON Schema of a wire message of ``kind`` (one of :data:`zenswarm.bus.wire.KINDS`) as JSON.

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
        props["scenario"] = {"type": "object", "description": "the scenario (zenswarm.scenario.config.scenario_to_dict)"}
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
    if kind in ("state", "ref"):  # optional: a plug-in's extra quantities (the plant model's records, a controller's shares)
        what = "what the plant model records with this state" if kind == "state" else "a controller plug-in's extra shared quantities"
        props["x"] = {
            "type": "object",
            "maxProperties": wire.MAX_EXTRA,
            "additionalProperties": {"type": "array", "items": {"type": "number"}},
            "description": f"{what}: name -> flat values (row-major)",
        }
    if kind == "ref":
        props["p"] = _vec3("the sender's true position when a radio model is active, m, ENU")
    return {
        "title": _KIND_TITLES[kind],
        "description": _KIND_DESCRIPTIONS[kind],
        "type": "object",
        "properties": props,
        "required": required,
        "additionalProperties": False,
    }


def wire_to_json(kind: str, payload: bytes) -> bytes:
    """Validate a msgpack wire payload with :func:`zenswarm.bus.wire.decode` and re-encode its wire
    map as compact JSON. Raises :class:`zenswarm.bus.fields.WireDecodeError` when it is rejected."""
    wire.decode(kind, payload)
    obj = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()



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


def _json_items(
    rec: Any, keys: wire.Keys, summary: ExportSummary, kinds: frozenset[str] | None = None
) -> tuple[list[tuple[int, int, str, str, bytes]], int]:
    """The recorded messages as JSON: ``(sim t ns, file order, topic, kind, json)`` (what cannot
    be exported is counted in ``summary.skipped``), and the time base, ns: the first received
    message's receive time minus its sim time (0 without messages). ``kinds``: only messages of
    these kinds (the others are left out, uncounted, and do not set the time base)."""
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
        if kinds is not None and kind not in kinds:
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


class _Out:
    """The export's Foxglove context: one JSON channel per recorded topic (registered at first
    use, with its kind's JSON Schema) and the scene's channels; log time = ``base`` + sim time."""

    def __init__(self, context: Any, base: int) -> None:
        self.context = context
        self.base = base
        self.channels: dict[str, Any] = {}

    def put(self, topic: str, kind: str, t_sim: int, data: bytes) -> None:
        from foxglove import Channel

        ch = self.channels.get(topic)
        if ch is None:
            ch = self.channels[topic] = Channel(topic, schema=wire_json_schema(kind), context=self.context)
        ch.log(data, log_time=self.base + t_sim)


@dataclass
class _Scene:
    """The scene's frames: ``frames`` = (sim t ns, tick) every ``stride`` ticks of ``ts``."""

    ts: Any
    frames: list[tuple[int, int]]
    stride: int
    trail_ticks: int
    channels: Any  # zenswarm.bridge.views.foxglove_scene.SceneChannels

    def put(self, out: _Out, j: int, diag: dict[str, dict[str, Any]]) -> None:
        """Write frame j on /scene, /tf and /metrics."""
        from zenswarm.bridge.views.scene import frame_from_series

        ts_ns, k = self.frames[j]
        self.channels.put(frame_from_series(self.ts, k, self.trail_ticks, self.stride), out.base + ts_ns, diag)


def scene_frames(ts: Any, sc: Any, scene_hz: float, trail_s: float) -> tuple[list[tuple[int, int]], int, int]:
    """The frames of the flight series ``ts`` at ``scene_hz`` of sim time: ``(sim t ns, tick)``
    every ``stride`` ticks, the stride and the trails' length in ticks (no frame without a series)."""
    if ts is None or not len(ts.t):
        return [], 1, 0
    dt = sc.timing.dt
    stride = max(1, int(round(1.0 / (scene_hz * dt))))
    return [(wire.t_ns(float(ts.t[k])), k) for k in range(0, len(ts.t), stride)], stride, int(round(trail_s / dt))


def _scene(ts: Any, sc: Any, out: _Out, scene_hz: float, trail_s: float) -> _Scene | None:
    """The scene of the flight series ``ts`` (None without one)."""
    from zenswarm.bridge.views.foxglove_scene import SceneChannels

    frames, stride, trail_ticks = scene_frames(ts, sc, scene_hz, trail_s)
    if not frames:
        return None
    return _Scene(ts, frames, stride, trail_ticks, SceneChannels(sc, out.context, trail_s))


def interleave(
    items: list[tuple[int, int, str, str, bytes]],
    frame_times: list[int],
    put_frame: Callable[[int, dict[str, dict[str, Any]]], None],
    put_message: Callable[[int, str, str, bytes], None],
) -> None:
    """Walk the recorded messages ``items`` (JSON, in sim-time order) and the frames at sim times
    ``frame_times`` (ns) together: ``put_frame(j, diag)`` for frame j before the messages of a
    later sim time, with the diagnostics received up to then (process -> its newest, as
    :func:`zenswarm.bridge.views.scene.diag_view`); ``put_message(t, topic, kind, json)`` for each message."""
    from zenswarm.bridge.views.scene import diag_view

    diag: dict[str, dict[str, Any]] = {}
    j = 0
    for t_sim, _, topic, kind, data in items:
        while j < len(frame_times) and frame_times[j] <= t_sim:
            put_frame(j, diag)
            j += 1
        put_message(t_sim, topic, kind, data)
        if kind == "diag":
            d = json.loads(data)
            diag[d["process"]] = diag_view(wire.Diag(d["t"], d["seq"], d["process"], d["counters"], d["info"]))
    for jj in range(j, len(frame_times)):
        put_frame(jj, diag)


def _write_messages(out: _Out, items: list[tuple[int, int, str, str, bytes]], scene: _Scene | None, summary: ExportSummary) -> None:
    """The recorded messages in sim-time order (file order among equal times), each scene frame
    before the messages of a later sim time (with the diagnostics received up to then)."""

    def put_frame(j: int, diag: dict[str, dict[str, Any]]) -> None:
        scene.put(out, j, diag)  # type: ignore[union-attr]
        summary.scene_frames += 1

    def put_message(t_sim: int, topic: str, kind: str, data: bytes) -> None:
        out.put(topic, kind, t_sim, data)
        summary.topics[topic] = summary.topics.get(topic, 0) + 1
        summary.messages += 1

    interleave(items, [t for t, _ in scene.frames] if scene is not None else [], put_frame, put_message)
    if summary.scene_frames:
        summary.topics[SCENE_TOPIC] = summary.topics[TF_TOPIC] = summary.topics[METRICS_TOPIC] = summary.scene_frames


def export_foxglove(recording: str | Path, out: str | Path, *, scene_hz: float = 20.0, trail_s: float = 10.0) -> ExportSummary:
    """Export a recording for Foxglove (see the module docstring). The file is written next to
    ``out`` and renamed into place when complete. Raises RecordingError for an unusable input."""
    import foxglove
    from foxglove.mcap import MCAPCompression, MCAPWriteOptions

    from zenswarm.bridge.reports.flight import flight_from_recording, load_recording

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
    context = foxglove.Context()  # this file's own: no other channel of this process lands in it
    opts = MCAPWriteOptions(compression=MCAPCompression.Zstd, profile="", chunk_size=4 * 1024 * 1024)
    with foxglove.open_mcap(tmp, allow_overwrite=True, context=context, writer_options=opts) as w:
        fo = _Out(context, base)
        items.sort(key=lambda it: (it[0], it[1]))
        _write_messages(fo, items, _scene(ts, rec.scenario, fo, scene_hz, trail_s), summary)
        w.write_metadata("zenswarm", dict(rec.metadata))
        w.write_metadata(
            "zenswarm_export",
            {"source": str(rec.path), "time_base_ns": str(base), "timeline": "base + sim time", "scene_hz": f"{scene_hz:g}"},
        )
        for name, d in rec.other_metadata:
            if name not in ("zenswarm", "zenswarm_export"):
                w.write_metadata(name, dict(d))
    os.replace(tmp, out)
    return summary

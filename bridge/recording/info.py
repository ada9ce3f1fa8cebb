"""``zenswarm info F.mcap``: what a recording holds, like ``ros2 bag info`` / ``mcap info``.

:func:`scan` reads a recording once (leniently: a truncated or damaged file gives what can be
read) and returns a :class:`RecordingInfo`: the file's state (footer and summary present, the
recorder's end marker, the damage met), the ``zenswarm`` metadata (swarm, mode, scenario name and
hash), the span in sim time (the payloads' ``t``, MCAP ``publish_time``) and in wall time
(receive time, MCAP ``log_time``), and per channel the message count, payload bytes and rates
over sim and wall time, and the signals the plant model recorded in the state messages (their
``extra``: :attr:`zenswarm.plant.api.PlantModel.records`). :mod:`zenswarm.bridge.replay.replay` uses
the same scan to validate its window and filters.

Exit status of the command: 0 for a complete recording, 1 for one that is readable but not
complete (no footer or summary: the recorder was killed; no end marker; a damaged chunk), 2 for
a file that is missing or not MCAP.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from zenswarm.bridge.recording.mcapio import DROPPED_OVERSIZE, RECORDER_END, RECORDER_LIBRARIES, _SequenceGaps, read_recording
from zenswarm.bus import wire

__all__ = ["ChannelInfo", "RecordingInfo", "scan", "scenario_hash", "format_info", "add_parser"]


def scenario_hash(scenario: dict[str, Any]) -> str:
    """First 16 hex digits of the SHA-256 of the scenario's canonical JSON (keys sorted, no
    spaces): the same scenario gives the same hash whatever file it was stored in."""
    text = json.dumps(scenario, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _rate(n: int, first: int | None, last: int | None) -> float | None:
    """Messages per second over [first, last] ns (None for fewer than 2 messages or no span)."""
    if n < 2 or first is None or last is None or last <= first:
        return None
    return (n - 1) / ((last - first) / 1e9)


@dataclass
class ChannelInfo:
    """One channel (one Zenoh key): counts, bytes, and its spans (ns) in wall and sim time."""

    topic: str
    kind: str = ""
    messages: int = 0
    payload_bytes: int = 0
    first_log_ns: int | None = None
    last_log_ns: int | None = None
    sim_messages: int = 0
    """Messages that carry a sim time ``t`` (the others have none: undecodable payloads)."""
    first_sim_ns: int | None = None
    last_sim_ns: int | None = None

    @property
    def rate_wall_hz(self) -> float | None:
        """Messages per second of receive (wall) time."""
        return _rate(self.messages, self.first_log_ns, self.last_log_ns)

    @property
    def rate_sim_hz(self) -> float | None:
        """Messages per second of sim time."""
        return _rate(self.sim_messages, self.first_sim_ns, self.last_sim_ns)

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "rate_wall_hz": self.rate_wall_hz, "rate_sim_hz": self.rate_sim_hz}


@dataclass
class RecordingInfo:
    """What :func:`scan` found. Times: ns (log = receive wall time since the Unix epoch; sim =
    the sender's sim time). ``complete``: finalized (footer and summary), the recorder's end
    marker present (for files written by the zenswarm recorder) and nothing damaged."""

    file: str
    file_bytes: int = 0
    library: str = ""
    finalized: bool = False
    """The file ends with a valid footer (and a summary section, whose CRC matches)."""
    summary: bool = False
    """The summary has its statistics record."""
    end_marker: bool = False
    """The recorder's end marker (it stopped cleanly and wrote everything it received)."""
    recorder_file: bool = False
    """Written by ``zenswarm record`` (or rewritten by ``zenswarm recover``)."""
    problems: list[str] = field(default_factory=list)
    swarm: str | None = None
    mode: str | None = None
    zenswarm_version: str | None = None
    scenario_name: str | None = None
    scenario_hash: str | None = None
    scenario_source: str | None = None
    uavs: int | None = None
    control_rate_hz: float | None = None
    fault_args: list[str] = field(default_factory=list)
    messages: int = 0
    payload_bytes: int = 0
    first_log_ns: int | None = None
    last_log_ns: int | None = None
    first_sim_ns: int | None = None
    last_sim_ns: int | None = None
    recorder_start_unix_ns: int | None = None
    recorder_end_unix_ns: int | None = None
    recorder_stop_reason: str | None = None
    recorder_stats: dict[str, Any] = field(default_factory=dict)
    dropped_oversize: dict[str, Any] = field(default_factory=dict)
    sequence_gaps: dict[str, int] = field(default_factory=dict)
    """key -> messages missing by the recorder's per-channel sequence numbers (known lost)."""
    channels: list[ChannelInfo] = field(default_factory=list)
    plant_records: dict[str, int] = field(default_factory=dict)
    """The plant model's recorded signals in the state messages (:attr:`zenswarm.bus.wire.State.extra`,
    from each state channel's first message): name -> values per UAV."""
    plant_units: dict[str, str] = field(default_factory=dict)
    """Their shapes and units as the recorded scenario's plant model declares them (when it can be
    loaded here): name -> e.g. ``(4,) N``."""

    @property
    def complete(self) -> bool:
        return self.finalized and self.summary and (self.end_marker or not self.recorder_file) and not self.problems

    @property
    def wall_s(self) -> float | None:
        """Receive-time span, first to last message, s."""
        if self.first_log_ns is None or self.last_log_ns is None:
            return None
        return (self.last_log_ns - self.first_log_ns) / 1e9

    @property
    def sim_s(self) -> float | None:
        """Sim-time span, first to last sim time, s."""
        if self.first_sim_ns is None or self.last_sim_ns is None:
            return None
        return (self.last_sim_ns - self.first_sim_ns) / 1e9

    def channel(self, topic: str) -> ChannelInfo | None:
        for c in self.channels:
            if c.topic == topic:
                return c
        return None

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["channels"] = [c.as_dict() for c in self.channels]
        d.update(complete=self.complete, wall_s=self.wall_s, sim_s=self.sim_s)
        return d


def _int(text: str | None) -> int | None:
    try:
        return int(text) if text is not None else None
    except ValueError:
        return None


def _json(text: str | None) -> Any:
    try:
        return json.loads(text) if text else None
    except ValueError:
        return None


def _min(a: int | None, b: int) -> int:
    return b if a is None or b < a else a


def _max(a: int | None, b: int) -> int:
    return b if a is None or b > a else a


def scan(path: str | Path) -> RecordingInfo:
    """Read the recording at ``path`` once, leniently, and describe it. Raises
    :class:`zenswarm.errors.RecordingError` only for a missing or non-MCAP file."""
    rec = read_recording(path, strict=False)
    info = RecordingInfo(file=str(path), file_bytes=rec.size, finalized=rec.complete)
    info.library = rec.header.library if rec.header is not None else ""
    info.recorder_file = info.library.startswith(RECORDER_LIBRARIES)
    gaps = _SequenceGaps()
    chans: dict[str, ChannelInfo] = {}
    for ch, m in rec.raw_messages():
        c = chans.get(ch.topic)
        if c is None:
            c = chans[ch.topic] = _new_channel(info, ch, m.data)
        c.messages += 1
        c.payload_bytes += len(m.data)
        c.first_log_ns = _min(c.first_log_ns, m.log_time)
        c.last_log_ns = _max(c.last_log_ns, m.log_time)
        if m.publish_time <= wire.MAX_T_NS:  # the recorder's publish_time: sim t, else log time
            c.sim_messages += 1
            c.first_sim_ns = _min(c.first_sim_ns, m.publish_time)
            c.last_sim_ns = _max(c.last_sim_ns, m.publish_time)
        if info.recorder_file:
            gaps.see(ch.topic, m.sequence)
    info.channels = [chans[t] for t in sorted(chans)]
    for c in info.channels:
        info.messages += c.messages
        info.payload_bytes += c.payload_bytes
        for a in ("first_log_ns", "first_sim_ns"):
            v = getattr(c, a)
            if v is not None:
                setattr(info, a, _min(getattr(info, a), v))
        for a in ("last_log_ns", "last_sim_ns"):
            v = getattr(c, a)
            if v is not None:
                setattr(info, a, _max(getattr(info, a), v))
    info.summary = rec.statistics is not None
    info.problems = list(rec.problems)
    info.sequence_gaps = dict(sorted(gaps.gaps.items()))
    meta = rec.info  # merged in file order; for a file without summary, as met while reading
    info.swarm, info.mode, info.zenswarm_version = rec.swarm, rec.mode, rec.zenswarm_version
    info.scenario_source = meta.get("scenario_source")
    info.recorder_start_unix_ns = _int(meta.get("recorder_start_unix_ns"))
    info.recorder_end_unix_ns = _int(meta.get(RECORDER_END))
    info.end_marker = info.recorder_end_unix_ns is not None
    info.recorder_stop_reason = meta.get("recorder_stop_reason")
    stats = _json(meta.get("recorder_stats_json"))
    info.recorder_stats = stats if isinstance(stats, dict) else {}
    dropped = _json(meta.get(DROPPED_OVERSIZE))
    info.dropped_oversize = dropped if isinstance(dropped, dict) else {}
    fa = _json(meta.get("fault_args"))
    info.fault_args = [str(x) for x in fa] if isinstance(fa, list) else []
    try:
        sc = rec.scenario
    except Exception as e:  # noqa: BLE001 - a damaged scenario is a problem to report, not a crash
        info.problems.append(str(e))
        sc = None
    if sc is not None:
        info.scenario_hash = scenario_hash(sc)
        name = sc.get("scenario", {}).get("name") if isinstance(sc.get("scenario"), dict) else None
        info.scenario_name = name if isinstance(name, str) else None
        formation = sc.get("formation", {})
        if isinstance(formation, dict) and isinstance(formation.get("initial_positions"), list):
            info.uavs = len(formation["initial_positions"])
        timing = sc.get("timing", {})
        if isinstance(timing, dict) and isinstance(timing.get("control_rate_hz"), (int, float)):
            info.control_rate_hz = float(timing["control_rate_hz"])
        if info.plant_records:
            info.plant_units = _plant_units(sc)
    return info


def _new_channel(info: RecordingInfo, ch: Any, first_payload: bytes) -> ChannelInfo:
    """A channel met for the first time; a state channel's first message says what the plant recorded."""
    c = ChannelInfo(ch.topic, dict(ch.metadata).get("kind", ""))
    if c.kind == "state":
        _plant_records(info, first_payload)
    return c


def _plant_records(info: RecordingInfo, payload: bytes) -> None:
    """The names and sizes of the plant records in one state payload (nothing if it does not decode)."""
    try:
        msg = wire.decode("state", payload)
    except wire.WireDecodeError:
        return
    for name, vals in msg.extra.items():
        info.plant_records.setdefault(name, len(vals))


def _plant_units(sc: dict[str, Any]) -> dict[str, str]:
    """name -> ``shape unit`` of the recorded scenario's plant model's records ({} when it cannot be loaded here)."""
    from zenswarm.scenario.plugins import records_of, resolve

    plant = sc.get("plant")
    name = plant.get("model", "quadrotor") if isinstance(plant, dict) else "quadrotor"
    try:
        recs = records_of(resolve("plant", str(name)))
    except Exception:  # noqa: BLE001 - a plug-in not installed here, or anything its import raised: no units
        return {}
    return {n: f"{s.shape} {s.unit}" for n, s in recs.items()}


# --------------------------------------------------------------------------- text


def _hz(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} B" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024  # type: ignore[assignment]
    return f"{n} B"  # pragma: no cover


def _utc(ns: int | None) -> str:
    if ns is None:
        return "?"
    return time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(ns / 1e9)) + f".{(ns // 1_000_000) % 1000:03d} UTC"


def _state(info: RecordingInfo) -> str:
    if info.complete:
        stop = f" ({info.recorder_stop_reason})" if info.recorder_stop_reason else ""
        marker = f", recorder end marker{stop}" if info.end_marker else ""
        return f"yes (footer, summary{marker})"
    why = []
    if not info.finalized:
        why.append("no footer/summary: the file was not closed (truncated)")
    elif not info.summary:
        why.append("no statistics in the summary")
    if info.recorder_file and not info.end_marker:
        why.append("no recorder end marker: the recorder did not stop cleanly, or predates the marker")
    if info.problems:
        why.append("damaged")
    return "NO (" + "; ".join(why) + ")"


def format_info(info: RecordingInfo) -> str:
    """The human-readable summary printed by ``zenswarm info``."""
    lines = [f"file:       {info.file} ({_size(info.file_bytes)}; {info.library or 'unknown writer'})"]
    lines.append(f"complete:   {_state(info)}")
    for p in info.problems:
        lines.append(f"problem:    {p}")
    lines.append(
        f"swarm:      {info.swarm or '?'}   mode: {info.mode or '?'}   zenswarm {info.zenswarm_version or '?'}"
    )
    if info.scenario_hash is not None:
        extra = []
        if info.uavs is not None:
            extra.append(f"{info.uavs} UAVs")
        if info.control_rate_hz is not None:
            extra.append(f"control {info.control_rate_hz:g} Hz")
        lines.append(
            f"scenario:   {info.scenario_name or '?'} ({', '.join(extra)}), hash {info.scenario_hash}"
            + (f", from {info.scenario_source}" if info.scenario_source else "")
        )
    else:
        lines.append("scenario:   none recorded")
    if info.fault_args:
        lines.append(f"faults:     {' '.join(info.fault_args)}")
    sim = "-" if info.sim_s is None else (
        f"{info.sim_s:.3f} s ({(info.first_sim_ns or 0) / 1e9:.3f} to {(info.last_sim_ns or 0) / 1e9:.3f} s)"
    )
    wall = "-" if info.wall_s is None else f"{info.wall_s:.3f} s (from {_utc(info.first_log_ns)})"
    lines.append(f"duration:   sim {sim}   wall {wall}")
    lines.append(f"messages:   {info.messages} on {len(info.channels)} channels, {_size(info.payload_bytes)} of payload")
    if info.recorder_stats:
        lines.append("recorder:   " + "  ".join(f"{k} {v}" for k, v in sorted(info.recorder_stats.items())))
    elif info.recorder_file:
        lines.append("recorder:   no statistics (written at a clean stop)")
    if info.dropped_oversize:
        n = sum(int(d.get("count", 0)) for d in info.dropped_oversize.values() if isinstance(d, dict))
        lines.append(f"dropped:    {n} oversize payloads not recorded, on {', '.join(sorted(info.dropped_oversize))}")
    if info.sequence_gaps:
        lines.append(
            "lost:       " + ", ".join(f"{k}: {n}" for k, n in info.sequence_gaps.items()) + " (gaps in the recorder's sequence numbers)"
        )
    if info.plant_records:
        recs = ", ".join(f"{n} [{info.plant_units.get(n, f'{k} values')}]" for n, k in info.plant_records.items())
        lines.append(f"plant:      records {recs} (in each uav/<i>/state's extra; timeseries.npz: plant.<name>)")
    w = max([len("topic")] + [len(c.topic) for c in info.channels])
    lines.append("channels:")
    lines.append(f"  {'topic':<{w}}  {'kind':<10} {'messages':>8} {'Hz sim':>8} {'Hz wall':>8} {'bytes':>10}")
    for c in info.channels:
        lines.append(
            f"  {c.topic:<{w}}  {c.kind or '-':<10} {c.messages:>8} {_hz(c.rate_sim_hz):>8} {_hz(c.rate_wall_hz):>8} {c.payload_bytes:>10}"
        )
    return "\n".join(lines)


def _run_info(args: argparse.Namespace) -> int:
    info = scan(args.file)
    if args.json:
        print(json.dumps(info.as_dict(), sort_keys=True))
    else:
        print(format_info(info))
    if not info.complete:
        print(f"info: {args.file} is not complete: what could be read is shown", file=sys.stderr)
        return 1
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info",
        help="summarise a recording (like `ros2 bag info` / `mcap info`)",
        description=(
            "Read FILE once and print: whether it is complete (footer and summary written, the "
            "recorder's end marker present, nothing damaged), swarm, mode, scenario name and hash, the "
            "duration in sim time and in wall (receive) time, the recorder's statistics, and per channel "
            "the message count, the rates over sim and wall time and the payload bytes. A truncated or "
            "damaged file is read up to the damage. Exit status: 0 complete, 1 readable but not complete, "
            "2 missing or not an MCAP file."
        ),
    )
    p.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text (same exit status)")
    p.set_defaults(func=_run_info)

"""The flight loaded from an MCAP recording: what ``zenswarm report`` and the views read.

:func:`load_recording` reads the file whole (:class:`Recording`: the messages in file order, the
scenario, swarm name and mode from the ``zenswarm`` metadata record; a truncated or damaged file
leniently, saying what was lost); :func:`flight_from_recording` rebuilds the flight's
:class:`zenswarm.judge.metrics.TimeSeries` from the recorded samples with the supervisor's
:class:`zenswarm.process.collector.Collector` (the code that builds it live) and counts the bus
traffic (:class:`Flight`); :func:`recorded_fault_plan` is the run's link-fault plan (the
scenario's ``[faults]`` and the recorded fault flags). The figures drawn from a flight are
:mod:`zenswarm.bridge.reports.figures`; the report, :mod:`zenswarm.bridge.reports.report`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from zenswarm.bus import wire
from zenswarm.errors import RecordingError
from zenswarm.judge.metrics import TimeSeries
from zenswarm.link import FaultPlan
from zenswarm.scenario.config import Scenario

__all__ = [
    "METADATA_NAME",
    "RecordedMessage",
    "Recording",
    "Flight",
    "load_recording",
    "flight_from_recording",
    "last_data_tick",
    "recorded_fault_plan",
]

METADATA_NAME = "zenswarm"
"""Name of the MCAP metadata record the recorder writes (keys scenario_json, swarm, mode)."""


# =========================================================================== reading a recording


class RecordedMessage(NamedTuple):
    """One recorded sample. log_time: receive wall time, ns; publish_time: sender's sim time, ns."""

    topic: str
    log_time: int
    publish_time: int
    data: bytes
    encoding: str


@dataclass
class Recording:
    """An MCAP recording of a swarm, loaded whole (messages in file order).

    metadata: the ``zenswarm`` metadata record(s), merged; scenario from its ``scenario_json``;
    swarm and mode (``lockstep``, ``realtime``; anything else counts as lockstep) from it too.
    truncated: the damage met while reading (file cut short, chunk failing its CRC), None for a
    complete, intact file. notes: what a reader must be told (:meth:`zenswarm.bridge.recording.mcapio.Recording.notes`:
    truncated or damaged, oversize payloads the recorder did not record).
    """

    path: Path
    metadata: dict[str, str]
    scenario: Scenario
    swarm: str
    mode: str
    messages: list[RecordedMessage]
    truncated: str | None = None
    other_metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def realtime(self) -> bool:
        return self.mode == "realtime"


def load_recording(path: str | Path) -> Recording:
    """Load a recording and the scenario it carries (read by :func:`zenswarm.bridge.recording.mcapio.read_recording`,
    leniently: a truncated file or a corrupted chunk costs only what is unreadable, and
    :attr:`Recording.truncated` says what happened).

    Raises :class:`RecordingError` naming the file when it is missing, not an MCAP file, has no
    ``zenswarm`` metadata record, or its scenario is missing or invalid.
    """
    from zenswarm.bridge.recording import mcapio

    p = Path(path)
    r = mcapio.read_recording(p, strict=False)
    meta = r.metadata.get(METADATA_NAME)
    if not meta:
        raise RecordingError(
            f"{p}: no '{METADATA_NAME}' metadata record: not a zenswarm recording "
            "(the recorder writes the scenario, swarm name and mode there)"
        )
    scenario = r.load_scenario()
    messages = [
        RecordedMessage(ch.topic, m.log_time, m.publish_time, bytes(m.data), ch.message_encoding) for ch, m in r.raw_messages()
    ]
    problems = ([r.summary_problem] if r.summary_problem else []) + [x for x in r.problems if x != r.summary_problem]
    swarm = meta.get("swarm") or _guess_swarm(messages)
    if swarm is None:
        raise RecordingError(f"{p}: no swarm name in the metadata and no swarm key among the messages")
    try:
        wire.validate_swarm_name(swarm)
    except wire.InvalidKeyError as e:
        raise RecordingError(f"{p}: {e}") from None
    mode = meta.get("mode") or "lockstep"
    others = [(name, dict(d)) for name, d in r.metadata.items() if name != METADATA_NAME]
    return Recording(p, dict(meta), scenario, swarm, mode, messages, "; ".join(problems) or None, others, r.notes())


def _guess_swarm(messages: Sequence[RecordedMessage]) -> str | None:
    for m in messages:
        parts = m.topic.split("/")
        if len(parts) >= 3 and parts[0] == "swarm":
            return parts[1]
    return None


# =========================================================================== the flight


@dataclass
class Flight:
    """What a report needs: the series, and (from a recording) the bus statistics."""

    series: TimeSeries
    scenario: Scenario
    message_counts: dict[str, int] = field(default_factory=dict)
    decoder_rejects: dict[str, int] = field(default_factory=dict)
    decoder_counters: dict[str, int] = field(default_factory=dict)
    diagnostics: dict[str, dict[str, Any]] = field(default_factory=dict)
    mode: str = "lockstep"
    swarm: str | None = None


def last_data_tick(ts: TimeSeries) -> int:
    """Index of the last tick that holds any sample (-1 if none)."""
    T = len(ts.t)
    if T == 0:
        return -1
    have = np.zeros(T, dtype=bool)
    for a in (ts.q0, ts.qref, ts.q, ts.u):
        have |= np.isfinite(a.reshape(T, -1)).any(axis=1)
    idx = np.flatnonzero(have)
    return int(idx[-1]) if len(idx) else -1


def flight_from_recording(rec: Recording) -> Flight:
    """Rebuild the flight's time series from the recorded samples with the supervisor's Collector.

    The series runs to the last tick that has any sample (the whole time limit for a complete
    run); realtime recordings are forward-filled over gaps, exactly as ``zenswarm up --realtime``
    does. Raises RecordingError when no sample of the swarm is in the file.
    """
    from zenswarm.process.collector import Collector

    keys = wire.Keys(rec.swarm)
    col = Collector(rec.scenario, keys)
    counts: dict[str, int] = {}
    for m in rec.messages:
        counts[m.topic] = counts.get(m.topic, 0) + 1
        if m.encoding == "msgpack":
            col.on_sample(m.topic, m.data)
    raw = col.series(None, fill=False)
    last = last_data_tick(raw)
    if last < 0:
        raise RecordingError(f"{rec.path}: no flight data (leader/ref, uav/*/state|ref|cmd) of swarm '{rec.swarm}'")
    ts = col.series(last + 1, fill=rec.realtime)
    return Flight(
        series=ts,
        scenario=rec.scenario,
        message_counts=counts,
        decoder_rejects=dict(col.decoder.rejects),
        decoder_counters=col.decoder.counters(),
        diagnostics={k: dict(v) for k, v in col.diag.items()},
        mode=rec.mode,
        swarm=rec.swarm,
    )


def recorded_fault_plan(rec: Recording) -> FaultPlan | None:
    """The link-fault plan of a recorded run: the scenario's ``[faults]`` table plus the fault
    flags the recorder was given (metadata ``fault_args``, as ``replay --verify`` reads them)."""
    from zenswarm.bridge.args import recorded_fault_plan as plan_of

    return plan_of(rec.metadata.get("fault_args", "[]"), rec.scenario, rec.path)

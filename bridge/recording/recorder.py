"""The recorder process (``recorder``): every sample of a swarm, written to an MCAP file.

``zenswarm record --swarm NAME --connect EP --out FILE.mcap [--scenario F] [--duration S]``

Subscribes to ``swarm/<name>/**`` and writes each sample as it was received (file layout: see
:mod:`zenswarm.bridge.recording.mcapio`). It declares its liveliness token ``swarm/<name>/alive/recorder`` only
once its subscriber is declared, so a plant that waits for the recorder loses nothing.

Threads and crash safety
------------------------
* The Zenoh callback only stamps the receive wall time and appends ``(log_time, key, payload)``
  to an unbounded ``queue.SimpleQueue``: no decoding, no I/O, no lock held across calls. Nothing
  the swarm's decoders could accept is ever dropped (memory is the bound; the peak backlog is
  reported).
* Oversize payloads are not recorded: a payload longer than the decoders' size bound for its
  key (:func:`payload_limit`: ``wire.MAX_PAYLOAD`` = 64 KiB, ``wire.MAX_MISSION_PAYLOAD`` = 1 MiB
  on the mission key) is one that every zenswarm decoder rejects unread, so the callback queues
  only its key and size (not a copy of it), and the writer counts it per key: count, bytes,
  largest. A flood of such payloads once wrote 1.76 GB of undecodable bytes into a recording.
  The counts go into the ``zenswarm`` metadata record (value ``dropped_oversize_json``, see
  :mod:`zenswarm.bridge.recording.mcapio`), rewritten at most once a second while they change and at the end, and
  into the ``diag/recorder`` counters (``dropped_oversize``); ``zenswarm report`` and
  ``zenswarm verify`` say how many were dropped, on which keys, and why.
* One writer thread owns the ``mcap.writer.Writer``: it registers a channel per new key, takes
  the sim time ``t`` out of the payload for ``publish_time`` (a msgpack map with an integer
  ``t``; anything else is counted as *undecodable* and still recorded, with
  ``publish_time = log_time``), and adds the message to the open chunk.
* Flushing: the open chunk is closed and the file flushed to the OS (``Writer.flush()``, no
  fsync) every ``flush_interval_s`` (default :data:`DEFAULT_FLUSH_INTERVAL_S` = 0.25 s), or
  earlier when it reaches ``chunk_size`` bytes (default 1 MiB, i.e. about 7,000 state messages).
  After a SIGKILL of the recorder the file therefore holds every sample received up to at most
  one flush interval (plus the writer's backlog, normally < 10 ms) before the kill: a quarter
  of a second, leaving margin under the 1 s goal. The OS page cache survives the death of the
  process; only a machine crash could lose more (we do not fsync: it would cost a disk sync
  four times a second for a guarantee that the goal does not ask for). Compression is zstd per
  chunk; small chunks compress a little worse, which is the price of the bound.
* SIGTERM and SIGINT reach the main thread's stop event through a relay thread
  (:class:`zenswarm.process.signals.SignalRelay`), never by setting the event in the signal
  handler: the main thread waits on that event, and a handler run while it held the event's lock
  would wait for it forever (the recorder then never exited).
* A clean stop (SIGTERM, SIGINT, ``--duration``): undeclare the token and the subscriber,
  close the session, let the writer drain the queue, write the end marker (a last ``zenswarm``
  metadata record: ``recorder_end_unix_ns``, ``recorder_stop_reason`` and
  ``recorder_stats_json``, the counters of :class:`RecorderStats`), then ``Writer.finish()``
  writes the summary (statistics, channels, chunk/message/metadata indexes) and the footer.
  ``zenswarm info`` shows all three.

Metadata: a ``zenswarm`` record is written right after the header (swarm, mode, version and,
with ``--scenario``, the scenario). Without ``--scenario`` a helper thread asks the leader's
mission queryable once a second until a leader answers, and a second ``zenswarm`` record with
``scenario_json`` is written when it does (readers merge the two).

Every ``--diag-interval`` seconds (default 1) the recorder publishes its counters on
``swarm/<name>/diag/recorder`` (recorded, channels, undecodable, backlog, ...); being in the key
space, they are recorded too. ``bench/recorder_throughput.py`` uses them to know when the
recorder has caught up.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import msgpack
import msgspec

from zenswarm import __version__, bus
from zenswarm.bridge.args import add_fault_args, add_plugin_args, add_security_args, link_faults
from zenswarm.bridge.recording.mcapio import DROPPED_OVERSIZE, MESSAGE_ENCODING, METADATA_NAME, RECORDER_END
from zenswarm.bus import wire
from zenswarm.link import LinkFaults
from zenswarm.process import security
from zenswarm.process.paths import check_output_file
from zenswarm.process.runtime import gc_policy, gc_safe_point, gc_startup_done
from zenswarm.process.signals import SignalRelay
from zenswarm.scenario.config import Scenario

__all__ = [
    "PROCESS_NAME",
    "DEFAULT_FLUSH_INTERVAL_S",
    "DEFAULT_CHUNK_SIZE",
    "RecorderStats",
    "McapSink",
    "payload_limit",
    "sim_time",
    "build_metadata",
    "RecorderSettings",
    "recorder_settings",
    "run",
    "run_settings",
    "main",
    "add_parser",
]

PROCESS_NAME: Final = "recorder"
DEFAULT_FLUSH_INTERVAL_S: Final = 0.25
"""Close the open chunk and flush the file to the OS at least this often, s."""
DEFAULT_CHUNK_SIZE: Final = 1 << 20
"""Close a chunk earlier when its uncompressed records reach this many bytes."""
DEFAULT_CONNECT_TIMEOUT_S: Final = 60.0
"""The recorder may start before the swarm's router: keep trying to reach it this long, s."""
DROPPED_METADATA_INTERVAL_S: Final = 1.0
"""Rewrite the oversize-drop counts into the file at most this often while they change, s."""
MAX_DROPPED_KEYS: Final = 1024
"""Distinct keys counted one by one in the oversize-drop counts; the rest under ``<other>``."""


class RecorderSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What the recorder is started with: ``zenswarm record``'s flags (:func:`recorder_settings`)
    or, under ``zenswarm up --record``, the flight's (msgpack on its standard input,
    :mod:`zenswarm.compose.commands`). One way in: :func:`run_settings`.

    out: the MCAP file. scenario: stored in the file (its plug-in names applied); None: asked of
    the leader's mission. scenario_source: what the metadata says it came from (``file:PATH``).
    mode: ``lockstep``, ``realtime`` or ``unknown`` (metadata; realtime also sets the GC policy).
    connect: router endpoints (empty: ``tcp/127.0.0.1:7447``); keys, tls: credentials of a
    secured router. faults: the swarm's link faults, not applied, stored for ``replay --verify``.
    Durations in seconds; chunk_size in bytes."""

    out: Path
    swarm: str = "default"
    connect: tuple[str, ...] = ()
    scenario: Scenario | None = None
    scenario_source: str = ""
    duration: float | None = None
    mode: str = "lockstep"
    connect_timeout: float = DEFAULT_CONNECT_TIMEOUT_S
    flush_interval: float = DEFAULT_FLUSH_INTERVAL_S
    chunk_size: int = DEFAULT_CHUNK_SIZE
    compression: str = "zstd"
    keys: Path | None = None
    tls: bool = False
    diag_interval: float = 1.0
    faults: LinkFaults = msgspec.field(default_factory=LinkFaults)


def recorder_settings(args: argparse.Namespace) -> RecorderSettings:
    """``zenswarm record``'s flags (:func:`add_parser`) as :class:`RecorderSettings`: the
    ``--scenario`` file parsed, the plug-in flags applied to it (what ``verify`` rebuilds the
    agents from); a bad file is a ScenarioError naming it (exit 2)."""
    from zenswarm.scenario.config import load_scenario
    from zenswarm.scenario.plugins import select

    scenario = None
    if args.scenario is not None:
        scenario = select(load_scenario(args.scenario), args.controller, args.planner, getattr(args, "plant_model", None))
    return RecorderSettings(
        out=args.out, swarm=args.swarm, connect=tuple(args.connect or ()), scenario=scenario,
        scenario_source=f"file:{args.scenario}" if scenario is not None else "", duration=args.duration,
        mode="realtime" if args.realtime else args.mode, connect_timeout=args.connect_timeout,
        flush_interval=args.flush_interval, chunk_size=args.chunk_size, compression=args.compression,
        keys=args.keys, tls=bool(args.tls), diag_interval=args.diag_interval, faults=link_faults(args),
    )  # fmt: skip


_STOP = object()
_META = object()
_OVERSIZE = object()


def payload_limit(keys: wire.Keys, key: str) -> int:
    """The decoders' size bound (bytes) for a payload on ``key``: :data:`zenswarm.bus.wire.MAX_MISSION_PAYLOAD`
    on the swarm's mission key, :data:`zenswarm.bus.wire.MAX_PAYLOAD` on every other key (also keys
    outside the swarm's layout, which no decoder reads at all). A longer payload is rejected by
    every :class:`zenswarm.bus.wire.Decoder` as ``oversize`` before it is unpacked."""
    return wire.MAX_MISSION_PAYLOAD if key == keys.mission else wire.MAX_PAYLOAD


def sim_time(payload: bytes) -> int | None:
    """The sender's sim time ``t`` (ns) of a zenswarm payload, or None if the payload is not a
    msgpack map with an integer ``t`` in ``0..wire.MAX_T_NS`` (bounded unpacking)."""
    n = len(payload)
    try:
        o = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=False,
            max_str_len=n,
            max_bin_len=n,
            max_array_len=n,
            max_map_len=n,
            max_ext_len=n,
        )
    except Exception:  # noqa: BLE001 - any garbage
        return None
    if type(o) is not dict:
        return None
    t = o.get("t")
    if type(t) is not int or not 0 <= t <= wire.MAX_T_NS:
        return None
    return t


def build_metadata(
    swarm: str, mode: str, scenario: dict[str, Any] | None, source: str, fault_args: list[str] | None = None
) -> dict[str, str]:
    """Values of the ``zenswarm`` metadata record (all strings, as MCAP requires).

    fault_args: the swarm's link-fault flags (``--link-loss 0.2 ...``), kept so that
    ``replay --verify`` can rebuild the same fault plan (with the scenario's ``[faults]``)."""
    meta = {
        "swarm": swarm,
        "zenswarm_version": __version__,
        "mode": mode,
        "scenario_source": source,
        "recorder_start_unix_ns": str(time.time_ns()),
    }
    if fault_args:
        meta["fault_args"] = json.dumps(list(fault_args))
    if scenario is not None:
        meta["scenario_json"] = json.dumps(scenario, sort_keys=True, allow_nan=False)
    return meta


@dataclass
class RecorderStats:
    messages: int = 0
    channels: int = 0
    payload_bytes: int = 0
    undecodable: int = 0
    flushes: int = 0
    peak_backlog: int = 0
    file_bytes: int = 0
    first_log_time: int | None = None
    last_log_time: int | None = None
    last_sim_t: int = 0
    dropped_oversize: int = 0
    dropped_oversize_bytes: int = 0
    dropped_by_key: dict[str, dict[str, int]] = field(default_factory=dict)
    """key -> ``{"count", "bytes", "largest", "limit"}`` of the payloads not recorded (oversize)."""

    def drop_oversize(self, key: str, size: int, limit: int) -> None:
        """Count one payload of ``size`` bytes on ``key`` that was not recorded (over ``limit``)."""
        self.dropped_oversize += 1
        self.dropped_oversize_bytes += size
        d = self.dropped_by_key.get(key)
        if d is None:
            if len(self.dropped_by_key) >= MAX_DROPPED_KEYS:
                key = wire.Decoder.OTHER
                d = self.dropped_by_key.get(key)
            if d is None:
                d = self.dropped_by_key[key] = {"count": 0, "bytes": 0, "largest": 0, "limit": limit}
        d["count"] += 1
        d["bytes"] += size
        if size > d["largest"]:
            d["largest"] = size

    def counters(self, backlog: int) -> dict[str, int | float]:
        """Counters for the recorder's own ``diag/recorder`` messages (:class:`zenswarm.bus.wire.Diag`
        counters; all of these are counts)."""
        return {
            "recorded": self.messages,
            "channels": self.channels,
            "payload_bytes": self.payload_bytes,
            "undecodable": self.undecodable,
            "dropped_oversize": self.dropped_oversize,
            "flushes": self.flushes,
            "backlog": backlog,
            "peak_backlog": self.peak_backlog,
        }

    def line(self) -> str:
        return (
            f"{self.messages} messages on {self.channels} channels, {self.payload_bytes} payload bytes, "
            f"{self.file_bytes} file bytes, {self.undecodable} undecodable, {self.flushes} flushes, "
            f"peak backlog {self.peak_backlog}"
            + (
                f"; {self.dropped_oversize} oversize payloads ({self.dropped_oversize_bytes} bytes) on "
                f"{len(self.dropped_by_key)} keys not recorded (over the decoders' size bound)"
                if self.dropped_oversize
                else ""
            )
        )


@dataclass
class _WriterState:
    """What the writer thread keeps between samples (that thread only); times time.monotonic() s."""

    next_flush: float  # the next periodic flush
    channels: dict[str, int] = field(default_factory=dict)  # key -> channel id
    seqs: dict[int, int] = field(default_factory=dict)  # channel id -> last sequence number
    limits: dict[str, int] = field(default_factory=dict)  # key -> payload size bound, bytes (a cache)
    last_lt: int = 0  # last log time written, ns
    dirty: bool = False  # messages written since the last flush
    dropped_written: int = 0  # stats.dropped_oversize when the counts were last written
    next_dropped: float = 0.0  # the oversize counts are written at most this often


class McapSink:
    """Owns the MCAP writer and its thread. ``put`` is called from the Zenoh callback.

    Usage: ``sink.start()``; ``sink.put(log_time, key, payload)`` (or, cheaper, from a hot
    callback, ``sink.put_item((log_time, key, payload))``) any number of times: thread safe,
    never blocks; ``sink.set_metadata(values)`` to add a ``zenswarm`` metadata record;
    ``sink.close()`` drains the queue and writes summary + footer. ``metadata`` is written right
    after the header, before any message. A payload over :func:`payload_limit` is counted, not
    written (``sink.put_oversize(log_time, key, size)`` counts one without its bytes).
    """

    def __init__(
        self,
        path: Path,
        keys: wire.Keys,
        *,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = "zstd",
        metadata: dict[str, str] | None = None,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = path
        self.keys = keys
        self.flush_interval_s = flush_interval_s
        self.stats = RecorderStats()
        self.error: BaseException | None = None
        self.stop_reason = "stopped"
        """Why the recording ended, stored in the end marker (set before :meth:`close`)."""
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(path, "wb")  # closed by the writer thread
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile="", library=f"zenswarm-recorder/{__version__}")
        if metadata is not None:
            self._writer.add_metadata(METADATA_NAME, metadata)
        self._file.flush()
        self._good_end = self._file.tell()  # the end of what reached the OS whole (see _salvage)
        self.salvaged: str | None = None  # how a failed file was ended (see _salvage), None if it was not
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self.put_item = self._q.put
        """Queue one ``(log_time_ns, key, payload)`` tuple (the Zenoh callback's hot path)."""

    def start(self) -> None:
        self._thread.start()

    @property
    def backlog(self) -> int:
        """Samples received but not yet written."""
        return self._q.qsize()

    def put(self, log_time: int, key: str, payload: bytes) -> None:
        """Queue one sample: receive wall time (ns), key, payload."""
        self._q.put((log_time, key, payload))

    def put_oversize(self, log_time: int, key: str, size: int) -> None:
        """Count one payload of ``size`` bytes on ``key`` that is over its size bound (not written)."""
        self._q.put((_OVERSIZE, key, size, log_time))

    def set_metadata(self, values: dict[str, str]) -> None:
        """Queue another ``zenswarm`` metadata record (readers merge them in file order)."""
        self._q.put((_META, values))

    def close(self, timeout_s: float = 60.0) -> None:
        """Drain the queue, write summary + footer, close the file (idempotent)."""
        if self._thread.is_alive():
            self._q.put(_STOP)
            self._thread.join(timeout_s)
        elif not self._file.closed and self._thread.ident is None:
            self._finish()

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        ws = _WriterState(next_flush=time.monotonic() + self.flush_interval_s)
        st = self.stats
        try:
            while True:
                item = self._next_item(ws)
                if item is _STOP:
                    break
                if item is not None and item[0] is _META:
                    self._write_metadata(item[1])
                    continue
                sample = self._admit(item, ws) if item is not None else None
                if sample is not None:
                    self._write_sample(ws, *sample)
                self._periodic(ws)
            # _STOP is queued after the session is closed, so every sample precedes it (FIFO)
            if st.dropped_oversize != ws.dropped_written:
                self._write_metadata(self._dropped_metadata())
            self._flush()  # the open chunk first: the end marker comes after every message
            self._write_metadata(self._end_metadata())
        except BaseException as e:  # noqa: BLE001 - report, and still try to finish the file
            self.error = e
        finally:
            self._finish()

    def _next_item(self, ws: _WriterState) -> Any:
        """The next queued item, or None when the next periodic flush is due first."""
        wait = ws.next_flush - time.monotonic()
        try:
            return self._q.get(timeout=wait) if wait > 0 else self._q.get_nowait()
        except queue.Empty:
            return None

    def _admit(self, item: tuple[Any, ...], ws: _WriterState) -> tuple[int, str, bytes] | None:
        """A queued sample ``(log_time, key, payload)`` to write, or None if it is over its key's
        size bound (counted in the stats, not written)."""
        if item[0] is _OVERSIZE:  # counted only
            _, key, size, _lt = item
            self.stats.drop_oversize(key, size, payload_limit(self.keys, key))
            return None
        lt, key, payload = item
        limit = ws.limits.get(key)
        if limit is None:
            limit = ws.limits[key] = payload_limit(self.keys, key)
            if len(ws.limits) > MAX_DROPPED_KEYS:
                ws.limits.clear()
        if len(payload) > limit:
            self.stats.drop_oversize(key, len(payload), limit)
            return None
        return lt, key, payload

    def _channel(self, ws: _WriterState, key: str) -> int:
        """The channel id of ``key``, registered at its first sample."""
        cid = ws.channels.get(key)
        if cid is None:
            try:
                kind = self.keys.parse(key)[0]
            except wire.InvalidKeyError:
                kind = ""
            cid = self._writer.register_channel(key, MESSAGE_ENCODING, 0, {"kind": kind})
            ws.channels[key] = cid
            ws.seqs[cid] = 0
            self.stats.channels += 1
        return cid

    def _write_sample(self, ws: _WriterState, lt: int, key: str, payload: bytes) -> None:
        """Write one message: log time = receive time (never decreasing in file order), publish
        time = the sender's sim time (or the log time if undecodable), per-channel sequence."""
        st = self.stats
        cid = self._channel(ws, key)
        if lt < ws.last_lt:
            lt = ws.last_lt  # keep log times non-decreasing in file order (clock steps)
        ws.last_lt = lt
        t = sim_time(payload)
        if t is None:
            st.undecodable += 1
            t = lt
        elif t > st.last_sim_t:
            st.last_sim_t = t
        s = (ws.seqs[cid] + 1) & 0xFFFFFFFF
        ws.seqs[cid] = s
        self._writer.add_message(cid, lt, payload, t, s)
        st.messages += 1
        st.payload_bytes += len(payload)
        if st.first_log_time is None:
            st.first_log_time = lt
        st.last_log_time = lt
        ws.dirty = True

    def _periodic(self, ws: _WriterState) -> None:
        """The oversize-drop counts (at most every DROPPED_METADATA_INTERVAL_S) and the periodic
        flush: close the open chunk, write it and flush it to the OS."""
        st = self.stats
        mono = time.monotonic
        if st.dropped_oversize != ws.dropped_written and mono() >= ws.next_dropped:
            ws.dropped_written = st.dropped_oversize
            ws.next_dropped = mono() + DROPPED_METADATA_INTERVAL_S
            self._write_metadata(self._dropped_metadata())
            ws.dirty = False  # _write_metadata flushed
        if mono() >= ws.next_flush:
            backlog = self._q.qsize()
            if backlog > st.peak_backlog:
                st.peak_backlog = backlog
            if ws.dirty:
                self._flush()  # closes the open chunk, writes it and flushes to the OS
                st.flushes += 1
                ws.dirty = False
            ws.next_flush = mono() + self.flush_interval_s

    def _dropped_metadata(self) -> dict[str, str]:
        """The ``zenswarm`` metadata values that carry the oversize-drop counts (cumulative)."""
        st = self.stats
        return {
            DROPPED_OVERSIZE: json.dumps(st.dropped_by_key, sort_keys=True),
            "payload_limit_bytes": str(wire.MAX_PAYLOAD),
            "mission_payload_limit_bytes": str(wire.MAX_MISSION_PAYLOAD),
        }

    def _end_metadata(self) -> dict[str, str]:
        """The recorder's end marker (:data:`zenswarm.bridge.recording.mcapio.RECORDER_END`), written on a
        clean stop after the last message: when and why it stopped, and its statistics."""
        st = self.stats
        stats = {**st.counters(0), "first_log_time_ns": st.first_log_time, "last_log_time_ns": st.last_log_time,
                 "last_sim_t_ns": st.last_sim_t, "dropped_oversize_bytes": st.dropped_oversize_bytes}
        stats.pop("backlog", None)
        return {
            RECORDER_END: str(time.time_ns()),
            "recorder_stop_reason": self.stop_reason,
            "recorder_stats_json": json.dumps(stats, sort_keys=True),
        }

    def _write_metadata(self, values: dict[str, str]) -> None:
        self._writer.add_metadata(METADATA_NAME, values)
        self._flush()

    def _flush(self) -> None:
        """Close the open chunk, write it and flush the file to the OS; the file is whole up to here."""
        self._writer.flush()
        self._good_end = self._file.tell()

    def _finish(self) -> None:
        """Write the summary and the footer, close the file. After a write error (a full disk:
        ENOSPC, an I/O error) the file is ended by :meth:`_salvage` instead."""
        try:
            if self.error is None:
                self._writer.finish()
                self._file.flush()
        except OSError as e:
            self.error = e
        finally:
            try:
                self._file.close()
            except OSError as e:  # what was still buffered did not fit either: cut by _salvage
                self.error = self.error or e
            if self.error is not None:
                self.salvaged = self._salvage()
            try:
                self.stats.file_bytes = os.path.getsize(self.path)
            except OSError:
                pass

    def _salvage(self) -> str:
        """End a file whose writing failed so that it is readable as it is, up to the last flush
        (at most ``flush_interval_s`` of samples lost before the failure): cut it back there, at a
        record boundary, then append the end marker (stop reason: the error), a data end and a
        footer without a summary (readers scan the data section). A partial chunk freed what it
        used, so the few hundred bytes of that ending usually fit on a full disk; if even they do
        not, the end marker is left out, and failing that the file is left cut at the last
        flush, which ``zenswarm recover`` (or a non-strict read) takes whole. Returns what was done."""
        import struct

        def record(opcode: int, body: bytes) -> bytes:
            return struct.pack("<BQ", opcode, len(body)) + body

        def text(v: str) -> bytes:
            b = v.encode()
            return struct.pack("<I", len(b)) + b

        self.stop_reason = f"writer failed: {self.error!r}"
        entries = b"".join(text(k) + text(v) for k, v in self._end_metadata().items())
        metadata = record(0x0C, text(METADATA_NAME) + struct.pack("<I", len(entries)) + entries)  # METADATA
        ending = record(0x0F, struct.pack("<I", 0)) + record(0x02, struct.pack("<QQI", 0, 0, 0))  # DATA_END, FOOTER
        ending += b"\x89MCAP0\r\n"
        try:
            fd = os.open(self.path, os.O_WRONLY)
        except OSError:
            return "not ended: the file could not be opened again"
        try:
            for tail, what in ((metadata + ending, "cut at the last flush, end marker and footer written"),
                               (ending, "cut at the last flush, footer written (no room for the end marker)")):
                os.ftruncate(fd, self._good_end)
                try:
                    if os.pwrite(fd, tail, self._good_end) == len(tail):
                        return what
                except OSError:
                    pass
            os.ftruncate(fd, self._good_end)
            return "cut at the last flush, no room for a footer (`zenswarm recover` reads it)"
        except OSError as e:
            return f"not ended: {e!r}"
        finally:
            os.close(fd)


def _fetch_mission(session: Any, keys: wire.Keys, stop: threading.Event, on_scenario: Any, log: Any) -> None:
    """Ask the leader's mission queryable until it answers or ``stop`` is set: at once when the
    leader's liveliness token appears (it declares the queryable before the token), and once a
    second in any case."""
    from zenswarm.scenario.config import scenario_from_dict, scenario_to_dict

    leader_seen = threading.Event()
    watch = None
    try:
        watch = session.liveliness().declare_subscriber(
            keys.alive("leader"), lambda sample: leader_seen.set(), history=True
        )
    except Exception:  # noqa: BLE001 - fall back to polling
        pass
    asked = 0
    try:
        while not stop.is_set():
            asked += 1
            leader_seen.clear()
            try:
                for reply in session.get(keys.mission, timeout=1.0):
                    ok = getattr(reply, "ok", None)
                    if ok is None:
                        continue
                    try:
                        msg = wire.decode("mission", ok.payload.to_bytes())
                        if not isinstance(msg, wire.Mission):  # decode("mission") gives a Mission or raises
                            raise TypeError(f"not a mission: {type(msg).__name__}")
                        sc = scenario_from_dict(msg.scenario)
                    except Exception as e:  # noqa: BLE001 - a bad answer: keep asking
                        log(f"recorder: ignoring an invalid mission answer: {e}")
                        continue
                    on_scenario(scenario_to_dict(sc))
                    log(f"recorder: scenario '{sc.name}' received from the leader's mission")
                    return
            except Exception as e:  # noqa: BLE001 - session closing, router gone: retry until stop
                if stop.is_set():
                    return
                if asked == 1:
                    log(f"recorder: mission query failed ({e}); retrying")
            if asked == 30:
                log("recorder: no leader has answered on the mission key yet; still asking")
            for _ in range(20):  # up to 1 s, sooner if the leader shows up
                if stop.is_set() or leader_seen.wait(0.05):
                    break
    finally:
        if watch is not None:
            try:
                watch.undeclare()
            except Exception:  # noqa: BLE001 - best effort
                pass


class _Stop:
    """The recorder's stop request: an event, and why it was set (the last line of the log).

    SIGINT/SIGTERM reach it through a :class:`zenswarm.process.signals.SignalRelay` (:meth:`install`):
    the main thread waits on ``event`` all the time (``_wait_and_report``), and a handler that set
    the event itself could run while the main thread held the event's lock, and wait for it forever
    (a recorder that never exited after SIGTERM, seen once under load)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.why = "stopped"
        self.relay: SignalRelay | None = None

    def install(self) -> None:
        """SIGINT and SIGTERM set the event (main thread only)."""
        self.relay = SignalRelay(self.on_signal, name="recorder-signals")

    def on_signal(self, signum: int) -> None:
        """A stop signal (called by the relay's thread, never in the signal handler)."""
        self.why = f"received {signal.Signals(signum).name}"
        self.event.set()

    def close(self) -> None:
        """Restore the previous signal handlers."""
        if self.relay is not None:
            self.relay.close()
            self.relay = None


def _undeclare(*entities: Any) -> None:
    """Undeclare Zenoh entities, best effort (on shutdown)."""
    for e in entities:
        try:
            e.undeclare()
        except Exception:  # noqa: BLE001 - best effort on shutdown
            pass


def _subscribe_all(session: Any, keys: wire.Keys, sink: McapSink) -> Any:
    """Subscribe to every key of the swarm; each sample goes to ``sink`` (over-size ones counted only)."""
    put_item = sink.put_item
    now_ns = time.time_ns
    small = wire.MAX_PAYLOAD  # the bound of every key but the mission's (payload_limit)
    mission_key, mission_limit = keys.mission, wire.MAX_MISSION_PAYLOAD

    def on_sample(sample: Any) -> None:  # the whole callback: stamp, copy, enqueue
        payload = sample.payload
        n = len(payload)
        if n > small:  # no decoder reads it: count it without copying it (payload_limit)
            key = str(sample.key_expr)
            if key != mission_key or n > mission_limit:
                put_item((_OVERSIZE, key, n, now_ns()))
                return
            put_item((now_ns(), key, payload.to_bytes()))
            return
        put_item((now_ns(), str(sample.key_expr), payload.to_bytes()))

    return session.declare_subscriber(keys.all, on_sample)


def _wait_and_report(s: RecorderSettings, stop: _Stop, session: Any, keys: wire.Keys, sink: McapSink, out: Path) -> None:
    """Until a stop request, ``--duration`` or a writer failure (``stop.why``), publishing the
    recorder's counters on diag/recorder every ``--diag-interval`` s."""
    deadline = None if s.duration is None else time.monotonic() + s.duration
    diag_pub = session.declare_publisher(keys.diag(PROCESS_NAME)) if s.diag_interval > 0 else None
    diag_seq = 0
    next_diag = time.monotonic() + (s.diag_interval if diag_pub is not None else 1e18)
    if s.mode == "realtime":
        gc_startup_done()  # subscribed, writer running: see zenswarm.process.runtime.GcPolicy (realtime only)
    while not stop.event.is_set():
        gc_safe_point()
        now = time.monotonic()
        left = min(0.2, next_diag - now)
        if deadline is not None:
            left = min(left, deadline - now)
            if left <= 0:
                stop.why = f"duration of {s.duration:g} s reached"
                break
        if left > 0:
            stop.event.wait(left)
        if sink.error is not None:
            stop.why = f"writer failed: {sink.error!r}"
            break
        if diag_pub is not None and time.monotonic() >= next_diag:
            diag_seq += 1
            next_diag += s.diag_interval
            st = sink.stats
            diag = wire.Diag(
                t=st.last_sim_t, seq=diag_seq, process=PROCESS_NAME, counters={**st.counters(sink.backlog), **gc_policy().counters()},
                info={"file": str(out)},
            )
            diag_pub.put(wire.encode(diag))


def run(s: RecorderSettings, exit_hard: bool = True) -> int:
    """Run the recorder until SIGTERM/SIGINT or ``--duration``. Exit code 0 on a clean stop.
    ``exit_hard`` False (in-process): the signal handlers are restored at the end."""
    gc_policy()  # a bad ZENSWARM_GC: exit 2 before any work
    stop = _Stop()
    stop.install()
    try:
        return _run(s, stop)
    finally:
        if not exit_hard:  # in-process: restore the handlers; the command
            stop.close()  # exits at once (main), where a second signal must change nothing


def _run(s: RecorderSettings, stop: _Stop) -> int:
    # One session's life in order (open, subscribe, record, close in one try/finally): reads better
    # whole than with its setup and its end in other functions.
    from zenswarm.scenario.config import scenario_to_dict

    def log(text: str) -> None:
        print(text, flush=True)

    keys = wire.Keys(s.swarm)
    mode = s.mode
    scenario: dict[str, Any] | None = None if s.scenario is None else scenario_to_dict(s.scenario)
    connect = list(s.connect) or ["tcp/127.0.0.1:7447"]
    out: Path = check_output_file(s.out, "--out")  # before joining: exit 2, nothing recorded in vain
    conf = bus.client_config(
        connect,
        connect_timeout_s=s.connect_timeout,
        # retry quickly while the swarm's router is not up yet
        settings={
            "connect/retry": {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2},
            **security.client_fragments(PROCESS_NAME, security.ClientSecurity(keys=s.keys, tls=s.tls), connect=s.connect, swarm=s.swarm),
        },
    )
    try:
        session_cm = bus.open_session(conf, handle_signals=False)
        session = session_cm.__enter__()
    except bus.BusError as e:
        print(f"recorder: error: {e} (router {', '.join(connect)})", file=sys.stderr, flush=True)
        return 3
    sink: McapSink | None = None
    fetcher: threading.Thread | None = None
    source = s.scenario_source if scenario is not None else "pending: asking the leader's mission"
    fault_args = s.faults.argv()
    try:
        sink = McapSink(
            out,
            keys,
            flush_interval_s=s.flush_interval,
            chunk_size=s.chunk_size,
            compression=s.compression,
            metadata=build_metadata(s.swarm, mode, scenario, source, fault_args),
        )
        sink.start()
        sub = _subscribe_all(session, keys, sink)
        token = bus.declare_alive(session, keys, PROCESS_NAME)  # only now: the subscriber is in place
        if scenario is None:
            the_sink = sink

            def on_mission(d: dict[str, Any]) -> None:
                the_sink.set_metadata(build_metadata(s.swarm, mode, d, "mission", fault_args))

            fetcher = threading.Thread(
                target=_fetch_mission,
                args=(session, keys, stop.event, on_mission, log),
                name="mission-fetch",
                daemon=True,
            )
            fetcher.start()
        log(
            f"recorder: recording {keys.all} from {', '.join(connect)} to {out} "
            f"(chunks flushed every {s.flush_interval:g} s; {mode})"
        )
        _wait_and_report(s, stop, session, keys, sink, out)
        stop.event.set()
        _undeclare(token, sub)
        if fetcher is not None:
            fetcher.join(timeout=3.0)
    finally:
        stop.event.set()
        session_cm.__exit__(None, None, None)  # closes the session: no callback runs after this
        if sink is not None:
            sink.stop_reason = stop.why
            sink.close()
    st = sink.stats
    log(f"recorder: {stop.why}; wrote {out}: {st.line()}")
    if sink.error is not None:
        ended = f"; {out}: {sink.salvaged}" if sink.salvaged else ""
        print(f"recorder: error: writing {out} failed: {sink.error!r}{ended}", file=sys.stderr, flush=True)
        return 3
    return 0


def run_settings(s: RecorderSettings, exit_hard: bool = True) -> int:
    """The recorder command with these settings (``zenswarm record``, or ``zenswarm up``'s
    recorder reading them on its standard input): :func:`run`, then the process ends."""
    rc = run(s, exit_hard)
    # The file is complete and closed, the session closed: leave without the interpreter's
    # shutdown, where a zenoh helper thread still unwinding native frames can abort the process
    # ("FATAL: exception not rethrown", seen once under load), which would turn a clean stop
    # into a crash report. Only when run as the `zenswarm record` command, not in-process.
    if exit_hard:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc


def main(args: argparse.Namespace) -> int:
    """``zenswarm record``: its flags as :class:`RecorderSettings`, recorded with them."""
    return run_settings(recorder_settings(args), getattr(args, "exit_hard", True))


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="record every message of a swarm to an MCAP file",
        description=(
            "Subscribe to swarm/<NAME>/** and write every sample, as received, to an MCAP file: one "
            "channel per key, message encoding msgpack, log_time = receive wall time, publish_time = "
            "the sender's sim time, the scenario in a metadata record. Crash-safe: chunks are closed "
            "and flushed to the OS at least every --flush-interval seconds; `zenswarm recover` rewrites "
            "a file cut by a crash. Stops cleanly on SIGINT/SIGTERM or after --duration. A payload over the "
            "decoders' size bound (64 KiB; 1 MiB on the mission key) is not written: it is counted per key, "
            "and the counts are stored in the file's metadata (dropped_oversize_json)."
        ),
    )
    p.add_argument("--swarm", default="default", help="swarm name: records swarm/<name>/** (default: default)")
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh router endpoint (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--out", type=Path, required=True, metavar="FILE.mcap", help="output MCAP file (overwritten)")
    p.add_argument("--scenario", type=Path, help="scenario TOML to store in the file; default: ask the leader's mission")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: run until SIGINT/SIGTERM)")
    p.add_argument(
        "--mode",
        choices=("lockstep", "realtime", "unknown"),
        default="lockstep",
        help="time mode of the swarm, stored in the metadata (default lockstep)",
    )
    p.add_argument("--realtime", action="store_true", help="same as --mode realtime")
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=DEFAULT_CONNECT_TIMEOUT_S,
        metavar="S",
        help=f"keep trying to reach the router this long (default {DEFAULT_CONNECT_TIMEOUT_S:g} s)",
    )
    p.add_argument(
        "--flush-interval",
        type=float,
        default=DEFAULT_FLUSH_INTERVAL_S,
        metavar="S",
        help=f"close the chunk and flush the file at least this often (default {DEFAULT_FLUSH_INTERVAL_S} s)",
    )
    p.add_argument(
        "--chunk-size", type=int, default=DEFAULT_CHUNK_SIZE, metavar="BYTES", help="close a chunk at this size (default 1 MiB)"
    )
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunk compression (default zstd)")
    add_security_args(p)
    p.add_argument(
        "--diag-interval",
        type=float,
        default=1.0,
        metavar="S",
        help="publish the recorder's counters on diag/recorder every S seconds (recorded too; 0 = never; default 1)",
    )
    add_fault_args(p)  # not applied here: stored in the metadata for `replay --verify`
    add_plugin_args(p)  # applied to the scenario stored (what `verify` rebuilds the agents from)
    p.set_defaults(func=main)

"""The recorder's MCAP sink: the writer side of ``zenswarm record`` (:class:`McapSink`), the
values it writes (:func:`build_metadata`, :func:`sim_time`, the size bound :func:`payload_limit`)
and its counters (:class:`RecorderStats`).

The recorder process (:mod:`zenswarm.bridge.recording.recorder`) subscribes and feeds the sink;
the file layout is :mod:`zenswarm.bridge.recording.mcapio`. Nothing of Zenoh here.

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
* Closing (:meth:`McapSink.close`): the writer drains the queue, writes the end marker (a last
  ``zenswarm`` metadata record: ``recorder_end_unix_ns``, ``recorder_stop_reason`` and
  ``recorder_stats_json``, the counters of :class:`RecorderStats`), then ``Writer.finish()``
  writes the summary (statistics, channels, chunk/message/metadata indexes) and the footer. A
  file whose writing failed (a full disk) is cut back to its last flush and ended readable there.
"""

from __future__ import annotations

import json
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import msgpack

from zenswarm import __version__
from zenswarm.bridge.recording.mcapio import DROPPED_OVERSIZE, MESSAGE_ENCODING, METADATA_NAME, RECORDER_END
from zenswarm.bus import wire

__all__ = [
    "DEFAULT_FLUSH_INTERVAL_S",
    "DEFAULT_CHUNK_SIZE",
    "DROPPED_METADATA_INTERVAL_S",
    "MAX_DROPPED_KEYS",
    "RecorderStats",
    "McapSink",
    "payload_limit",
    "sim_time",
    "build_metadata",
]

DEFAULT_FLUSH_INTERVAL_S: Final = 0.25
"""Close the open chunk and flush the file to the OS at least this often, s."""
DEFAULT_CHUNK_SIZE: Final = 1 << 20
"""Close a chunk earlier when its uncompressed records reach this many bytes."""
DROPPED_METADATA_INTERVAL_S: Final = 1.0
"""Rewrite the oversize-drop counts into the file at most this often while they change, s."""
MAX_DROPPED_KEYS: Final = 1024
"""Distinct keys counted one by one in the oversize-drop counts; the rest under ``<other>``."""

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

"""The MCAP layout of a zenswarm flight recording, and reading one robustly.

Pure-ish: the :mod:`mcap` library, the standard library and nothing of Zenoh. Shared by the
recorder's tools (``zenswarm replay``, ``zenswarm info``, ``zenswarm recover``) and the flight
report. Rewriting a damaged recording into a complete one is :mod:`zenswarm.bridge.recording.recover`
(built on this reader, which never imports it).

A zenswarm recording (written by :mod:`zenswarm.bridge.recording.recorder` through its sink,
:mod:`zenswarm.bridge.recording.sink`) is an MCAP file with

* one channel per concrete Zenoh key (``topic`` = the key, e.g. ``swarm/demo/uav/2/state``),
  ``message_encoding = "msgpack"`` (MCAP's well-known encoding), no schema (``schema_id = 0``,
  as the MCAP registry allows for self-describing encodings), channel metadata ``{"kind": ...}``
  (the key kind of :meth:`zenswarm.bus.keys.Keys.parse`, empty for keys outside the swarm layout);
* messages with ``log_time`` = receive wall time (ns since the Unix epoch; non-decreasing in
  file order), ``publish_time`` = the sender's sim time ``t`` (ns) when the payload carries one,
  else ``log_time``, ``sequence`` = running count per channel (1, 2, ..., modulo 2**32), and
  ``data`` = the payload exactly as received;
* metadata records named ``"zenswarm"`` (:data:`METADATA_NAME`) with string values ``swarm``,
  ``zenswarm_version``, ``mode``, ``scenario_source``, ``recorder_start_unix_ns`` and
  ``scenario_json`` (json of :func:`zenswarm.scenario.config.scenario_to_dict`). The first is written
  right after the header; when the scenario comes from the leader's mission rather than
  ``--scenario``, a second one carrying ``scenario_json`` follows when it arrives. Readers merge
  them in file order (:attr:`Recording.metadata`). When the recorder did not record oversize
  payloads (over the decoders' size bound, :func:`zenswarm.bridge.recording.sink.payload_limit`), a further
  ``zenswarm`` record carries ``dropped_oversize_json`` (:data:`DROPPED_OVERSIZE`: json of
  key -> ``{"count", "bytes", "largest", "limit"}``, cumulative, rewritten while they change)
  and ``payload_limit_bytes`` / ``mission_payload_limit_bytes``; for a file without summary,
  records met while reading the messages are merged as they are met
  (:attr:`Recording.dropped_oversize`, :meth:`Recording.notes`); on a clean stop the recorder
  writes a last ``zenswarm`` record, its end marker (:data:`RECORDER_END`:
  ``recorder_end_unix_ns``, ``recorder_stop_reason``, ``recorder_stats_json``);
* small zstd chunks closed at least every :data:`zenswarm.bridge.recording.sink.DEFAULT_FLUSH_INTERVAL_S`, and
  on a clean stop a summary section (statistics, channels, chunk and metadata indexes) + footer.

Reading is done by a bounded record walker of our own on top of ``mcap.records`` (the parsing
primitives of the mcap library) rather than by ``mcap.reader``: the stock readers either need
the summary (seeking) or stop with a bare exception at the first damaged byte (streaming), and
we want to say *where* a file is damaged, keep everything before it, and step over a chunk whose
CRC does not match when the records around it are intact.

Errors are :class:`zenswarm.errors.RecordingError` and always name the file.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Callable, Generator, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.stream_reader import breakup_chunk
from mcap.well_known import MessageEncoding

from zenswarm.errors import RecordingError

__all__ = [
    "MAGIC",
    "METADATA_NAME",
    "MESSAGE_ENCODING",
    "DROPPED_OVERSIZE",
    "RECORDER_END",
    "RecordedMessage",
    "Recording",
    "read_recording",
    "file_is_complete",
]

MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes that start and end every MCAP file."""
METADATA_NAME = "zenswarm"
"""Name of the metadata record that describes a zenswarm recording."""
MESSAGE_ENCODING = MessageEncoding.MessagePack  # "msgpack"
DROPPED_OVERSIZE = "dropped_oversize_json"
"""``zenswarm`` metadata value: the payloads the recorder did not record because they were over
the decoders' size bound, json of key -> ``{"count", "bytes", "largest", "limit"}``."""
RECORDER_END = "recorder_end_unix_ns"
"""``zenswarm`` metadata value written last by a recorder that stopped cleanly (its end marker):
the wall time it stopped (ns since the Unix epoch), with ``recorder_stop_reason`` and
``recorder_stats_json`` (json of the recorder's counters: recorded, channels, payload_bytes,
undecodable, dropped_oversize, flushes, peak_backlog, ...)."""
RECORDER_LIBRARIES = ("zenswarm-recorder/", "zenswarm-recover/")
"""Header ``library`` prefixes of files whose message ``sequence`` is the running count per
channel (1, 2, ...), so a gap in it is a lost message."""

MAX_CHUNK_UNCOMPRESSED = 1 << 30
"""A chunk claiming to decompress to more than this (bytes) is treated as corrupted."""

_FOOTER_LEN = 1 + 8 + 20  # opcode, length, summary_start(8) summary_offset_start(8) crc(4)
_KNOWN_OPCODES = frozenset(int(o) for o in Opcode)


class RecordedMessage(NamedTuple):
    """One recorded sample: the key, receive wall time (ns), sender sim time (ns), raw payload."""

    topic: str
    log_time: int
    publish_time: int
    payload: bytes


class _SequenceGaps:
    """Per-topic gaps in the recorder's running sequence numbers (messages known to be lost)."""

    def __init__(self) -> None:
        self.last: dict[str, int] = {}
        self.gaps: dict[str, int] = {}

    def see(self, topic: str, sequence: int) -> None:
        prev = self.last.get(topic, 0)
        gap = (sequence - prev - 1) & 0xFFFFFFFF
        if gap and gap < 0x80000000:  # (a sequence going back is not a loss)
            self.gaps[topic] = self.gaps.get(topic, 0) + gap
        self.last[topic] = sequence



# --------------------------------------------------------------------------- low level


class _Damage(Exception):
    """Internal: a record cannot be read. ``fatal`` = the framing is lost (stop reading)."""

    def __init__(self, offset: int, text: str, fatal: bool, truncated: bool = False) -> None:
        super().__init__(text)
        self.offset = offset
        self.text = text
        self.fatal = fatal
        self.truncated = truncated


def _parse(opcode: int, body: bytes) -> Any:
    s = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.MESSAGE:
        return Message.read(s, len(body))
    reader = {
        Opcode.HEADER: Header.read,
        Opcode.FOOTER: Footer.read,
        Opcode.SCHEMA: Schema.read,
        Opcode.CHANNEL: Channel.read,
        Opcode.CHUNK: Chunk.read,
        Opcode.MESSAGE_INDEX: MessageIndex.read,
        Opcode.CHUNK_INDEX: ChunkIndex.read,
        Opcode.ATTACHMENT: Attachment.read,
        Opcode.ATTACHMENT_INDEX: AttachmentIndex.read,
        Opcode.STATISTICS: Statistics.read,
        Opcode.METADATA: Metadata.read,
        Opcode.METADATA_INDEX: MetadataIndex.read,
        Opcode.SUMMARY_OFFSET: SummaryOffset.read,
        Opcode.DATA_END: DataEnd.read,
    }[Opcode(opcode)]
    return reader(s)


def _walk(f: io.BufferedReader, start: int, end: int, *, complete: bool) -> Iterator[tuple[int, int, Any]]:
    """Yield ``(offset, opcode, record)`` for the records in ``[start, end)`` of ``f``.

    Stops after a Footer. Raises :class:`_Damage` (fatal) where the framing breaks: an unknown
    opcode, a length running past ``end``, a record that does not parse. ``complete`` only
    chooses the wording (a record cut by the end of a file without footer is a truncation).
    """
    f.seek(start)
    pos = start
    while pos < end:
        hdr = f.read(9)
        if len(hdr) < 9:
            raise _Damage(pos, f"file ends inside a record header at offset {pos}", True, truncated=not complete)
        opcode, length = struct.unpack("<BQ", hdr)
        if opcode not in _KNOWN_OPCODES:
            raise _Damage(pos, f"unknown record opcode 0x{opcode:02x} at offset {pos}", True)
        if length > end - pos - 9:
            name = Opcode(opcode).name
            if complete:
                raise _Damage(pos, f"{name} record at offset {pos} claims {length} bytes, past the end of its section", True)
            raise _Damage(pos, f"{name} record at offset {pos} is cut short by the end of the file", True, truncated=True)
        body = f.read(length)
        if len(body) != length:
            raise _Damage(pos, f"file ends inside the record at offset {pos}", True, truncated=True)
        try:
            rec = _parse(opcode, body)
        except Exception as e:  # noqa: BLE001 - mcap raises EndOfFile, struct.error, UnicodeDecodeError...
            raise _Damage(pos, f"{Opcode(opcode).name} record at offset {pos} does not parse ({type(e).__name__}: {e})", True) from None
        yield pos, opcode, rec
        pos += 9 + length
        if opcode == Opcode.FOOTER:
            return


def _chunk_records(chunk: Chunk, offset: int) -> list[Any]:
    """Records inside a chunk, its CRC checked. Raises :class:`_Damage` (not fatal: the chunk
    was framed correctly, so the records after it can still be read)."""
    if chunk.uncompressed_size > MAX_CHUNK_UNCOMPRESSED:
        raise _Damage(offset, f"chunk at offset {offset} claims {chunk.uncompressed_size} uncompressed bytes", False)
    if chunk.compression not in ("", "zstd", "lz4"):
        raise _Damage(offset, f"chunk at offset {offset} has unknown compression {chunk.compression!r}", False)
    try:
        return breakup_chunk(chunk, validate_crc=True)
    except Exception as e:  # noqa: BLE001 - CRCValidationError, zstd/lz4 errors, EndOfFile, struct.error
        raise _Damage(offset, f"chunk at offset {offset} is corrupted ({type(e).__name__}: {e})", False) from None


def _read_tail(f: io.BufferedReader, size: int) -> Footer | str:
    """The footer if the file ends with a valid footer + magic (and, if the footer has a summary
    CRC, the summary matches it); else why not (a sentence)."""
    if size < 8 + _FOOTER_LEN + 8:
        return f"file is only {size} bytes: no footer"
    f.seek(size - 8 - _FOOTER_LEN)
    tail = f.read(_FOOTER_LEN + 8)
    if tail[-8:] != MAGIC:
        return "no closing magic at the end of the file: it was not closed cleanly (truncated)"
    opcode, length = struct.unpack("<BQ", tail[:9])
    if opcode != Opcode.FOOTER or length != 20:
        return "no footer record before the closing magic"
    summary_start, summary_offset_start, summary_crc = struct.unpack("<QQI", tail[9:29])
    footer = Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=summary_crc)
    footer_pos = size - 8 - _FOOTER_LEN
    if summary_start and not 8 <= summary_start <= footer_pos:
        return f"footer points at a summary outside the file (offset {summary_start})"
    if summary_crc:
        if summary_start:
            f.seek(summary_start)
            data = f.read(footer_pos - summary_start)
        else:
            data = b""
        crc = zlib.crc32(data)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        if crc != summary_crc:
            return "summary section fails its CRC check (corrupted)"
    return footer


def _cut_chunk_header(f: io.BufferedReader, offset: int, end: int) -> dict[str, Any] | None:
    """The log-time span in the header of a chunk record at ``offset`` that the end of the file
    cuts short (None if the record there is not a chunk or its header is cut too)."""
    f.seek(offset)
    head = f.read(9 + 16)
    if len(head) < 25 or head[0] != Opcode.CHUNK or offset + 25 > end:
        return None
    start, stop = struct.unpack("<QQ", head[9:25])
    if stop < start:
        return None
    return {"offset": offset, "message_start_time": start, "message_end_time": stop}


def file_is_complete(path: str | os.PathLike[str]) -> bool:
    """True if ``path`` is an MCAP file that ends with a valid footer (and summary CRC)."""
    try:
        with open(path, "rb") as f:
            if f.read(8) != MAGIC:
                return False
            return isinstance(_read_tail(f, os.fstat(f.fileno()).st_size), Footer)
    except OSError:
        return False


# --------------------------------------------------------------------------- Recording


class Recording:
    """A zenswarm recording opened by :func:`read_recording`.

    Attributes
    ----------
    path: the file. complete: it ends with a valid footer (and a summary, for recorder files).
    summary_problem: why it is not complete (None if complete).
    metadata: name -> values of the metadata records, merged in file order (a later record of
        the same name adds or overrides keys: the recorder writes a first ``zenswarm`` record at
        start and a second one with the scenario when it learns it from the leader).
    scenario: the recorded scenario as a dict (``scenario_to_dict`` form) or None.
    swarm, mode, zenswarm_version: from the ``zenswarm`` metadata record (None if absent).
    statistics: the summary's Statistics record (complete files) or None.
    channels: channel id -> ``mcap.records.Channel``: from the summary when complete, else as
        discovered while iterating.
    problems: damage found (lenient mode): why the file is incomplete, then what was met while
        iterating, each naming the offset.
    """

    def __init__(self, path: Path, strict: bool) -> None:
        self.path = path
        self.strict = strict
        self.size = 0
        self.complete = False
        self.summary_problem: str | None = None
        self.header: Header | None = None
        self.metadata: dict[str, dict[str, str]] = {}
        self.metadata_records: list[Metadata] = []
        self.statistics: Statistics | None = None
        self.channels: dict[int, Channel] = {}
        self.schemas: dict[int, Schema] = {}
        self.problems: list[str] = []
        self.skipped_messages = 0
        self.damage_offset: int | None = None
        """Where the framing broke or the file was cut while reading the messages (None: not met)."""
        self.discarded_bytes = 0
        """Bytes from :attr:`damage_offset` to the end of the data that could not be read."""
        self.skipped_chunks: list[dict[str, Any]] = []
        """Chunks skipped as corrupted: offset, log-time span and, from the message indexes that
        follow them, how many messages they held (``messages``; None if no index follows)."""
        self.cut_chunk: dict[str, Any] | None = None
        """The chunk cut by the end of a truncated file, if its header could be read: offset, log-time span."""
        self._footer: Footer | None = None
        self._summary_start = 0
        self._meta_offsets: set[int] = set()

    # ------------------------------------------------------------------ info
    @property
    def info(self) -> dict[str, str]:
        """Values of the ``zenswarm`` metadata record ({} if absent)."""
        return self.metadata.get(METADATA_NAME, {})

    @property
    def scenario(self) -> dict[str, Any] | None:
        import json

        text = self.info.get("scenario_json")
        if not text:
            return None
        try:
            d = json.loads(text)
        except ValueError as e:
            raise RecordingError(f"{self.path}: metadata scenario_json is not valid JSON: {e}") from None
        if not isinstance(d, dict):
            raise RecordingError(f"{self.path}: metadata scenario_json is not a JSON object")
        return d

    def load_scenario(self) -> Any:
        """The recorded scenario as a :class:`zenswarm.scenario.config.Scenario` (validated); raises
        RecordingError if the recording has none."""
        from zenswarm.errors import ScenarioError
        from zenswarm.scenario.config import scenario_from_dict

        d = self.scenario
        if d is None:
            raise RecordingError(
                f"{self.path}: no scenario in the recording's metadata (record with --scenario, "
                "or while a leader serves the mission)"
            )
        try:
            return scenario_from_dict(d)
        except ScenarioError as e:
            raise RecordingError(f"{self.path}: recorded scenario is invalid: {e}") from None

    @property
    def dropped_oversize(self) -> dict[str, dict[str, int]]:
        """Payloads the recorder did not record because they were over the decoders' size bound:
        key -> ``{"count", "bytes", "largest", "limit"}`` ({} if none, or if the file predates the
        count). For a file without summary, complete only after the messages were read."""
        import json

        text = self.info.get(DROPPED_OVERSIZE)
        if not text:
            return {}
        try:
            d = json.loads(text)
        except ValueError:
            return {}
        return d if isinstance(d, dict) else {}

    def notes(self) -> list[str]:
        """What a reader of this recording should be told, one sentence each: that it is truncated
        or damaged (and the report covers only what was read), and the oversize payloads the
        recorder did not record. Call after reading the messages (the damage found while reading,
        and the counts of a file without summary, are known only then)."""
        out: list[str] = []
        if not self.complete:
            out.append(
                f"the recording is incomplete ({self.summary_problem}): only what could be read from it is covered"
                + (f" ({self.discarded_bytes} bytes at the end could not be read)" if self.discarded_bytes else "")
            )
        elif self.problems:
            out.append(f"the recording is damaged ({'; '.join(self.problems)}): only what could be read from it is covered")
        dropped = self.dropped_note()
        if dropped is not None:
            out.append(dropped)
        return out

    def dropped_note(self) -> str | None:
        """How many payloads the recorder did not record, on which keys, and why (None if none)."""
        dropped = self.dropped_oversize
        if not dropped:
            return None
        n = sum(int(d.get("count", 0)) for d in dropped.values())
        b = sum(int(d.get("bytes", 0)) for d in dropped.values())
        per = ", ".join(f"{k}: {d.get('count')} (largest {d.get('largest')} bytes)" for k, d in sorted(dropped.items()))
        lim = self.info.get("payload_limit_bytes", "?")
        return (
            f"the recorder did not record {n} payloads ({b} bytes) longer than the decoders' size bound "
            f"({lim} bytes; on the mission key {self.info.get('mission_payload_limit_bytes', '?')}), which every "
            f"zenswarm decoder rejects unread: {per}"
        )

    @property
    def swarm(self) -> str | None:
        return self.info.get("swarm")

    @property
    def mode(self) -> str | None:
        return self.info.get("mode")

    @property
    def zenswarm_version(self) -> str | None:
        return self.info.get("zenswarm_version")

    @property
    def message_count(self) -> int | None:
        """From the summary statistics (complete files), else None."""
        return self.statistics.message_count if self.statistics is not None else None

    def topics(self) -> list[str]:
        """Topics of the known channels, sorted."""
        return sorted({c.topic for c in self.channels.values()})

    def __repr__(self) -> str:
        return f"Recording({str(self.path)!r}, complete={self.complete}, channels={len(self.channels)})"

    # ------------------------------------------------------------------ iteration
    def _fail(self, text: str) -> None:
        """Strict: raise; lenient: note it."""
        if self.strict:
            raise RecordingError(f"{self.path}: {text}")
        if text not in self.problems:
            self.problems.append(text)

    def raw_messages(
        self, topics: Callable[[str], bool] | None = None
    ) -> Iterator[tuple[Channel, Message]]:
        """``(channel, mcap Message)`` in file order (= log-time order for recorder files).

        topics: optional predicate on the topic. Strict: raises RecordingError (naming the file
        and offset) at the first damage, after yielding everything before it. Lenient: skips a
        chunk that fails its CRC (or does not decompress) and goes on; stops where the framing
        breaks or the file ends; every problem goes to :attr:`problems`.
        """
        end = self._summary_start if (self.complete and self._summary_start) else self.size
        if self.complete and not self._summary_start:
            end = self.size - 8 - _FOOTER_LEN
        self.skipped_chunks = []
        skipped: dict[str, Any] | None = None  # the last chunk skipped, while its message indexes follow
        with open(self.path, "rb") as f:
            try:
                for pos, opcode, rec in _walk(f, 8, end, complete=self.complete):
                    if opcode == Opcode.MESSAGE_INDEX:
                        if skipped is not None:
                            skipped["messages"] = (skipped["messages"] or 0) + len(rec.records)
                        continue
                    skipped = None
                    if opcode == Opcode.CHUNK:
                        skipped = yield from self._chunk_messages(rec, pos, topics)
                    elif opcode == Opcode.MESSAGE:
                        yield from self._selected(rec, f"at offset {pos}", topics)
                    elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                        return
                    else:
                        self._note_record(pos, opcode, rec)
            except _Damage as d:
                self.damage_offset = d.offset
                self.discarded_bytes = max(0, end - d.offset)
                if d.truncated:
                    self.cut_chunk = _cut_chunk_header(f, d.offset, end)
                self._fail(d.text)
                return
            if not self.complete:
                # walked to the end of a file without summary: nothing was cut mid-record
                self._fail(f"file ends after {self.size} bytes without a data-end record, summary or footer (truncated)")

    def _chunk_messages(
        self, chunk: Any, pos: int, topics: Callable[[str], bool] | None
    ) -> Generator[tuple[Channel, Message], None, dict[str, Any] | None]:
        """The selected messages of the chunk at offset ``pos`` (its channels and schemas noted);
        returns the :attr:`skipped_chunks` entry if the chunk is damaged (lenient), else None."""
        try:
            inner = _chunk_records(chunk, pos)
        except _Damage as d:
            skipped: dict[str, Any] = {
                "offset": pos,
                "message_start_time": chunk.message_start_time,
                "message_end_time": chunk.message_end_time,
                "messages": None,
            }
            self.skipped_chunks.append(skipped)
            self._fail(d.text)
            return skipped
        for r in inner:
            if isinstance(r, Message):
                yield from self._selected(r, f"in chunk at offset {pos}", topics)
            elif isinstance(r, Channel):
                self.channels.setdefault(r.id, r)
            elif isinstance(r, Schema):
                self.schemas.setdefault(r.id, r)
        return None

    def _selected(self, m: Message, where: str, topics: Callable[[str], bool] | None) -> Iterator[tuple[Channel, Message]]:
        """``(channel, m)`` if its topic is selected; nothing (counted, noted) if its channel is unknown."""
        ch = self.channels.get(m.channel_id)
        if ch is None:
            self.skipped_messages += 1
            self._fail(f"message on unknown channel id {m.channel_id} {where}")
            return
        if topics is None or topics(ch.topic):
            yield ch, m

    def _note_record(self, pos: int, opcode: int, rec: Any) -> None:
        """A channel, schema or metadata record met in the data section (others are ignored)."""
        if opcode == Opcode.CHANNEL:
            self.channels.setdefault(rec.id, rec)
        elif opcode == Opcode.SCHEMA:
            self.schemas.setdefault(rec.id, rec)
        elif opcode == Opcode.METADATA and pos not in self._meta_offsets:  # one the opening did not reach (no summary)
            self._add_metadata(pos, rec)

    def _add_metadata(self, pos: int, rec: Metadata) -> None:
        """Note the metadata record at offset ``pos`` (records of one name are merged in file order)."""
        self._meta_offsets.add(pos)
        self.metadata_records.append(rec)
        self.metadata.setdefault(rec.name, {}).update(rec.metadata)

    def messages(self, topics: Callable[[str], bool] | None = None) -> Iterator[RecordedMessage]:
        """``RecordedMessage(topic, log_time, publish_time, payload)`` in log-time order (file
        order: the recorder writes non-decreasing log times). See :meth:`raw_messages`."""
        for ch, m in self.raw_messages(topics):
            yield RecordedMessage(ch.topic, m.log_time, m.publish_time, m.data)

    __iter__ = messages


def _load_metadata(rec: Recording, f: io.BufferedReader, everything: bool) -> None:
    """Fill rec.header and rec.metadata. Complete files: via the summary's metadata indexes;
    otherwise by walking the records (chunks are not decompressed) until a ``zenswarm`` record
    with the scenario is found, or to the end when ``everything``."""
    summary_mi = _load_summary(rec, f) if rec.complete and rec._summary_start else []
    # header
    try:
        first = next(_walk(f, 8, rec.size, complete=rec.complete), None)
    except _Damage as d:
        raise RecordingError(f"{rec.path}: cannot read the header record: {d.text}") from None
    if first is None or first[1] != Opcode.HEADER:
        raise RecordingError(f"{rec.path}: not an MCAP file (no header record after the magic)")
    rec.header = first[2]
    if summary_mi and not everything:
        for mi in summary_mi:
            try:
                for pos, opcode, r in _walk(f, mi.offset, mi.offset + mi.length, complete=True):
                    if opcode == Opcode.METADATA:
                        rec._add_metadata(pos, r)
            except _Damage as d:
                raise RecordingError(f"{rec.path}: metadata record is damaged: {d.text}") from None
        return
    _scan_metadata(rec, f, everything)


def _load_summary(rec: Recording, f: io.BufferedReader) -> list[MetadataIndex]:
    """Read a complete file's summary section: statistics, channels, schemas; its metadata indexes."""
    summary_mi: list[MetadataIndex] = []
    end = rec.size - 8 - _FOOTER_LEN
    try:
        for _, opcode, r in _walk(f, rec._summary_start, end, complete=True):
            if opcode == Opcode.STATISTICS:
                rec.statistics = r
            elif opcode == Opcode.CHANNEL:
                rec.channels.setdefault(r.id, r)
            elif opcode == Opcode.SCHEMA:
                rec.schemas.setdefault(r.id, r)
            elif opcode == Opcode.METADATA_INDEX:
                summary_mi.append(r)
    except _Damage as d:
        raise RecordingError(f"{rec.path}: summary section is damaged: {d.text}") from None
    return summary_mi


def _scan_metadata(rec: Recording, f: io.BufferedReader, everything: bool) -> None:
    """Walk the data section for metadata records (chunks are not decompressed): until the
    ``zenswarm`` record with the scenario, or to the end when ``everything``. Damage stops the
    walk silently: it is reported (strict: raised) when the messages are read."""
    end = rec._summary_start if rec._summary_start else rec.size
    try:
        for pos, opcode, r in _walk(f, 8, end, complete=rec.complete):
            if opcode == Opcode.METADATA:
                rec._add_metadata(pos, r)
                if r.name == METADATA_NAME and "scenario_json" in r.metadata and not everything:
                    return
            elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
                return
    except _Damage:
        return  # reported (strict: raised) when the messages are read


def read_recording(path: str | os.PathLike[str], *, strict: bool = True) -> Recording:
    """Open a recording: check it, read its metadata (scenario) and summary.

    strict (default): the file must be complete; raises :class:`RecordingError` naming the file
    if it is missing, not an MCAP file, truncated (no footer/summary: the recorder was killed),
    or its summary is corrupted; iterating raises at the first corrupted chunk (after yielding
    everything before it).

    strict=False: only a missing or non-MCAP file raises; a truncated file yields every message
    that was written out before the cut, a chunk that fails its CRC is skipped, and the damage is
    listed in ``Recording.problems`` (filled while iterating) and ``summary_problem``.
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file")
    if not p.is_file():
        raise RecordingError(f"{p}: not a regular file")
    rec = Recording(p, strict)
    try:
        with open(p, "rb") as f:
            rec.size = os.fstat(f.fileno()).st_size
            head = f.read(8)
            if head != MAGIC:
                what = "empty file" if not head else f"starts with {head[:8]!r}"
                raise RecordingError(f"{p}: not an MCAP file ({what}, expected the MCAP magic)")
            footer = _read_tail(f, rec.size)
            if isinstance(footer, str):
                why = footer
                rec.summary_problem = why
                rec.problems.append(why)
                if strict:
                    raise RecordingError(
                        f"{p}: incomplete recording: {why}. Read what it holds without strictness (`zenswarm verify` "
                        f"without --strict; strict=False), or rewrite it with `zenswarm recover {p} --out FIXED.mcap`"
                    )
            else:
                rec.complete = True
                rec._footer = footer
                rec._summary_start = footer.summary_start
            _load_metadata(rec, f, everything=False)
    except OSError as e:
        raise RecordingError(f"{p}: cannot read: {e}") from None
    except McapError as e:  # pragma: no cover - _walk wraps parsing errors already
        raise RecordingError(f"{p}: {e}") from None
    return rec

"""Recovering a damaged zenswarm recording: rewriting a truncated or corrupted MCAP file into a
complete one (``zenswarm recover``), and saying what is known about what was lost.

Built on the tolerant reader of :mod:`zenswarm.bridge.recording.mcapio` (a lenient
:func:`~zenswarm.bridge.recording.mcapio.read_recording` keeps everything written before a crash
and steps over a chunk that fails its CRC); this module only writes what that reader could read,
with :mod:`mcap.writer`. It imports the reader, never the reverse.

Errors are :class:`zenswarm.errors.RecordingError` and always name the file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from zenswarm.bridge.recording.mcapio import RECORDER_LIBRARIES, Recording, _load_metadata, _SequenceGaps, read_recording
from zenswarm.errors import RecordingError

__all__ = ["RecoverStats", "recover"]


@dataclass
class RecoverStats:
    """What :func:`recover` did, and what it can tell about what was lost.

    ``problems`` lists the damage found in the source. ``source_complete``: the source ends with
    a valid footer (and summary); ``intact``: complete and nothing found damaged. What is known
    about losses: ``discarded_bytes`` of the source could not be read (from where the framing
    broke, or the file was cut, to its end); ``lost_known`` messages are known to be lost: the
    gaps in the recorder's per-key sequence numbers (``sequence_gaps``, key -> count; only for
    files written by the zenswarm recorder) plus messages read on a channel whose definition was
    lost; ``skipped_chunks`` lists each chunk skipped as corrupted with the log-time span and
    (``messages``, from the message indexes that follow it, None if they are not there) how many
    messages it held; ``cut_chunk`` the same for a chunk cut by the end of a truncated file.
    ``tail_unknown``: the source is not complete, so the messages after ``last_log_time`` that
    the recorder never wrote (or that were in the cut record) may be lost, and their number cannot
    be known from the file.
    """

    src: str
    dst: str
    messages: int = 0
    channels: int = 0
    metadata: int = 0
    source_complete: bool = False
    intact: bool = False
    problems: list[str] = field(default_factory=list)
    first_log_time: int | None = None
    last_log_time: int | None = None
    discarded_bytes: int = 0
    lost_known: int = 0
    sequence_gaps: dict[str, int] = field(default_factory=dict)
    skipped_chunks: list[dict[str, Any]] = field(default_factory=list)
    cut_chunk: dict[str, Any] | None = None
    tail_unknown: bool = False

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)

    def losses(self) -> list[str]:
        """What is known about the messages lost, one sentence each ([] for an intact source)."""
        out: list[str] = []
        if self.lost_known:
            by = ", ".join(f"{k}: {n}" for k, n in sorted(self.sequence_gaps.items()))
            out.append(f"{self.lost_known} messages known lost" + (f" (per-key sequence gaps: {by})" if by else ""))
        for c in self.skipped_chunks:
            n = c.get("messages")
            out.append(
                f"chunk at offset {c['offset']} skipped as corrupted: "
                + (f"{n} messages" if n is not None else "an unknown number of messages")
                + f" logged over {_span(c)}"
            )
        if self.discarded_bytes:
            where = "the damaged tail" if self.source_complete else "the cut tail"
            out.append(f"{self.discarded_bytes} bytes of {where} could not be read")
        if self.cut_chunk is not None:
            out.append(
                f"the cut record is a chunk of messages logged over {_span(self.cut_chunk)} "
                "(their number is unknown: the chunk's message index was never written)"
            )
        if self.tail_unknown:
            last = "no message could be read"
            if self.last_log_time is not None:
                last = f"the last good message was logged at {self.last_log_time} ns (Unix time)"
                if self.first_log_time is not None:
                    last += f", {(self.last_log_time - self.first_log_time) / 1e9:.3f} s after the first"
            out.append(
                f"the recording was not closed: messages received after the last chunk written out are not in "
                f"the file, and how many cannot be known from it; {last}"
            )
        return out


def _span(c: dict[str, Any]) -> str:
    return f"{(c['message_end_time'] - c['message_start_time']) / 1e9:.3f} s from log time {c['message_start_time']} ns"


def _copy_messages(rec: Recording, w: Any, stats: RecoverStats, gaps: _SequenceGaps | None) -> None:
    """Write every readable message of ``rec`` to the writer ``w`` (channels and schemas
    registered at first use), counting them in ``stats`` and their sequence gaps in ``gaps``."""
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    for ch, msg in rec.raw_messages():
        cid = channel_ids.get(ch.id)
        if cid is None:
            sid = 0
            if ch.schema_id:
                sid = schema_ids.get(ch.schema_id, 0)
                sc = rec.schemas.get(ch.schema_id)
                if not sid and sc is not None:
                    sid = w.register_schema(sc.name, sc.encoding, sc.data)
                    schema_ids[ch.schema_id] = sid
            cid = w.register_channel(ch.topic, ch.message_encoding, sid, dict(ch.metadata))
            channel_ids[ch.id] = cid
        w.add_message(cid, msg.log_time, msg.data, msg.publish_time, msg.sequence)
        if gaps is not None:
            gaps.see(ch.topic, msg.sequence)
        stats.messages += 1
        if stats.first_log_time is None:
            stats.first_log_time = msg.log_time
        stats.last_log_time = msg.log_time
    stats.channels = len(channel_ids)


def recover(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str],
    *,
    chunk_size: int = 1 << 20,
) -> RecoverStats:
    """Rewrite ``src`` (possibly truncated or corrupted) into a complete MCAP file ``dst``.

    Keeps every readable message (same topic, log/publish time, sequence and payload, in the
    same order), every readable metadata record (first, before the messages), and the channels
    and schemas they use; writes a summary with statistics and indexes. ``dst`` is written to a
    temporary file beside it and renamed into place. Raises RecordingError if ``src`` is missing
    or not MCAP, or if ``dst`` is ``src``.
    """
    from mcap.writer import CompressionType, Writer

    from zenswarm import __version__

    s, d = Path(src), Path(dst)
    if d.exists() and s.exists() and os.path.samefile(s, d):
        raise RecordingError(f"{d}: recover must write to another file than its source")
    rec = read_recording(s, strict=False)
    stats = RecoverStats(src=str(s), dst=str(d), source_complete=rec.complete)
    # all metadata (a full walk: metadata may come after the first chunks)
    with open(s, "rb") as f:
        rec.metadata_records.clear()
        rec.metadata.clear()
        rec._meta_offsets.clear()
        _load_metadata(rec, f, everything=True)
    library = rec.header.library if rec.header is not None else ""
    counted = library.startswith(RECORDER_LIBRARIES)  # sequence = running count per channel
    gaps = _SequenceGaps()
    d.parent.mkdir(parents=True, exist_ok=True)
    tmp = d.with_name(d.name + ".partial")
    try:
        with open(tmp, "wb") as out:
            w = Writer(out, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            profile = rec.header.profile if rec.header is not None else ""
            w.start(profile=profile, library=f"zenswarm-recover/{__version__}")
            for m in rec.metadata_records:
                w.add_metadata(m.name, dict(m.metadata))
                stats.metadata += 1
            _copy_messages(rec, w, stats, gaps if counted else None)
            w.finish()
        os.replace(tmp, d)
    finally:
        if tmp.exists():
            tmp.unlink()
    for p in rec.problems:
        if p not in stats.problems:
            stats.problems.append(p)
    stats.intact = rec.complete and not stats.problems
    stats.sequence_gaps = dict(sorted(gaps.gaps.items()))
    stats.lost_known = sum(gaps.gaps.values()) + rec.skipped_messages
    stats.discarded_bytes = rec.discarded_bytes
    stats.skipped_chunks = list(rec.skipped_chunks)
    stats.cut_chunk = rec.cut_chunk
    stats.tail_unknown = not rec.complete
    return stats

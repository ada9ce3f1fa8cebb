"""The parts of ``zenswarm replay`` that need no Zenoh: topic filters, the swarm a recording's keys
are under (and their rewriting under another), the playback clock, loop re-stamping and the
keyboard controls. :mod:`zenswarm.bridge.replay.replay` puts them together;
:mod:`zenswarm.bridge.replay.verify` takes the swarm name from here too.

Times: sim time = a payload's ``t`` (ns, MCAP ``publish_time``); receive time = MCAP
``log_time`` (ns since the Unix epoch); wall pacing on ``time.monotonic()`` (s).
"""

from __future__ import annotations

import fnmatch
import os
import select
import threading
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import msgpack

from zenswarm.bus import wire
from zenswarm.errors import ScenarioError

if TYPE_CHECKING:
    from zenswarm.bridge.recording.mcapio import Recording

__all__ = ["TopicFilter", "original_swarm", "rewrite_topic", "restamp", "Pacer", "Controls", "KeyboardControls", "parse_keys"]


# --------------------------------------------------------------------------- topic filters


def _keyexpr(pattern: str) -> Any | None:
    import zenoh

    try:
        return zenoh.KeyExpr(pattern)
    except Exception:  # noqa: BLE001 - zenoh raises ZError: not a key expression, used as a glob only
        return None


class TopicFilter:
    """``--topic`` / ``--exclude`` patterns. A recorded key is selected if some ``--topic``
    pattern matches it (every key when there is none) and no ``--exclude`` pattern does.

    A pattern matches a key if, read as a Zenoh key expression, it intersects the key (``*`` one
    chunk, ``**`` any number), or, read as a shell glob (:func:`fnmatch.fnmatchcase`: ``*`` and
    ``?`` also cross ``/``, ``[13]`` classes), it matches the key; either against the full key
    (``swarm/demo/uav/2/state``) or against the key without its ``swarm/<name>/`` prefix
    (``uav/2/state``)."""

    def __init__(self, include: Sequence[str] = (), exclude: Sequence[str] = ()) -> None:
        self.include = list(include)
        self.exclude = list(exclude)
        self._ke = {p: _keyexpr(p) for p in self.include + self.exclude}
        self._cache: dict[str, bool] = {}

    def __bool__(self) -> bool:
        return bool(self.include or self.exclude)

    def _one(self, pattern: str, topic: str) -> bool:
        parts = topic.split("/", 2)
        names = [topic] + ([parts[2]] if len(parts) == 3 and parts[0] == "swarm" else [])
        ke = self._ke[pattern]
        for name in names:
            if fnmatch.fnmatchcase(name, pattern):
                return True
            if ke is not None:
                k = _keyexpr(name)
                if k is not None and ke.intersects(k):
                    return True
        return False

    def __call__(self, topic: str) -> bool:
        r = self._cache.get(topic)
        if r is None:
            r = (not self.include or any(self._one(p, topic) for p in self.include)) and not any(
                self._one(p, topic) for p in self.exclude
            )
            self._cache[topic] = r
        return r

    def validate(self, topics: Sequence[str], path: Any) -> None:
        """Every pattern must match some recorded key, and something must be left to replay:
        else :class:`ScenarioError` naming the flag and listing the recorded keys."""
        shown = ", ".join(topics[:20]) + (f", ... ({len(topics)} keys)" if len(topics) > 20 else "")
        for flag, pats in (("--topic", self.include), ("--exclude", self.exclude)):
            for p in pats:
                if not any(self._one(p, t) for t in topics):
                    raise ScenarioError(flag, f"{p!r} matches none of the keys recorded in {path}: {shown or 'none'}")
        if topics and not any(self(t) for t in topics):
            raise ScenarioError("--exclude", f"the filters leave none of the keys recorded in {path} to replay: {shown}")


# --------------------------------------------------------------------------- swarm names


def original_swarm(rec: Recording, first_topic: str | None) -> str | None:
    """The swarm ``rec`` was recorded from: its metadata's, else the ``<name>`` of
    ``first_topic`` when that is ``swarm/<name>/...``; None if neither says."""
    if rec.swarm:
        return rec.swarm
    if first_topic and first_topic.startswith("swarm/"):
        parts = first_topic.split("/")
        if len(parts) > 2:
            return parts[1]
    return None


def rewrite_topic(topic: str, orig: str | None, new: str | None) -> str:
    """``swarm/<orig>/rest`` -> ``swarm/<new>/rest`` (unchanged if not under ``swarm/<orig>/``)."""
    if not new or not orig or new == orig:
        return topic
    prefix = f"swarm/{orig}/"
    if topic.startswith(prefix):
        return f"swarm/{new}/" + topic[len(prefix) :]
    return topic


# --------------------------------------------------------------------------- loop re-stamping


def restamp(payload: bytes, dt_ns: int, dseq: int) -> bytes | None:
    """``payload`` with ``t`` moved on by ``dt_ns`` and ``seq`` by ``dseq`` (a msgpack map with
    integer ``t`` and ``seq``: every zenswarm message); None if it is not such a map or the new
    ``t`` would pass :data:`zenswarm.bus.wire.MAX_T_NS`. Floats stay float64, so every other field
    is the same bit for bit."""
    n = len(payload)
    try:
        o = msgpack.unpackb(payload, raw=False, strict_map_key=False, max_str_len=n, max_bin_len=n,
                            max_array_len=n, max_map_len=n, max_ext_len=n)  # fmt: skip
    except Exception:  # noqa: BLE001 - not msgpack
        return None
    if type(o) is not dict or type(o.get("t")) is not int or type(o.get("seq")) is not int:
        return None
    t = o["t"] + dt_ns
    if not 0 <= t <= wire.MAX_T_NS:
        return None
    o["t"] = t
    o["seq"] = o["seq"] + dseq
    return bytes(msgpack.packb(o, use_bin_type=True))


# --------------------------------------------------------------------------- controls


class Controls:
    """Pause, resume, step and quit, shared by the keyboard thread and the player.

    ``step()`` while paused lets the next group of messages through (those up to the next
    timestamp: one tick of a lockstep recording paced by sim time), then the replay is paused
    again."""

    def __init__(self, paused: bool = False) -> None:
        self.cond = threading.Condition()
        self.paused = paused
        self.steps = 0
        self.quit = False
        self.pauses = 0  # how often it was paused (progress, tests)
        self.on_change: Callable[[str], None] | None = None

    def _say(self, text: str) -> None:
        if self.on_change is not None:
            self.on_change(text)

    def toggle(self) -> None:
        with self.cond:
            self.paused = not self.paused
            self.pauses += self.paused
            self.cond.notify_all()
        self._say("paused (space: resume, s or right arrow: step)" if self.paused else "resumed")

    def step(self) -> None:
        with self.cond:
            if not self.paused:
                return
            self.steps += 1
            self.cond.notify_all()
        self._say("step")

    def stop(self) -> None:
        with self.cond:
            self.quit = True
            self.cond.notify_all()

    def wait_go(self, stop: threading.Event) -> str:
        """Block while paused; ``"run"`` once resumed, ``"step"`` (one step taken) or ``"stop"``."""
        with self.cond:
            while True:
                if self.quit or stop.is_set():
                    return "stop"
                if not self.paused:
                    return "run"
                if self.steps:
                    self.steps -= 1
                    return "step"
                self.cond.wait(0.1)


def parse_keys(data: bytes, controls: Controls) -> None:
    """Act on keys read from the terminal: space = pause/resume, ``s`` or right arrow
    (``ESC [ C``) = step, ``q`` = quit."""
    i = 0
    while i < len(data):
        if data[i : i + 3] in (b"\x1b[C", b"\x1bOC"):
            controls.step()
            i += 3
            continue
        c = data[i : i + 1]
        if c == b" ":
            controls.toggle()
        elif c in (b"s", b"S"):
            controls.step()
        elif c in (b"q", b"Q"):
            controls.stop()
        i += 1


class KeyboardControls:
    """Read keys from the terminal ``fd`` on a thread (:func:`parse_keys`), with the terminal in
    cbreak mode (keys arrive at once, unechoed; Ctrl-C still sends SIGINT). :meth:`close` (also
    on leaving the ``with`` block, whatever ended it) restores the terminal's settings."""

    def __init__(self, controls: Controls, fd: int) -> None:
        import termios
        import tty

        self.controls = controls
        self.fd = fd
        self.saved = termios.tcgetattr(fd)
        tty.setcbreak(fd, termios.TCSANOW)
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, name="replay-keys", daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                r, _, _ = select.select([self.fd], [], [], 0.1)
                if r:
                    data = os.read(self.fd, 64)
                    if not data:
                        return
                    parse_keys(data, self.controls)
            except (OSError, ValueError):
                return

    def close(self) -> None:
        import termios

        self._stop.set()
        self._t.join(1.0)
        try:
            termios.tcsetattr(self.fd, termios.TCSADRAIN, self.saved)
        except (OSError, termios.error):
            pass

    def __enter__(self) -> KeyboardControls:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- pacing


class Pacer:
    """When to publish a message of timestamp ``ts`` (ns: sim time or receive time): at
    ``anchor_wall + (ts - anchor_ts) / rate``; re-anchored after a pause or a step, so playback
    goes on from where it stood. ``rate`` 0: as fast as possible."""

    def __init__(self, rate: float, stop: threading.Event, controls: Controls) -> None:
        self.rate = rate
        self.stop = stop
        self.controls = controls
        self.anchor: tuple[float, int] | None = None
        self.max_lag_s = 0.0
        self.step_until: int | None = None  # while stepping: the timestamp of the group let through
        self.started: float | None = None  # monotonic time of the first message let through

    def reanchor(self, ts: int) -> None:
        self.anchor = (time.monotonic(), ts)
        if self.started is None:
            self.started = self.anchor[0]

    def wait(self, ts: int) -> bool:
        """Block until the message of timestamp ``ts`` is due; False if the replay is to stop."""
        c = self.controls
        if c.paused or c.steps:
            if self.step_until is not None and ts <= self.step_until:
                return True  # the rest of the group being stepped
            self.step_until = None
            how = c.wait_go(self.stop)
            if how == "stop":
                return False
            if how == "step":
                self.step_until = ts
                self.anchor = None
                return True
            self.anchor = None  # resumed: go on from here
        self.step_until = None
        if self.anchor is None:
            self.reanchor(ts)
            return not (self.stop.is_set() or c.quit)
        if self.rate > 0:
            w0, t0 = self.anchor
            target = w0 + (ts - t0) / 1e9 / self.rate
            while True:
                left = target - time.monotonic()
                if left <= 0 or self.stop.is_set() or c.quit:
                    break
                if c.paused:
                    return self.wait(ts)
                self.stop.wait(min(left, 0.05))
            lag = time.monotonic() - target
            if lag > self.max_lag_s:
                self.max_lag_s = lag
        return not (self.stop.is_set() or c.quit)

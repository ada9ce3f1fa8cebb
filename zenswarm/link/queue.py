"""Bandwidth and queueing on the swarm's links: a capacity in bytes/s and a bounded FIFO queue.

Pure: numpy, msgspec (through :mod:`zenswarm.bus.wire`) and the standard library; no clock, no files.
Used by :mod:`zenswarm.link.decisions` (a :class:`~zenswarm.link.decisions.FaultState` adds what this module
computes to every decision), so the simulator and the lockstep processes agree bit for bit.

Model
-----
A *queue* is either one sender's shared medium (``medium = "sender"``: every link of that sender
whose spec has a capacity shares one queue, e.g. all the copies of ``agent:3``'s reference and its
command) or one directed link (``medium = "link"``). Each queue serves its messages first come,
first served at ``capacity_Bps`` bytes/s.

* Time is the tick grid: every message of tick k enters its queue at ``a = k dt`` (the nominal
  send time, in lockstep and in realtime alike). Within a tick the messages of one queue enter in
  the order of :func:`queue_order` (kind ``cmd``, ``state``, ``leader``, ``ref``, then by
  destination).
* *Size* of a message: the length in bytes of its real msgpack encoding (:func:`message_size`,
  which calls :func:`zenswarm.bus.wire.encode` on the message the processes send at that tick; the
  floats are always packed as float64, so the size depends only on the kind, ``t`` and ``seq``).
  The paper's controller shares no extra quantities; a controller plug-in's ``x`` extras are not
  counted. Zenoh sends one copy of a publication per subscriber, so a reference heard by m
  neighbours costs m copies on its sender's medium.
* *Admission*: the queue holds the messages admitted and not yet fully sent (the one in
  transmission included) at ``a``. A queue bounded in messages (``limit_unit = "msg"``) admits the
  arriving message if it holds fewer than ``limit``; one bounded in bytes (``"B"``) admits it if
  the bytes held plus its size are at most ``limit``. Otherwise the message is dropped (reason
  ``queue``; it never leaves the sender, so it takes no capacity).
* *Delay*: an admitted message starts when the queue is free, ``start = max(a, finish of the
  previous one)``, and is sent at ``finish = start + size / capacity_Bps``; the delay it adds is
  ``finish - a`` (its wait plus its serialization time). Queue time is kept in integer
  nanoseconds (``a = k * round(dt * 1e9)``, serialization ``ceil(size * 1e9 / capacity_Bps)``
  ns), so the arithmetic is exact and ties are unambiguous. The link's own delay, jitter, loss and
  partitions (or its trace) apply after it: a message lost on the air still took its time on the
  medium.
* Tick 0 (the start-up exchange, never faulted) is not queued: queues start empty at tick 1.

Everything is a pure function of (specs, links, dt, tick): a receiver recomputes its senders'
queues without seeing their other messages, because every process sends one message per link per
tick. :class:`LinkQueues` computes them in chunks of :data:`CHUNK` ticks, in order, and keeps
each queue's content at every chunk boundary.
"""

from __future__ import annotations

import math
import re
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from zenswarm.bus import wire
from zenswarm.errors import ScenarioError

__all__ = [
    "CHUNK",
    "DEFAULT_QUEUE",
    "MEDIA",
    "QueueSpec",
    "LinkQueues",
    "parse_capacity",
    "parse_queue",
    "message_size",
    "queue_order",
    "queue_spec",
]

CHUNK = 256
"""Ticks per chunk of queue computation (a cache granularity, not part of the definition)."""
DEFAULT_QUEUE = (16, "msg")
"""Queue bound when a capacity is given without one: 16 messages."""
MEDIA = ("sender", "link")

_WIDE_TICK = 10**5  # t >= 2**32 ns and seq >= 2**16: the widest msgpack ints of any run under 2**31 ticks
_KIND_ORDER = {"cmd": 0, "state": 1, "leader": 2, "ref": 3}
_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_RATE_RE = re.compile(rf"^\s*(?P<num>[+-]?{_NUM})\s*(?P<unit>[A-Za-z]+/s|bps|kbps|Mbps)?\s*$")
_RATE_UNITS = {
    "B/s": 1.0,
    "kB/s": 1e3,
    "KB/s": 1e3,
    "MB/s": 1e6,
    "KiB/s": 1024.0,
    "MiB/s": 1024.0**2,
    "bit/s": 1 / 8,
    "kbit/s": 1e3 / 8,
    "Mbit/s": 1e6 / 8,
    "bps": 1 / 8,
    "kbps": 1e3 / 8,
    "Mbps": 1e6 / 8,
}
_SIZE_RE = re.compile(rf"^\s*(?P<num>[+-]?{_NUM})\s*(?P<unit>B|kB|KB|MB|KiB|MiB|msg)?\s*$")
_SIZE_UNITS = {"B": 1, "kB": 1000, "KB": 1000, "MB": 10**6, "KiB": 1024, "MiB": 1024**2}

Link = tuple[str, str, str]


def parse_capacity(text: str | float | int) -> float:
    """A capacity > 0 in bytes/s: ``"20kB/s"``, ``"160kbit/s"``, ``"1.5Mbps"``, ``"2KiB/s"`` or a
    bare number (bytes/s). Units: B/s, kB/s (1000 B/s), MB/s, KiB/s, MiB/s, bit/s, kbit/s, Mbit/s,
    bps, kbps, Mbps. Raises ValueError naming the bad text."""
    if isinstance(text, bool):
        raise ValueError(f"invalid capacity {text!r}: expected bytes/s such as '20kB/s'")
    if isinstance(text, (int, float)):
        v = float(text)
    elif isinstance(text, str):
        m = _RATE_RE.match(text)
        unit = m.group("unit") if m else None
        if not m or (unit is not None and unit not in _RATE_UNITS):
            raise ValueError(f"invalid capacity {text!r}: expected a number with a unit ({', '.join(_RATE_UNITS)}), e.g. '20kB/s'")
        v = float(m.group("num")) * (_RATE_UNITS[unit] if unit else 1.0)
    else:
        raise ValueError(f"invalid capacity {text!r}: expected bytes/s such as '20kB/s'")
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"invalid capacity {text!r}: must be a finite number > 0")
    return v


def parse_queue(text: str | int) -> tuple[int, str]:
    """A queue bound: an integer >= 1 of messages (``8``, ``"8"``, ``"8msg"``) or a size in bytes
    (``"4kB"``, ``"4096B"``, ``"4KiB"``). Returns ``(limit, "msg" | "B")``. Raises ValueError
    naming the bad text."""
    if isinstance(text, bool):
        raise ValueError(f"invalid queue {text!r}: expected a number of messages (8) or bytes ('4kB')")
    if isinstance(text, int):
        n, unit = text, "msg"
    elif isinstance(text, str):
        m = _SIZE_RE.match(text)
        if not m:
            raise ValueError(f"invalid queue {text!r}: expected a number of messages (8) or a size ('4kB', '4096B')")
        unit = m.group("unit") or "msg"
        v = float(m.group("num")) * (1 if unit == "msg" else _SIZE_UNITS[unit])
        if not (math.isfinite(v) and v == int(v)):
            raise ValueError(f"invalid queue {text!r}: must be a whole number of {'messages' if unit == 'msg' else 'bytes'}")
        n, unit = int(v), ("msg" if unit == "msg" else "B")
    else:
        raise ValueError(f"invalid queue {text!r}: expected a number of messages (8) or bytes ('4kB')")
    if n < 1:
        raise ValueError(f"invalid queue {text!r}: must be >= 1")
    return n, unit


@dataclass(frozen=True)
class QueueSpec:
    """Capacity of a link: capacity_Bps > 0 (bytes/s); limit >= 1 in ``limit_unit`` (``msg``:
    messages, ``B``: bytes); medium ``sender`` (one queue per sender) or ``link`` (one per link)."""

    capacity_Bps: float
    limit: int = DEFAULT_QUEUE[0]
    limit_unit: str = DEFAULT_QUEUE[1]
    medium: str = "sender"

    def __post_init__(self) -> None:
        c = self.capacity_Bps
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not (math.isfinite(c) and c > 0):
            raise ValueError(f"capacity must be a finite number > 0 bytes/s, got {c!r}")
        object.__setattr__(self, "capacity_Bps", float(c))
        if isinstance(self.limit, bool) or not isinstance(self.limit, int) or self.limit < 1:
            raise ValueError(f"queue limit must be an integer >= 1, got {self.limit!r}")
        if self.limit_unit not in ("msg", "B"):
            raise ValueError(f"queue limit unit must be 'msg' or 'B', got {self.limit_unit!r}")
        if self.medium not in MEDIA:
            raise ValueError(f"medium must be one of {', '.join(MEDIA)}, got {self.medium!r}")

    def __str__(self) -> str:
        return f"{self.capacity_Bps:g} B/s, queue {self.limit} {self.limit_unit}, medium {self.medium}"


@lru_cache(maxsize=8)
def _dt_ns(dt: float) -> int:
    return wire.t_ns(dt)


def message_size(kind: str, tick: int, dt: float) -> int:
    """Encoded size in bytes of the message of link kind ``kind`` that belongs to ``tick``, as the
    processes send it in an uninterrupted run: ``t = tick * dt`` (ns) and ``seq`` = ``tick + 1``
    (plant ``state``, leader ``leader``), ``2 tick + 1`` (an agent's ``ref``: it sends ref and cmd
    alternately from seq 1), ``2 tick + 2`` (``cmd``); float fields are float64 (9 bytes each
    whatever their value), so this is the real length."""
    t = int(tick) * _dt_ns(dt)
    z = np.zeros(3)
    k = int(tick)
    msg: wire.Message
    if kind == "state":
        msg = wire.State(t=t, seq=k + 1, q=z, v=z, rpy=z, w=z)
    elif kind == "leader":
        msg = wire.Ref(t=t, seq=k + 1, q=z, v=z)
    elif kind == "ref":
        msg = wire.Ref(t=t, seq=2 * k + 1, q=z, v=z)
    elif kind == "cmd":
        msg = wire.Cmd(t=t, seq=2 * k + 2, thrust=0.0, rpy=z, u=z, d_hat=z)
    else:
        raise ValueError(f"unknown message kind {kind!r}")
    return len(wire.encode(msg))


def _dst_key(name: str) -> tuple[int, int]:
    if name.startswith("agent:"):
        return (1, int(name.split(":")[1]))
    return (0, 0 if name == "plant" else 1)


def queue_order(links: Iterable[Link]) -> list[Link]:
    """The order in which one tick's messages of a queue enter it: by kind (cmd, state, leader,
    ref), then by destination (plant, leader, agent:1, agent:2, ...), then by source."""
    return sorted(set(links), key=lambda lk: (_KIND_ORDER.get(lk[2], 9), _dst_key(lk[1]), _dst_key(lk[0])))


_QueueContent = tuple[tuple[tuple[int, int], ...], int]
"""A queue's content at a chunk boundary: ((finish_ns, size_B) of every message held, oldest
first), finish time of the last admitted message (ns)."""


class LinkQueues:
    """Queue decisions of every link with a :class:`QueueSpec`.

    specs: ``{(src, dst, kind): QueueSpec}`` for every link of the run that has a capacity (the
    links must be all of each sender's links with a capacity, since they share its medium; links
    not given have no queue). dt: control period, s. size: message size function (default
    :func:`message_size`). Raises ValueError when the links of one sender's shared medium disagree
    on the capacity or the queue bound.
    """

    def __init__(self, specs: Mapping[Link, QueueSpec], dt: float, size: Callable[[str, int, float], int] = message_size) -> None:
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt!r}")
        self.dt = float(dt)
        self.size = size
        groups: dict[tuple[str, ...], list[Link]] = {}
        gspec: dict[tuple[str, ...], QueueSpec] = {}
        for link, spec in specs.items():
            gid = ("sender", link[0]) if spec.medium == "sender" else ("link", *link)
            prev = gspec.setdefault(gid, spec)
            if prev != spec:
                raise ValueError(f"the links of {link[0]} share its medium but disagree: {prev} vs {spec} on {link[0]}->{link[1]}")
            groups.setdefault(gid, []).append(link)
        self.groups = {g: queue_order(lks) for g, lks in groups.items()}
        self.gspec = gspec
        self._group_of: dict[Link, tuple[str, ...]] = {lk: g for g, lks in self.groups.items() for lk in lks}
        self._starts: dict[tuple[str, ...], list[_QueueContent]] = {g: [((), 0)] for g in self.groups}
        self._cache: OrderedDict[tuple[tuple[str, ...], int], dict[Link, tuple[np.ndarray, np.ndarray]]] = OrderedDict()
        self._sizes: OrderedDict[tuple[str, int], list[int]] = OrderedDict()

    def __contains__(self, link: object) -> bool:
        return link in self._group_of

    @property
    def links(self) -> list[Link]:
        return list(self._group_of)

    def spec(self, link: Link) -> QueueSpec | None:
        g = self._group_of.get(link)
        return None if g is None else self.gspec[g]

    def max_wait_s(self, link: Link) -> float:
        """An upper bound of the delay the queue adds on ``link`` (s; 0 without a queue): the
        bytes it can hold ahead of a message plus the message, over the capacity."""
        g = self._group_of.get(link)
        if g is None:
            return 0.0
        spec = self.gspec[g]
        big = max(self.size(k, _WIDE_TICK, self.dt) for k in {lk[2] for lk in self.groups[g]})
        held = spec.limit * big if spec.limit_unit == "msg" else spec.limit
        return (held + big) / spec.capacity_Bps + 1e-9 * (spec.limit + 1 if spec.limit_unit == "msg" else held + 1)  # + ns rounding

    def _chunk_sizes(self, kind: str, c: int) -> list[int]:
        key = (kind, c)
        s = self._sizes.get(key)
        if s is None:
            s = self._sizes[key] = [self.size(kind, k, self.dt) for k in range(c * CHUNK, (c + 1) * CHUNK)]
            if len(self._sizes) > 32:
                self._sizes.popitem(last=False)
        return s

    def _compute(self, g: tuple[str, ...], c: int, start: _QueueContent) -> tuple[dict[Link, tuple[np.ndarray, np.ndarray]], _QueueContent]:
        spec = self.gspec[g]
        links = self.groups[g]
        cap, limit, by_msg = spec.capacity_Bps, spec.limit, spec.limit_unit == "msg"
        dt_ns = _dt_ns(self.dt)
        ser: dict[int, int] = {}
        held: deque[tuple[int, int]] = deque(start[0])
        held_bytes = sum(s for _, s in held)
        last = start[1]
        sizes = {kind: self._chunk_sizes(kind, c) for kind in {lk[2] for lk in links}}
        out = {lk: (np.zeros(CHUNK, dtype=bool), np.zeros(CHUNK)) for lk in links}
        for i in range(CHUNK):
            k = c * CHUNK + i
            if k < 1:
                continue
            a = k * dt_ns
            while held and held[0][0] <= a:
                held_bytes -= held.popleft()[1]
            for lk in links:
                size = sizes[lk[2]][i]
                if (len(held) >= limit) if by_msg else (held_bytes + size > limit):
                    out[lk][0][i] = True
                    continue
                s_ns = ser.get(size)
                if s_ns is None:
                    s_ns = ser[size] = math.ceil(size * 1e9 / cap)
                finish = max(a, last) + s_ns
                last = finish
                held.append((finish, size))
                held_bytes += size
                out[lk][1][i] = (finish - a) / 1e9
        return out, (tuple(held), last)

    def _results(self, g: tuple[str, ...], c: int) -> dict[Link, tuple[np.ndarray, np.ndarray]]:
        key = (g, c)
        r = self._cache.get(key)
        if r is not None:
            self._cache.move_to_end(key)
            return r
        starts = self._starts[g]
        while len(starts) <= c:  # bounded: c + 1 - len(starts) chunks, computed in order
            cc = len(starts) - 1
            res, end = self._compute(g, cc, starts[cc])
            starts.append(end)
            self._store((g, cc), res)
        r = self._cache.get(key)
        if r is None:
            r, _ = self._compute(g, c, starts[c])
            self._store(key, r)
        return r

    def _store(self, key: tuple[tuple[str, ...], int], r: dict[Link, tuple[np.ndarray, np.ndarray]]) -> None:
        self._cache[key] = r
        self._cache.move_to_end(key)
        if len(self._cache) > 64 + 4 * len(self.groups):
            self._cache.popitem(last=False)

    def one(self, link: Link, tick: int) -> tuple[bool, float]:
        """(dropped by the queue, delay the queue adds in s) of ``link``'s message of ``tick``;
        (False, 0.0) for a link without a queue."""
        g = self._group_of.get(link)
        if g is None:
            return False, 0.0
        c, i = divmod(int(tick), CHUNK)
        d, w = self._results(g, c)[link]
        return bool(d[i]), float(w[i])

    def batch(self, link: Link, ticks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`one` over an int array of ticks (m,): (dropped (m,) bool, delay (m,) s)."""
        ticks = np.asarray(ticks, dtype=np.int64)
        dropped = np.zeros(ticks.shape, dtype=bool)
        wait = np.zeros(ticks.shape)
        g = self._group_of.get(link)
        if g is None:
            return dropped, wait
        for c in np.unique(ticks // CHUNK).tolist():
            sel = (ticks // CHUNK) == c
            d, w = self._results(g, int(c))[link]
            idx = ticks[sel] % CHUNK
            dropped[sel] = d[idx]
            wait[sel] = w[idx]
        return dropped, wait


def queue_spec(
    fields: tuple[str, str, str],
    capacity: str | float | int | bool | None,
    queue: str | int | None,
    medium: str | None,
    inherit: QueueSpec | None,
) -> QueueSpec | None:
    """The :class:`QueueSpec` of a table (or of the command line) that sets any of ``capacity``
    (bytes/s text or number; ``false``: no capacity on these links), ``queue`` and ``medium``;
    unset values come from ``inherit``. ``fields`` are the names of the three settings for errors
    (``("faults.capacity", "faults.queue", "faults.medium")`` or the flags). Raises
    :class:`ScenarioError` naming the field."""
    if capacity is False:
        if queue is not None or medium is not None:
            raise ScenarioError(fields[1] if queue is not None else fields[2], "set without a capacity (capacity is false)")
        return None
    if capacity is True:
        raise ScenarioError(fields[0], "expected a capacity such as \"20kB/s\" or false, got true")
    if capacity is None and queue is None and medium is None:
        return inherit
    if capacity is not None:
        try:
            cap = parse_capacity(capacity)
        except ValueError as e:
            raise ScenarioError(fields[0], str(e)) from None
    elif inherit is not None:
        cap = inherit.capacity_Bps
    else:
        raise ScenarioError(fields[1] if queue is not None else fields[2], f"needs a capacity ({fields[0]}) to queue behind")
    limit, unit = (inherit.limit, inherit.limit_unit) if inherit is not None else DEFAULT_QUEUE
    if queue is not None:
        try:
            limit, unit = parse_queue(queue)
        except ValueError as e:
            raise ScenarioError(fields[1], str(e)) from None
    med = inherit.medium if inherit is not None else "sender"
    if medium is not None:
        if medium not in MEDIA:
            raise ScenarioError(fields[2], f"unknown medium {medium!r} (allowed: {', '.join(MEDIA)})")
        med = medium
    return QueueSpec(cap, limit, unit, med)

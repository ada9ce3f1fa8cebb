"""What a process accepts of what it receives: the input guard and the decoder's counters.

Malformed input (issue 5). Every sample a process subscribed to goes through
:meth:`zenswarm.process.runtime.SwarmProcess.handle_sample`, which never raises: first the :class:`zenswarm.bus.wire.Decoder`
(bytes, size, msgpack, version, kind, fields, types, lengths, finiteness, t/seq ranges), then an
:class:`InputGuard` that judges the decoded message against what this key has delivered so far.
Each reject is counted per key and per reason (:data:`GUARD_REASONS` beside the decoder's
:data:`zenswarm.bus.wire.REASONS`) and shows up in the process's diag counters as ``rejected``,
``rejected.<reason>`` and ``rejected@<key>.<reason>`` (``<key>`` without ``swarm/<name>/``).

Sender identity. :meth:`zenswarm.process.runtime.SwarmProcess.publish` stamps every sample with the
publisher's ``zenoh.SourceInfo`` (zenoh 1.10 does not fill it in by itself: ``Sample.source_info``
is None unless the publisher sets it), and :meth:`zenswarm.process.runtime.SwarmProcess.announce` declares, beside the
process's token ``alive/<process>``, a second liveliness token ``alive/<process>/<zid>`` that
ties the process name to its session id. A receiver pins, per key, the session id of the sender
it accepts; samples from any other session are ``foreign_sender`` unless the pinned session's
token is gone and the new one holds the expected sender's token (a restarted process). The ids are
not authenticated (any client can forge a ``SourceInfo``). In an open swarm this guards against
mistakes (a process started with the wrong ``--id``, a stray tool), not an attacker. In secure mode
(``--keys``) the router's access control already admits only the right process to each key, and
to the sender token ``alive/<process>/*``; the same pinning then also turns away a second session
that presents that process's credentials (a copy started twice, stolen keys), unless it forges
the first session's id in its ``SourceInfo`` as well.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable
from typing import Any

from zenswarm.bus import wire
from zenswarm.errors import ZenswarmError

__all__ = ["InputGuard", "GUARD_REASONS", "MAX_ABS_VALUE", "GUARD_MARGIN_TICKS", "sample_sender", "expected_senders"]

GUARD_REASONS = (
    "out_of_range",  # a finite value so large it can only be garbage (|x| > MAX_ABS_VALUE)
    "foreign_sender",  # not the session pinned for this key (open mode)
    "stale",  # seq not greater than the last accepted on this key (repeated or older)
    "duplicate",  # a second message for a tick this key already delivered
    "past",  # older than the newest tick of this key, or than the lockstep/fault horizon
    "future",  # beyond the mission's end, or too far ahead of this key's stream
    "internal",  # the guard itself failed (a bug; counted, never raised)
)
"""Reasons of :class:`InputGuard` rejects (the decoder's are :data:`zenswarm.bus.wire.REASONS`)."""

MAX_ABS_VALUE = 1e9
"""Largest magnitude accepted for any vector element or scalar of a state, ref or cmd (SI units).
Finite values above it are garbage, and would overflow to inf in the controllers' arithmetic."""

GUARD_MARGIN_TICKS = 4
"""Ticks of slack on both sides of the time window, beyond the link-fault delay horizon."""

PACED_LATE_CREDIT_S = 1.0
"""Realtime input guard: a message delivered up to this late does not pull its stream's expected
tick back (:class:`InputGuard`, ``paced``), so the on-time messages after it are not ``future``."""


def sample_sender(sample: Any) -> str:
    """Session id (zid, hex) of a sample's publisher from its ``source_info``; ``""`` when the
    publisher did not set one (or the sample is not a zenoh Sample). Never raises."""
    try:
        si = sample.source_info
        if si is None:
            return ""
        return str(si.source_id.zid)
    except Exception:  # noqa: BLE001 - a fake or odd sample: anonymous
        return ""


def expected_senders(keys: wire.Keys, key: str) -> tuple[str, ...]:
    """Process names allowed to publish on ``key`` (``()`` for a key of unknown layout)::

        clock, uav/<i>/state   plant (or the MAVLink bridge in its place)
        uav/<i>/ref, cmd        agent:<i>
        leader/ref, mission     leader
        diag/<p>                p
    """
    try:
        kind, idx, proc = keys.parse(key)
    except ZenswarmError:
        return ()
    if kind in ("clock", "state"):
        return ("plant", "bridge")
    if kind in ("ref", "cmd") and idx is not None:
        return (wire.agent(idx),)
    if kind in ("leader_ref", "mission"):
        return ("leader",)
    if kind == "diag" and proc is not None:
        return (proc,)
    return ()


def _implausible(msg: Any) -> bool:
    """True if a decoded state, ref or cmd holds a finite value above :data:`MAX_ABS_VALUE`."""
    big = MAX_ABS_VALUE
    vecs = getattr(type(msg), "_vecs", ())
    base = getattr(msg, vecs[0][0]).base if vecs else None
    if base is not None and base.shape == (3 * len(vecs),) and all(getattr(msg, n).base is base for n, _ in vecs):
        # a decoded message: its vectors are views of one array (zenswarm.bus.wire.decode)
        vals = base.tolist()
        thrust = getattr(msg, "thrust", 0.0)
        return not (-big <= min(vals) and max(vals) <= big and -big <= thrust <= big)
    for name in ("q", "v", "rpy", "w", "u", "d_hat"):
        a = getattr(msg, name, None)
        if a is None:
            continue
        x, y, z = a.tolist()
        if not (-big <= x <= big and -big <= y <= big and -big <= z <= big):
            return True
    thrust = getattr(msg, "thrust", None)
    return thrust is not None and not -big <= thrust <= big


class _KeyState:
    """What one key has delivered: pinned sender, newest seq and tick, recent ticks."""

    __slots__ = ("pin", "last_seq", "last_tick", "last_rx", "recent", "ahead", "ahead_rx")

    def __init__(self) -> None:
        self.pin: str | None = None
        self.last_seq: int | None = None
        self.last_tick: int | None = None  # None: no stream position (new key, new sender, or a gap)
        self.last_rx = 0.0
        self.recent: deque[int] = deque(maxlen=64)
        self.ahead: int | None = None  # tick of the last message refused as too far ahead
        self.ahead_rx = 0.0

    def reset(self) -> None:
        self.pin = None
        self.last_seq = None
        self.last_tick = None
        self.recent.clear()
        self.ahead = None


class InputGuard:
    """Checks a decoded message against what its key has delivered; counts rejects.

    Called after the decoder, once per sample, with the key, the key's expected senders (process
    names, see :func:`expected_senders`), the message's tick, seq and the publishing session's
    id. In this order (the first failing check names the reject):

    1. ``out_of_range``: a state, ref or cmd value above :data:`MAX_ABS_VALUE` (finite garbage).
    2. ``foreign_sender`` (only with ``check_sender``): the key is pinned to the first session it
       accepted; another session is rejected, unless the pinned one no longer holds a liveliness
       token and the new one does (or nobody does yet): a restarted process, accepted again with a
       fresh stream. Before anything is pinned, a session is rejected if others hold the expected
       sender's token and it does not. Tokens are reported with :meth:`token`. Without
       ``check_sender`` (for a receiver that trusts whoever may publish on the key; swarm
       processes always check) a new session on a key is that process restarted: a fresh
       stream, no reject.
    3. ``stale``: seq not greater than the newest accepted on this key (repeated or older seq).
    4. ``duplicate``: a tick this key already delivered (the last 64 kept).
    5. ``past``: older than this key's newest tick, or (lockstep, once ticking) older than
       ``now_tick() - window`` with ``window = horizon_ticks + margin_ticks``: a legitimate input
       is never later than the link-fault horizon unless the receiver already gave up on it.
    6. ``future``: beyond ``n_ticks + window`` (the mission's end), or more than ``window`` ticks
       plus one tick per ``growth_period_s`` of silence ahead of ``max(this key's newest tick,
       now_tick())``. The window is relative to the key's own stream, not only to the receiver's
       tick: in lockstep a receiver may legitimately lag its senders by many ticks (a partitioned
       or slow agent whose inputs the others no longer wait for), and rejecting the plant's next
       state there would stall it forever. A stream's first message (new key, new sender, or
       after :meth:`discontinuity`) is bounded by the mission's end only: a restarted agent joins
       at whatever tick the plant has reached. A lockstep stream never skips a tick; a realtime
       one does (a process catching up runs faster than the wall clock for a while), so a jump is
       taken when the next message agrees with the one refused (within ``window`` of it): one
       lost message per jump, and a single stray far tick moves nothing.
       With ``paced`` (realtime: every stream's tick follows the wall clock) the stream's
       expected position is not pulled back by a message that arrived late: a message delivered
       up to :data:`PACED_LATE_CREDIT_S` late (a host or router that stalled while the sender
       went on, then skipped the ticks it missed) keeps the position its on-time predecessors
       had, so the on-time message after it is not ``future``.

    Accepted messages move the key's stream (pin, seq, tick). ``clock`` is injectable (tests).
    Thread-safe.
    """

    def __init__(
        self,
        *,
        dt_ns: int,
        n_ticks: int,
        horizon_ticks: int = 0,
        margin_ticks: int = GUARD_MARGIN_TICKS,
        growth_period_s: float = 0.01,
        paced: bool = False,
        check_sender: bool = True,
        now_tick: Callable[[], int | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        max_keys: int = 1024,
        prefix: str = "",
    ) -> None:
        self.dt_ns = int(dt_ns)
        self.window = int(horizon_ticks) + int(margin_ticks)
        self.cap = int(n_ticks) + self.window
        self.growth_period_s = max(float(growth_period_s), 1e-6)
        self.paced = paced
        self.check_sender = check_sender
        self.now_tick = now_tick
        self.clock = clock
        self.max_keys = max_keys
        self._plen = len(prefix)
        self._lock = threading.Lock()
        self._keys: dict[str, _KeyState] = {}
        self._holders: dict[str, set[str]] = defaultdict(set)  # process name -> zids holding its token
        self._gone: dict[str, deque[str]] = defaultdict(lambda: deque(maxlen=64))  # zids whose token went away
        self.accepted = 0
        self.reasons: dict[str, int] = {}
        self.by_key: dict[tuple[str, str], int] = {}
        self.last_reject: str | None = None

    # ------------------------------------------------------------------ sender tokens
    def token(self, name: str, zid: str, alive: bool) -> None:
        """``alive/<name>/<zid>`` appeared (alive) or went away. A pinned session whose token
        comes back (a client that reconnected) restarts its keys' streams (messages were lost)."""
        with self._lock:
            holders = self._holders[name]
            if alive:
                back = zid not in holders and zid in self._gone[name]
                holders.add(zid)
                if back:
                    for st in self._keys.values():
                        if st.pin == zid:
                            st.last_tick = None
            else:
                holders.discard(zid)
                gone = self._gone[name]
                if zid not in gone:
                    gone.append(zid)

    def discontinuity(self) -> None:
        """Messages may have been lost on every key (our own link to the router came back):
        each key's next message starts a fresh stream position (pins and seqs are kept)."""
        with self._lock:
            for st in self._keys.values():
                st.last_tick = None

    def _holders_of(self, senders: tuple[str, ...]) -> set[str]:
        out: set[str] = set()
        for s in senders:
            h = self._holders.get(s)
            if h:
                out |= h
        return out

    def _was_holder(self, senders: tuple[str, ...], zid: str) -> bool:
        return any(zid in self._gone[s] for s in senders if s in self._gone)

    # ------------------------------------------------------------------ the check
    def check(self, key: str, senders: tuple[str, ...], tick: int, msg: Any, zid: str) -> str | None:
        """None if accepted (the key's stream moves on), else the reject reason (counted)."""
        try:
            if self._accept_next(key, tick, msg, zid):
                return None
        except Exception:  # noqa: BLE001 - the full check below says what is wrong
            pass
        detail = ""
        try:
            reason = self._check(key, senders, int(tick), msg, str(zid))
            if reason is not None:
                st = self._keys.get(key)
                detail = f" (tick {tick} seq {getattr(msg, 'seq', '?')} from {zid or '?'}"
                if st is not None:
                    detail += f"; key at tick {st.last_tick} seq {st.last_seq} from {st.pin or '?'}"
                detail += ")"
        except Exception as e:  # noqa: BLE001 - never raise into a callback
            reason, detail = "internal", f": {type(e).__name__}: {e}"
        if reason is None:
            with self._lock:
                self.accepted += 1
        else:
            self.count(key, reason)
            if detail:
                self.last_reject = f"{key}: {reason}{detail}"  # what count() set, with the detail
        return reason

    def _accept_next(self, key: str, tick: Any, msg: Any, zid: Any) -> bool:
        """The usual message, accepted at once: from the session pinned for its key, in order
        (seq and tick past the stream's), within the window. Exactly what :meth:`_check` would
        accept, with fewer steps; False (nothing changed) sends the message through
        :meth:`_check`."""
        if type(tick) is not int or type(zid) is not str or _implausible(msg):
            return False
        seq = msg.seq
        with self._lock:
            st = self._keys.get(key)
            if st is None or st.pin != zid or st.last_seq is None or st.last_tick is None:
                return False
            last_tick = st.last_tick
            if type(seq) is not int or seq <= st.last_seq or tick < last_tick or tick > self.cap or tick in st.recent:
                return False
            now = self.clock()
            c = self.now_tick() if self.now_tick is not None else None
            if c is not None:
                if tick < c - self.window:
                    return False
                if c > last_tick:
                    last_tick = c
            if tick > last_tick + self.window + (now - st.last_rx) / self.growth_period_s:
                return False
            st.last_rx = self._rx_after(st, tick, now)
            st.last_seq = seq
            st.last_tick = tick
            st.recent.append(tick)
            st.ahead = None
            self.accepted += 1
            return True

    def _check(self, key: str, senders: tuple[str, ...], tick: int, msg: Any, zid: str) -> str | None:
        if _implausible(msg):
            return "out_of_range"
        seq = int(msg.seq)
        with self._lock:
            st = self._keys.get(key)
            if st is None:
                if len(self._keys) >= self.max_keys:
                    return "internal"
                st = self._keys[key] = _KeyState()
            now = self.clock()
            reason, repin = self._sender_verdict(st, senders, zid)
            if reason is None:
                reason = self._order_verdict(st, repin or st.pin is None, tick, seq, now)
            if reason is not None:
                return reason
            # accepted
            if repin:
                st.reset()
            st.last_rx = self._rx_after(st, tick, now)
            st.pin = zid
            st.last_seq = seq
            st.last_tick = tick
            st.recent.append(tick)
            st.ahead = None
            return None

    def _sender_verdict(self, st: _KeyState, senders: tuple[str, ...], zid: str) -> tuple[str | None, bool]:
        """Check 2 (``foreign_sender``): (reject reason or None, whether the key re-pins to
        ``zid``: a restarted process). Under the lock."""
        if not self.check_sender:
            return None, st.pin is not None and zid != st.pin  # a new session is the process restarted
        if st.pin is None:
            holders = self._holders_of(senders)
            return ("foreign_sender" if holders and zid not in holders else None), False
        if zid == st.pin:
            return None, False
        holders = self._holders_of(senders)
        if st.pin in holders:
            return "foreign_sender", False
        if zid in holders or (not holders and self._was_holder(senders, st.pin)):
            return None, True  # the pinned session is gone: a restarted process
        return "foreign_sender", False

    def _order_verdict(self, st: _KeyState, fresh: bool, tick: int, seq: int, now: float) -> str | None:
        """Checks 3-6 (``stale``, ``duplicate``, ``past``, ``future``) of a message on a key whose
        stream is ``st`` (``fresh``: a new stream, nothing to compare with). Under the lock."""
        if not fresh:
            if st.last_seq is not None and seq <= st.last_seq:
                return "stale"
            if tick in st.recent:
                return "duplicate"
        last_tick = None if fresh else st.last_tick
        if last_tick is not None and tick < last_tick:
            return "past"
        c = self.now_tick() if self.now_tick is not None else None
        if c is not None and tick < c - self.window:
            return "past"
        if tick > self.cap:
            return "future"
        if last_tick is not None and self._too_far_ahead(st, tick, last_tick if c is None else max(last_tick, c), now):
            return "future"
        return None

    def _rx_after(self, st: _KeyState, tick: int, now: float) -> float:
        """The stream's ``last_rx`` once ``tick`` is accepted at ``now`` (under the lock): the wall
        time at which the stream was at ``tick``. Without ``paced``, or for a stream's first
        message, ``now``. With ``paced`` a stream moves one tick per ``growth_period_s``, so a
        message that arrived late (its tick behind where the stream's earlier messages put it by
        now) keeps that earlier position, for at most :data:`PACED_LATE_CREDIT_S` of lateness."""
        if not self.paced or st.last_tick is None or tick < st.last_tick:
            return now
        on_time = st.last_rx + (tick - st.last_tick) * self.growth_period_s
        return max(min(now, on_time), now - PACED_LATE_CREDIT_S)

    def _too_far_ahead(self, st: _KeyState, tick: int, base: int, now: float) -> bool:
        """Check 6 relative to the stream: more than ``window`` ticks (plus one per
        ``growth_period_s`` of silence) past ``base``, unless a second message agrees with the
        one refused last (the stream did jump)."""
        growth = (now - st.last_rx) / self.growth_period_s
        if tick <= base + self.window + growth:
            return False
        a = st.ahead
        if a is None or not a < tick <= a + self.window + (now - st.ahead_rx) / self.growth_period_s:
            st.ahead, st.ahead_rx = tick, now
            return True
        return False

    # ------------------------------------------------------------------ counters
    def count(self, key: str, reason: str) -> None:
        """Count a reject of ``reason`` on ``key``."""
        with self._lock:
            self.reasons[reason] = self.reasons.get(reason, 0) + 1
            k = (key, reason)
            if k in self.by_key or len(self.by_key) < self.max_keys:
                self.by_key[k] = self.by_key.get(k, 0) + 1
            self.last_reject = f"{key}: {reason}"

    @property
    def rejected(self) -> int:
        """Total rejects of the guard."""
        with self._lock:
            return sum(self.reasons.values())

    def counters(self) -> dict[str, int]:
        """``rejected.<reason>`` for every guard reason and ``rejected@<key>.<reason>`` for the
        keys that had rejects (``<key>`` without the ``swarm/<name>/`` prefix)."""
        with self._lock:
            out = {f"rejected.{r}": self.reasons.get(r, 0) for r in GUARD_REASONS}
            for (key, reason), n in self.by_key.items():
                out[f"rejected@{key[self._plen:]}.{reason}"] = n
        return out

    def pinned(self) -> dict[str, str]:
        """key -> pinned sender session id (diagnostics)."""
        with self._lock:
            return {k: st.pin for k, st in self._keys.items() if st.pin is not None}


class _KeyedDecoder(wire.Decoder):
    """:class:`zenswarm.bus.wire.Decoder` that also counts rejects per (key, reason)."""

    def __init__(self, **kw: Any) -> None:
        super().__init__(**kw)
        self.by_key: dict[tuple[str, str], int] = {}

    def _reject(self, key: str, reason: str, text: str) -> None:
        super()._reject(key, reason, text)
        k = (str(key), reason)
        if k in self.by_key or len(self.by_key) < self.max_keys:
            self.by_key[k] = self.by_key.get(k, 0) + 1

    def reject(self, key: str, reason: str, text: str) -> None:
        """Count a payload rejected before decoding (e.g. unreadable sample)."""
        self._reject(key, reason, text)

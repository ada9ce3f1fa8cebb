"""What every swarm process shares: its Zenoh session, an inbox of decoded inputs, lockstep waits,
diagnostics, liveliness, and a clean exit on SIGINT/SIGTERM.

The process shells (``agents/process.py``, ``leader/process.py``, ``plant/process.py``) are thin:
decode -> pure step -> encode. This module is the glue they share; messages cross the network in
:mod:`zenswarm.bus` (sessions) and :mod:`zenswarm.bus.wire` (keys and payloads).

Malformed input (issue 5). Every sample a process subscribed to goes through
:meth:`SwarmProcess.handle_sample`, which never raises: first the :class:`zenswarm.bus.wire.Decoder`
(bytes, size, msgpack, version, kind, fields, types, lengths, finiteness, t/seq ranges), then an
:class:`InputGuard` that judges the decoded message against what this key has delivered so far.
Each reject is counted per key and per reason (:data:`GUARD_REASONS` beside the decoder's
:data:`zenswarm.bus.wire.REASONS`) and shows up in the process's diag counters as ``rejected``,
``rejected.<reason>`` and ``rejected@<key>.<reason>`` (``<key>`` without ``swarm/<name>/``).

Sender identity. :meth:`SwarmProcess.publish` stamps every sample with the
publisher's ``zenoh.SourceInfo`` (zenoh 1.10 does not fill it in by itself: ``Sample.source_info``
is None unless the publisher sets it), and :meth:`SwarmProcess.announce` declares, beside the
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

import gc
import os
import signal
import sys
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import zenoh

from zenswarm import bus
from zenswarm.bus import wire
from zenswarm.errors import EXIT_PLUGIN_FAILED, PluginFailure, ScenarioError, ZenswarmError
from zenswarm.process import rtsched, security
from zenswarm.scenario.config import Scenario, load_scenario, scenario_from_dict

if TYPE_CHECKING:
    from zenswarm.link import FaultPlan

__all__ = ["Inbox", "SwarmProcess", "ProcessOptions", "run_process", "LoopStats", "WallClock", "sleep_until",
           "InputGuard", "GUARD_REASONS", "sample_sender", "expected_senders", "GcPolicy", "gc_policy",
           "gc_startup_done", "gc_safe_point", "GC_ENV"]

# Lockstep: a missing input is waited for this long (wall clock) before it counts as a drop.
DEFAULT_LOCKSTEP_TIMEOUT_S = 5.0

DEFAULT_ROUTER_LOST_TIMEOUT_S = 30.0
"""``--router-lost-timeout``: wall seconds a process waits for its router to come back once zenoh
has closed the link to it (the session lease, 10 s, ran out) before it gives up, stops and exits
with :data:`EXIT_ROUTER_LOST`: the router, or the host it runs on, is gone for good."""

EXIT_ROUTER_LOST = 3
"""Exit status of a process that gave up on its router (``--router-lost-timeout``)."""

# Zenoh runs Python callbacks on its own threads; with the default 5 ms GIL switch interval a
# callback thread can keep the main loop waiting for the GIL for milliseconds per message.
SWITCH_INTERVAL_S = 0.0002

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

CLOCK_EVERY_TICKS = 4
"""Lockstep: the plant publishes ``clock`` at every this many ticks (and at the last one), not at
every tick. Only the leader and the supervisor read it; the agents' clock is their own state."""

LEADER_AHEAD_TICKS = 4
"""Lockstep: the leader publishes its reference up to this many ticks past the newest clock. Its
trajectory does not depend on the swarm, so it may run ahead; at least :data:`CLOCK_EVERY_TICKS`
keeps every leader ref published before the ticks that need it."""

assert LEADER_AHEAD_TICKS >= CLOCK_EVERY_TICKS <= GUARD_MARGIN_TICKS


# --------------------------------------------------------------------------- the garbage collector
GC_ENV = "ZENSWARM_GC"
"""Environment variable choosing how a swarm process manages Python's cyclic garbage collector:
``managed`` (default, :class:`GcPolicy`) or ``python`` (CPython's own automatic collector, as
before issue 16: for comparisons, ``bench/soak.py --gc python``)."""

GC_YOUNG_LIMIT = 2000
"""Managed collector: a safe point collects generation 0 once this many GC-tracked objects were
allocated and not freed since the last collection (``gc.get_count()[0]``; CPython's own threshold
is 700). A tick that makes no cyclic garbage frees what it allocates and never gets here."""

GC_OLDER_LIMIT = 10
"""Managed collector: generation 1 is collected every this many generation-0 collections, and
generation 2 every this many generation-1 ones (CPython's own cadence)."""

GC_FORCE_LIMIT = 20 * GC_YOUNG_LIMIT
"""Managed collector: above this many young objects a safe point collects even without slack
(bounded memory first: a loop that is always late still collects)."""

GC_MIN_SLACK_S = 0.002
"""Managed collector: a realtime loop collects only when at least this much time is left before
its next deadline (a young generation of :data:`GC_YOUNG_LIMIT` objects takes well under 1 ms)."""


class GcPolicy:
    """How a swarm process manages Python's cyclic garbage collector (issue 16, item 5).

    CPython's automatic collector runs whenever allocations outnumber frees by 700, in the middle
    of whatever the process is doing; every few hundred of those it scans every object the
    process holds (numpy, zenoh, msgpack, the scenario: a few hundred thousand objects) and stalls
    a realtime loop for tens of milliseconds. The swarm processes of a realtime flight instead
    (a lockstep flight has no deadline and keeps CPython's collector, faster there):

    1. after start-up (:meth:`startup_done`: imports, scenario, session, subscriptions), collect
       once, then ``gc.freeze()``: everything alive then is moved to the permanent generation and
       is never scanned again; then ``gc.disable()``: no automatic collection;
    2. collect explicitly at safe points only (:meth:`safe_point`): the end of a realtime loop's
       period before it sleeps (:meth:`WallClock.wait`), the end of a lockstep tick
       (:class:`Lockstep`), the supervisor's and the recorder's loops. Generation 0 once
       :data:`GC_YOUNG_LIMIT` young objects have accumulated, older generations every
       :data:`GC_OLDER_LIMIT` collections of the younger one; in a realtime loop only with at
       least :data:`GC_MIN_SLACK_S` left before the deadline (or above :data:`GC_FORCE_LIMIT`).
       What survives a full (generation 2) collection is frozen too, so a process whose live
       data grows (the supervisor's flight record) never rescans it: no full collection gets
       longer as the flight goes on. The price: a frozen object that later becomes cyclic
       garbage is never freed; the ticks make none (below).

    The ticks make no cyclic garbage (``tests/test_gc.py``), so in flight the young generation
    barely grows and collections are rare and short. ``ZENSWARM_GC=python`` (:data:`GC_ENV`)
    keeps CPython's own collector, for comparison. Counters (:meth:`counters`, in each process's
    diagnostics): ``gc.collections``, ``gc.collected`` (unreachable objects found: cyclic
    garbage), ``gc.max_ms``, ``gc.total_ms``, ``gc.frozen`` (objects frozen at start-up).
    """

    def __init__(self, mode: str | None = None) -> None:
        mode = mode if mode is not None else os.environ.get(GC_ENV, "managed") or "managed"
        if mode not in ("managed", "python"):
            raise ScenarioError(GC_ENV, f"must be 'managed' or 'python', got {mode!r}")
        self.mode = mode
        self.active = False  # startup_done() ran in managed mode
        self.collections = 0
        self.collected = 0
        self.total_s = 0.0
        self.max_s = 0.0
        self.frozen = 0
        self._lock = threading.Lock()

    def startup_done(self) -> None:
        """Start-up is over: collect, freeze what is alive, disable the automatic collector
        (managed mode; idempotent, a second call freezes what start-up added since)."""
        if self.mode != "managed":
            return
        with self._lock:
            gc.collect()
            gc.freeze()
            gc.disable()
            self.frozen = gc.get_freeze_count()
            self.active = True

    def safe_point(self, slack_s: float = float("inf")) -> int:
        """A moment where a collection stalls nothing (``slack_s``: seconds left before the
        caller's next deadline). Collects what is due (see the class); returns the number of
        unreachable objects found (0 if nothing was collected)."""
        if not self.active:
            return 0
        c0, c1, c2 = gc.get_count()
        if c0 < GC_YOUNG_LIMIT or (slack_s < GC_MIN_SLACK_S and c0 < GC_FORCE_LIMIT):
            return 0
        gen = 2 if c2 >= GC_OLDER_LIMIT else 1 if c1 >= GC_OLDER_LIMIT else 0
        with self._lock:
            t0 = time.perf_counter()
            found = gc.collect(gen)
            if gen == 2:
                gc.freeze()  # what survived a full collection is long-lived: never scan it again
            dt = time.perf_counter() - t0
            self.collections += 1
            self.collected += found
            self.total_s += dt
            self.max_s = max(self.max_s, dt)
        return found

    def counters(self) -> dict[str, float]:
        """``gc.*`` counters for the diagnostics (see the class)."""
        return {"gc.managed": float(self.active), "gc.collections": self.collections, "gc.collected": self.collected,
                "gc.max_ms": 1e3 * self.max_s, "gc.total_ms": 1e3 * self.total_s, "gc.frozen": self.frozen}


_GC: GcPolicy | None = None


def gc_policy() -> GcPolicy:
    """This process's :class:`GcPolicy` (created on first use from :data:`GC_ENV`)."""
    global _GC
    if _GC is None:
        _GC = GcPolicy()
    return _GC


def gc_startup_done() -> None:
    """:meth:`GcPolicy.startup_done` of this process's policy."""
    gc_policy().startup_done()


def gc_safe_point(slack_s: float = float("inf")) -> int:
    """:meth:`GcPolicy.safe_point` of this process's policy."""
    return gc_policy().safe_point(slack_s)


class Inbox:
    """Decoded messages by key: the latest one, and (for lockstep) one per tick index.

    Filled from Zenoh callbacks (other threads); read by the process loop. ``wait`` blocks until
    every (key, tick) needed is present or a deadline passes.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.latest_rx: dict[str, float] = {}
        self._by_tick: dict[str, dict[int, Any]] = defaultdict(dict)

    def put(self, key: str, tick: int, msg: Any) -> None:
        with self._cond:
            self.latest[key] = msg
            self.latest_rx[key] = time.monotonic()
            self._by_tick[key][tick] = msg
            self._cond.notify_all()

    def get(self, key: str, tick: int) -> Any | None:
        # No lock: a dict lookup is atomic under the GIL, and this one inserts nothing (the
        # lockstep checks call it a few times per message: the lock cost more than the rest).
        d = self._by_tick.get(key)
        return None if d is None else d.get(tick)

    def wait(self, needs: list[tuple[str, int]], timeout_s: float, stop: threading.Event | None = None) -> list[tuple[str, int]]:
        """Wait until every (key, tick) in ``needs`` has arrived; return the ones still missing."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                missing = [(k, t) for (k, t) in needs if t not in self._by_tick[k]]
                if not missing:
                    return []
                left = deadline - time.monotonic()
                if left <= 0 or (stop is not None and stop.is_set()):
                    return missing
                self._cond.wait(min(left, 0.2))

    def forget_before(self, tick: int) -> None:
        """Drop per-tick entries older than ``tick`` (bounded memory)."""
        with self._cond:
            for d in self._by_tick.values():
                for t in [t for t in d if t < tick]:
                    del d[t]

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()


class LoopStats:
    """Realtime loop timing: period jitter and missed deadlines.

    A loop's figures cover its flight: a loop that starts before it has anything to act on (an
    agent before the plant's first state, the leader before the first clock) calls
    :meth:`flight_started` when it first has, which drops the waiting ticks (counted in
    ``idle_ticks``): they are start-up, while the other processes still import and connect,
    not control deadlines."""

    def __init__(self, period_s: float) -> None:
        self.period = period_s
        self.ticks = 0
        self.missed = 0
        self.max_jitter_s = 0.0
        self._sum_jitter = 0.0
        self.idle_ticks = 0
        self._flying = False

    def flight_started(self) -> None:
        """The loop has work from now on: start the figures afresh (once; later calls do nothing)."""
        if self._flying:
            return
        self._flying = True
        self.idle_ticks += self.ticks
        self.ticks = self.missed = 0
        self.max_jitter_s = self._sum_jitter = 0.0

    def record(self, lateness_s: float) -> None:
        self.ticks += 1
        j = abs(lateness_s)
        self._sum_jitter += j
        self.max_jitter_s = max(self.max_jitter_s, j)
        if lateness_s > self.period:
            self.missed += 1

    def as_dict(self) -> dict[str, float]:
        return {
            "loop_ticks": self.ticks,
            "missed_deadlines": self.missed,
            "jitter_max_ms": 1e3 * self.max_jitter_s,
            "jitter_mean_ms": 1e3 * self._sum_jitter / self.ticks if self.ticks else 0.0,
            "idle_ticks": self.idle_ticks,
        }


def sleep_until(deadline: float, stop: threading.Event | None = None, slice_s: float = float("inf")) -> None:
    """Sleep until ``time.monotonic()`` reaches ``deadline`` (s); at once if it has. With ``stop``,
    sleep in slices of at most ``slice_s`` and return early once it is set."""
    while True:
        left = deadline - time.monotonic()
        if left <= 0 or (stop is not None and stop.is_set()):
            return
        time.sleep(min(left, slice_s))


class WallClock:
    """A fixed-rate loop on the wall clock (``time.monotonic``): the one every realtime loop uses.

    :meth:`wait` sleeps until the next deadline, records the lateness in :attr:`stats`
    (:class:`LoopStats`) and moves the deadline one ``period_s`` on. The first deadline is now, or
    one period from now with ``first_wait`` (a loop that works first, then waits). A late loop
    catches up (deadlines stay on the grid) unless ``catch_up`` is False: then the next deadline is
    one period after the wait ended (pacing: never faster than real time, never in a burst). With
    ``resync_after_s``, a loop later than that starts its grid again one period from now (counted
    in :attr:`resyncs`) instead of catching up in a burst::

        clock = WallClock(dt, proc.stop)
        while clock.wait():
            ...  # one period's work
    """

    def __init__(self, period_s: float, stop: threading.Event | None = None, *, first_wait: bool = False,
                 catch_up: bool = True, resync_after_s: float | None = None) -> None:
        self.period = period_s
        self.stop = stop
        self.catch_up = catch_up
        self.resync_after_s = resync_after_s
        self.resyncs = 0
        self.stats = LoopStats(period_s)
        self.next = time.monotonic() + (period_s if first_wait else 0.0)

    def wait(self) -> bool:
        """Sleep until the next deadline; False (at once) if ``stop`` is set."""
        if self.stop is not None and self.stop.is_set():
            return False
        gc_safe_point(self.next - time.monotonic())  # the period's work is done: collect in its slack
        sleep_until(self.next)
        now = time.monotonic()
        late = now - self.next
        self.stats.record(late)
        resync = self.resync_after_s is not None and late > self.resync_after_s
        self.resyncs += resync
        self.next = now + self.period if resync or not self.catch_up else self.next + self.period
        return True


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


@dataclass(frozen=True)
class ProcessOptions:
    """What every swarm process is started with (the common flags, typed; the command line is
    turned into these at the edge, :mod:`zenswarm.compose.roles`).

    scenario: scenario TOML (None: fetched from the leader's mission key). swarm: key prefix
    ``swarm/<swarm>``. connect: Zenoh router endpoints (empty: ``tcp/127.0.0.1:7447``).
    realtime: wall clock, latest value wins (else lockstep). lockstep_timeout: wall seconds an
    input is waited for before it counts as a drop. keys, tls: credentials of a secured router
    (:mod:`zenswarm.process.security`). link_delay, link_jitter, link_loss, partition, link_range,
    link_fade, link_capacity, link_queue, link_medium, link_trace: the whole-swarm link faults
    (:mod:`zenswarm.link.swarm`); seed: disturbances and fault decisions (None: the
    scenario's). controller, planner, plant_model: plug-in names overriding the scenario's
    (:func:`zenswarm.scenario.plugins.select`; None: the scenario's). rt_priority: realtime only, run
    the process's threads under ``SCHED_FIFO`` at this priority once start-up is over
    (:mod:`zenswarm.process.rtsched`; None: the fair scheduler). router_lost_timeout: wall seconds to wait
    for a lost router to come back before giving up (:data:`DEFAULT_ROUTER_LOST_TIMEOUT_S`).
    kill_at_tick: lockstep only, the process SIGKILLs itself just before it runs this tick
    (:class:`Lockstep`; ``zenswarm up --kill``), so the fault falls on the same tick in every run.
    """

    scenario: Path | None = None
    swarm: str = "default"
    connect: tuple[str, ...] = ()
    realtime: bool = False
    lockstep_timeout: float = DEFAULT_LOCKSTEP_TIMEOUT_S
    keys: Path | None = None
    tls: bool = False
    link_delay: str | None = None
    link_jitter: str | None = None
    link_loss: str | None = None
    partition: tuple[str, ...] = ()
    seed: int | None = None
    link_range: str | None = None
    link_fade: str | None = None
    controller: str | None = None
    link_capacity: str | None = None
    link_queue: str | None = None
    link_medium: str | None = None
    link_trace: str | None = None
    planner: str | None = None
    rt_priority: int | None = None
    plant_model: str | None = None
    router_lost_timeout: float = DEFAULT_ROUTER_LOST_TIMEOUT_S
    kill_at_tick: int | None = None

    @classmethod
    def of(cls, obj: Any) -> ProcessOptions:
        """The options read off any object with these attribute names (e.g. a parsed command
        line); a missing or None attribute takes the default."""
        if isinstance(obj, ProcessOptions):
            return obj

        def get(name: str, default: Any) -> Any:
            value = getattr(obj, name, None)
            return default if value is None else value

        return cls(
            scenario=get("scenario", None),
            swarm=str(get("swarm", "default")),
            connect=tuple(get("connect", ())),
            realtime=bool(get("realtime", False)),
            lockstep_timeout=float(get("lockstep_timeout", DEFAULT_LOCKSTEP_TIMEOUT_S)),
            keys=get("keys", None),
            tls=bool(get("tls", False)),
            link_delay=get("link_delay", None),
            link_jitter=get("link_jitter", None),
            link_loss=get("link_loss", None),
            partition=tuple(get("partition", ())),
            seed=get("seed", None),
            link_range=get("link_range", None),
            link_fade=get("link_fade", None),
            controller=get("controller", None),
            planner=get("planner", None),
            link_capacity=get("link_capacity", None),
            link_queue=get("link_queue", None),
            link_medium=get("link_medium", None),
            link_trace=get("link_trace", None),
            rt_priority=get("rt_priority", None),
            plant_model=get("plant_model", None),
            router_lost_timeout=float(get("router_lost_timeout", DEFAULT_ROUTER_LOST_TIMEOUT_S)),
            kill_at_tick=get("kill_at_tick", None),
        )

    def fault_plan(self, scenario: Scenario) -> FaultPlan | None:
        """The link-fault plan of this run (scenario's ``[faults]`` plus the flags); None when no
        fault is active. Raises :class:`zenswarm.errors.ScenarioError` naming the bad field."""
        from zenswarm.link import plan_for

        return plan_for(
            scenario, self.link_delay, self.link_jitter, self.link_loss, self.partition, self.seed,
            link_range=self.link_range, link_fade=self.link_fade, link_capacity=self.link_capacity,
            link_queue=self.link_queue, link_medium=self.link_medium, link_trace=self.link_trace,
        )  # fmt: skip


class SwarmProcess:
    """A process of the swarm: session, keys, decoder, inbox, diagnostics, liveliness, stop flag.

    Use as a context manager; the session is always closed (a session left open with Python
    callbacks hangs interpreter exit).
    """

    def __init__(self, name: str, options: ProcessOptions | Any) -> None:
        self.name = name
        self.options = ProcessOptions.of(options)
        self.args = options  # what it was started with: an edge's own flags (bridge/mavlink.py)
        self.keys = wire.Keys(self.options.swarm)
        self.decoder = _KeyedDecoder()
        self.inbox = Inbox()
        self.stop = threading.Event()
        self.session: zenoh.Session | None = None
        self._subs: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._token: zenoh.LivelinessToken | None = None
        self.counters: dict[str, float] = defaultdict(float)
        self._diag_seq = 0
        self._scenario: Scenario | None = None
        self._on_input: Callable[[str, int, Any], None] | None = None
        self._lockstep: Lockstep | None = None
        self.subscribed: list[str] = []  # every key this process subscribed to (contract tests)
        self.extra_counters: Callable[[], dict[str, float]] | None = None
        self._delay_line: Any = None
        self._dl_lock = threading.Lock()
        self._links: dict[str, tuple[str, str, str]] = {}
        self._alive: dict[str, bool] = {}
        self._alive_subs: list[Any] = []
        # input hardening (see the module docstring): sender pinning, open or secure swarm (the
        # secure router admits alive/<process>/<zid> from the process's own credentials only)
        self.check_sender = True
        self._guard: InputGuard | None = None
        self._watched_senders: set[str] = set()
        self._zid_token: zenoh.LivelinessToken | None = None
        self._source_info: dict[str, Any] = {}
        self._transport_listener: bus.Undeclarable | None = None
        self._link_lost = False
        self._lost_since: float | None = None  # monotonic s when zenoh closed the link to the router
        self.router_gone = False  # gave up on the router (--router-lost-timeout): exit EXIT_ROUTER_LOST
        self.on_reconnect: Callable[[], None] | None = None  # called (zenoh's thread) when the link to the router is back

    @property
    def scenario(self) -> Scenario:
        """The scenario of this run: loaded (or fetched from the leader) on entering the ``with``
        block; :class:`ScenarioError` before that."""
        sc = self._scenario
        if sc is None:
            raise ScenarioError("--scenario", f"{self.name}: not loaded yet (use the process as a context manager)")
        return sc

    @scenario.setter
    def scenario(self, sc: Scenario) -> None:
        self._scenario = sc

    def _zenoh(self) -> zenoh.Session:
        """The open session (inside the ``with`` block); :class:`zenswarm.bus.BusError` outside it."""
        s = self.session
        if s is None:
            raise bus.BusError(f"{self.name}: no open zenoh session (use the process as a context manager)")
        return s

    @property
    def on_input(self) -> Callable[[str, int, Any], None] | None:
        """Called with (key, tick, msg) of every accepted message. Assigning a
        :meth:`Lockstep.poke` also tells the input guard the process's current tick."""
        return self._on_input

    @on_input.setter
    def on_input(self, hook: Callable[[str, int, Any], None] | None) -> None:
        self._on_input = hook
        owner = getattr(hook, "__self__", None)
        if isinstance(owner, Lockstep):
            self._lockstep = owner

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> SwarmProcess:
        gc_policy()  # a bad ZENSWARM_GC: exit 2 before any work
        self._check_rt_priority()  # a bad or forbidden --rt-priority: exit 2 before any work
        self._check_kill_at_tick()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        bus.use_swarm_runtime()  # before the first session: zenoh reads it once per process
        connect = list(self.options.connect) or ["tcp/127.0.0.1:7447"]
        conf = bus.client_config(connect, settings=security.client_fragments(
                self.name,
                security.ClientSecurity(self.options.keys, self.options.tls),
                connect=self.options.connect,
                swarm=self.options.swarm,
            ))
        self._session_cm = bus.open_session(conf, handle_signals=False)
        self.session = session = self._session_cm.__enter__()
        try:
            self._transport_listener = session.info.declare_transport_events_listener(self._on_transport)
        except Exception:  # noqa: BLE001 - diagnostics only
            self._transport_listener = None
        self.scenario = self._load_scenario()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _check_kill_at_tick(self) -> None:
        """``--kill-at-tick K``: a tick >= 0, lockstep only (realtime processes do not run tick by tick)."""
        k = self.options.kill_at_tick
        if k is None:
            return
        if self.options.realtime:
            raise ScenarioError("--kill-at-tick", f"{self.name}: lockstep only (a realtime process is killed from outside)")
        if int(k) < 0:
            raise ScenarioError("--kill-at-tick", f"{self.name}: a tick >= 0, got {k}")

    def _check_rt_priority(self) -> None:
        """``--rt-priority``: an integer 1-99, realtime only, and permitted to this user; what
        :meth:`announce` applies once start-up is over (:mod:`zenswarm.process.rtsched`)."""
        rtsched.set_requested(rtsched.validate(self.options.rt_priority, realtime=self.options.realtime))

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.stop.set()
        self.inbox.wake()

    def close(self) -> None:
        s, self.session = self.session, None
        if s is None:
            return
        for tok in (self._token, self._zid_token, self._transport_listener):
            try:
                if tok is not None:
                    bus.undeclare(tok)
            except Exception:  # noqa: BLE001 - best effort on shutdown
                pass
        for sub in self._subs + self._alive_subs:
            try:
                bus.undeclare(sub)
            except Exception:  # noqa: BLE001
                pass
        self._session_cm.__exit__(None, None, None)

    def _load_scenario(self) -> Scenario:
        from zenswarm.scenario.plugins import check_selection, select

        sc = self._fetch_scenario()
        seed = self.options.seed
        sc = sc if seed is None else replace(sc, seed=int(seed))
        sc = select(sc, self.options.controller, self.options.planner, self.options.plant_model)
        check_selection(sc)  # a bad plug-in name or parameter: exit 2 before any work
        return sc

    def _fetch_scenario(self) -> Scenario:
        if self.options.scenario is not None:
            return load_scenario(self.options.scenario)
        # Fetch the mission from the leader (late joiners, other hosts). A reply that does not
        # decode or is not a valid scenario is counted (decoder / rejected.value) and skipped.
        deadline = time.monotonic() + 30.0
        key = self.keys.mission
        while time.monotonic() < deadline and not self.stop.is_set():
            for reply in self._zenoh().get(key, timeout=2.0):
                ok = getattr(reply, "ok", None)
                if ok is None:
                    continue
                try:
                    payload = ok.payload.to_bytes()
                except Exception as e:  # noqa: BLE001
                    self.decoder.reject(key, "malformed", f"unreadable reply: {e}")
                    continue
                msg = self.decoder.decode(key, "mission", payload)
                if not isinstance(msg, wire.Mission):  # None: rejected (counted)
                    continue
                try:
                    return scenario_from_dict(msg.scenario)
                except ZenswarmError as e:
                    self.decoder.reject(key, "value", f"not a valid scenario: {e}")
            time.sleep(0.2)
        raise ScenarioError("--scenario", "not given, and no leader answered on the mission key within 30 s")

    # ------------------------------------------------------------------ bus
    @property
    def guard(self) -> InputGuard:
        """The input guard of this process (created on first use, from the scenario and flags)."""
        g = self._guard
        if g is None:
            sc = self.scenario
            dt = sc.timing.dt
            timeout = self.options.lockstep_timeout
            realtime = self.options.realtime
            g = self._guard = InputGuard(
                dt_ns=wire.t_ns(dt),
                n_ticks=sc.timing.n_ticks,
                horizon_ticks=self._fault_horizon_ticks(),
                growth_period_s=dt if realtime else min(dt, timeout),
                paced=realtime,
                check_sender=self.check_sender,
                now_tick=self._now_tick,
                prefix=self.keys.prefix + "/",
            )
        return g

    def _fault_horizon_ticks(self) -> int:
        """Largest link-fault delay of the run, in ticks (+1), 0 without faults."""
        try:
            plan = self.options.fault_plan(self.scenario)
        except Exception:  # noqa: BLE001 - bad flags are reported by the process itself
            return 0
        if plan is None:
            return 0
        from zenswarm.link import delivery_tick

        worst = plan.worst_delay_s()
        return delivery_tick(0, worst, self.scenario.timing.dt) + 1 if worst > 0 else 0

    def _now_tick(self) -> int | None:
        """Lockstep: the tick this process is at, once it ran one (None before, and in realtime)."""
        ls = self._lockstep
        if ls is None or not ls.started:
            return None
        return ls.k

    def handle_sample(self, key: str, kind: str, sample: Any, senders: tuple[str, ...] = (),
                      on_msg: Callable[[str, Any], None] | None = None) -> Any | None:
        """One received sample of ``key``: decode, guard, then hand it on (delay line or inbox,
        ``on_msg``, :attr:`on_input`). Returns the accepted message, or None if it was rejected
        (counted). Never raises for a bad sample (exceptions of the hand-on callbacks propagate)."""
        try:
            payload = sample.payload.to_bytes()
        except Exception as e:  # noqa: BLE001 - not a readable zenoh sample
            self.decoder.reject(key, "malformed", f"unreadable sample: {type(e).__name__}")
            return None
        msg = self.decoder.decode(key, kind, payload)
        if msg is None:
            return None
        dt_ns = self.guard.dt_ns
        tick = (msg.t + dt_ns // 2) // dt_ns
        if self.guard.check(key, senders, tick, msg, sample_sender(sample)) is not None:
            return None
        dl = self._delay_line
        if dl is not None and key in self._links:
            with self._dl_lock:
                dl.offer(time.monotonic(), self._links[key], key, tick, msg)
            return msg
        self.inbox.put(key, tick, msg)
        if on_msg is not None:
            on_msg(key, msg)
        hook = self._on_input
        if hook is not None:
            hook(key, tick, msg)
        return msg

    def subscribe(self, key: str, kind: str, on_msg: Callable[[str, Any], None] | None = None) -> None:
        """Subscribe to ``key``; decoded messages that pass the input guard go to the inbox keyed
        by their tick (see :meth:`handle_sample`)."""
        senders = expected_senders(self.keys, key)
        self.guard  # noqa: B018 - create it before the first sample
        if self.check_sender:
            self._watch_sender_tokens(senders)
        handle = self.handle_sample

        def cb(sample: zenoh.Sample) -> None:
            handle(key, kind, sample, senders, on_msg)

        # On zenoh's receiving thread (bus.direct_callback). Lockstep ticks, and their puts, run
        # there; in realtime the callback only files the message and the main loop puts. A put
        # releases the GIL while it waits for queue space, so a main-loop put never keeps this
        # callback from running (tests/test_bus.py checks it).
        self._subs.append(self._zenoh().declare_subscriber(key, bus.direct_callback(cb)))
        self.subscribed.append(key)

    def _watch_sender_tokens(self, names: tuple[str, ...]) -> None:
        """Follow ``alive/<name>/<zid>`` of each sender name (which sessions are that process)."""
        guard = self.guard
        for name in names:
            if name in self._watched_senders:
                continue
            self._watched_senders.add(name)
            prefix = self.keys.alive(name) + "/"

            def cb(sample: Any, name: str = name, prefix: str = prefix) -> None:
                key = str(sample.key_expr)
                if key.startswith(prefix):
                    guard.token(name, key[len(prefix):], sample.kind == zenoh.SampleKind.PUT)

            self._alive_subs.append(self._zenoh().liveliness().declare_subscriber(prefix + "*", cb, history=True))

    def _on_transport(self, event: Any) -> None:
        """Our link to the router went away or came back (zenoh clients reconnect by themselves)."""
        try:
            up = event.kind == zenoh.SampleKind.PUT
        except Exception:  # noqa: BLE001
            return
        if not up:
            self._link_lost = True
            since = self._lost_since = time.monotonic()
            self.counters["router_link_lost"] += 1
            wait = self.options.router_lost_timeout
            self.log(f"{self.name}: link to the router lost; zenoh keeps trying to reconnect for {wait:g} s (--router-lost-timeout)")
            t = threading.Timer(wait, self._router_lost_for_good, args=(since,))
            t.daemon = True
            t.start()
        elif self._link_lost:
            self._link_lost = False
            self._lost_since = None
            self.counters["router_reconnects"] += 1
            if self._guard is not None:
                self._guard.discontinuity()
            self.log(f"{self.name}: reconnected to the router (messages sent meanwhile are lost)")
            hook = self.on_reconnect
            if hook is not None:
                hook()

    def _router_lost_for_good(self, since: float) -> None:
        """The router did not come back within ``--router-lost-timeout`` of the link loss at
        ``since``: stop the process (its loop ends, it exits with :data:`EXIT_ROUTER_LOST`)."""
        if not self._link_lost or self._lost_since != since or self.stop.is_set():
            return
        self.router_gone = True
        self.counters["router_lost"] += 1
        self.log(f"{self.name}: error: the router has been unreachable for {self.options.router_lost_timeout:g} s "
                 f"(--router-lost-timeout); giving up, exit {EXIT_ROUTER_LOST}")
        self.stop.set()
        self.inbox.wake()

    def publisher(self, key: str) -> Any:
        pub = self._pubs.get(key)
        if pub is None:
            # BLOCK: lockstep traffic must not be dropped. No express (one batch per message): it
            # costs a write, and a wake-up of zenoh's thread, per put: 16 puts of a State cost 42 µs
            # wall / 64 µs CPU each with express, 2.7 / 13.5 µs without; realtime at 16 UAVs missed
            # 0.73-0.76 % of deadlines with express, 0.09-0.42 % without, p99 25 ms against 9-14 ms
            # (BENCHMARKS.md, "Scheduling of the lockstep tick"). The lockstep gain when express was
            # first turned off (up to 36 %, with zenoh's default threads) is in git history:
            # `git show 3ff7b8f:BENCHMARKS.md`.
            pub = self._zenoh().declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                express=False,
                reliability=zenoh.Reliability.RELIABLE,
            )
            self._pubs[key] = pub
        return pub

    def publish(self, key: str, msg: Any) -> None:
        """Encode and put ``msg`` on ``key``, stamped with this publisher's id (``SourceInfo``),
        so receivers can tell which session sent it."""
        self.put(key, wire.encode(msg))

    def put(self, key: str, payload: bytes) -> None:
        """Put an encoded message (:func:`zenswarm.bus.wire.encode`, or its hot paths such as
        :func:`zenswarm.bus.wire.encode_state`) on ``key``, stamped like :meth:`publish`."""
        pub = self._pubs.get(key)
        if pub is None:
            pub = self.publisher(key)
        si = self._source_info.get(key)
        if si is None:
            si = self._source_info[key] = zenoh.SourceInfo(pub.id, 0)
        pub.put(payload, source_info=si)

    def announce(self) -> None:
        """Declare this process's liveliness token: all its subscriptions are in place. Also
        ``alive/<process>/<zid>``: which session is this process (the receivers pin to it)."""
        session = self._zenoh()
        if self.check_sender and self._zid_token is None:
            self._zid_token = session.liveliness().declare_token(f"{self.keys.alive(self.name)}/{session.zid()}")
        self._token = session.liveliness().declare_token(self.keys.alive(self.name))
        if self.options.realtime:
            gc_startup_done()  # subscribed and announced: start-up is over (see GcPolicy; realtime only)
            rtsched.apply_after_startup(self.log)  # --rt-priority: the loops under SCHED_FIFO from now on

    def wait_for_alive(self, names: list[str], timeout_s: float = 60.0) -> list[str]:
        """Block until every named process has announced itself; return those still missing."""
        deadline = time.monotonic() + timeout_s
        want = {self.keys.alive(n): n for n in names}
        while not self.stop.is_set():
            seen = set()
            for reply in self._zenoh().liveliness().get(self.keys.alive_all, timeout=1.0):
                ok = getattr(reply, "ok", None)
                if ok is not None:
                    seen.add(str(ok.key_expr))
            missing = [n for k, n in want.items() if k not in seen]
            if not missing or time.monotonic() > deadline:
                return missing
            time.sleep(0.02)
        return list(want.values())

    # ------------------------------------------------------------------ liveliness of senders
    def watch_alive(self, names: list[str], on_change: Callable[[], None] | None = None) -> None:
        """Track the liveliness tokens of ``names`` (one subscriber each, with history)."""
        for name in names:
            self._alive.setdefault(name, True)  # assume alive until told otherwise

            def cb(sample: Any, name: str = name) -> None:
                self._alive[name] = sample.kind == zenoh.SampleKind.PUT
                if on_change is not None:
                    on_change()

            self._alive_subs.append(self._zenoh().liveliness().declare_subscriber(self.keys.alive(name), cb, history=True))

    def linger_until_gone(self, name: str, timeout_s: float = 30.0) -> None:
        """Lockstep end: stay (token held) until ``name`` is gone, so a receiver still on its last
        tick never mistakes our normal exit for a crash and stops waiting for what we sent."""
        if name not in self._alive:
            self.watch_alive([name])
        deadline = time.monotonic() + timeout_s
        while self._alive.get(name, False) and not self.stop.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)

    def is_alive(self, name: str) -> bool:
        """False once ``name``'s liveliness token is gone (True for names not watched)."""
        return self._alive.get(name, True)

    # ------------------------------------------------------------------ realtime link faults
    def use_delay_line(self, state: Any, links: dict[str, tuple[str, str, str]]) -> None:
        """Realtime link faults on these keys: decided on receipt, released after their delay."""
        from zenswarm.link import DelayLine

        self._links = dict(links)
        self._delay_line = DelayLine(state, self.scenario.timing.dt)

    def release_delayed(self) -> None:
        """Hand over the delayed messages whose time has come (call from the process loop)."""
        dl = self._delay_line
        if dl is None:
            return
        with self._dl_lock:
            dl.release(time.monotonic(), self.inbox.put)

    def publish_diag(self, t_ns: int, info: dict[str, Any] | None = None) -> None:
        counters = self.diag_counters()
        self._diag_seq += 1
        self.publish(
            self.keys.diag(self.name),
            wire.Diag(
                t=t_ns,
                seq=self._diag_seq,
                process=self.name,
                counters=counters,
                info={
                    "subscriptions": ",".join(sorted(self.subscribed)),
                    "zenoh_threads": bus.zenoh_threads(),
                    **self._reject_info(),
                    **(info or {}),
                },
            ),
        )

    def _reject_info(self) -> dict[str, str]:
        """The last rejected input, for the humans reading diagnostics."""
        out = {}
        if self.decoder.last_error:
            out["last_decode_error"] = self.decoder.last_error[:200]
        if self._guard is not None and self._guard.last_reject:
            out["last_reject"] = self._guard.last_reject[:200]
        return out

    def diag_counters(self) -> dict[str, float]:
        """Every counter of this process: its own, the decoder's (``decoded``, ``rejected``,
        ``rejected.<reason>``), the input guard's (``accepted``, ``rejected.<reason>``), rejects
        per key (``rejected@<key>.<reason>``), link faults and the process's extra counters."""
        counters = dict(self.counters)
        counters.update(self.decoder.counters())
        plen = len(self.keys.prefix) + 1
        for (key, reason), n in list(self.decoder.by_key.items()):
            counters[f"rejected@{key[plen:] if key.startswith(self.keys.prefix) else key}.{reason}"] = n
        if self._guard is not None:
            for name, n in self._guard.counters().items():  # out_of_range is a decoder reason too: add up
                counters[name] = counters.get(name, 0) + n
            counters["rejected"] = self.decoder.rejected + self._guard.rejected
            counters["accepted"] = self._guard.accepted
        counters.update(gc_policy().counters())
        counters.update(rtsched.counters())
        if self.extra_counters is not None:
            counters.update(self.extra_counters())
        if self._delay_line is not None:
            counters.update(self._delay_line.dropped)
        return counters

    def log(self, text: str) -> None:
        print(text, flush=True)


PLUGIN_FAILURE_MARK = "zenswarm-plugin-failure "
"""The line a swarm process prints (``MARK`` + JSON of :meth:`zenswarm.errors.PluginFailure.to_dict`)
before it exits with :data:`zenswarm.errors.EXIT_PLUGIN_FAILED`: how its supervisor learns
which plug-in failed, where and when."""


PLUGIN_FAILURE_LINGER_S = 30.0
"""Wall seconds a process whose plug-in failed stays up at most (its token held), until the plant
is gone or it is stopped: what it published last reaches its receivers, and they never mistake
it for a crash."""


def report_plugin_failure(proc: SwarmProcess | None, e: PluginFailure) -> None:
    """Say that a plug-in failed: a line for humans, the machine-readable line
    (:data:`PLUGIN_FAILURE_MARK`) for the supervisor, and a diagnostic on the bus (best effort);
    then linger (:data:`PLUGIN_FAILURE_LINGER_S`) until the flight is over."""
    import json

    print(f"{e.process}: plugin_error: {e}", file=sys.stderr, flush=True)
    print(PLUGIN_FAILURE_MARK + json.dumps(e.to_dict(), sort_keys=True), file=sys.stderr, flush=True)
    if proc is not None and proc.session is not None:
        try:
            dt_ns = wire.t_ns(proc.scenario.timing.dt) if proc.scenario is not None else 0
            proc.publish_diag(e.tick * dt_ns, {"plugin_failure": json.dumps(e.to_dict(), sort_keys=True)})
        except Exception:  # noqa: BLE001 - the line above is what counts
            pass
        if proc.name != "plant":
            proc.linger_until_gone("plant", PLUGIN_FAILURE_LINGER_S)


def run_process(fn: Callable[[SwarmProcess], int], name: str, options: ProcessOptions | Any) -> int:
    """Run ``fn`` inside a :class:`SwarmProcess` started with ``options`` (or any object with
    their attribute names, see :meth:`ProcessOptions.of`); map errors to exit codes (2: bad
    scenario, credentials, unreachable router; 4: a plug-in failed, :func:`report_plugin_failure`)
    and always close."""
    try:
        with SwarmProcess(name, options) as proc:
            try:
                rc = fn(proc)
            except PluginFailure as e:
                report_plugin_failure(proc, e)
                return EXIT_PLUGIN_FAILED
            return EXIT_ROUTER_LOST if proc.router_gone else rc
    except ZenswarmError as e:  # bad scenario, credentials, unreachable router: say what, exit 2
        print(f"{name}: error: {e}", file=sys.stderr, flush=True)
        return 2


def kill_self_line(tick: int) -> str:
    """The end of the line :func:`kill_self` writes (the supervisor knows a self-kill by it)."""
    return f"SIGKILL at tick {tick} (--kill-at-tick)"


def kill_self(name: str, tick: int) -> NoReturn:
    """SIGKILL this process now, as ``kill -9`` from outside would (nothing is flushed, no
    handler runs), after one line saying so (:func:`kill_self_line`): the fault ``--kill-at-tick``
    injects at ``tick``."""
    sys.stdout.write(f"{name or 'process'}: {kill_self_line(tick)}\n")
    sys.stdout.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    raise SystemExit(137)  # not reached: SIGKILL is not caught


class Lockstep:
    """Event-driven lockstep loop: tick k runs as soon as its inputs are there.

    ``ready(k)`` says whether tick k's inputs have all arrived; ``step(k, forced)`` runs the tick
    (``forced`` = some input timed out and the tick runs with held values). ``prepare(k)`` runs
    before each readiness check (e.g. to publish what others need from us first).
    ``can_force(k)`` says whether a timed-out tick may run anyway (False when the missing input
    is the clock itself). ``kill_at``: the process SIGKILLs itself (:func:`kill_self`) just before
    tick ``kill_at`` would run (``--kill-at-tick``); ``name`` names it in that line.

    Ticks run inside the Zenoh callback that delivered the last missing input (call
    :meth:`poke` from every subscriber callback), so no thread hand-off sits on the critical
    path; a lock serialises callbacks of different subscribers. :meth:`run` (main thread)
    waits for the end and forces timed-out ticks.
    """

    def __init__(
        self,
        n_ticks: int,
        ready: Callable[[int], bool],
        step: Callable[[int, bool], None],
        timeout_s: float,
        stop: threading.Event,
        prepare: Callable[[int], None] | None = None,
        can_force: Callable[[int], bool] | None = None,
        on_msg: Callable[[str, int, Any], None] | None = None,
        kill_at: int | None = None,
        name: str = "",
    ) -> None:
        self.n = n_ticks
        self.kill_at = kill_at
        self.name = name
        self.k = 0
        self._ready = ready
        self._step = step
        self._prepare = prepare
        self._can_force = can_force or (lambda k: True)
        self._on_msg = on_msg
        self.timeout = timeout_s
        self.stop = stop
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.error: BaseException | None = None
        self.forced = 0
        self._wait_since: float | None = None
        self.step_s = 0.0  # wall time spent inside step(), s
        self.wait_s = 0.0  # wall time between the end of a tick and the start of the next, s
        self._t_end: float | None = None

    def poke(self, key: str | None = None, tick: int = 0, msg: Any = None) -> None:
        """Take a message (``on_msg``, under the lock) and advance as far as the inputs allow.

        Safe to call from any thread; ``poke()`` without a message just re-checks readiness
        (e.g. after a sender's liveliness changed)."""
        with self.lock:
            if key is not None and self._on_msg is not None:
                try:
                    self._on_msg(key, tick, msg)
                except BaseException as e:  # noqa: BLE001 - surfaced by run()
                    self.error = e
                    self.done.set()
                    return
            self._advance(False)

    def _advance(self, force: bool) -> None:
        if self.done.is_set():
            return
        try:
            while self.k < self.n and not self.stop.is_set():
                k = self.k
                if k == self.kill_at:
                    kill_self(self.name, k)
                if self._prepare is not None:
                    self._prepare(k)
                ok = self._ready(k)
                if not ok and not force:
                    if self._wait_since is None:
                        self._wait_since = time.monotonic()
                    return
                t0 = time.perf_counter()
                if self._t_end is not None:
                    self.wait_s += t0 - self._t_end
                self._step(k, not ok)
                gc_safe_point()  # between ticks, never inside one
                self._t_end = time.perf_counter()
                self.step_s += self._t_end - t0
                if not ok:
                    self.forced += 1
                force = False
                self._wait_since = None
                self.k = k + 1
            self.done.set()
        except BaseException as e:  # noqa: BLE001 - surfaced by run() in the main thread
            self.error = e
            self.done.set()

    @property
    def started(self) -> bool:
        """True once a tick ran."""
        return self._t_end is not None

    def timing(self) -> dict[str, float]:
        """Mean step and wait times per tick, ms (for diagnostics)."""
        n = max(self.k, 1)
        return {"step_ms_mean": 1e3 * self.step_s / n, "wait_ms_mean": 1e3 * self.wait_s / n, "forced_ticks": self.forced}

    def run(self) -> int:
        """Block until every tick ran (or stop); returns the number of ticks run."""
        self.poke()
        while not self.done.is_set() and not self.stop.is_set():
            self.done.wait(0.05)
            with self.lock:
                ws = self._wait_since
                if ws is not None and time.monotonic() - ws > self.timeout and self._can_force(self.k):
                    self._advance(True)
        if self.error is not None:
            raise self.error
        return self.k

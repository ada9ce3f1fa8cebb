"""How a swarm process manages Python's cyclic garbage collector (issue 16): :class:`GcPolicy`,
one per process (:func:`gc_policy`), collecting only at the safe points its loops offer."""

from __future__ import annotations

import gc
import os
import threading
import time

from zenswarm.errors import ScenarioError

__all__ = ["GcPolicy", "gc_policy", "gc_startup_done", "gc_safe_point", "GC_ENV", "GC_YOUNG_LIMIT", "GC_OLDER_LIMIT",
           "GC_FORCE_LIMIT", "GC_MIN_SLACK_S"]

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
       period before it sleeps (:meth:`zenswarm.process.clocks.WallClock.wait`), the end of a lockstep tick
       (:class:`zenswarm.process.lockstep.Lockstep`), the supervisor's and the recorder's loops. Generation 0 once
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

"""The wall clock of a realtime loop: :class:`WallClock` (one fixed-rate loop, resynchronised after
a stall), its :class:`LoopStats`, and :func:`sleep_until`."""

from __future__ import annotations

import threading
import time

from zenswarm.process.gcpolicy import gc_safe_point

__all__ = ["LoopStats", "WallClock", "sleep_until"]


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

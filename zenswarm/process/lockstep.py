"""The lockstep loop (:class:`Lockstep`: tick k runs as soon as its inputs are there), its pace
(the plant's clock every :data:`CLOCK_EVERY_TICKS` ticks, the leader up to
:data:`LEADER_AHEAD_TICKS` ahead), and the fault ``--kill-at-tick`` (:func:`kill_self`)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, NoReturn

from zenswarm.process.gcpolicy import gc_safe_point
from zenswarm.process.guard import GUARD_MARGIN_TICKS

__all__ = ["Lockstep", "kill_self", "kill_self_line", "CLOCK_EVERY_TICKS", "LEADER_AHEAD_TICKS"]

CLOCK_EVERY_TICKS = 4
"""Lockstep: the plant publishes ``clock`` at every this many ticks (and at the last one), not at
every tick. Only the leader and the supervisor read it; the agents' clock is their own state."""

LEADER_AHEAD_TICKS = 4
"""Lockstep: the leader publishes its reference up to this many ticks past the newest clock. Its
trajectory does not depend on the swarm, so it may run ahead; at least :data:`CLOCK_EVERY_TICKS`
keeps every leader ref published before the ticks that need it."""

assert LEADER_AHEAD_TICKS >= CLOCK_EVERY_TICKS <= GUARD_MARGIN_TICKS


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

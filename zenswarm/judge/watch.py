"""When a flight ends: the one end-of-flight watch of the simulator and of the swarm's supervisor.

A flight ends early when its outcome can no longer change (:func:`zenswarm.judge.verdict.decide_end`:
a stalled leader, a diverged or non-finite UAV, a non-finite leader), unless the whole time limit
is asked for (``full_time``); with ``stop_at_goal`` also once the goal is reached and every UAV has
been in its slot for the settle window; and when a plug-in failed, after the ticks before the
failed one (unless the outcome was decided before it: then the run had ended there). The
:class:`EndWatch` holds these rules and says which ticks are judged (:class:`Ending`).

It reads the flight through a small protocol, :class:`Record`: the ticks recorded so far as a
:class:`~zenswarm.judge.metrics.TimeSeries`. The simulator's series (filled tick by tick) and the
supervisor's :class:`zenswarm.process.collector.Collector` (assembled from the bus) both are one.
The simulator, whose series is in memory, looks exactly every :data:`DECIDE_EVERY` ticks
(:meth:`EndWatch.block`). The supervisor first glances at what is cheap (:class:`LiveRecord`: the
leader's series, each UAV's newest state and reference), so the swarm's whole series is decoded
only once an end is in sight, and then takes the same exact decision on the ticks complete so far
(:meth:`EndWatch.look`). The decision is causal (tick k reads ticks <= k), so both end after the
same tick.

Pure (numpy only).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from zenswarm.judge.metrics import TimeSeries
from zenswarm.judge.verdict import TERMINAL, Criteria, decide_end, in_slots, judge, leader_stall_tick, uav_decided

__all__ = ["DECIDE_EVERY", "Ending", "EndWatch", "LiveRecord", "Record"]

DECIDE_EVERY = 50
"""Ticks between two exact looks of the simulator (:meth:`EndWatch.block`): the run ends after the
tick the look names, so looking in blocks costs less and ends at the same tick."""


@runtime_checkable
class Record(Protocol):
    """A flight's record so far, as the watch's exact decision reads it: the simulator's
    :class:`~zenswarm.judge.metrics.TimeSeries` and the supervisor's collector both are one."""

    def series(self, upto_tick: int | None = None, fill: bool = False) -> TimeSeries:
        """Ticks 0 .. ``upto_tick`` - 1 (all without it), NaN where nothing was recorded; ``fill``:
        a gap holds the previous value and the ticks before every field had one are dropped (realtime)."""
        ...


@runtime_checkable
class LiveRecord(Record, Protocol):
    """A flight as it flies, as the supervisor's watch glances at it (cheap: no decoding of the whole
    series; :class:`zenswarm.process.collector.Collector` is one)."""

    @property
    def q0(self) -> np.ndarray:
        """(T, 3) m: the leader's reference per tick, NaN where not known (yet)."""
        ...

    @property
    def leader_ticks(self) -> int:
        """The leader's references of ticks 0 .. leader_ticks - 1 may have arrived."""
        ...

    @property
    def goal_tick(self) -> int | None:
        """The first tick the leader was within the goal tolerance; None before."""
        ...

    def latest(self, kind: str) -> dict[int, tuple[int, np.ndarray]]:
        """UAV number (1-based) -> (tick, q (3,) m) of its newest ``state`` or ``ref``."""
        ...

    def complete_ticks(self, upto: int) -> int:
        """How many ticks from 0, up to ``upto``, have every UAV's state."""
        ...

    def clock_ticks(self) -> int:
        """The ticks the flight's clock has reached (0 before its first tick)."""
        ...


@dataclass(frozen=True)
class Ending:
    """A flight that ends before its time limit: the ticks judged, 0 .. ``upto`` - 1; ``why``, said
    on the supervisor's console; ``plugin_failed``: it ends on a plug-in's failure (exit status 4)."""

    upto: int
    why: str = ""
    plugin_failed: bool = False


class EndWatch:
    """The end-of-flight watch of one flight of ``n_ticks`` ticks (its time limit), judged against
    ``c``. ``full_time``: fly the whole time limit even when the outcome is decided;
    ``stop_at_goal``: end once the goal is reached and every UAV is settled in its slot
    (supervisor); ``realtime``: a tick without a message holds the previous value (the exact look
    reads the filled series; a plug-in's failure ends the flight at once, there is no tick to wait for).
    :attr:`ending` is the end found, None while the flight runs its course."""

    def __init__(self, c: Criteria, n_ticks: int, *, full_time: bool = False, stop_at_goal: bool = False, realtime: bool = False) -> None:
        self.c = c
        self.T = int(n_ticks)
        self.full_time = full_time
        self.stop_at_goal = stop_at_goal
        self.realtime = realtime
        self.ending: Ending | None = None
        self.checked = 0  # ticks already given to the exact decision in blocks (the simulator's)
        self._stall_checked = 0  # leader ticks already glanced at for a stall (the supervisor's)
        self._deciding = False  # a glance saw the outcome decided: the exact look confirms it
        self._in_slots_since: int | None = None  # --stop-at-goal: the tick every UAV was in its slot from

    # ------------------------------------------------------------------ the exact decision
    def _decide(self, record: Record, k0: int, k1: int) -> int | None:
        """The first tick in [k0, k1) that decided the run, None if none (or ``full_time``)."""
        if self.full_time:
            return None
        ts = record.series(k1)
        return decide_end(ts.q0, ts.q, ts.qref, self.c, k0, k1)

    def due(self, k: int) -> bool:
        """The simulator, about to fly tick k: time for an exact look (:data:`DECIDE_EVERY` ticks since the last)."""
        return k - self.checked >= DECIDE_EVERY

    def block(self, record: Record, upto: int) -> Ending | None:
        """The simulator's exact look at the ticks flown since its last one, [checked, ``upto``)
        (every tick of them complete): the run ends after the tick that decided it."""
        stop = self._decide(record, self.checked, upto)
        self.checked = upto
        if stop is not None:
            self.ending = Ending(stop + 1)
        return self.ending

    def plugin_failed(self, record: Record, tick: int) -> Ending:
        """A plug-in failed at ``tick`` (the first failed (tick, stage)): the ticks before it are
        judged, unless the outcome was decided before it (then the run had ended there, and the
        failure is no part of it: ``plugin_failed`` false). Realtime: the ticks before it."""
        k = min(tick, self.T)
        stop = None if self.realtime else self._decide(record, self.checked, k)
        if stop is not None:
            why = f"the outcome was decided at sim time {stop * self.c.dt:.2f} s, before the plug-in failed"
            self.ending = Ending(stop + 1, why)
        else:
            self.ending = Ending(k, plugin_failed=True)
        return self.ending

    # ------------------------------------------------------------------ the supervisor's look
    def look(self, flight: LiveRecord) -> Ending | None:
        """One look at a flight as it flies (the supervisor's, every fraction of a second): has its
        outcome been decided, or (``stop_at_goal``) is every UAV settled at the goal? Cheap until
        an end is in sight: the leader's series and each UAV's newest state and reference; the
        exact decision is then taken on the ticks complete so far."""
        c = self.c
        if not self.full_time:
            lead_known = flight.leader_ticks
            if leader_stall_tick(flight.q0, c, self._stall_checked, lead_known) is not None:
                self._deciding = True
            self._stall_checked = max(self._stall_checked, lead_known)
        if self._deciding:  # decided: stop once the series holds the deciding tick
            return self._decided_exactly(flight)
        states, refs = flight.latest("state"), flight.latest("ref")
        n = len(c.offsets)
        if len(states) < n:
            return None
        kmin = min(states[i][0] for i in range(1, n + 1))
        q = np.array([states[i][1] for i in range(1, n + 1)])
        if not self.full_time and len(refs) == n:
            qref = np.array([refs[i][1] for i in range(1, n + 1)])
            if uav_decided(q, qref, c) is not None:
                self._deciding = True
                return self._decided_exactly(flight)
        if self.stop_at_goal and flight.goal_tick is not None:
            return self._settled_at_goal(flight, q, kmin)
        return None

    def _decided_exactly(self, flight: LiveRecord) -> Ending | None:
        """The exact decision on the ticks complete so far (realtime: the ticks the clock reached,
        a skipped tick holding the previous value, as in the results); None while the deciding
        tick is still on its way."""
        if self.realtime:
            ts = flight.series(flight.clock_ticks(), fill=True)
        else:
            ts = flight.series(flight.complete_ticks(self.T))
        c = self.c
        k = decide_end(ts.q0, ts.q, ts.qref, c)
        if k is None:
            return None
        why = judge(ts.t[: k + 1], ts.q0[: k + 1], ts.q[: k + 1], ts.qref[: k + 1], c).failures
        first = next((f for f in why if f.cause in TERMINAL), None)
        text = first.detail if first is not None else "the outcome is decided"
        self.ending = Ending(int(round(ts.t[k] / c.dt)) + 1, f"at sim time {ts.t[k]:.2f} s {text}; ending the run (--full-time flies on)")
        return self.ending

    def _settled_at_goal(self, flight: LiveRecord, q: np.ndarray, kmin: int) -> Ending | None:
        """``stop_at_goal``, the goal reached: every UAV in its slot (``q`` (N, 3) m, the newest
        states, the oldest of tick ``kmin``) for the settle window, checked on the series?"""
        c = self.c
        if not in_slots(q, c):
            self._in_slots_since = None
            return None
        if self._in_slots_since is None:
            self._in_slots_since = kmin
        if kmin - self._in_slots_since + 1 < c.settle_ticks:
            return None
        ts = flight.series(kmin + 1, fill=self.realtime)  # the exact check
        if not (len(ts.t) >= c.settle_ticks and in_slots(ts.q[-c.settle_ticks :], c)):
            return None
        goal_tick = flight.goal_tick if flight.goal_tick is not None else kmin
        self.ending = Ending(
            kmin + 1,
            f"goal reached at sim time {goal_tick * c.dt:.2f} s and every UAV in its slot for "
            f"{c.settle_window_s:g} s at {kmin * c.dt:.2f} s; stopping (--stop-at-goal)",
        )
        return self.ending

    # ------------------------------------------------------------------ the end
    def judged_ticks(self, flight: LiveRecord, stopped: bool, fill: bool) -> int | None:
        """How many ticks the results judge, None for the whole record. A flight that ended (its
        course, or early): the :attr:`ending`'s ticks. One stopped (a process died, a signal): the
        ticks its clock reached, and (``fill`` false) only those whose every state arrived."""
        if not stopped:
            return None if self.ending is None else self.ending.upto
        upto = flight.clock_ticks()
        return upto if fill else flight.complete_ticks(upto)

"""The plug-in failures a swarm's processes report to ``zenswarm up``'s supervisor, and when the
flight they ended can be judged.

A process whose plug-in failed prints one line (:data:`zenswarm.process.runtime.PLUGIN_FAILURE_MARK`
and the failure as JSON) and exits 4; a role on another host (``--external``) puts the same JSON in
its diagnostics (``plugin_failure``). :class:`PluginFailures` takes both. The processes run
concurrently, where the simulator calls the plug-ins in turn, so the flight is judged only once
the failed (tick, stage) is settled (:func:`failure_settled`, pure over the collector: the ticks
before it complete and every other process past that stage or failed in it), which the supervisor
waits for (:func:`await_settled`); then the watch judges it as the simulator does
(:meth:`zenswarm.judge.watch.EndWatch.plugin_failed`).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from zenswarm.bus import wire
from zenswarm.compose.children import Child
from zenswarm.errors import EXIT_PLUGIN_FAILED, PluginFailure
from zenswarm.process.runtime import PLUGIN_FAILURE_MARK
from zenswarm.scenario.plugins import STAGE_BUILD, STAGE_SHARE, STAGE_STEP, first_failures

__all__ = ["SETTLE_GRACE_S", "PluginFailures", "TickOutputs", "await_settled", "failure_settled", "parse_failure"]

SETTLE_GRACE_S = 10.0
"""How long past ``--lockstep-timeout`` the supervisor waits for a failed (tick, stage) to settle (:func:`await_settled`)."""


def parse_failure(text: str) -> PluginFailure | None:
    """A failure as a process reports it (:meth:`PluginFailure.to_dict` as JSON); None if it is not one."""
    try:
        return PluginFailure.from_dict(json.loads(text))
    except (ValueError, KeyError, TypeError, AttributeError, AssertionError):  # AttributeError: JSON, but not an object
        return None


class PluginFailures:
    """The plug-in failures reported so far (iterable, false while none), each said on ``say``
    (the supervisor's console) as it is taken."""

    def __init__(self, say: Callable[[str], None]) -> None:
        self.say = say
        self.reported: list[PluginFailure] = []

    def __iter__(self) -> Iterator[PluginFailure]:
        return iter(self.reported)

    def __len__(self) -> int:
        return len(self.reported)

    def take_line(self, line: str) -> bool:
        """One line of a child's output: True if it reports its plug-in's failure (taken, said)."""
        at = line.find(PLUGIN_FAILURE_MARK)
        f = parse_failure(line[at + len(PLUGIN_FAILURE_MARK) :]) if at >= 0 else None
        if f is None:
            return False
        self.reported.append(f)
        self.say(f"plug-in failed: {f}")
        return True

    def from_diagnostics(self, diag: Mapping[str, Mapping[str, Any]], names: Iterable[str]) -> None:
        """The roles ``names`` on other hosts (``--external``): a failure in a role's last
        diagnostics (:func:`zenswarm.process.runtime.report_plugin_failure`), taken once."""
        for name in names:
            text = (diag.get(name) or {}).get("plugin_failure")
            if not isinstance(text, str) or self.reported_by(name):
                continue
            f = parse_failure(text)
            if f is not None:
                self.reported.append(f)
                self.say(f"plug-in failed on {name}: {f}")

    def reported_by(self, process: str) -> bool:
        """Has ``process`` reported its plug-in's failure?"""
        return any(f.process == process for f in self.reported)

    def reported_at_exit(self, child: Child) -> bool:
        """``child`` exited with 4: did it report its plug-in's failure (its last lines read, up to 5
        s: its output ends with it)? If not, it died."""
        child.join_output(5.0)
        return self.reported_by(child.name)

    def take_exits(self, children: Iterable[Child]) -> set[str]:
        """The exit statuses of ``children`` that ended since the last look, taken (with the reports
        of those that exited with 4: their last lines read); the names of every child that exited."""
        for c in children:
            rc = c.proc.poll()
            if rc is not None and c.returncode is None:
                c.returncode = rc
                if rc == EXIT_PLUGIN_FAILED:
                    self.reported_at_exit(c)
        return {c.name for c in children if c.returncode is not None}

    def first(self) -> list[PluginFailure]:
        """The failures of the first (tick, stage): what the flight ends on."""
        return first_failures(self.reported)

    def keep(self, failures: Sequence[PluginFailure]) -> None:
        """Keep only ``failures`` (the first ones; none when the flight was decided before them)."""
        self.reported = list(failures)


class TickOutputs(Protocol):
    """What :func:`failure_settled` reads of a flight (:class:`zenswarm.process.collector.Collector` is one)."""

    T: int
    """The flight's ticks (its time limit)."""

    def tick_complete(self, k: int) -> bool:
        """Every message of tick k arrived."""
        ...

    def outputs_of_tick(self, kind: str, k: int) -> np.ndarray:
        """(N,) bool: each UAV's ``ref`` or ``cmd`` of tick k arrived."""
        ...


def failure_settled(
    flight: TickOutputs, first: Sequence[PluginFailure], *, realtime: bool, roles: Sequence[str], announced: Collection[str],
    exited: Collection[str],
) -> bool:  # fmt: skip
    """May the flight be judged on the failures ``first`` (those of the first (tick, stage))?
    Lockstep: the ticks before the failed one are complete and every other process has passed the
    failed (tick, stage) or failed in it: at the plug-ins' build, every role of ``roles`` has
    ``announced`` itself (its liveliness token), ``exited`` or failed; at the agents' share or
    step, every agent's output of the tick arrived, or it exited or failed. Realtime: at once
    (ticks are held, there is none to wait for)."""
    if realtime:
        return True
    k, stage = first[0].order
    failed = {f.process for f in first}
    if stage == STAGE_BUILD:
        return all(r in announced or r in exited or r in failed for r in roles)
    if k > 0 and not flight.tick_complete(k - 1):
        return False
    if stage in (STAGE_SHARE, STAGE_STEP) and k < flight.T:
        have = flight.outputs_of_tick("ref" if stage == STAGE_SHARE else "cmd", k)
        agents = [wire.agent(i + 1) for i in range(len(have))]
        return all(have[i] or a in failed or a in exited for i, a in enumerate(agents))
    return True


def await_settled(
    failures: PluginFailures,
    flight: TickOutputs,
    poll: Callable[[], Collection[str]],
    *,
    realtime: bool,
    roles: Sequence[str],
    announced: Collection[str],
    timeout_s: float,
    stop: threading.Event,
    say: Callable[[str], None],
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> list[PluginFailure]:
    """A plug-in failed: ``poll`` (one look at the flight: its messages taken into ``flight``, the
    processes' exits and failures into ``failures``; the processes that exited) until the
    failures of the first (tick, stage) are settled (:func:`failure_settled`), ``stop`` is set, or
    ``timeout_s`` wall seconds (``clock``) went by (then said); those failures."""
    deadline = clock() + timeout_s
    while True:
        exited = poll()
        first = failures.first()
        if failure_settled(flight, first, realtime=realtime, roles=roles, announced=announced, exited=exited) or stop.is_set():
            return first
        if clock() > deadline:
            say("not every process gave its output of the failed tick in time; judging what arrived")
            return first
        sleep(0.02)

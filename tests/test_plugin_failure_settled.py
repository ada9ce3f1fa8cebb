"""When a flight a plug-in failed in may be judged (zenswarm.compose.plugin_failures, issue 44): the
supervisor's wait, on synthetic flights and reports, without a process. The swarm's end of the same
rule is tests/test_plugin_failures.py (the same named failure in sim, up and api.fly)."""

from __future__ import annotations

import json
import threading
from collections.abc import Callable

import numpy as np

from zenswarm.compose.plugin_failures import PluginFailures, await_settled, failure_settled, parse_failure
from zenswarm.errors import PluginFailure
from zenswarm.process.runtime import PLUGIN_FAILURE_MARK
from zenswarm.scenario.plugins import STAGE_BUILD, STAGE_PLANT, STAGE_SHARE, STAGE_STEP

ROLES = ["plant", "leader", "agent:1", "agent:2", "agent:3"]


class Flight:
    """A flight of ``T`` ticks whose ticks before ``complete`` arrived whole, and whose agents' refs
    and commands of each tick are given per UAV (``outputs[kind][k]``: (3,) bool)."""

    def __init__(self, T: int, complete: int, outputs: dict[str, dict[int, list[bool]]] | None = None) -> None:
        self.T = T
        self.complete = complete
        self.outputs = outputs or {}

    def tick_complete(self, k: int) -> bool:
        return k < self.complete

    def outputs_of_tick(self, kind: str, k: int) -> np.ndarray:
        return np.array(self.outputs.get(kind, {}).get(k, [False, False, False]))


def failure(process: str, tick: int, stage: int) -> PluginFailure:
    uavs = (int(process.split(":")[1]),) if process.startswith("agent:") else ()
    return PluginFailure("controller", "bad", process, uavs, tick, stage, "step", "it raised")


def settled(flight: Flight, first: list[PluginFailure], *, realtime: bool = False, announced: set[str] | None = None,
            exited: set[str] | None = None) -> bool:  # fmt: skip
    return failure_settled(flight, first, realtime=realtime, roles=ROLES, announced=announced or set(), exited=exited or set())


def test_at_a_step_every_other_agent_must_give_its_command_or_fail() -> None:
    first = [failure("agent:2", 5, STAGE_STEP)]
    flight = Flight(T=10, complete=5, outputs={"cmd": {5: [True, False, False]}})
    assert not settled(flight, first), "agent:3's command of tick 5 has not arrived"
    assert settled(flight, first, exited={"agent:3"}), "agent:3 exited: nothing more to wait for"
    flight.outputs["cmd"][5] = [True, False, True]
    assert settled(flight, first)
    assert not settled(Flight(T=10, complete=4, outputs=flight.outputs), first), "tick 4 is not complete"
    assert settled(Flight(T=10, complete=0), first, realtime=True), "realtime: at once"


def test_at_a_share_the_references_count_and_a_failed_agent_is_not_waited_for() -> None:
    first = [failure("agent:1", 3, STAGE_SHARE), failure("agent:3", 3, STAGE_SHARE)]
    flight = Flight(T=10, complete=3, outputs={"ref": {3: [False, True, False]}, "cmd": {3: [False, False, False]}})
    assert settled(flight, first)
    assert not settled(flight, first[:1]), "agent:3 neither gave its reference nor failed"


def test_at_the_build_every_role_announces_itself_exits_or_fails() -> None:
    first = [failure("leader", 0, STAGE_BUILD)]
    flight = Flight(T=10, complete=0)
    assert not settled(flight, first, announced={"plant", "agent:1", "agent:2"})
    assert settled(flight, first, announced={"plant", "agent:1", "agent:2"}, exited={"agent:3"})


def test_the_plants_stage_and_a_tick_past_the_end_wait_only_for_the_ticks_before() -> None:
    assert not settled(Flight(T=10, complete=6), [failure("plant", 7, STAGE_PLANT)])
    assert settled(Flight(T=10, complete=7), [failure("plant", 7, STAGE_PLANT)])
    assert settled(Flight(T=10, complete=10), [failure("agent:1", 10, STAGE_STEP)])


def test_reports_are_taken_from_a_childs_line_and_an_external_roles_diagnostics() -> None:
    said: list[str] = []
    fails = PluginFailures(said.append)
    f = failure("agent:2", 4, STAGE_STEP)
    assert not fails.take_line("agent:2: an ordinary line") and not fails
    assert not fails.take_line(f"{PLUGIN_FAILURE_MARK}{{not json")
    assert fails.take_line(f"[agent:2] {PLUGIN_FAILURE_MARK}{json.dumps(f.to_dict())}")
    assert fails.reported_by("agent:2") and not fails.reported_by("agent:1") and len(said) == 1
    g = failure("agent:1", 4, STAGE_SHARE)
    diag = {"agent:1": {"plugin_failure": json.dumps(g.to_dict())}, "agent:3": {"plugin_failure": "garbage"}}
    fails.from_diagnostics(diag, ["agent:1", "agent:3"])
    fails.from_diagnostics(diag, ["agent:1"])  # taken once
    assert [x.process for x in fails] == ["agent:2", "agent:1"] and said[-1].startswith("plug-in failed on agent:1")
    assert [x.process for x in fails.first()] == ["agent:1"], "the first (tick, stage): the share before the step"
    fails.keep([])
    assert not fails and parse_failure("[]") is None


class Clock:
    """Wall time that moves only when the wait sleeps (s)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s


def wait(
    fails: PluginFailures, flight: Flight, poll: Callable[[], set[str]], clock: Clock, stop: threading.Event | None = None
) -> list[str]:
    """The supervisor's wait (at most 1 s of ``clock``) on ``flight``: the processes of the failures it ends on."""
    first = await_settled(
        fails,
        flight,
        poll,
        realtime=False,
        roles=ROLES,
        announced=set(),
        timeout_s=1.0,
        stop=stop or threading.Event(),
        say=fails.say,
        clock=clock,
        sleep=clock.sleep,
    )
    return [f.process for f in first]


def test_the_wait_ends_once_settled_with_the_first_failures() -> None:
    said: list[str] = []
    fails = PluginFailures(said.append)
    fails.reported = [failure("agent:2", 5, STAGE_STEP)]
    flight = Flight(T=10, complete=5, outputs={"cmd": {5: [True, False, False]}})  # agent:1 gave its command
    clock, looks = Clock(), []

    def poll() -> set[str]:  # agent:3 fails too, seen on the third look
        looks.append(clock())
        if len(looks) == 3:
            fails.reported.append(failure("agent:3", 5, STAGE_STEP))
        return set()

    assert wait(fails, flight, poll, clock) == ["agent:2", "agent:3"] and len(looks) == 3 and clock() < 0.1
    assert said == [], "settled in time: nothing said"
    clock.t = 0.0
    assert wait(fails, Flight(T=10, complete=5), lambda: {"agent:1"}, clock) == ["agent:2", "agent:3"], "agent:1 exited"
    assert clock() == 0.0 and said == []


def test_the_wait_stops_at_its_deadline_and_says_so_or_at_once_when_stopped() -> None:
    said: list[str] = []
    fails = PluginFailures(said.append)
    fails.reported = [failure("agent:2", 5, STAGE_STEP)]
    flight = Flight(T=10, complete=5)  # no other agent ever gives its command of tick 5
    clock = Clock()
    assert wait(fails, flight, set, clock) == ["agent:2"] and 1.0 < clock() < 1.1
    assert said == ["not every process gave its output of the failed tick in time; judging what arrived"]
    stop = threading.Event()
    stop.set()
    clock.t, said[:] = 0.0, []
    assert wait(fails, flight, set, clock, stop) == ["agent:2"] and clock() == 0.0 and said == [], "stopped: no wait, nothing said"

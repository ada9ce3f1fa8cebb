"""The supervisor's restart bookkeeping (zenswarm.compose.restarts, issue 44): deaths, the restarts
the policy allows, when each is due and how many were made, against delays computed by hand;
wall times are given, no process runs. The swarm's end of the same rule is tests/test_fault_swarm.py."""

from __future__ import annotations

from zenswarm.compose.policy import RestartPolicy
from zenswarm.compose.restarts import Restarts


def death(role: str, t: float = 1.0) -> dict[str, object]:
    return {"process": role, "how": "killed by SIGKILL", "sim_time_s": t}


def test_each_restart_waits_its_backoff_and_the_limit_ends_them() -> None:
    r = Restarts(RestartPolicy(enabled=True, initial_delay_s=0.5, factor=3.0, max_delay_s=2.0, max_restarts=3))
    # by hand: 0.5, 0.5*3 = 1.5, 0.5*9 = 4.5 -> 2.0 (the cap), then none (3 restarts made)
    delays, now = [], 100.0
    for n in (1, 2, 3):
        d = r.died(death("agent:2"), now)
        assert d is not None and r.waiting("agent:2")
        delays.append(d)
        assert r.restart_now("agent:2", now + d - 1e-6) is None, "not due before its delay"
        assert r.restart_now("agent:2", now + d) == n and not r.waiting("agent:2")
        assert r.restart_now("agent:2", now + d + 1) is None, "made once"
        now += 10.0
    assert delays == [0.5, 1.5, 2.0]
    assert r.died(death("agent:2"), now) is None and not r.waiting("agent:2")
    assert r.limit_reached("agent:2"), "the policy would have restarted it: the limit is what stops it"
    assert r.done == {"agent:2": 3} and len(r.deaths) == 4 and r.deaths[-1] == death("agent:2")


def test_each_role_counts_its_own_restarts() -> None:
    r = Restarts(RestartPolicy(enabled=True, initial_delay_s=0.2, factor=2.0, max_delay_s=5.0, max_restarts=2))
    assert r.died(death("agent:1"), 0.0) == 0.2 and r.restart_now("agent:1", 0.2) == 1
    assert r.died(death("agent:1"), 1.0) == 0.4  # its second: 0.2 * 2
    assert r.died(death("leader"), 1.0) == 0.2  # the leader's first
    assert r.restart_now("leader", 1.3) == 1 and r.restart_now("agent:1", 1.3) is None and r.restart_now("agent:1", 1.4) == 2
    assert r.done == {"agent:1": 2, "leader": 1}


def test_the_plant_and_a_disabled_policy_restart_nothing() -> None:
    r = Restarts(RestartPolicy(enabled=True))
    assert r.died(death("plant"), 0.0) is None and not r.limit_reached("plant") and not r.waiting("plant")
    off = Restarts(RestartPolicy(enabled=False))
    assert off.died(death("agent:1"), 0.0) is None and not off.limit_reached("agent:1")
    assert off.deaths == [death("agent:1")] and off.done == {}


def test_the_flights_end_cancels_the_restarts_waited_for() -> None:
    r = Restarts(RestartPolicy(enabled=True, initial_delay_s=1.0))
    r.died(death("agent:1"), 0.0)
    r.died(death("agent:3"), 0.5)
    assert sorted(r.cancel_pending()) == ["agent:1", "agent:3"] and r.cancel_pending() == []
    assert r.restart_now("agent:1", 10.0) is None and r.done == {}


def test_after_the_flights_end_no_restart_and_a_grace_then_over() -> None:
    r = Restarts(RestartPolicy(enabled=True, initial_delay_s=1.0))
    r.died(death("agent:2"), 10.0)
    assert r.flight_ended(10.5, grace_s=3.0) == (["agent:2"], False), "the restart due at 11.0 is not made"
    assert r.restart_now("agent:2", 11.0) is None and r.done == {}
    assert r.flight_ended(13.49, grace_s=3.0) == ([], False), "the grace counts from the end first seen (10.5)"
    assert r.flight_ended(13.5, grace_s=3.0) == ([], True)

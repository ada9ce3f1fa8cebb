"""``zenswarm up --kill ROLE@T``: who delivers each SIGKILL (zenswarm.compose.kills, issue 44), without a process."""

from __future__ import annotations

from zenswarm.compose.kills import split_kills


def test_lockstep_roles_kill_themselves_at_the_first_tick_at_or_after_t_the_rest_are_killed_at_a_sim_time() -> None:
    pending, ticks = split_kills([("agent:2", 1.0), ("recorder", 1.5), ("plant", 0.015), ("leader", 0.02)], realtime=False, dt=0.01)
    assert pending == {"recorder": 1_500_000_000}
    assert ticks == {"agent:2": 100, "plant": 2, "leader": 2}


def test_realtime_every_kill_is_the_supervisors() -> None:
    pending, ticks = split_kills([("agent:2", 1.0), ("leader", 0.5)], realtime=True, dt=0.01)
    assert pending == {"agent:2": 1_000_000_000, "leader": 500_000_000} and ticks == {}

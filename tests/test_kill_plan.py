"""``zenswarm up --kill ROLE@T``: who delivers each SIGKILL (zenswarm.compose.kills, issue 44), without a process."""

from __future__ import annotations

from zenswarm.compose.kills import Kills, split_kills


def test_lockstep_roles_kill_themselves_at_the_first_tick_at_or_after_t_the_rest_are_killed_at_a_sim_time() -> None:
    pending, ticks = split_kills([("agent:2", 1.0), ("recorder", 1.5), ("plant", 0.015), ("leader", 0.02)], realtime=False, dt=0.01)
    assert pending == {"recorder": 1_500_000_000}
    assert ticks == {"agent:2": 100, "plant": 2, "leader": 2}


def test_realtime_every_kill_is_the_supervisors() -> None:
    pending, ticks = split_kills([("agent:2", 1.0), ("leader", 0.5)], realtime=True, dt=0.01)
    assert pending == {"agent:2": 1_000_000_000, "leader": 500_000_000} and ticks == {}


def test_a_flights_kills_first_start_only_its_death_time_and_the_supervisors_due() -> None:
    from zenswarm.process.lockstep import kill_self_line

    k = Kills([("agent:2", 1.0), ("recorder", 0.5)], realtime=False, dt=0.01)
    assert k.take_tick("agent:2") == 100 and k.take_tick("agent:2") is None, "a restarted agent is not killed again"
    assert k.take_tick("leader") is None
    said = ["agent:2: its last step", f"agent:2: {kill_self_line(100)}"]
    assert k.death_time("agent:2", -9, said, t_s=1.07) == 1.0, "it killed itself just before tick 100"
    assert k.death_time("agent:2", -9, said, t_s=1.07) == 1.07, "taken once: its restart dies at the time seen"
    # the recorder is the supervisor's to kill, once its sim time came and it runs
    assert k.kills_due(400_000_000, ["recorder"]) == [] and k.kills_due(500_000_000, ["plant"]) == []
    assert k.kills_due(500_000_000, ["plant", "recorder"]) == ["recorder"] and k.kills_due(900_000_000, ["recorder"]) == []


def test_a_death_that_was_not_the_kill_is_dated_when_seen() -> None:
    k = Kills([("plant", 0.5)], realtime=False, dt=0.01)
    assert k.take_tick("plant") == 50
    assert k.death_time("plant", 3, ["plant: error"], t_s=0.31) == 0.31, "exit 3: not its kill"

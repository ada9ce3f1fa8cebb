"""A user's tests of their controller plug-in (the example package zenswarm-consensus), written
with zenswarm's public pytest fixtures only (docs/testing.md). Run them anywhere with
zenswarm and the plug-in installed:  python -m pytest test_consensus.py

Short flights (6 s of paper example 1) in the in-process simulator and as the lockstep swarm of
OS processes; the fixture fails a test that leaves a process behind.
"""

from __future__ import annotations

import pytest

SCENARIO = "paper_example1"
SHORT = {
    "controller": "consensus",
    "duration": 6.0,  # s of sim time: the leader is still on its way, so "timeout" and "off_slot" are expected
    "overrides": {"timing.settle_time_s": 3.0},  # formation error measured from 3 s on (the UAVs start off their slots)
}
EXPECTED = ("timeout", "off_slot")  # what a flight cut short fails with
FORMATION_BOUND_M = 0.1  # m: fault-free about 0.06 m at 3-6 s, converging


@pytest.mark.parametrize("mode", ["sim", "swarm"])
def test_formation_holds_under_20_percent_loss_and_50ms_delay(zenswarm_fly, mode: str) -> None:
    f = zenswarm_fly(SCENARIO, mode=mode, link_loss=0.2, link_delay="50ms", seed=7, **SHORT)
    assert not f.failures_other_than(*EXPECTED), f.summary
    assert f.metrics.max_formation_error_m < FORMATION_BOUND_M, f.summary
    assert f.metrics.min_inter_uav_margin_m > 0 and f.metrics.min_obstacle_margin_m > 0, f.summary


def test_survives_sigkill_of_an_agent_with_restart(zenswarm_fly) -> None:
    """As processes: agent 2 is SIGKILLed at 2 s and restarted; it rejoins and the formation
    holds (the plant's failsafe hovers UAV 2 meanwhile)."""
    f = zenswarm_fly(SCENARIO, mode="swarm", kill=[("agent:2", 2.0)], restart=True, **SHORT)
    assert f.restarts == {"agent:2": 1}, f.log[-2000:]
    assert not f.failures_other_than(*EXPECTED), f.summary
    assert f.metrics.max_formation_error_m < 2 * FORMATION_BOUND_M, f.summary


def test_survives_losing_an_agent_in_process(zenswarm_fly) -> None:
    """In process, where there is no process to kill: agent 2 cut off from every link for 1 s
    (what its neighbours and the vehicle see of an outage); the formation holds."""
    f = zenswarm_fly(SCENARIO, partitions=["agent:2@2s-3s"], **SHORT)
    assert not f.failures_other_than(*EXPECTED), f.summary
    assert f.metrics.max_formation_error_m < 2 * FORMATION_BOUND_M, f.summary

"""The process shells' shared pieces: one agent tick (stacked == per agent, bit for bit), the
wall-clock loop helper and the typed process options built from the command line."""

from __future__ import annotations

import argparse
import threading
import time
from pathlib import Path

import numpy as np

from zenswarm.agents.core import AgentCore, AgentRow, StackedAgents
from zenswarm.bridge.args import add_process_args
from zenswarm.process.runtime import DEFAULT_LOCKSTEP_TIMEOUT_S, ProcessOptions, WallClock
from zenswarm.scenario.config import load_scenario
from zenswarm.vehicle.params import QuadParams

EX1 = Path(__file__).resolve().parents[1] / "compose" / "scenarios" / "paper_example1.toml"


def test_stacked_agents_tick_as_each_agent_does() -> None:
    """StackedAgents (the simulator's fast path) gives every agent's AgentCore results bit for bit."""
    sc = load_scenario(EX1)
    p = QuadParams.from_vehicle(sc.vehicle)
    rows = [AgentRow.from_scenario(sc, i, p.mass, p.g) for i in range(sc.n)]
    rng = np.random.default_rng(3)
    q, v = rng.normal(size=(sc.n, 3)), rng.normal(size=(sc.n, 3))
    stacked, cores = StackedAgents(rows), [AgentCore(r) for r in rows]
    stacked.reset(q, v)
    for i, c in enumerate(cores):
        c.reset(q[i], v[i])
    for _ in range(20):
        q0, v0 = rng.normal(size=3), rng.normal(size=3)
        qm, vm = q + 0.1 * rng.normal(size=q.shape), v + 0.1 * rng.normal(size=v.shape)
        refs = [(c.q_ref, c.v_ref) for c in cores]
        cmd = stacked.finish(qm, vm, stacked.rates_all(q0, v0))
        for i, c in enumerate(cores):
            nbr = [argparse.Namespace(q=refs[j][0], v=refs[j][1]) for j in c.row.neighbours]
            lead = argparse.Namespace(q=q0, v=v0) if c.row.pinned else None
            one = c.finish(qm[i], vm[i], c.rates_from(nbr, lead))
            assert one.thrust == cmd.thrust[i]
            for name in ("rpy", "u", "d_hat", "vdot_ref"):
                assert getattr(one, name).tobytes() == getattr(cmd, name)[i].tobytes(), name
            assert c.q_ref.tobytes() == stacked.q_ref[i].tobytes() and c.v_ref.tobytes() == stacked.v_ref[i].tobytes()


def test_wall_clock_keeps_the_period_and_stops() -> None:
    stop = threading.Event()
    clock = WallClock(0.01, stop)
    t0 = time.monotonic()
    for _ in range(5):
        assert clock.wait()
    assert time.monotonic() - t0 >= 0.04 - 1e-3  # the first deadline is now, then one per period
    assert clock.stats.ticks == 5
    stop.set()
    assert not clock.wait()


def test_wall_clock_resyncs_instead_of_a_burst() -> None:
    clock = WallClock(0.01, first_wait=True, resync_after_s=0.02)
    time.sleep(0.06)  # a stall: 5 periods late
    stall_end = time.monotonic()
    assert clock.wait() and clock.resyncs == 1
    # the next deadline is a period after the wait, not on the old grid (in the past): no burst
    assert clock.next >= stall_end + 0.01
    paced = WallClock(0.01, catch_up=False)
    time.sleep(0.03)
    late_end = time.monotonic()
    paced.wait()
    assert paced.next >= late_end + 0.01 and paced.resyncs == 0


def test_process_options_from_the_command_line() -> None:
    p = argparse.ArgumentParser()
    add_process_args(p)
    o = ProcessOptions.of(p.parse_args([]))
    assert o == ProcessOptions() and o.lockstep_timeout == DEFAULT_LOCKSTEP_TIMEOUT_S and o.connect == ()
    o = ProcessOptions.of(p.parse_args([
        "--swarm", "s1", "--connect", "tcp/127.0.0.1:1", "--connect", "tcp/127.0.0.1:2", "--realtime",
        "--lockstep-timeout", "2.5", "--link-loss", "0.2", "--partition", "agent:2@1s-2s", "--seed", "7",
        "--scenario", "x.toml",
    ]))
    assert o == ProcessOptions(scenario=Path("x.toml"), swarm="s1", connect=("tcp/127.0.0.1:1", "tcp/127.0.0.1:2"),
                               realtime=True, lockstep_timeout=2.5, link_loss="0.2", partition=("agent:2@1s-2s",), seed=7)
    assert ProcessOptions.of(o) is o

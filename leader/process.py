"""The leader process: runs the AAPF (eqs 8-15) and publishes the virtual leader's (q0, v0).

Publishes ``leader/ref`` and answers queries on ``mission`` with the scenario, so processes that
join late (or run on other hosts without the scenario file) can fetch it.

Lockstep: the leader's trajectory does not depend on the swarm, so it runs ahead: on the plant's
clock(c) (published every :data:`zenswarm.runtime.CLOCK_EVERY_TICKS` ticks) it publishes every
ref up to ref(c + :data:`zenswarm.runtime.LEADER_AHEAD_TICKS`), so pinned agents never wait for it
(the plant starts the clock only once every process has subscribed, so nothing is published into
the void; a leader that starts late catches up at once). Realtime: it follows the plant's clock on a fixed
loop, integrating from its current time to the newest clock time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from zenswarm import wire
from zenswarm.config import scenario_to_dict
from zenswarm.runtime import LEADER_AHEAD_TICKS, Lockstep, LoopStats, SwarmProcess, add_common_args, run_process

from .aapf import AapfParams, integrate_leader, total_force

__all__ = ["main", "add_parser"]


def _run(proc: SwarmProcess) -> int:
    sc = proc.scenario
    keys = proc.keys
    p = AapfParams.from_scenario(sc)
    dt = sc.timing.dt
    dt_ns = wire.t_ns(dt)
    nsub = sc.timing.substeps
    n_ticks = sc.timing.n_ticks
    mission = wire.encode(wire.Mission(t=0, seq=1, scenario=scenario_to_dict(sc)))

    def on_query(query) -> None:
        query.reply(keys.mission, mission)

    queryable = proc.session.declare_queryable(keys.mission, on_query)
    proc.subscribe(keys.clock, "clock")
    proc.watch_alive(["plant"])
    proc.announce()

    q0 = np.asarray(sc.leader.start, dtype=float).copy()
    k_q = 0  # tick index of q0
    seq = 0
    capped = 0

    def publish_current() -> None:
        nonlocal seq
        seq += 1
        proc.publish(keys.leader_ref, wire.Ref(t=k_q * dt_ns, seq=seq, q=q0.copy(), v=total_force(q0, p)))

    def advance() -> None:
        nonlocal q0, k_q, capped
        q0, info = integrate_leader(q0, dt, p, nsub)
        capped += int(info.capped)
        k_q += 1

    try:
        if not proc.args.realtime:
            def ready(k: int) -> bool:
                clk = proc.inbox.latest.get(keys.clock)
                return clk is not None and k <= (clk.t + dt_ns // 2) // dt_ns + LEADER_AHEAD_TICKS

            def step(k: int, forced: bool) -> None:
                if k > 0:
                    advance()
                publish_current()
                proc.inbox.forget_before(k - 2 * LEADER_AHEAD_TICKS)
                if k % 500 == 0:
                    proc.counters["substep_cap_hits"] = capped
                    proc.publish_diag(k * dt_ns)

            ls = Lockstep(n_ticks, ready, step, proc.args.lockstep_timeout, proc.stop, can_force=lambda k: False)
            proc.on_input = ls.poke
            k = ls.run()
            proc.publish_diag(k * dt_ns, {"finished": k >= n_ticks, **ls.timing()})
            proc.linger_until_gone("plant")
            return 0

        stats = LoopStats(dt)
        next_t = time.monotonic()
        published = -1
        limit = wire.t_ns(sc.timing.time_limit_s)
        while not proc.stop.is_set():
            now = time.monotonic()
            if now < next_t:
                time.sleep(next_t - now)
            stats.record(time.monotonic() - next_t)
            next_t += dt
            clk = proc.inbox.latest.get(keys.clock)
            if clk is not None and not proc.is_alive("plant"):
                break  # the plant is gone: the flight is over
            target = 0 if clk is None else int(round(clk.t / dt_ns)) + 1
            while k_q < target:
                advance()
            if k_q != published:
                publish_current()
                published = k_q
            if clk is not None and clk.t >= limit:
                break
            if stats.ticks % 100 == 0:
                proc.publish_diag(k_q * dt_ns, stats.as_dict())
        proc.publish_diag(k_q * dt_ns, stats.as_dict())
        return 0
    finally:
        queryable.undeclare()


def main(args: argparse.Namespace) -> int:
    return run_process(_run, "leader", args)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "leader",
        help="run the leader process (AAPF virtual leader)",
        description="Run the virtual leader: AAPF planner (eqs 8-15); publishes leader/ref and serves the mission.",
    )
    add_common_args(p)
    p.set_defaults(func=main)

"""The leader process: runs the scenario's planner (the paper's AAPF, eqs 8-15, by default) and
publishes the virtual leader's (q0, v0).

Publishes ``leader/ref`` and answers queries on ``mission`` with the scenario, so processes that
join late (or run on other hosts without the scenario file) can fetch it.

Lockstep: the leader's trajectory does not depend on the swarm, so it runs ahead: on the plant's
clock(c) (published every :data:`zenswarm.process.runtime.CLOCK_EVERY_TICKS` ticks) it publishes every
ref up to ref(c + :data:`zenswarm.process.runtime.LEADER_AHEAD_TICKS`), so pinned agents never wait for it
(the plant starts the clock only once every process has subscribed, so nothing is published into
the void; a leader that starts late catches up at once). Realtime: it follows the plant's clock on a fixed
loop (:class:`zenswarm.process.clocks.WallClock`), integrating from its current time to the newest clock time.

The leader's tick is :class:`zenswarm.leader.core.LeaderCore` (the in-process simulator runs the same).
Started with :class:`zenswarm.process.options.ProcessOptions` by :func:`run` (the command line is parsed at
the edge, :mod:`zenswarm.compose.roles`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from zenswarm.bus import wire
from zenswarm.leader.core import LeaderCore
from zenswarm.process.runtime import (
    LEADER_AHEAD_TICKS,
    Lockstep,
    ProcessOptions,
    SwarmProcess,
    WallClock,
    run_process,
)
from zenswarm.scenario.config import scenario_to_dict

if TYPE_CHECKING:
    import zenoh

__all__ = ["run"]


class _Leader:
    """The leader's publications around its :class:`LeaderCore`."""

    def __init__(self, proc: SwarmProcess) -> None:
        sc = proc.scenario
        assert sc is not None, "the process loads its scenario on start"
        self.sc = sc
        self.proc = proc
        self.keys = proc.keys
        self.core = LeaderCore.from_scenario(sc)
        self.dt_ns = wire.t_ns(sc.timing.dt)
        self.n_ticks = sc.timing.n_ticks
        self.seq = 0

    def publish_current(self) -> None:
        """ref(k) of the core's tick k: (q0, v0)."""
        self.seq += 1
        q0, v0 = self.core.ref()
        self.proc.put(self.keys.leader_ref, wire.encode_ref(self.core.k * self.dt_ns, self.seq, q0, v0))

    def diag(self, info: dict | None = None) -> None:
        self.proc.counters.update(self.core.planner.counters())
        self.proc.publish_diag(self.core.k * self.dt_ns, info)

    # ------------------------------------------------------------------ lockstep
    def ready(self, k: int) -> bool:
        """Tick k may run: at most LEADER_AHEAD_TICKS past the newest clock."""
        clk = self.proc.inbox.latest.get(self.keys.clock)
        return clk is not None and k <= (clk.t + self.dt_ns // 2) // self.dt_ns + LEADER_AHEAD_TICKS

    def step(self, k: int, forced: bool) -> None:
        if k > 0:
            self.core.advance()
        self.publish_current()
        self.proc.inbox.forget_before(k - 2 * LEADER_AHEAD_TICKS)
        if k % 500 == 0:
            self.diag()

    def run_lockstep(self) -> int:
        proc = self.proc
        ls = Lockstep(self.n_ticks, self.ready, self.step, proc.options.lockstep_timeout, proc.stop, can_force=lambda k: False,
                      kill_at=proc.options.kill_at_tick, name=proc.name)
        proc.on_input = ls.poke
        k = ls.run()
        proc.publish_diag(k * self.dt_ns, {"finished": k >= self.n_ticks, **ls.timing()})
        proc.linger_until_gone("plant")
        return 0

    # ------------------------------------------------------------------ realtime
    def run_realtime(self) -> int:
        """Follow the plant's clock on a fixed loop: integrate up to the newest clock time."""
        proc, core = self.proc, self.core
        clock = WallClock(self.sc.timing.dt, proc.stop)
        published = -1
        limit = wire.t_ns(self.sc.timing.time_limit_s)
        while clock.wait():
            clk = proc.inbox.latest.get(self.keys.clock)
            if clk is not None and not proc.is_alive("plant"):
                break  # the plant is gone: the flight is over
            target = 0 if clk is None else int(round(clk.t / self.dt_ns)) + 1
            if clk is not None:
                clock.stats.flight_started()  # the loop's figures cover the flight (LoopStats)
            while core.k < target:
                core.advance()
            proc.inbox.forget_before(target - 2)  # only the latest clock is used: keep memory flat
            if core.k != published:
                self.publish_current()
                published = core.k
            if clk is not None and clk.t >= limit:
                break
            if clock.stats.ticks % 100 == 0:
                proc.publish_diag(core.k * self.dt_ns, clock.stats.as_dict())
        proc.publish_diag(core.k * self.dt_ns, clock.stats.as_dict())
        return 0


def _run(proc: SwarmProcess) -> int:
    leader = _Leader(proc)
    keys = proc.keys
    mission = wire.encode(wire.Mission(t=0, seq=1, scenario=scenario_to_dict(leader.sc)))

    def on_query(query: zenoh.Query) -> None:
        query.reply(keys.mission, mission)

    session = proc.session
    assert session is not None, "the process opens its session on start"
    queryable = session.declare_queryable(keys.mission, on_query)
    proc.subscribe(keys.clock, "clock")
    proc.watch_alive(["plant"])
    proc.announce()
    try:
        return leader.run_realtime() if proc.options.realtime else leader.run_lockstep()
    finally:
        queryable.undeclare()


def run(options: ProcessOptions) -> int:
    """Run the leader until the flight ends; the exit code (2: bad input)."""
    return run_process(_run, "leader", options)

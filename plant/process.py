"""The plant process: simulates every UAV with the core model and is the clock in lockstep.

Subscribes to each UAV's ``uav/<i>/cmd``; publishes ``clock`` and each ``uav/<i>/state`` (with what
the plant model records, :attr:`zenswarm.plant.core.PlantCore.recorded`, in its ``extra``).
Lockstep tick k: publish state_i(k) for all i, wait for every cmd_i(k) (a timeout
counts as a drop and holds the UAV's previous command; an agent whose liveliness token is gone is
not waited for), then integrate ``timing.substeps`` physics sub-steps. A UAV whose newest command
is too old goes into the failsafe of :mod:`zenswarm.plant.failsafe` (hover, then land). The clock, read by
the leader and the supervisor only, goes out every :data:`zenswarm.process.runtime.CLOCK_EVERY_TICKS`
ticks: clock(0) with the first states, then clock(k + 1) as the integration of tick k starts, so
the leader's burst of refs overlaps the integration, not the agents' work. It starts only
when the leader and every agent have announced themselves. After its last tick it stays (token
held) until every live agent's command of the last tick has arrived, at most
:data:`LAST_COMMANDS_TIMEOUT_S`: with delay on the command links its last tick needs only older
commands, so it can finish while an agent is still ticking, and the leader and the agents leave
once the plant is gone (a receiver does not wait for a sender whose token is gone).
Realtime: a fixed-rate loop at the control rate (:class:`zenswarm.process.clocks.WallClock`); each period
integrates one control period of physics with the latest command of each UAV (hover thrust, level,
before the first one).

The plant's tick is :class:`zenswarm.plant.core.PlantCore` (the in-process simulator runs the same).
Started with :class:`PlantOptions` by :func:`run` (the command line is parsed at the edge,
:mod:`zenswarm.compose.roles`; ``plant --mavlink`` runs :mod:`zenswarm.plant.mavlink_vehicle` instead).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from zenswarm.bus import wire
from zenswarm.link import Box, FaultState, box_counters, due_tick
from zenswarm.plant.core import PlantCore
from zenswarm.process.runtime import (
    CLOCK_EVERY_TICKS,
    Lockstep,
    ProcessOptions,
    SwarmProcess,
    WallClock,
    run_process,
)

__all__ = ["PlantOptions", "run", "LAST_COMMANDS_TIMEOUT_S"]

LAST_COMMANDS_TIMEOUT_S = 30.0
"""Lockstep end: wall seconds the plant stays for the agents' commands of the last tick (the
leader and the agents stay as long for the plant: :meth:`zenswarm.process.runtime.SwarmProcess.linger_until_gone`)."""


@dataclass(frozen=True)
class PlantOptions:
    """The common process options, and ``expect``: more processes (e.g. ``recorder``) to wait
    for before the first tick, beside the leader and every agent."""

    process: ProcessOptions = field(default_factory=ProcessOptions)
    expect: tuple[str, ...] = ()


class _Plant:
    """The plant's keys, links and publications around its :class:`PlantCore`."""

    def __init__(self, proc: SwarmProcess) -> None:
        sc = proc.scenario
        assert sc is not None, "the process loads its scenario on start"
        self.sc = sc
        self.proc = proc
        self.keys = proc.keys
        self.core = PlantCore(sc)
        self.n = sc.n
        self.dt = sc.timing.dt
        self.dt_ns = wire.t_ns(self.dt)
        self.n_ticks = sc.timing.n_ticks
        self.realtime = proc.options.realtime
        self.cmd_keys = [self.keys.cmd(i + 1) for i in range(self.n)]
        self.state_keys = [self.keys.state(i + 1) for i in range(self.n)]
        self.agents = [wire.agent(i + 1) for i in range(self.n)]
        self.boxes: dict[str, Box] = {}
        self.seq = 0

    def use_faults(self) -> None:
        """Link faults: lockstep commands go through receive boxes, realtime ones a delay line."""
        proc = self.proc
        plan = proc.options.fault_plan(self.sc)
        if plan is None:
            return
        links = {key: (self.agents[i], "plant", "cmd") for i, key in enumerate(self.cmd_keys)}
        if self.realtime:
            proc.use_delay_line(FaultState(plan), links)
            return
        fstate = FaultState(plan)
        boxes = self.boxes = {key: Box(fstate, *links[key], self.dt) for key in self.cmd_keys}

        def link_counters() -> dict[str, float]:
            return dict(box_counters(boxes))

        proc.extra_counters = link_counters

    def publish_tick(self, k: int) -> None:
        """state_i(k) of every UAV (and, in realtime or at k = 0, clock(k))."""
        self.seq += 1
        t = k * self.dt_ns
        st = self.core.state
        put, enc, seq = self.proc.put, wire.encode_state, self.seq
        recorded = self.core.recorded
        if recorded:  # the model's records of this state, per UAV: name -> flat list of floats
            rows = {name: a.reshape(self.n, -1).tolist() for name, a in recorded.items()}
            for i, (key, q, v, rpy, w) in enumerate(zip(self.state_keys, st.q, st.v, st.rpy, st.w, strict=True)):
                put(key, enc(t, seq, q, v, rpy, w, {name: r[i] for name, r in rows.items()}))
        else:
            for key, q, v, rpy, w in zip(self.state_keys, st.q, st.v, st.rpy, st.w, strict=True):
                put(key, enc(t, seq, q, v, rpy, w))  # the states first: they are what the agents wait for
        if self.realtime or k == 0:  # lockstep: publish_clock_early
            self.proc.publish(self.keys.clock, wire.Clock(t=t, seq=self.seq))

    def publish_clock_early(self, k: int) -> None:
        """Lockstep: clock(k + 1) once the commands of tick k are in, before integrating: the
        leader then runs ahead while the plant integrates (when the agents wait) rather than
        when the agents compute. Every CLOCK_EVERY_TICKS ticks and at the end."""
        k1 = k + 1
        if k1 % CLOCK_EVERY_TICKS == 0 or k1 >= self.n_ticks:
            self.proc.publish(self.keys.clock, wire.Clock(t=k1 * self.dt_ns, seq=self.seq + 1))

    def integrate(self, k: int) -> None:
        """Step 7 of tick k (:meth:`PlantCore.step`); failsafe changes are logged and diagnosed."""
        events = self.core.step(k)
        if events:
            proc = self.proc
            for ev in events:
                proc.log(f"plant: tick {ev[0]} (t = {ev[0] * self.dt:.2f} s): UAV {ev[1]} failsafe {ev[2]} -> {ev[3]}")
            proc.counters["failsafe_events"] = len(self.core.failsafe.events)
            proc.publish_diag(k * self.dt_ns, {"failsafe": self.failsafe_summary()})

    def failsafe_summary(self) -> str:
        return self.core.failsafe.summary() or "none"


class _LockstepPlant:
    """The lockstep clock: publish state(k), wait for every cmd(k) (:class:`Lockstep`), integrate."""

    def __init__(self, plant: _Plant) -> None:
        self.p = plant
        self.proc = plant.proc
        # while an agent is down, run no faster than real time
        self.pacer = WallClock(plant.dt, catch_up=False)
        self.ls = Lockstep(
            plant.n_ticks,
            self.ready,
            self.step,
            self.proc.options.lockstep_timeout,
            self.proc.stop,
            on_msg=self.on_msg,
            kill_at=self.proc.options.kill_at_tick,
            name=self.proc.name,
        )
        self.seen: set[str] = set()  # agents seen alive
        self.back: set[str] = set()  # agents that died and have sent nothing since (restarted: not waited for)
        self.sender = dict(zip(plant.cmd_keys, plant.agents, strict=True))
        self.index = {key: i for i, key in enumerate(plant.cmd_keys)}
        # tick k and the UAVs (indices) whose cmd(k) is not in yet: ready(k) checks only these
        self.missing_k = -1
        self.missing: set[int] = set()

    def on_msg(self, key: str, k: int, msg: wire.Cmd) -> None:  # under the lockstep lock
        if k == self.missing_k:
            self.missing.discard(self.index.get(key, -1))
        if self.p.boxes:
            self.p.boxes[key].offer(k, msg.seq, msg)
        if self.back:
            self.back.discard(self.sender.get(key, ""))  # a restarted agent's first command: wait for it again

    def needed(self, i: int, k: int) -> bool:
        """Wait for agent i's cmd(k)? Not if it is gone or has moved past the tick of the
        command due (a restarted agent that skipped it; with link faults, its box's due one:
        :func:`zenswarm.link.swarm.due_tick`)."""
        name = self.p.agents[i]
        if not self.proc.is_alive(name):
            if name in self.seen:
                self.back.add(name)  # it died: once back, it joins at the next state it sees
            return False
        self.seen.add(name)
        if name in self.back:
            return False  # back, nothing from it yet: state(k) went out before it subscribed
        key = self.p.cmd_keys[i]
        m = self.proc.inbox.latest.get(key)
        return m is None or m.t <= due_tick(self.p.boxes.get(key) if self.p.boxes else None, k) * self.p.dt_ns

    def ready(self, k: int) -> bool:
        p, inbox = self.p, self.proc.inbox
        if p.boxes:
            return all(b.ready(k) or not self.needed(i, k) for i, b in enumerate(p.boxes.values()))
        if k != self.missing_k:  # once per tick; then on_msg takes each command off
            self.missing_k = k
            self.missing = {i for i, key in enumerate(p.cmd_keys) if inbox.get(key, k) is None}
        return all(not self.needed(i, k) for i in self.missing)

    def pace(self) -> None:
        """While an agent is down, run no faster than real time: failsafe timers and restart
        delays then mean in sim time what they mean on the wall clock."""
        if all(self.proc.is_alive(a) for a in self.p.agents):
            return
        self.proc.counters["paced_ticks"] += 1
        self.pacer.wait()

    def take_commands(self, k: int, forced: bool) -> None:
        """Hold each UAV's command of tick k (from its receive box with link faults)."""
        p = self.p
        for i, key in enumerate(p.cmd_keys):
            if p.boxes:
                b = p.boxes[key]
                if forced and not b.ready(k):
                    b.timed_out(k)
                held = b.at(k)
                if held is not None:
                    p.core.hold(i, held.value.thrust, held.value.rpy, held.send_tick)
            else:
                c = self.proc.inbox.get(key, k)
                if c is not None:
                    p.core.hold(i, c.thrust, c.rpy, k)

    def step(self, k: int, forced: bool) -> None:
        p, proc = self.p, self.proc
        if forced:
            proc.counters["cmd_timeouts"] += 1
        self.take_commands(k, forced)
        p.publish_clock_early(k)
        p.integrate(k)
        proc.inbox.forget_before(k - 1)
        if k % 500 == 0:
            proc.publish_diag(k * p.dt_ns)
        self.pace()
        p.publish_tick(k + 1)  # the last one is the final state, t = time limit

    def run(self) -> int:
        p, proc = self.p, self.proc
        proc.watch_alive(p.agents, self.ls.poke)
        with self.ls.lock:
            p.publish_tick(0)
        k = self.ls.run()
        proc.publish_diag(k * p.dt_ns, {"finished": k >= p.n_ticks, "failsafe": p.failsafe_summary(), **self.ls.timing()})
        if k >= p.n_ticks:
            self.await_last_commands()
        return 0

    def await_last_commands(self, timeout_s: float = LAST_COMMANDS_TIMEOUT_S) -> None:
        """Stay (token held) until every agent whose token is present has sent its command of the
        last tick, i.e. has run all its ticks, at most ``timeout_s`` (then the agents still
        missing are said) or until stopped. With delay on the command links the
        plant's last tick needs commands of earlier ticks only, so it can finish while an agent is
        still a few ticks behind; the leader and the agents leave once the plant is gone, and an
        agent still ticking would then take its neighbours' and the leader's normal exit for a
        crash and stop waiting for the messages they sent (under load their tokens' removal can
        overtake those messages in the router): the swarm would not fly the simulator's flight."""
        p, proc = self.p, self.proc
        last_t = (p.n_ticks - 1) * p.dt_ns

        def behind() -> list[str]:
            latest = proc.inbox.latest
            return [
                a
                for a, key in zip(p.agents, p.cmd_keys, strict=True)
                if proc.is_alive(a) and ((m := latest.get(key)) is None or m.t < last_t)
            ]

        deadline = time.monotonic() + timeout_s
        while (left := behind()) and not proc.stop.is_set():
            if time.monotonic() > deadline:
                proc.log(f"plant: leaving after {timeout_s:g} s without the last tick's command of {', '.join(left)}")
                return
            time.sleep(0.005)  # poll interval of a bounded wait


def _run_realtime(p: _Plant) -> int:
    """Each period: publish the states, integrate one control period with the latest commands."""
    proc, core = p.proc, p.core
    clock = WallClock(p.dt, proc.stop, first_wait=True)
    k = 0
    while k <= p.n_ticks and not proc.stop.is_set():
        p.publish_tick(k)
        if k == p.n_ticks:
            break
        proc.release_delayed()
        for i, key in enumerate(p.cmd_keys):
            c = proc.inbox.latest.get(key)
            if c is not None and c.t >= core.last_cmd_tick[i] * p.dt_ns:
                core.hold(i, c.thrust, c.rpy, int(round(c.t / p.dt_ns)))
        p.integrate(k)
        proc.inbox.forget_before(k - 2)  # only the latest commands are used: keep memory flat
        k += 1
        clock.wait()
        if k % 100 == 0:
            proc.publish_diag(k * p.dt_ns, clock.stats.as_dict())
    proc.publish_diag(k * p.dt_ns, {**clock.stats.as_dict(), "finished": k >= p.n_ticks, "failsafe": p.failsafe_summary()})
    return 0


def _run(proc: SwarmProcess, expect: tuple[str, ...]) -> int:
    plant = _Plant(proc)
    plant.use_faults()
    lockstep = None if plant.realtime else _LockstepPlant(plant)
    if lockstep is not None:
        proc.on_input = lockstep.ls.poke
    for key in plant.cmd_keys:
        proc.subscribe(key, "cmd")
    proc.announce()
    missing = proc.wait_for_alive(["leader"] + plant.agents + list(expect), timeout_s=60.0)
    if proc.stop.is_set():
        return 0
    if missing:
        proc.log(f"plant: these processes never announced themselves: {', '.join(missing)}")
        return 3
    return _run_realtime(plant) if lockstep is None else lockstep.run()


def run(options: PlantOptions) -> int:
    """Run the plant until the flight ends; the exit code (2: bad input, 3: a process never came,
    4: the plant model failed, :class:`zenswarm.errors.PluginFailure`, reported by
    :func:`zenswarm.process.runtime.run_process`)."""
    return run_process(lambda proc: _run(proc, options.expect), "plant", options.process)

"""The agent process: one per UAV. A shell around the scenario's controller plug-in
(:class:`zenswarm.agents.api.Controller`; the paper's by default): it decodes inputs, hands them
to the controller (:func:`zenswarm.agents.api.prepare` / :func:`zenswarm.agents.api.finish`, the
simulator's tick) and publishes what it computes.

Subscribes to exactly its graph row: its own state ``uav/<i>/state``, its neighbours'
references ``uav/<j>/ref`` (a_ij > 0) and, only if pinned (b_i > 0), ``leader/ref``. Publishes its
reference ``uav/<i>/ref`` and its command ``uav/<i>/cmd``. See :func:`subscriptions`.

Lockstep tick k: wait for state(k) (the plant's clock); first tick: start the generator from it
and publish ref(k); wait for the neighbours' ref(k) and, if pinned, leader ref(k); compute and
publish cmd(k) and ref(k+1) (the controller's :meth:`~zenswarm.agents.api.Controller.share`).
A two-phase controller (the paper's: its generator rates of tick k need only the references)
prepares as soon as the references are in (usually while the plant integrates): when state(k)
arrives, only the control law (28) and the inversion stand between it and cmd(k).
A timeout (``--lockstep-timeout``) counts as a drop and holds
the newest earlier value; a sender whose liveliness token is gone is not waited for. With link
faults each input goes through its link's :class:`zenswarm.link.swarm.Box` (hold last value),
exactly as in the in-process simulator. A (re)started agent joins at the first state it sees and
restarts its generator from it.
Realtime: the same computation at the control rate on the wall clock with the latest values
(:class:`zenswarm.process.clocks.WallClock`), on each new state; when states were skipped (late, lost,
or a MAVLink vehicle's telemetry slower than the control rate) the ESO and the generator integrate
over the time that elapsed since the state last ticked on (its tick index, see
:func:`zenswarm.agents.core.elapsed_dt` and :meth:`zenswarm.agents.core.AgentCore.advance_elapsed`),
so the references keep pace with the leader, which catches up to the clock. Counters
``skipped_ticks`` and ``max_gap_ticks`` in the diagnostics.

Started with :class:`AgentOptions` by :func:`run` (the command line is parsed at the edge,
:mod:`zenswarm.compose.roles`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from zenswarm.agents.api import (
    Command,
    Controller,
    boundary_of,
    build_controller,
    checked_finish,
    checked_prepare,
    checked_reset,
    checked_share,
)
from zenswarm.agents.core import AgentRow, elapsed_dt
from zenswarm.bus import wire
from zenswarm.errors import ScenarioError
from zenswarm.link import Box, FaultState, box_counters, due_tick
from zenswarm.process.runtime import (
    Lockstep,
    ProcessOptions,
    SwarmProcess,
    WallClock,
    run_process,
)
from zenswarm.scenario.plugins import plant_vehicle

__all__ = ["AgentOptions", "run", "subscriptions"]

REALTIME_JOIN_GRACE_S = 1.0
"""Sim seconds into a realtime flight within which an agent's first state is an on-time start
(the plant's clock starts once every agent is up; its first states may pass before the agent
subscribed), not a late join to report."""


@dataclass(frozen=True)
class AgentOptions:
    """Agent ``id`` (UAV number, 1..N as in the paper) and the common process options."""

    id: int
    process: ProcessOptions = field(default_factory=ProcessOptions)


def subscriptions(keys: wire.Keys, row: AgentRow) -> list[tuple[str, str]]:
    """(key, kind) pairs agent ``row.i`` subscribes to: its graph row and nothing more."""
    subs = [(keys.state(row.i + 1), "state")]
    subs += [(keys.ref(j + 1), "ref") for j in row.neighbours]
    if row.pinned:
        subs.append((keys.leader_ref, "ref"))
    return subs


@dataclass
class _Early:
    """Phase 1 of tick ``k`` (:func:`zenswarm.agents.api.prepare`) done ahead from ``msgs`` (the
    input messages, in ``input_keys`` order) by the controller in generation ``gen``."""

    k: int
    gen: int
    msgs: list[Any]
    prepared: Any


class _Agent:
    """Agent ``index``'s keys, links and publications around its controller."""

    def __init__(self, proc: SwarmProcess, index: int) -> None:
        sc = proc.scenario
        assert sc is not None, "the process loads its scenario on start"
        self.sc = sc
        self.proc = proc
        self.index = index
        self.me = wire.agent(index)
        self.quad = params = plant_vehicle(sc)  # the plant model's vehicle (mass, g)
        self.row = AgentRow.from_scenario(sc, index - 1, params.mass, params.g)
        self.bound = boundary_of(sc, index - 1)  # where the controller is called: its failures are named
        self.ctrl: Controller = build_controller(sc, index - 1, params.mass, params.g)
        self.gen = 0  # counts the controller's ticks and restarts (what a prepared phase 1 belongs to)
        keys = self.keys = proc.keys
        self.state_key = keys.state(index)
        self.nbr_keys = [keys.ref(j + 1) for j in self.row.neighbours]
        self.input_keys = self.nbr_keys + ([keys.leader_ref] if self.row.pinned else [])
        self.sender = {self.state_key: "plant", keys.leader_ref: "leader"}
        self.sender.update({keys.ref(j + 1): wire.agent(j + 1) for j in self.row.neighbours})
        self.ref_key, self.cmd_key = keys.ref(index), keys.cmd(index)
        self.dt = sc.timing.dt
        self.dt_ns = wire.t_ns(self.dt)
        self.n_ticks = sc.timing.n_ticks
        self.seq = 0
        self.boxes: dict[str, Box] = {}
        self.radio = False  # a radio model is active: stamp refs with the position (zenswarm.link.radio)
        self.stamp: Any = None  # the position stamped on the next ref: the raw state of the tick it is sent on

    def links(self) -> dict[str, tuple[str, str, str]]:
        """key -> (sender, receiver, link kind) of every input."""
        kind = {self.state_key: "state", self.keys.leader_ref: "leader"}
        return {key: (self.sender[key], self.me, kind.get(key, "ref")) for key in [self.state_key] + self.input_keys}

    def use_faults(self) -> None:
        """Link faults: lockstep inputs go through receive boxes, realtime ones a delay line."""
        proc = self.proc
        plan = proc.options.fault_plan(self.sc)
        if plan is None:
            return
        self.radio = plan.radio_active
        if proc.options.realtime:
            proc.use_delay_line(FaultState(plan), self.links())
            return
        fstate = FaultState(plan)
        boxes = self.boxes = {key: Box(fstate, *link, self.dt) for key, link in self.links().items()}

        def link_counters() -> dict[str, float]:
            return dict(box_counters(boxes))

        proc.extra_counters = link_counters

    def publish_ref(self, t_ns: int) -> None:
        """The controller's :meth:`~zenswarm.agents.api.Controller.share` for sim time ``t_ns``
        (its tick: ``t_ns / dt``), checked, as ``uav/<i>/ref``."""
        sh = checked_share(self.ctrl, self.bound, int(round(t_ns / self.dt_ns)))
        self.seq += 1
        pos = tuple(self.stamp) if self.radio and self.stamp is not None else ()
        if sh.extra:
            self.proc.publish(self.ref_key, wire.Ref(t=t_ns, seq=self.seq, q=sh.q, v=sh.v, extra=dict(sh.extra), pos=pos))  # type: ignore[arg-type]
        elif pos:
            self.proc.publish(self.ref_key, wire.Ref(t=t_ns, seq=self.seq, q=sh.q, v=sh.v, pos=pos))
        else:
            self.proc.put(self.ref_key, wire.encode_ref(t_ns, self.seq, sh.q, sh.v))

    def publish_cmd(self, t_ns: int, cmd: Command) -> None:
        self.seq += 1
        self.proc.put(self.cmd_key, wire.encode_cmd(t_ns, self.seq, cmd.thrust, cmd.rpy, cmd.u, cmd.d_hat))

    def start(self, st: wire.State, k: int) -> None:
        """(Re)start the controller from a measured state and share ref(k). A late join (a rejoin,
        a restarted process, a lockstep start after tick 0, a realtime one more than
        :data:`REALTIME_JOIN_GRACE_S` into the flight) is said; a realtime agent whose first
        state is one of the first ticks (the plant's clock starts once every agent is up) joined on time."""
        late = self.gen > 0 or (k > 0 and (not self.proc.options.realtime or k * self.dt > REALTIME_JOIN_GRACE_S))
        self.gen += 1
        checked_reset(self.ctrl, self.bound, k, st.q, st.v)
        self.stamp = st.q
        self.publish_ref(k * self.dt_ns)
        if late:
            self.proc.log(f"{self.me}: joined at tick {k} (t = {k * self.dt:.2f} s), generator restarted from the measured state")

    def restart(self) -> None:
        """A fresh controller that starts at the next state (a rejoin)."""
        self.gen += 1
        self.ctrl = build_controller(self.sc, self.index - 1, self.quad.mass, self.quad.g)

    def prepare(self, inputs: Mapping[str, Any], k: int) -> Any:
        """Phase 1 of tick k from the inputs given (a missing neighbour or leader: None)."""
        return checked_prepare(self.ctrl, self.bound, k, [inputs.get(key) for key in self.nbr_keys], inputs.get(self.keys.leader_ref))

    def tick(self, k: int, st: wire.State, prepared: Any, dt: float | None = None) -> None:
        """Tick k (phase 2 with the state) over ``dt`` s (None: one control period, always so in
        lockstep; a realtime agent that skipped ticks passes the time that elapsed), then publish
        cmd(k) and ref(k+1)."""
        cmd = checked_finish(self.ctrl, self.bound, k, st.q, st.v, prepared, self.dt if dt is None else dt)
        self.gen += 1
        t = st.t if self.proc.options.realtime else k * self.dt_ns
        self.publish_cmd(t, cmd)
        self.publish_ref(t + self.dt_ns)


class _LockstepAgent:
    """The lockstep tick of an agent: wait for its inputs of tick k (:class:`Lockstep`), then tick."""

    def __init__(self, agent: _Agent) -> None:
        self.a = agent
        self.proc = agent.proc
        self.held: dict[str, wire.Ref] = {}
        self.join_tick = 0
        self.early: _Early | None = None  # rates of a tick computed ahead
        self.seen: set[str] = set()  # senders seen alive
        self.back: set[str] = set()  # senders that died and have sent nothing since (restarted: not waited for)
        self.ls = Lockstep(
            agent.n_ticks, self.ready, self.step, self.proc.options.lockstep_timeout, self.proc.stop,
            prepare=self.prepare, can_force=self.state_in, on_msg=self.on_msg,
            kill_at=self.proc.options.kill_at_tick, name=self.proc.name,
        )

    def state_in(self, k: int) -> bool:
        """The plant's state of tick k (the clock) is in."""
        return self.proc.inbox.get(self.a.state_key, k) is not None

    def on_msg(self, key: str, k: int, msg: Any) -> None:  # under the lockstep lock
        a = self.a
        self.back.discard(a.sender[key])  # a restarted sender's first message: wait for it again
        if a.boxes:
            if key == a.state_key:
                a.boxes[key].offer(k, msg.seq, msg)
                for b in a.boxes.values():  # the receiver's true position of tick k (radio links)
                    b.own_position(k, msg.q)
            elif key == a.keys.leader_ref:
                a.boxes[key].offer(k, msg.seq, msg, msg.q)  # the leader flies q0 (zenswarm.link.radio)
            else:
                a.boxes[key].offer(k, msg.seq, msg, msg.pos)
        if key == a.state_key and not a.ctrl.initialised and k > self.ls.k:
            self.ls.k = self.join_tick = k  # a (re)started agent joins at the first state it sees

    def prepare(self, k: int) -> None:
        a, inbox = self.a, self.proc.inbox
        if not a.ctrl.initialised:
            st = inbox.get(a.state_key, k)
            if st is not None:
                a.start(st, k)
            return
        # A two-phase controller's first phase depends on the references only: run it as soon
        # as every input of tick k is in, usually while the plant integrates, so that when
        # state(k) arrives only the second phase stands between it and cmd(k).
        if (self.early is not None and self.early.k == k) or a.boxes or not getattr(a.ctrl, "two_phase", False):
            return
        msgs = [inbox.get(key, k) for key in a.input_keys]
        if None in msgs:
            return
        self.early = _Early(k, a.gen, msgs, a.prepare(dict(zip(a.input_keys, msgs, strict=True)), k))

    def needed(self, key: str, k: int) -> bool:
        """Wait for this input of tick k? Not if its sender is gone, or if the sender has
        already moved past the tick of the message due (a restarted neighbour that skipped it:
        one key's messages arrive in the order they were sent, so one never sent is never
        coming). With link faults the message due is its box's (:func:`due_tick`)."""
        name = self.a.sender[key]
        if not self.proc.is_alive(name):
            if name in self.seen:
                self.back.add(name)  # it died: once back, it joins at the next state it sees
            return False
        self.seen.add(name)
        if name in self.back:
            return False  # back, nothing from it yet: what it would send for tick k needs a state it missed
        m = self.proc.inbox.latest.get(key)
        return m is None or m.t <= due_tick(self.a.boxes.get(key), k) * self.a.dt_ns

    def ready(self, k: int) -> bool:
        a, inbox = self.a, self.proc.inbox
        if not self.state_in(k):
            return False
        if k == self.join_tick and k > 0:
            return True  # rejoining: the inputs of this tick were sent before we subscribed
        if a.boxes:
            return all(b.ready(k) or not self.needed(key, k) for key, b in a.boxes.items())
        return all(inbox.get(key, k) is not None or not self.needed(key, k) for key in a.input_keys)

    def _boxed_inputs(self, k: int, forced: bool) -> tuple[wire.State, dict[str, Any]]:
        """State and inputs of tick k as the receive boxes hold them (link faults)."""
        boxes = self.a.boxes
        if forced:
            for b in boxes.values():
                if not b.ready(k):
                    b.timed_out(k)
        got = {key: b.at(k) for key, b in boxes.items()}
        held_state = got.pop(self.a.state_key)
        inputs = {key: h.value for key, h in got.items() if h is not None}
        if held_state is None:
            # A (re)joined agent whose first state has not come through its faulty link yet: it
            # ticks on the state it joined with, as received (ready(k): state(k) is in).
            st = self.proc.inbox.get(self.a.state_key, k)
            assert st is not None, "ready(k): the state of tick k is in"
            return st, inputs
        return held_state.value, inputs

    def _held_inputs(self, k: int) -> tuple[wire.State, list[Any], Mapping[str, Any]]:
        """State, the messages of tick k (None: missing) and the inputs with the newest earlier
        value held for a missing one."""
        inbox = self.proc.inbox
        msgs = [inbox.get(key, k) for key in self.a.input_keys]
        for key, m in zip(self.a.input_keys, msgs, strict=True):
            if m is not None:
                self.held[key] = m
            elif key in self.held:
                self.proc.counters["held_inputs"] += 1
        st = inbox.get(self.a.state_key, k)
        assert st is not None, "ready(k): the state of tick k is in"
        return st, msgs, self.held

    def step(self, k: int, forced: bool) -> None:
        a, proc = self.a, self.proc
        e, self.early = self.early, None
        if a.boxes:
            st, inputs = self._boxed_inputs(k, forced)
            prepared = a.prepare(inputs, k)
        else:
            st, msgs, held = self._held_inputs(k)
            if e is not None and e.k == k and e.gen == a.gen and all(x is y for x, y in zip(e.msgs, msgs, strict=True)):
                prepared = e.prepared  # the same inputs as prepared ahead
            else:
                prepared = a.prepare(held, k)
        if forced:
            proc.counters["input_timeouts"] += 1
            # said at once (rare): `verify` names it when the recording cannot reproduce this tick
            proc.publish_diag(k * a.dt_ns, {"lockstep_timeout_tick": k})
        raw = proc.inbox.get(a.state_key, k)  # the plant's state of tick k as sent (true position)
        a.stamp = raw.q if raw is not None else st.q
        a.tick(k, st, prepared)
        proc.inbox.forget_before(k - 2)
        if k % 500 == 0:
            proc.publish_diag(k * a.dt_ns)

    def on_reconnect(self) -> None:
        """Back from a split longer than the session lease: what we waited for is lost, so
        rejoin like a restarted agent, at the next state we see, from the measured state."""
        with self.ls.lock:
            self.a.restart()
            self.proc.log(f"{self.a.me}: will rejoin at the next state (generator restarted from it)")

    def run(self) -> int:
        a, proc = self.a, self.proc
        proc.on_input = self.ls.poke
        proc.on_reconnect = self.on_reconnect
        proc.watch_alive(sorted(set(a.sender[key] for key in [a.state_key] + a.input_keys)), self.ls.poke)
        for key, kind in subscriptions(a.keys, a.row):
            proc.subscribe(key, kind)
        proc.announce()
        k = self.ls.run()
        proc.publish_diag(k * a.dt_ns, {"finished": k >= a.n_ticks, **self.ls.timing()})
        proc.linger_until_gone("plant")
        return 0


def _run_realtime(a: _Agent) -> int:
    """Fixed-rate loop on the wall clock: tick on each new state with the latest inputs."""
    proc = a.proc
    for key, kind in subscriptions(a.keys, a.row):
        proc.subscribe(key, kind)
    proc.watch_alive(["plant", "bridge"])  # the plant, or a vehicle bridge in its place
    proc.announce()
    clock = WallClock(a.dt, proc.stop)
    last_state_t = -1
    k_prev: int | None = None
    limit_ns = wire.t_ns(a.sc.timing.time_limit_s)
    while not (last_state_t >= 0 and not (proc.is_alive("plant") and proc.is_alive("bridge"))) and clock.wait():
        # (the plant or bridge gone: its last messages may never come, the flight is over; a UAV
        # whose vehicle the bridge lost gets no state at the last tick)
        proc.release_delayed()
        st = proc.inbox.latest.get(a.state_key)
        if st is None or st.t == last_state_t:
            continue
        last_state_t = st.t
        if st.t >= limit_ns:
            break
        k = int(round(st.t / a.dt_ns))
        if not a.ctrl.initialised:
            a.start(st, k)
            k_prev = None
            clock.stats.flight_started()  # the loop's figures cover the flight (LoopStats)
        # Integrate over the time that elapsed since the state we last ticked on (states we
        # never saw, or saw too late, were skipped): the generator keeps pace with the leader.
        dt = elapsed_dt(k, k_prev, a.dt)
        if dt is not None and k_prev is not None:
            proc.counters["skipped_ticks"] += k - k_prev - 1
            proc.counters["max_gap_ticks"] = max(proc.counters["max_gap_ticks"], k - k_prev)
        a.stamp = st.q
        a.tick(k, st, a.prepare({key: m for key in a.input_keys if (m := proc.inbox.latest.get(key)) is not None}, k), dt)
        k_prev = k
        proc.inbox.forget_before(k - 2)  # only the latest values are used: keep memory flat
        if clock.stats.ticks % 100 == 0:
            proc.publish_diag(st.t, clock.stats.as_dict())
    proc.publish_diag(max(last_state_t, 0), clock.stats.as_dict())
    return 0


def _run(proc: SwarmProcess, index: int) -> int:
    sc = proc.scenario
    assert sc is not None, "the process loads its scenario on start"
    if not 1 <= index <= sc.n:  # exit 2 (run_process): "agent:I: error: --id: ..."
        raise ScenarioError("--id", f"UAV {index} is not in this scenario: expected 1..{sc.n}")
    agent = _Agent(proc, index)
    agent.use_faults()
    if proc.options.realtime:
        return _run_realtime(agent)
    return _LockstepAgent(agent).run()


def run(options: AgentOptions) -> int:
    """Run agent ``options.id`` until the flight ends; the exit code (2: bad input)."""
    return run_process(lambda proc: _run(proc, options.id), wire.agent(options.id), options.process)

"""The agent process: one per UAV. Thin shell around :class:`agents.core.AgentCore`.

Subscribes to exactly its graph row: its own state ``uav/<i>/state``, its neighbours'
references ``uav/<j>/ref`` (a_ij > 0) and, only if pinned (b_i > 0), ``leader/ref``. Publishes its
reference ``uav/<i>/ref`` and its command ``uav/<i>/cmd``. See :func:`subscriptions`.

Lockstep tick k: wait for state(k) (the plant's clock); first tick: start the generator from it
and publish ref(k); wait for the neighbours' ref(k) and, if pinned, leader ref(k); compute and
publish cmd(k); then step the ESO and the generator and publish ref(k+1). The generator rates
of tick k need only the references, so they are computed as soon as those are in (usually while
the plant integrates): when state(k) arrives, only the control law (28) and the inversion stand
between it and cmd(k). A timeout (``--lockstep-timeout``) counts as a drop and holds
the newest earlier value; a sender whose liveliness token is gone is not waited for. With link
faults each input goes through its link's :class:`zenswarm.linkfaults.Box` (hold last value),
exactly as in the in-process simulator. A (re)started agent joins at the first state it sees and
restarts its generator from it.
Realtime: the same computation at the control rate on the wall clock with the latest values.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from zenswarm.params import QuadParams
from zenswarm import wire
from zenswarm.faults import FaultState
from zenswarm.linkfaults import Box, box_counters, plan_from_args
from zenswarm.runtime import Lockstep, LoopStats, SwarmProcess, add_common_args, run_process

from .core import AgentCore, AgentRow

__all__ = ["subscriptions", "main", "add_parser"]


def subscriptions(keys: wire.Keys, row: AgentRow) -> list[tuple[str, str]]:
    """(key, kind) pairs agent ``row.i`` subscribes to: its graph row and nothing more."""
    subs = [(keys.state(row.i + 1), "state")]
    subs += [(keys.ref(j + 1), "ref") for j in row.neighbours]
    if row.pinned:
        subs.append((keys.leader_ref, "ref"))
    return subs


def _run(proc: SwarmProcess, index: int) -> int:
    sc = proc.scenario
    if not 1 <= index <= sc.n:
        proc.log(f"agent index {index} out of range 1..{sc.n}")
        return 2
    params = QuadParams.from_vehicle(sc.vehicle)
    row = AgentRow.from_scenario(sc, index - 1, params.mass, params.g)
    core = AgentCore(row)
    keys = proc.keys
    me = f"agent:{index}"
    state_key = keys.state(index)
    nbr_keys = [keys.ref(j + 1) for j in row.neighbours]
    input_keys = nbr_keys + ([keys.leader_ref] if row.pinned else [])
    sender = {state_key: "plant", keys.leader_ref: "leader"}
    sender.update({keys.ref(j + 1): f"agent:{j + 1}" for j in row.neighbours})
    ref_key, cmd_key = keys.ref(index), keys.cmd(index)
    dt = sc.timing.dt
    dt_ns = wire.t_ns(dt)
    n_ticks = sc.timing.n_ticks
    timeout = proc.args.lockstep_timeout
    seq = 0

    plan = plan_from_args(sc, proc.args)
    links = {key: (sender[key], me, "state" if key == state_key else ("leader" if key == keys.leader_ref else "ref"))
             for key in [state_key] + input_keys}
    boxes: dict[str, Box] = {}
    if plan is not None and not proc.args.realtime:
        fstate = FaultState(plan)
        boxes = {key: Box(fstate, *link, dt) for key, link in links.items()}
        proc.extra_counters = lambda: box_counters(boxes)
    elif plan is not None:
        proc.use_delay_line(FaultState(plan), links)

    def publish_cmd(k_t_ns: int, cmd) -> None:  # noqa: ANN001
        nonlocal seq
        seq += 1
        proc.publish(cmd_key, wire.Cmd(t=k_t_ns, seq=seq, thrust=cmd.thrust, rpy=cmd.rpy, u=cmd.u, d_hat=cmd.d_hat))

    def publish_ref(k_t_ns: int) -> None:
        nonlocal seq
        seq += 1
        proc.publish(ref_key, wire.Ref(t=k_t_ns, seq=seq, q=core.q_ref, v=core.v_ref))

    def start(st: wire.State, k: int) -> None:
        """(Re)start the generator from a measured state and share ref(k)."""
        core.reset(st.q, st.v)
        publish_ref(k * dt_ns)
        if k > 0:
            proc.log(f"{me}: joined at tick {k} (t = {k * dt:.2f} s), generator restarted from the measured state")

    def rates_from(inputs: dict[str, wire.Ref]) -> tuple[np.ndarray, np.ndarray]:
        """Generator rates (16-17) from the inputs given (a missing neighbour or leader is left
        out this tick)."""
        present = [x for x, key in enumerate(nbr_keys) if key in inputs]
        qn = np.array([inputs[nbr_keys[x]].q for x in present]).reshape(-1, 3)
        vn = np.array([inputs[nbr_keys[x]].v for x in present]).reshape(-1, 3)
        lead = inputs.get(keys.leader_ref)
        return core.rates(qn, vn, lead.q if lead else None, lead.v if lead else None, present)

    def tick(k: int, st: wire.State, inputs: dict[str, wire.Ref] | None, rates=None) -> None:  # noqa: ANN001
        """Tick k: the command first (what the plant waits for), then ESO and generator to k+1
        and ref(k+1) (what the neighbours need only next tick). ``rates``: the generator rates
        already computed from these inputs (see ``prepare``)."""
        dq, dv = rates if rates is not None else rates_from(inputs)
        cmd = core.command(st.q, st.v, dv)
        t = k * dt_ns if not proc.args.realtime else st.t
        publish_cmd(t, cmd)
        core.advance(st.q, cmd.u, dq, dv)
        publish_ref(t + dt_ns)

    if not proc.args.realtime:
        held: dict[str, wire.Ref] = {}
        join_tick = [0]
        # rates of tick k computed ahead: (k, q_ref they started from, the input messages, rates)
        early: list = [None]

        def on_msg(key: str, k: int, msg) -> None:  # noqa: ANN001 - under the lockstep lock
            if boxes:
                boxes[key].offer(k, msg.seq, msg)
            if key == state_key and not core.initialised and k > ls.k:
                ls.k = join_tick[0] = k  # a (re)started agent joins at the first state it sees

        def prepare(k: int) -> None:
            if not core.initialised:
                st = proc.inbox.get(state_key, k)
                if st is not None:
                    start(st, k)
                return
            # The generator rates depend on the references only: compute them as soon as every
            # input of tick k is in, usually while the plant integrates, so that when state(k)
            # arrives only the control law stands between it and cmd(k).
            if boxes or (early[0] is not None and early[0][0] == k):
                return
            msgs = [proc.inbox.get(key, k) for key in input_keys]
            if None in msgs:
                return
            early[0] = (k, core.q_ref, msgs, rates_from(dict(zip(input_keys, msgs))))

        def needed(key: str, k: int) -> bool:
            """Wait for this input of tick k? Not if its sender is gone, or if the sender has
            already moved past tick k (a restarted neighbour that skipped it)."""
            if not proc.is_alive(sender[key]):
                return False
            m = proc.inbox.latest.get(key)
            return m is None or m.t <= k * dt_ns

        def ready(k: int) -> bool:
            if proc.inbox.get(state_key, k) is None:  # the plant's state of tick k is the clock
                return False
            if k == join_tick[0] and k > 0:
                return True  # rejoining: the inputs of this tick were sent before we subscribed
            if boxes:
                return all(b.ready(k) or not needed(key, k) for key, b in boxes.items())
            return all(proc.inbox.get(key, k) is not None or not needed(key, k) for key in input_keys)

        def step(k: int, forced: bool) -> None:
            if boxes:
                if forced:
                    for b in boxes.values():
                        if not b.ready(k):
                            b.mark_timeout(b.due(k))
                got = {key: b.at(k) for key, b in boxes.items()}
                st = got.pop(state_key).value
                inputs = {key: h.value for key, h in got.items() if h is not None}
            else:
                st = proc.inbox.get(state_key, k)
                msgs = []
                for key in input_keys:
                    m = proc.inbox.get(key, k)
                    msgs.append(m)
                    if m is not None:
                        held[key] = m
                    elif key in held:
                        proc.counters["held_inputs"] += 1
                inputs = held
            if forced:
                proc.counters["input_timeouts"] += 1
            e, early[0] = early[0], None
            if not boxes and e is not None and e[0] == k and e[1] is core.q_ref and all(a is b for a, b in zip(e[2], msgs)):
                tick(k, st, None, e[3])  # the same inputs as computed ahead
            else:
                tick(k, st, inputs)
            proc.inbox.forget_before(k - 2)
            if k % 500 == 0:
                proc.publish_diag(k * dt_ns)

        ls = Lockstep(
            n_ticks, ready, step, timeout, proc.stop, prepare=prepare,
            can_force=lambda k: proc.inbox.get(state_key, k) is not None,
            on_msg=on_msg,
        )
        def on_reconnect() -> None:
            """Back from a split longer than the session lease: what we waited for is lost, so
            rejoin like a restarted agent, at the next state we see, from the measured state."""
            with ls.lock:
                core.q_ref = None
                proc.log(f"{me}: will rejoin at the next state (generator restarted from it)")

        proc.on_input = ls.poke
        proc.on_reconnect = on_reconnect
        proc.watch_alive(sorted(set(sender[key] for key in [state_key] + input_keys)), ls.poke)
        for key, kind in subscriptions(keys, row):
            proc.subscribe(key, kind)
        proc.announce()
        k = ls.run()
        proc.publish_diag(k * dt_ns, {"finished": k >= n_ticks, **ls.timing()})
        proc.linger_until_gone("plant")
        return 0

    # realtime: fixed-rate loop on the wall clock, latest value wins
    for key, kind in subscriptions(keys, row):
        proc.subscribe(key, kind)
    proc.watch_alive(["plant"])
    proc.announce()
    stats = LoopStats(dt)
    next_t = time.monotonic()
    last_state_t = -1
    limit_ns = wire.t_ns(sc.timing.time_limit_s)
    while not proc.stop.is_set():
        if last_state_t >= 0 and not proc.is_alive("plant"):
            break  # the plant is gone (its last messages may never come): the flight is over
        now = time.monotonic()
        if now < next_t:
            time.sleep(next_t - now)
        stats.record(time.monotonic() - next_t)
        next_t += dt
        proc.release_delayed()
        st = proc.inbox.latest.get(state_key)
        if st is None or st.t == last_state_t:
            continue
        last_state_t = st.t
        if st.t >= limit_ns:
            break
        k = int(round(st.t / dt_ns))
        if not core.initialised:
            start(st, k)
        inputs = {key: m for key in input_keys if (m := proc.inbox.latest.get(key)) is not None}
        tick(k, st, inputs)
        if stats.ticks % 100 == 0:
            proc.publish_diag(st.t, stats.as_dict())
    proc.publish_diag(max(last_state_t, 0), stats.as_dict())
    return 0


def main(args: argparse.Namespace) -> int:
    return run_process(lambda proc: _run(proc, args.id), f"agent:{args.id}", args)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "agent",
        help="run one UAV's agent process (generator, ESO, controller)",
        description="Run agent I: reference generator (16-17), ESO (27) and controller (28) of UAV I, over Zenoh.",
    )
    p.add_argument("--id", type=int, required=True, metavar="I", help="UAV number, 1..N as in the paper")
    add_common_args(p)
    p.set_defaults(func=main)

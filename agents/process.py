"""The agent process: one per UAV. Thin shell around :class:`agents.core.AgentCore`.

Subscribes to exactly its graph row: its own state ``uav/<i>/state``, its neighbours'
references ``uav/<j>/ref`` (a_ij > 0) and, only if pinned (b_i > 0), ``leader/ref``. Publishes its
reference ``uav/<i>/ref`` and its command ``uav/<i>/cmd``. See :func:`subscriptions`.

Lockstep tick k: wait for state(k); (first tick: start the generator from it and publish
ref(k)); wait for the neighbours' ref(k) and, if pinned, leader ref(k) (a timeout counts as a drop
and holds the newest earlier value); compute and publish cmd(k); publish ref(k+1).
Realtime: the same computation at the control rate on the wall clock with the latest values.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from plant.params import QuadParams
from zenswarm import wire
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


def _ref_msg(t_ns: int, seq: int, q: np.ndarray, v: np.ndarray) -> wire.Ref:
    return wire.Ref(t=t_ns, seq=seq, q=q, v=v)


def _run(proc: SwarmProcess, index: int) -> int:
    sc = proc.scenario
    if not 1 <= index <= sc.n:
        proc.log(f"agent index {index} out of range 1..{sc.n}")
        return 2
    params = QuadParams.from_vehicle(sc.vehicle)
    row = AgentRow.from_scenario(sc, index - 1, params.mass, params.g)
    core = AgentCore(row)
    keys = proc.keys
    for key, kind in subscriptions(keys, row):
        proc.subscribe(key, kind)
    proc.announce()
    state_key = keys.state(index)
    nbr_keys = [keys.ref(j + 1) for j in row.neighbours]
    input_keys = nbr_keys + ([keys.leader_ref] if row.pinned else [])
    ref_key, cmd_key = keys.ref(index), keys.cmd(index)
    dt = sc.timing.dt
    dt_ns = wire.t_ns(dt)
    n_ticks = sc.timing.n_ticks
    timeout = proc.args.lockstep_timeout
    seq = 0
    held: dict[str, wire.Ref] = {}

    def compute(k_t_ns: int, st: wire.State, k: int) -> None:
        """Tick k with the inputs of tick k; a missing one holds the newest earlier value."""
        nonlocal seq
        for key in input_keys:
            m = proc.inbox.get(key, k)
            if m is not None:
                held[key] = m
            elif key in held:
                proc.counters["held_inputs"] += 1
        present = [x for x, key in enumerate(nbr_keys) if key in held]
        qn = np.array([held[nbr_keys[x]].q for x in present]).reshape(-1, 3)
        vn = np.array([held[nbr_keys[x]].v for x in present]).reshape(-1, 3)
        lead = held.get(keys.leader_ref) if row.pinned else None
        q0 = lead.q if lead is not None else None
        v0 = lead.v if lead is not None else None
        cmd = core.tick(st.q, st.v, qn, vn, q0, v0, present)
        seq += 1
        proc.publish(cmd_key, wire.Cmd(t=k_t_ns, seq=seq, thrust=cmd.thrust, rpy=cmd.rpy, u=cmd.u, d_hat=cmd.d_hat))
        seq += 1
        proc.publish(ref_key, _ref_msg(k_t_ns + dt_ns, seq, core.q_ref, core.v_ref))

    if not proc.args.realtime:

        def prepare(k: int) -> None:
            if not core.initialised:
                st = proc.inbox.get(state_key, k)
                if st is not None:  # first state: start the generator there and share ref(k)
                    nonlocal seq
                    core.reset(st.q, st.v)
                    seq += 1
                    proc.publish(ref_key, _ref_msg(k * dt_ns, seq, core.q_ref, core.v_ref))

        def ready(k: int) -> bool:
            get = proc.inbox.get
            return get(state_key, k) is not None and all(get(key, k) is not None for key in input_keys)

        def step(k: int, forced: bool) -> None:
            if forced:
                proc.counters["input_timeouts"] += 1
            compute(k * dt_ns, proc.inbox.get(state_key, k), k)
            proc.inbox.forget_before(k - 2)
            if k % 500 == 0:
                proc.publish_diag(k * dt_ns)

        ls = Lockstep(
            n_ticks, ready, step, timeout, proc.stop, prepare=prepare,
            can_force=lambda k: proc.inbox.get(state_key, k) is not None,  # the plant is the clock
        )
        proc.on_input = ls.poke
        k = ls.run()
        proc.publish_diag(k * dt_ns, {"finished": k >= n_ticks, **ls.timing()})
        return 0

    # realtime: fixed-rate loop on the wall clock, latest value wins
    stats = LoopStats(dt)
    next_t = time.monotonic()
    last_state_t = -1
    while not proc.stop.is_set():
        now = time.monotonic()
        if now < next_t:
            time.sleep(next_t - now)
        stats.record(time.monotonic() - next_t)
        next_t += dt
        st = proc.inbox.latest.get(state_key)
        if st is None or st.t == last_state_t:
            continue
        last_state_t = st.t
        k = int(round(st.t / dt_ns))
        if st.t >= wire.t_ns(sc.timing.time_limit_s):
            break
        if not core.initialised:
            core.reset(st.q, st.v)
        for key in input_keys:
            m = proc.inbox.latest.get(key)
            if m is not None:
                proc.inbox.put(key, k, m)  # latest value wins: present it as this tick's input
        compute(st.t, st, k)
        proc.inbox.forget_before(k - 2)
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

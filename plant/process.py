"""The plant process: simulates every UAV with the core model and is the clock in lockstep.

Subscribes to each UAV's ``uav/<i>/cmd``; publishes ``clock`` and each ``uav/<i>/state``.
Lockstep tick k: publish clock(k) and state_i(k) for all i, wait for every cmd_i(k) (a timeout
counts as a drop and holds the UAV's previous command), then integrate ``timing.substeps``
physics sub-steps. It starts only when the leader and every agent have announced themselves.
Realtime: a fixed-rate loop at the control rate; each period integrates one control period of
physics with the latest command of each UAV (hover thrust, level, before the first one).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from zenswarm import wire
from zenswarm.runtime import Lockstep, LoopStats, SwarmProcess, add_common_args, run_process

from .disturbance import DisturbanceModel
from .params import QuadParams
from .quadrotor import initial_state, step

__all__ = ["main", "add_parser"]


def _run(proc: SwarmProcess) -> int:
    sc = proc.scenario
    keys = proc.keys
    n = sc.n
    params = QuadParams.from_vehicle(sc.vehicle)
    dt = sc.timing.dt
    dt_ns = wire.t_ns(dt)
    nsub = sc.timing.substeps
    h = dt / nsub
    n_ticks = sc.timing.n_ticks
    rng = np.random.default_rng(sc.seed)
    dist = DisturbanceModel(sc.disturbance, n, rng)
    plant = initial_state(np.asarray(sc.initial_positions, dtype=float))
    thrust = np.full(n, params.mass * params.g)
    rpy_cmd = np.zeros((n, 3))
    rpy_cmd[:, 2] = sc.controller.yaw
    cmd_keys = [keys.cmd(i + 1) for i in range(n)]
    for key in cmd_keys:
        proc.subscribe(key, "cmd")
    proc.announce()
    others = ["leader"] + [f"agent:{i + 1}" for i in range(n)]
    missing = proc.wait_for_alive(others, timeout_s=60.0)
    if proc.stop.is_set():
        return 0
    if missing:
        proc.log(f"plant: these processes never announced themselves: {', '.join(missing)}")
        return 3
    seq = 0

    def publish_tick(k: int) -> None:
        nonlocal seq
        seq += 1
        t = k * dt_ns
        proc.publish(keys.clock, wire.Clock(t=t, seq=seq))
        for i in range(n):
            proc.publish(
                keys.state(i + 1),
                wire.State(t=t, seq=seq, q=plant.q[i].copy(), v=plant.v[i].copy(), rpy=plant.rpy[i].copy(), w=plant.w[i].copy()),
            )

    def apply(i: int, c: wire.Cmd) -> None:
        thrust[i] = c.thrust
        rpy_cmd[i] = c.rpy

    def integrate(k: int) -> None:
        t = k * dt
        for j in range(nsub):
            d_p, d_a = dist.sample(t + j * h, h)
            step(plant, thrust, rpy_cmd, params, h, d_p, d_a)

    if not proc.args.realtime:

        def ready(k: int) -> bool:
            return all(proc.inbox.get(key, k) is not None for key in cmd_keys)

        def step_tick(k: int, forced: bool) -> None:
            if forced:
                proc.counters["cmd_timeouts"] += 1
            for i, key in enumerate(cmd_keys):
                c = proc.inbox.get(key, k)
                if c is not None:
                    apply(i, c)
            integrate(k)
            proc.inbox.forget_before(k - 1)
            if k % 500 == 0:
                proc.publish_diag(k * dt_ns)
            publish_tick(k + 1)  # the last one is the final state, t = time limit

        ls = Lockstep(n_ticks, ready, step_tick, proc.args.lockstep_timeout, proc.stop)
        proc.on_input = ls.poke
        with ls.lock:
            publish_tick(0)
        k = ls.run()
        proc.publish_diag(k * dt_ns, {"finished": k >= n_ticks, **ls.timing()})
        return 0

    stats = LoopStats(dt)
    next_t = time.monotonic()
    k = 0
    while k <= n_ticks and not proc.stop.is_set():
        publish_tick(k)
        if k == n_ticks:
            break
        for i, key in enumerate(cmd_keys):
            c = proc.inbox.latest.get(key)
            if c is not None:
                apply(i, c)
        integrate(k)
        k += 1
        next_t += dt
        now = time.monotonic()
        if now < next_t:
            time.sleep(next_t - now)
        stats.record(time.monotonic() - next_t)
        if k % 100 == 0:
            proc.publish_diag(k * dt_ns, stats.as_dict())
    proc.publish_diag(k * dt_ns, {**stats.as_dict(), "finished": k >= n_ticks})
    return 0


def main(args: argparse.Namespace) -> int:
    return run_process(_run, "plant", args)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plant",
        help="run the plant process (simulated quadrotors; the lockstep clock)",
        description="Simulate every UAV of the scenario (eqs 1-5, onboard attitude PID) and publish their states.",
    )
    add_common_args(p)
    p.set_defaults(func=main)

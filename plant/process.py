"""The plant process: simulates every UAV with the core model and is the clock in lockstep.

Subscribes to each UAV's ``uav/<i>/cmd``; publishes ``clock`` and each ``uav/<i>/state``.
Lockstep tick k: publish state_i(k) for all i, wait for every cmd_i(k) (a timeout
counts as a drop and holds the UAV's previous command; an agent whose liveliness token is gone is
not waited for), then integrate ``timing.substeps`` physics sub-steps. A UAV whose newest command
is too old goes into the failsafe of :mod:`plant.failsafe` (hover, then land). The clock, read by
the leader and the supervisor only, goes out every :data:`zenswarm.runtime.CLOCK_EVERY_TICKS`
ticks: clock(0) with the first states, then clock(k + 1) as the integration of tick k starts, so
the leader's burst of refs overlaps the integration, not the agents' work. It starts only
when the leader and every agent have announced themselves.
Realtime: a fixed-rate loop at the control rate; each period integrates one control period of
physics with the latest command of each UAV (hover thrust, level, before the first one).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from zenswarm import wire
from zenswarm.faults import FaultState
from zenswarm.linkfaults import Box, box_counters, plan_from_args
from zenswarm.runtime import CLOCK_EVERY_TICKS, Lockstep, LoopStats, SwarmProcess, add_common_args, run_process

from .disturbance import DisturbanceModel
from .failsafe import FailsafeState, failsafe_config
from zenswarm.params import QuadParams
from .quadrotor import initial_state, step_held

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
    yaw = sc.controller.yaw
    rng = np.random.default_rng(sc.seed)
    dist = DisturbanceModel(sc.disturbance, n, rng)
    plant = initial_state(np.asarray(sc.initial_positions, dtype=float))
    failsafe = FailsafeState(n, failsafe_config(sc.failsafe))
    thrust = np.full(n, params.mass * params.g)
    rpy_cmd = np.zeros((n, 3))
    rpy_cmd[:, 2] = yaw
    last_cmd_tick = [0] * n
    cmd_keys = [keys.cmd(i + 1) for i in range(n)]
    agents = [f"agent:{i + 1}" for i in range(n)]
    plan = plan_from_args(sc, proc.args)
    boxes: dict[str, Box] = {}
    if plan is not None and not proc.args.realtime:
        fstate = FaultState(plan)
        boxes = {key: Box(fstate, agents[i], "plant", "cmd", dt) for i, key in enumerate(cmd_keys)}
        proc.extra_counters = lambda: box_counters(boxes)
    elif plan is not None:
        proc.use_delay_line(FaultState(plan), {key: (agents[i], "plant", "cmd") for i, key in enumerate(cmd_keys)})
    seq = 0

    def publish_tick(k: int) -> None:
        nonlocal seq
        seq += 1
        t = k * dt_ns
        for i in range(n):  # the states first: they are what the agents wait for
            proc.publish(
                keys.state(i + 1),
                wire.State(t=t, seq=seq, q=plant.q[i].copy(), v=plant.v[i].copy(), rpy=plant.rpy[i].copy(), w=plant.w[i].copy()),
            )
        if proc.args.realtime or k == 0:  # lockstep: publish_clock_early
            proc.publish(keys.clock, wire.Clock(t=t, seq=seq))

    def publish_clock_early(k: int) -> None:
        """Lockstep: clock(k + 1) once the commands of tick k are in, before integrating: the
        leader then runs ahead while the plant integrates (when the agents wait) rather than
        when the agents compute. Every CLOCK_EVERY_TICKS ticks and at the end."""
        k1 = k + 1
        if k1 % CLOCK_EVERY_TICKS == 0 or k1 >= n_ticks:
            proc.publish(keys.clock, wire.Clock(t=k1 * dt_ns, seq=seq + 1))

    def apply(i: int, c: wire.Cmd, k_cmd: int) -> None:
        thrust[i] = c.thrust
        rpy_cmd[i] = c.rpy
        last_cmd_tick[i] = k_cmd

    def integrate(k: int) -> None:
        before = len(failsafe.events)
        ages = [(k - last_cmd_tick[i]) * dt for i in range(n)]
        f_app, r_app = failsafe.apply(k, ages, plant.q, plant.v, thrust, rpy_cmd, params.mass, params.g, yaw)
        if len(failsafe.events) > before:
            for ev in failsafe.events[before:]:
                proc.log(f"plant: tick {ev[0]} (t = {ev[0] * dt:.2f} s): UAV {ev[1]} failsafe {ev[2]} -> {ev[3]}")
            proc.counters["failsafe_events"] = len(failsafe.events)
            proc.publish_diag(k * dt_ns, {"failsafe": failsafe.summary() or "none"})
        step_held(plant, f_app, r_app, params, h, nsub, dist.sampler(k * dt, h))

    if not proc.args.realtime:

        def on_msg(key: str, k: int, msg) -> None:  # noqa: ANN001 - under the lockstep lock
            if boxes:
                boxes[key].offer(k, msg.seq, msg)

        def needed(i: int, k: int) -> bool:
            """Wait for agent i's cmd(k)? Not if it is gone or has moved past tick k."""
            if not proc.is_alive(agents[i]):
                return False
            m = proc.inbox.latest.get(cmd_keys[i])
            return m is None or m.t <= k * dt_ns

        def ready(k: int) -> bool:
            if boxes:
                return all(b.ready(k) or not needed(i, k) for i, b in enumerate(boxes.values()))
            return all(proc.inbox.get(key, k) is not None or not needed(i, k) for i, key in enumerate(cmd_keys))

        last_tick_wall = [0.0]

        def pace() -> None:
            """While an agent is down, run no faster than real time: failsafe timers and restart
            delays then mean in sim time what they mean on the wall clock."""
            if all(proc.is_alive(a) for a in agents):
                return
            proc.counters["paced_ticks"] += 1
            wait = last_tick_wall[0] + dt - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            last_tick_wall[0] = time.monotonic()

        def step_tick(k: int, forced: bool) -> None:
            if forced:
                proc.counters["cmd_timeouts"] += 1
            for i, key in enumerate(cmd_keys):
                if boxes:
                    b = boxes[key]
                    if forced and not b.ready(k):
                        b.mark_timeout(b.due(k))
                    held = b.at(k)
                    if held is not None:
                        apply(i, held.value, held.send_tick)
                else:
                    c = proc.inbox.get(key, k)
                    if c is not None:
                        apply(i, c, k)
            publish_clock_early(k)
            integrate(k)
            proc.inbox.forget_before(k - 1)
            if k % 500 == 0:
                proc.publish_diag(k * dt_ns)
            pace()
            publish_tick(k + 1)  # the last one is the final state, t = time limit

        ls = Lockstep(n_ticks, ready, step_tick, proc.args.lockstep_timeout, proc.stop, on_msg=on_msg)
        proc.on_input = ls.poke
    for key in cmd_keys:
        proc.subscribe(key, "cmd")
    proc.announce()
    missing = proc.wait_for_alive(["leader"] + agents + list(proc.args.expect or []), timeout_s=60.0)
    if proc.stop.is_set():
        return 0
    if missing:
        proc.log(f"plant: these processes never announced themselves: {', '.join(missing)}")
        return 3

    if not proc.args.realtime:
        proc.watch_alive(agents, ls.poke)
        with ls.lock:
            publish_tick(0)
        k = ls.run()
        proc.publish_diag(k * dt_ns, {"finished": k >= n_ticks, "failsafe": failsafe.summary() or "none", **ls.timing()})
        return 0

    stats = LoopStats(dt)
    next_t = time.monotonic()
    k = 0
    while k <= n_ticks and not proc.stop.is_set():
        publish_tick(k)
        if k == n_ticks:
            break
        proc.release_delayed()
        for i, key in enumerate(cmd_keys):
            c = proc.inbox.latest.get(key)
            if c is not None and c.t >= last_cmd_tick[i] * dt_ns:
                apply(i, c, int(round(c.t / dt_ns)))
        integrate(k)
        k += 1
        next_t += dt
        now = time.monotonic()
        if now < next_t:
            time.sleep(next_t - now)
        stats.record(time.monotonic() - next_t)
        if k % 100 == 0:
            proc.publish_diag(k * dt_ns, stats.as_dict())
    proc.publish_diag(k * dt_ns, {**stats.as_dict(), "finished": k >= n_ticks, "failsafe": failsafe.summary() or "none"})
    return 0


def main(args: argparse.Namespace) -> int:
    if getattr(args, "mavlink", False):
        return _run_mavlink(args)
    return run_process(_run, "plant", args)


def _run_mavlink(args: argparse.Namespace) -> int:
    """``plant --mavlink``: the scenario's quadrotors as simulated MAVLink vehicles over UDP
    (:mod:`plant.mavlink_vehicle`; no Zenoh session: the MAVLink bridge is their swarm side)."""
    from dataclasses import replace

    from zenswarm.config import load_scenario
    from zenswarm.errors import ScenarioError

    from .mavlink_vehicle import run_fleet

    if args.scenario is None:
        raise ScenarioError("--scenario", "plant --mavlink needs the scenario file (it has no bus to fetch it from)")
    sc = load_scenario(args.scenario)
    if args.seed is not None:
        sc = replace(sc, seed=int(args.seed))
    return run_fleet(sc, args)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plant",
        help="run the plant process (simulated quadrotors; the lockstep clock)",
        description="Simulate every UAV of the scenario (eqs 1-5, onboard attitude PID) and publish their states.",
    )
    add_common_args(p)
    p.add_argument(
        "--expect",
        action="append",
        metavar="PROCESS",
        help="also wait for this process (e.g. recorder) to announce itself before the first tick",
    )
    from .mavlink_vehicle import add_vehicle_args

    p.add_argument(
        "--mavlink",
        action="store_true",
        help="run the quadrotors as simulated MAVLink vehicles over UDP instead (vehicle i on UDP --base-port + i - 1; "
        "fly them with `zenswarm bridge mavlink`); the bus flags are then ignored",
    )
    add_vehicle_args(p)
    p.set_defaults(func=main)

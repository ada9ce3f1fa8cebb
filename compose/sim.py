"""In-process simulator: the whole scheme in one process, vectorised over UAVs.

This is the reference the distributed swarm must reproduce. Discrete-time semantics, one control
tick k (t_k = k dt, dt = 1 / timing.control_rate_hz):

1. leader: v0_k = Gamma*_total(q0_k) (eq. 15).
2. every agent i reads its measured state (q_i, v_i)_k from the plant.
   At k = 0 the generator starts at q*_i = q_i(0), v*_i = 0 and the ESO at
   (q_hat, v_hat, d_hat) = (q_i(0), v_i(0), 0).
3. generator rates (q*_i', v*_i')_k from eqs (16)-(17), using the neighbours' (q*_j, v*_j)_k of
   the same tick and, if pinned, (q0, v0)_k.
4. u_k from eq. (28) with v*_i'_k as feed-forward and d_hat_k (zero with the ESO disabled);
   thrust and (roll, pitch) by the inversion after (28), yaw = controller.yaw.
5. ESO explicit Euler step with (q_i_k, u_k) -> estimate of k+1 (eq. 27).
6. generator explicit Euler step -> (q*, v*)_{k+1}.
7. plant: ``timing.substeps`` physics sub-steps of 1 / physics_rate_hz with the command held
   (zero-order hold), onboard attitude PID at the physics rate, disturbances sampled every
   sub-step; semi-implicit Euler (see :func:`plant.quadrotor.step`; :func:`~plant.quadrotor.step_held`
   runs the sub-steps of a tick).
8. leader: q0_{k+1} by :func:`leader.aapf.integrate_leader` (explicit Euler, at least
   ``timing.substeps`` sub-steps, adaptively refined near obstacles).

The distributed lockstep swarm runs exactly these steps, each in the process that owns it.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
from msgspec.structs import replace as replace_table

from zenswarm.agents.controller import composite_control, invert_thrust_attitude
from zenswarm.agents.core import AgentCore, AgentRow
from zenswarm.agents.eso import eso_step
from zenswarm.agents.generator import euler_step, generator_rates_all
from zenswarm.leader.aapf import AapfParams, integrate_leader, total_force
from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.failsafe import FailsafeState, failsafe_config
from zenswarm.params import QuadParams
from zenswarm.plant.quadrotor import initial_state, step_held

from zenswarm.config import Scenario
from zenswarm.faults import FaultPlan, FaultState
from zenswarm.linkfaults import Box, box_counters
from zenswarm.metrics import TimeSeries, add_failure, compute_results
from zenswarm.verdict import criteria_from_scenario, decide_end

__all__ = ["simulate", "SimResult", "run_sim_cli"]


@dataclass
class SimResult:
    series: TimeSeries
    results: dict


ProgressFn = Callable[[int, int, float], None]

DECIDE_EVERY = 50
"""Ticks between two checks of :func:`zenswarm.verdict.decide_end` (the run ends after the tick it
names: checking in blocks costs less and ends at the same tick)."""


def simulate(
    scenario: Scenario,
    progress: ProgressFn | None = None,
    n_ticks: int | None = None,
    faults: FaultPlan | None = None,
    full_time: bool = False,
) -> SimResult:
    """Run ``scenario`` for ``n_ticks`` control ticks (default: the time limit).

    progress(k, n_ticks, dist_to_goal_m) is called about every 100 ticks. ``faults``: a link
    fault plan (:func:`zenswarm.linkfaults.plan_for`); each receiver then holds the newest value
    its links delivered (:class:`zenswarm.linkfaults.Box`), exactly as the lockstep processes do.
    The run ends after the tick where its outcome was decided (a stalled leader or a diverged
    UAV, :func:`zenswarm.verdict.decide_end`) unless ``full_time``. Ctrl-C (KeyboardInterrupt)
    ends it too: the ticks flown are judged and the results carry an ``interrupted`` failure.
    Returns the time series (one sample per tick, taken at step 2 of the tick) and the results.
    """
    wall0 = time.perf_counter()
    tm = scenario.timing
    dt = tm.dt
    nsub = tm.substeps
    h_phys = dt / nsub
    T = tm.n_ticks if n_ticks is None else int(n_ticks)
    n = scenario.n

    params = QuadParams.from_vehicle(scenario.vehicle)
    g = params.g
    mass = params.mass
    aapf = AapfParams.from_scenario(scenario)
    A = np.asarray(scenario.graph.adjacency, dtype=float)
    b = np.asarray(scenario.graph.pinning, dtype=float)
    h = np.asarray(scenario.offsets, dtype=float)
    kp = np.asarray(scenario.controller.kp, dtype=float)
    kd = np.asarray(scenario.controller.kd, dtype=float)
    beta = tuple(scenario.eso.beta)
    mu1, mu2 = scenario.generator.mu1, scenario.generator.mu2
    yaw = scenario.controller.yaw
    goal = np.asarray(scenario.leader.goal, dtype=float)

    rng = np.random.default_rng(scenario.seed)
    dist = DisturbanceModel(scenario.disturbance, n, rng)
    plant = initial_state(np.asarray(scenario.initial_positions, dtype=float))
    q0 = np.asarray(scenario.leader.start, dtype=float).copy()

    ts = TimeSeries.allocate(T, n)
    qref = vref = q_hat = v_hat = d_hat = None
    rpy_cmd = np.zeros((n, 3))
    rpy_cmd[:, 2] = yaw
    zeros = np.zeros((n, 3))

    faulty = faults is not None and faults.active
    if faulty:
        fstate = FaultState(faults)
        rows = [AgentRow.from_scenario(scenario, i, mass, g) for i in range(n)]
        cores = [AgentCore(r) for r in rows]
        st_box = [Box(fstate, "plant", f"agent:{i + 1}", "state", dt) for i in range(n)]
        nb_box = [[Box(fstate, f"agent:{j + 1}", f"agent:{i + 1}", "ref", dt) for j in r.neighbours] for i, r in enumerate(rows)]
        ld_box = [Box(fstate, "leader", f"agent:{i + 1}", "leader", dt) if r.pinned else None for i, r in enumerate(rows)]
        cmd_box = [Box(fstate, f"agent:{i + 1}", "plant", "cmd", dt) for i in range(n)]
        failsafe = FailsafeState(n, failsafe_config(scenario.failsafe))

    crit = criteria_from_scenario(scenario)
    flown = 0  # ticks whose samples are complete in ts
    checked = 0  # ticks already given to decide_end
    interrupted = False
    try:
        for k in range(T):
            if k - checked >= DECIDE_EVERY:  # the run ends after a tick that decided its outcome
                stop = None if full_time else decide_end(ts.q0, ts.q, ts.qref, crit, checked, k)
                if stop is not None:
                    flown = stop + 1
                    break
                checked = k
            flown = k
            t = k * dt
            v0 = total_force(q0, aapf)
            q = plant.q.copy()
            v = plant.v.copy()
            if faulty:
                # every agent reads its links (hold last value), then ticks; the plant reads its links
                for i in range(n):
                    st_box[i].offer(k, k, (q[i], v[i]))
                    if not cores[i].initialised:
                        held = st_box[i].at(k)
                        cores[i].reset(*held.value)
                refs = [(c.q_ref, c.v_ref) for c in cores]
                for i, r in enumerate(rows):
                    for x, j in enumerate(r.neighbours):
                        nb_box[i][x].offer(k, k, refs[j])
                    if ld_box[i] is not None:
                        ld_box[i].offer(k, k, (q0, v0))
                for i, r in enumerate(rows):
                    qm, vm = st_box[i].at(k).value
                    nb = [box.at(k).value for box in nb_box[i]]
                    qn = np.array([x[0] for x in nb]).reshape(-1, 3)
                    vn = np.array([x[1] for x in nb]).reshape(-1, 3)
                    lead = ld_box[i].at(k).value if ld_box[i] is not None else (None, None)
                    cmd = cores[i].tick(qm, vm, qn, vn, lead[0], lead[1])
                    ts.qref[k, i], ts.vref[k, i] = refs[i]
                    ts.u[k, i] = cmd.u
                    ts.thrust[k, i] = cmd.thrust
                    ts.d_hat[k, i] = cmd.d_hat
                    cmd_box[i].offer(k, k, (cmd.thrust, cmd.rpy))
                thrust_held = np.empty(n)
                ages = []
                for i in range(n):
                    held = cmd_box[i].at(k)
                    thrust_held[i], rpy_cmd[i] = held.value
                    ages.append(held.age_ticks * dt)
                thrust_applied, rpy_applied = failsafe.apply(k, ages, plant.q, plant.v, thrust_held, rpy_cmd, mass, g, yaw)
                ts.t[k], ts.q0[k], ts.v0[k], ts.q[k], ts.v[k], ts.rpy[k] = t, q0, v0, q, v, plant.rpy
                step_held(plant, thrust_applied, rpy_applied, params, h_phys, nsub, dist.sampler(t, h_phys))
                q0, _info = integrate_leader(q0, dt, aapf, nsub)
                if progress is not None and (k % 100 == 0 or k == T - 1):
                    progress(k + 1, T, float(np.linalg.norm(q0 - goal)))
                continue
            if k == 0:
                qref, vref = q.copy(), np.zeros((n, 3))
                q_hat, v_hat, d_hat = q.copy(), v.copy(), np.zeros((n, 3))
            dqr, dvr = generator_rates_all(qref, vref, h, A, b, q0, v0, mu1, mu2)
            d_used = d_hat if scenario.eso.enabled else zeros
            u = composite_control(qref, vref, dvr, q, v, d_used, kp, kd, g)
            F, phi, theta = invert_thrust_attitude(u, mass, yaw)
            rpy_cmd[:, 0] = phi
            rpy_cmd[:, 1] = theta

            ts.t[k] = t
            ts.q0[k] = q0
            ts.v0[k] = v0
            ts.qref[k] = qref
            ts.vref[k] = vref
            ts.q[k] = q
            ts.v[k] = v
            ts.rpy[k] = plant.rpy
            ts.u[k] = u
            ts.thrust[k] = F
            ts.d_hat[k] = d_used

            q_hat, v_hat, d_hat = eso_step(q_hat, v_hat, d_hat, q, u, beta, dt, g)
            qref, vref = euler_step(qref, vref, dqr, dvr, dt)
            step_held(plant, F, rpy_cmd, params, h_phys, nsub, dist.sampler(t, h_phys))
            q0, _info = integrate_leader(q0, dt, aapf, nsub)

            if progress is not None and (k % 100 == 0 or k == T - 1):
                progress(k + 1, T, float(np.linalg.norm(q0 - goal)))
        else:
            flown = T
            stop = None if full_time else decide_end(ts.q0, ts.q, ts.qref, crit, checked, T)
            if stop is not None:
                flown = stop + 1
    except KeyboardInterrupt:  # Ctrl-C: judge and keep what was flown
        interrupted = True

    wall = time.perf_counter() - wall0
    if flown < T:
        ts = ts.truncated(flown)
    results = compute_results(ts, scenario, wall_time_s=wall, early_end=not full_time)
    if interrupted:
        add_failure(results, "interrupted", f"interrupted (Ctrl-C) at sim time {flown * dt:.2f} s", flown * dt)
    if faulty:
        boxes = {f"{b.src}{b.dst}{b.kind}": b for lst in (st_box, cmd_box, [x for x in ld_box if x]) for b in lst}
        boxes.update({f"{b.src}{b.dst}{b.kind}": b for lst in nb_box for b in lst})
        results["link_counters"] = box_counters(boxes)
        results["failsafe_events"] = [list(e) for e in failsafe.events]
    return SimResult(ts, results)


class ProgressPrinter:
    """Prints a progress line to a stream (stderr) at most every ``every_s`` seconds of wall time."""

    def __init__(self, label: str, sim_dt: float, stream=sys.stderr, every_s: float = 1.0) -> None:
        self.label = label
        self.sim_dt = sim_dt
        self.stream = stream
        self.every_s = every_s
        self._last = 0.0
        self._t0 = time.perf_counter()

    def __call__(self, k: int, total: int, dist: float) -> None:
        now = time.perf_counter()
        if now - self._last < self.every_s and k != total:
            return
        self._last = now
        el = now - self._t0
        speed = (k * self.sim_dt) / el if el > 0 else float("inf")
        print(
            f"[{self.label}] t={k * self.sim_dt:6.2f}/{total * self.sim_dt:.2f} s  "
            f"{100.0 * k / total:5.1f}%  leader->goal {dist:.3f} m  {speed:5.1f}x real time",
            file=self.stream,
            flush=True,
        )


def write_outputs(out: Path, series: TimeSeries, results: dict) -> None:
    """Write ``results.json`` and ``timeseries.npz`` into ``out`` (created if needed)."""
    out.mkdir(parents=True, exist_ok=True)
    series.save(str(out / "timeseries.npz"))
    (out / "results.json").write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")


def apply_overrides(scenario: Scenario, no_eso: bool = False, fixed_gain: float | None = None) -> Scenario:
    """Scenario copy with the CLI's comparison switches applied."""
    if no_eso:
        scenario = replace(scenario, eso=replace_table(scenario.eso, enabled=False))
    if fixed_gain is not None:
        scenario = replace(scenario, leader=replace_table(scenario.leader, adaptive=False, k_rep_fixed=float(fixed_gain)))
    return scenario


def run_sim_cli(scenario: Scenario, out: Path, quiet: bool = False, faults: FaultPlan | None = None, full_time: bool = False) -> int:
    """``zenswarm sim``: run, write outputs, print a summary. Exit code 0 on mission success, 1 on
    failure, 130 when interrupted (Ctrl-C; what was flown is judged and written)."""
    prog = None if quiet else ProgressPrinter("sim", scenario.timing.dt)
    res = simulate(scenario, progress=prog, faults=faults, full_time=full_time)
    write_outputs(out, res.series, res.results)
    r = res.results
    print(summary_line(r))
    print(f"wrote {out / 'results.json'} and {out / 'timeseries.npz'}")
    if any(f["cause"] == "interrupted" for f in r["failures"]):
        return 130
    return 0 if r["success"] else 1


def _fmt(x: object, unit: str = " m") -> str:
    return "n/a" if x is None else f"{x:.4f}{unit}"


MAX_SUMMARY_FAILURES = 6
"""Failures named in the summary line; results.json lists them all."""


def failure_text(f: dict) -> str:
    """``collision_ground uav 2 at 3.41 s`` for one failure of a results dict."""
    uavs = f.get("uavs") or []
    who = f" uav {uavs[0]}" if len(uavs) == 1 else (f" uavs {','.join(map(str, uavs))}" if uavs else "")
    when = f" at {f['t_s']:.2f} s" if f.get("t_s") is not None else ""
    return f"{f['cause']}{who}{when}"


def summary_line(r: dict) -> str:
    """One line: the verdict with its named failures, the goal time and the headline figures."""
    fails = r.get("failures") or []
    if r["success"]:
        verdict = "SUCCESS"
    else:
        named = "; ".join(failure_text(f) for f in fails[:MAX_SUMMARY_FAILURES])
        more = f"; (+{len(fails) - MAX_SUMMARY_FAILURES} more in results.json)" if len(fails) > MAX_SUMMARY_FAILURES else ""
        verdict = f"FAILED: {named}{more}" if fails else "FAILED"
    ttg = r.get("time_to_goal_s")
    wall = r.get("wall_time_s")
    return (
        f"{r['scenario']}: {verdict}\n"
        f"  goal {'reached at %.2f s' % ttg if ttg is not None else 'NOT reached'}  "
        f"max formation error {_fmt(r.get('max_formation_error_m'))} (vehicles; generator {_fmt(r.get('max_generator_formation_error_m'))})  "
        f"final slot error {_fmt(r.get('max_final_slot_error_m'))}  rms tracking {_fmt(r.get('rms_tracking_error_m'))}\n"
        f"  min margin to obstacles {_fmt(r.get('min_obstacle_margin_m'))}  between UAVs {_fmt(r.get('min_inter_uav_margin_m'))}  "
        f"(vehicle radius {_fmt(r.get('vehicle_radius_m'))})  sim {r.get('sim_time_s', 0.0):.2f} s"
        + (f"  wall {wall:.2f} s" if wall is not None else "")
    )

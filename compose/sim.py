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
   sub-step; semi-implicit Euler (see :func:`zenswarm.plant.quadrotor.step`; :func:`~zenswarm.plant.quadrotor.step_held`
   runs the sub-steps of a tick).
8. leader: q0_{k+1} by :func:`zenswarm.leader.aapf.integrate_leader` (explicit Euler, at least
   ``timing.substeps`` sub-steps, adaptively refined near obstacles).

The distributed lockstep swarm runs exactly these steps, each in the process that owns it.
"""

from __future__ import annotations

import math
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from msgspec.structs import replace as replace_table

from zenswarm.agents.api import (
    Controller,
    boundary_of,
    build_controller,
    check_command,
    check_shared,
    checked_finish,
    checked_prepare,
    checked_reset,
    checked_share,
)
from zenswarm.agents.core import AgentRow, StackedAgents
from zenswarm.agents.paper import PaperController
from zenswarm.errors import PluginFailure
from zenswarm.judge.metrics import TimeSeries, exit_code_of
from zenswarm.judge.results import closing_lines, flight_results
from zenswarm.judge.results import failure_text as failure_text  # re-exported: these moved to zenswarm.judge.results
from zenswarm.judge.results import radio_results as radio_results
from zenswarm.judge.results import summary_line as summary_line
from zenswarm.judge.results import write_outputs as write_outputs
from zenswarm.judge.verdict import criteria_from_scenario
from zenswarm.judge.watch import EndWatch
from zenswarm.leader.core import LeaderCore
from zenswarm.link import Box, FaultPlan, FaultState, Held, box_counters
from zenswarm.plant.core import PlantCore
from zenswarm.scenario.config import Scenario
from zenswarm.scenario.plugins import STAGE_SHARE, STAGE_STEP, Boundary, first_failures, plant_records, plant_vehicle

__all__ = ["simulate", "SimResult", "run_sim_cli"]


@dataclass
class SimResult:
    series: TimeSeries
    results: dict


ProgressFn = Callable[[int, int, float], None]

class PluginsFailed(Exception):
    """Plug-ins failed in one stage of a tick (:class:`zenswarm.errors.PluginFailure` each):
    the simulator ends the run there."""

    def __init__(self, failures: list[PluginFailure]) -> None:
        super().__init__("; ".join(str(f) for f in failures))
        self.failures = failures


def _collect(failures: list[PluginFailure], fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)``, a PluginFailure added to ``failures`` (None returned) instead of raised."""
    try:
        return fn(*args)
    except PluginFailure as e:
        failures.append(e)
        return None


_FINITE_PY_MAX = 48
"""Arrays up to this many values are checked on Python floats in :func:`_finite`, larger ones
with one numpy reduction (at 1000 UAVs the Python path cost 0.43 ms a tick, numpy's 0.02)."""


def _finite(*arrays: np.ndarray) -> bool:
    """Every value of these arrays is finite, checked every tick: on Python floats for a few
    UAVs (cheaper than numpy's reductions there), with ``np.isfinite`` for many."""
    return all(
        all(map(math.isfinite, a.ravel().tolist())) if a.size <= _FINITE_PY_MAX else bool(np.isfinite(a).all()) for a in arrays
    )


def _each(bounds: list[Boundary], k: int, stage: int, what: str, fn: Callable[[], Any]) -> Any:
    """``fn()`` for every UAV at once: an exception is every UAV's failure (each agent process
    would raise it alone)."""
    try:
        return fn()
    except Exception as e:
        err = e
        failed: list[PluginFailure] = []

        def again() -> None:
            raise err

        for b in bounds:
            _collect(failed, b.call, k, stage, what, again)
        raise PluginsFailed(failed) from e


class _Ref(NamedTuple):
    """A reference as it travels on a link: (q, v), each (3,) (a :class:`zenswarm.agents.core.RefLike`)."""

    q: np.ndarray
    v: np.ndarray


class _Links:
    """With link faults: every directed link of the swarm as a receive box
    (:class:`zenswarm.link.swarm.Box`, hold last value), as in the lockstep processes."""

    def __init__(self, plan: FaultPlan, rows: list[AgentRow], dt: float) -> None:
        fs = FaultState(plan)
        n = len(rows)
        self.state = [Box(fs, "plant", f"agent:{i + 1}", "state", dt) for i in range(n)]
        self.nbr = [[Box(fs, f"agent:{j + 1}", f"agent:{i + 1}", "ref", dt) for j in r.neighbours] for i, r in enumerate(rows)]
        self.lead = [Box(fs, "leader", f"agent:{i + 1}", "leader", dt) if r.pinned else None for i, r in enumerate(rows)]
        self.cmd = [Box(fs, f"agent:{i + 1}", "plant", "cmd", dt) for i in range(n)]
        self.radio = plan.radio_active
        self.prev_q: np.ndarray | None = None  # the plant's positions of the previous tick (radio geometry of refs)

    def geometry(self, k: int, q: np.ndarray) -> None:
        """Tell every radio box its receiver's true position at tick k (the plant's)."""
        if not self.radio:
            return
        for i in range(len(self.nbr)):
            for box in self.nbr[i]:
                box.own_position(k, q[i])
            lead = self.lead[i]
            if lead is not None:
                lead.own_position(k, q[i])

    def counters(self) -> dict[str, int]:
        boxes = [*self.state, *self.cmd, *(b for b in self.lead if b), *(b for lst in self.nbr for b in lst)]
        return box_counters({f"{b.src}{b.dst}{b.kind}": b for b in boxes})


class _Swarm:
    """The whole swarm in one process: the leader's, the agents' and the plant's cores
    (:class:`zenswarm.leader.core.LeaderCore`, :class:`zenswarm.agents.core.AgentCore`, :class:`zenswarm.plant.core.PlantCore`),
    ticked in the order of the module docstring. The agents are the scenario's controller plug-in
    (:mod:`zenswarm.agents.api`), one per UAV, each behind its receive boxes when there are link
    faults; the paper's controller without link faults runs as one
    :class:`zenswarm.agents.core.StackedAgents` (the same functions, bit for bit)."""

    def __init__(self, scenario: Scenario, faults: FaultPlan | None) -> None:
        self.dt = scenario.timing.dt
        failed: list[PluginFailure] = []  # every plug-in's constructor runs, as in the swarm's processes
        leader = _collect(failed, LeaderCore.from_scenario, scenario)
        plant = _collect(failed, PlantCore, scenario)  # the plant model's constructor
        p = plant_vehicle(scenario)  # the model's vehicle, as the agent processes build their controllers with
        rows = [AgentRow.from_scenario(scenario, i, p.mass, p.g) for i in range(scenario.n)]
        self.links = _Links(faults, rows, self.dt) if faults is not None and faults.active else None
        ctrls = [_collect(failed, build_controller, scenario, i, p.mass, p.g) for i in range(scenario.n)]
        if failed:
            raise PluginsFailed(failed)
        self.leader: LeaderCore = leader
        self.plant: PlantCore = plant
        self.ctrls: list[Controller] = ctrls
        self.bounds: list[Boundary] = [boundary_of(scenario, i) for i in range(scenario.n)]
        self.stacked = StackedAgents(rows) if self.links is None and all(type(c) is PaperController for c in self.ctrls) else None

    def tick(self, k: int, ts: TimeSeries) -> None:
        """Control tick k: steps 1-8; the samples of step 2 go into ``ts[k]``. A plug-in that
        fails raises :class:`PluginsFailed` with every failure of the stage it failed in."""
        q0, v0 = self.leader.ref()
        st = self.plant.state
        q, v = st.q.copy(), st.v.copy()
        ts.t[k], ts.q0[k], ts.v0[k], ts.q[k], ts.v[k], ts.rpy[k] = k * self.dt, q0, v0, q, v, st.rpy
        for name, a in self.plant.recorded.items():  # what the plant model records, with its state
            dst = ts.plant.get(name)
            if dst is None:  # a series allocated without it
                dst = ts.plant[name] = np.full((len(ts.t), *a.shape), np.nan)
            dst[k] = a
        if self.stacked is not None:
            self._agents_stacked(self.stacked, k, q, v, q0, v0, ts)
        else:
            self._agents_each(self.links, k, q, v, q0, v0, ts)
        self.plant.step(k)
        self.leader.advance()

    def _agents_stacked(
        self, ag: StackedAgents, k: int, q: np.ndarray, v: np.ndarray, q0: np.ndarray, v0: np.ndarray, ts: TimeSeries
    ) -> None:
        """The built-in controller of every UAV at once; its outputs are checked per UAV as the
        agent processes check theirs (:func:`zenswarm.agents.api.check_shared` / ``check_command``)."""
        from zenswarm.agents.api import Command, Shared

        bounds = self.bounds
        what = "finish" if PaperController.two_phase else "step"
        if k == 0:
            _each(bounds, k, STAGE_SHARE, "reset", lambda: ag.reset(q, v))
        q_ref, v_ref = ag.q_ref, ag.v_ref
        assert q_ref is not None and v_ref is not None, "reset at tick 0"
        ts.qref[k], ts.vref[k] = q_ref, v_ref
        failed: list[PluginFailure] = []
        if not _finite(q_ref, v_ref):  # then name them as the agents would
            for i, b in enumerate(bounds):
                _collect(failed, b.check, k, STAGE_SHARE, "share", check_shared(Shared(q_ref[i], v_ref[i]), {}))
            raise PluginsFailed(failed)
        cmd = _each(bounds, k, STAGE_STEP, what, lambda: ag.finish(q, v, ag.rates_all(q0, v0)))
        if not _finite(cmd.thrust, cmd.rpy, cmd.u, cmd.d_hat):
            for i, b in enumerate(bounds):
                one = Command(float(cmd.thrust[i]), cmd.rpy[i], cmd.u[i], cmd.d_hat[i])
                _collect(failed, b.check, k, STAGE_STEP, what, check_command(one))
            raise PluginsFailed(failed)
        ts.u[k], ts.thrust[k], ts.d_hat[k], ts.rpy_cmd[k] = cmd.u, cmd.thrust, cmd.d_hat, cmd.rpy
        self.plant.hold_all(cmd.thrust, cmd.rpy, k)

    def _shares(self, lk: _Links | None, k: int, q: np.ndarray, v: np.ndarray) -> list[Any]:
        """Stage share of tick k: every controller (re)started if it is not yet, then what it
        shares (checked); :class:`PluginsFailed` with every failure of the stage."""
        failed: list[PluginFailure] = []
        for i, c in enumerate(self.ctrls):
            if lk is not None:
                lk.state[i].offer(k, k, (q[i], v[i]))
            if not c.initialised:
                qv = _present(lk.state[i].at(k)).value if lk is not None else (q[i], v[i])
                _collect(failed, checked_reset, c, self.bounds[i], k, *qv)
        shared = [_collect(failed, checked_share, c, self.bounds[i], k) for i, c in enumerate(self.ctrls)]
        if failed:
            raise PluginsFailed(failed)
        return shared

    def _agents_each(
        self, lk: _Links | None, k: int, q: np.ndarray, v: np.ndarray, q0: np.ndarray, v0: np.ndarray, ts: TimeSeries
    ) -> None:
        """Every agent's controller ticks on its inputs (through its links' receive boxes, hold
        last value, when there are link faults), as the agent processes do; the plant reads the
        commands (through their links)."""
        ctrls, bounds = self.ctrls, self.bounds
        shared = self._shares(lk, k, q, v)
        failed: list[PluginFailure] = []
        lead_ref = _Ref(q0, v0)
        if lk is not None:
            lk.geometry(k, q)
            # a ref of tick k was sent at tick k - 1: stamped with its sender's position then
            prev = lk.prev_q if lk.radio and lk.prev_q is not None else None
            for i, c in enumerate(ctrls):
                for x, nb in enumerate(c.ctx.neighbours):
                    lk.nbr[i][x].offer(k, k, shared[nb.index], None if prev is None else prev[nb.index])
                lead_box = lk.lead[i]
                if lead_box is not None:
                    lead_box.offer(k, k, lead_ref, q0)
            lk.prev_q = q
        for i, c in enumerate(ctrls):
            if lk is not None:
                qm, vm = _present(lk.state[i].at(k)).value
                nbr = [_held(box.at(k)) for box in lk.nbr[i]]
                lead_box = lk.lead[i]
                lead = _held(lead_box.at(k)) if lead_box is not None else None
            else:
                qm, vm = q[i], v[i]
                nbr = [shared[nb.index] for nb in c.ctx.neighbours]
                lead = lead_ref if c.ctx.pinned else None
            before = len(failed)
            prepared = _collect(failed, checked_prepare, c, bounds[i], k, nbr, lead)
            cmd = _collect(failed, checked_finish, c, bounds[i], k, qm, vm, prepared, self.dt) if len(failed) == before else None
            if cmd is None:
                continue  # the tick ends with this stage's failures, after every agent's step ran
            ts.qref[k, i], ts.vref[k, i] = shared[i].q, shared[i].v
            ts.u[k, i], ts.thrust[k, i], ts.d_hat[k, i], ts.rpy_cmd[k, i] = cmd.u, cmd.thrust, cmd.d_hat, cmd.rpy
            if lk is not None:
                lk.cmd[i].offer(k, k, (cmd.thrust, cmd.rpy))
            else:
                self.plant.hold(i, cmd.thrust, cmd.rpy, k)
        if failed:
            raise PluginsFailed(failed)
        if lk is not None:
            for i, box in enumerate(lk.cmd):
                held = _present(box.at(k))
                thrust, rpy = held.value
                self.plant.hold(i, thrust, rpy, held.send_tick)

    def fault_results(self) -> dict:
        """``link_counters`` and ``failsafe_events`` of a run with link faults ({} without)."""
        if self.links is None:
            return {}
        return {"link_counters": self.links.counters(), "failsafe_events": [list(e) for e in self.plant.failsafe.events]}


def _held(h: Held | None) -> Any:
    """The value a box holds (None before its first delivery)."""
    return None if h is None else h.value


def _present(h: Held | None) -> Held:
    """What a box holds where something must be held: the state and command links carry a
    message every tick from tick 0, which a :class:`zenswarm.link.swarm.Box` always delivers at once."""
    assert h is not None, "a state or command link holds nothing"
    return h


class _Flight:
    """Ticks a :class:`_Swarm` into a time series; ``flown``: ticks whose samples are complete
    (what a Ctrl-C keeps). When it ends is the end-of-flight watch's (:class:`zenswarm.judge.watch.EndWatch`),
    the supervisor's too."""

    def __init__(self, swarm: _Swarm, ts: TimeSeries, scenario: Scenario, progress: ProgressFn | None, full_time: bool) -> None:
        self.swarm = swarm
        self.ts = ts
        self.crit = criteria_from_scenario(scenario)
        self.full_time = full_time
        self.goal = np.asarray(scenario.leader.goal, dtype=float)
        self.progress = progress
        self.flown = 0
        self.failures: list[PluginFailure] = []  # the plug-in failures the run ended on

    def run(self, T: int) -> int:
        """Tick until T, or until the tick that decided the run (unless ``full_time``), or until
        a plug-in failed (:attr:`failures`: the failures of its first (tick, stage); the ticks
        before it are judged, unless the run was decided before). Returns the ticks flown."""
        watch = EndWatch(self.crit, T, full_time=self.full_time)
        try:
            for k in range(T):
                if watch.due(k) and (end := watch.block(self.ts, k)) is not None:  # ends after the deciding tick
                    self.flown = end.upto
                    return self.flown
                self.flown = k
                self.swarm.tick(k, self.ts)
                if self.progress is not None and (k % 100 == 0 or k == T - 1):
                    self.progress(k + 1, T, float(np.linalg.norm(self.swarm.leader.q0 - self.goal)))
        except (PluginsFailed, PluginFailure) as e:
            first = first_failures(e.failures if isinstance(e, PluginsFailed) else [e])
            end = watch.plugin_failed(self.ts, first[0].tick)  # the ticks before the failed one are complete
            self.flown = end.upto
            if end.plugin_failed:  # else decided before the plug-in failed: as the swarm's supervisor judges it
                self.failures = first
            return self.flown
        end = watch.block(self.ts, T)
        self.flown = T if end is None else end.upto
        return self.flown


def simulate(
    scenario: Scenario,
    progress: ProgressFn | None = None,
    n_ticks: int | None = None,
    faults: FaultPlan | None = None,
    full_time: bool = False,
) -> SimResult:
    """Run ``scenario`` for ``n_ticks`` control ticks (default: the time limit).

    progress(k, n_ticks, dist_to_goal_m) is called about every 100 ticks. ``faults``: a link
    fault plan (:func:`zenswarm.link.swarm.plan_for`); each receiver then holds the newest value
    its links delivered (:class:`zenswarm.link.swarm.Box`), exactly as the lockstep processes do.
    The run ends after the tick where its outcome was decided (a stalled leader or a diverged
    UAV, :func:`zenswarm.judge.verdict.decide_end`) unless ``full_time``. Ctrl-C (KeyboardInterrupt)
    ends it too: the ticks flown are judged and the results carry an ``interrupted`` failure.
    Returns the time series (one sample per tick, taken at step 2 of the tick) and the results.
    """
    wall0 = time.perf_counter()
    dt = scenario.timing.dt
    T = scenario.timing.n_ticks if n_ticks is None else int(n_ticks)
    ts = TimeSeries.allocate(T, scenario.n, {name: sig.shape for name, sig in plant_records(scenario).items()})
    try:
        swarm: _Swarm | None = _Swarm(scenario, faults)
    except PluginsFailed as e:  # a plug-in's constructor raised: nothing flown
        swarm, built = None, first_failures(e.failures)
    except PluginFailure as e:
        swarm, built = None, [e]
    interrupted = False
    if swarm is not None:
        flight = _Flight(swarm, ts, scenario, progress, full_time)
        try:
            flight.run(T)
        except KeyboardInterrupt:  # Ctrl-C: judge and keep what was flown
            interrupted = True
        flown, failed = flight.flown, flight.failures
    else:
        flown, failed = 0, built
    wall = time.perf_counter() - wall0
    if flown < T:
        ts = ts.truncated(flown)
    if flown == 0:
        ts.plant = {}  # nothing recorded: as the swarm's collector has it (a series comes with its first value)
    results = flight_results(
        ts, scenario, wall_time_s=wall, full_time=full_time, faults=faults if swarm is not None else None,
        facts=swarm.fault_results() if swarm is not None else {},  # link_counters, failsafe_events
        t_s=flown * dt, interrupted="Ctrl-C" if interrupted else None, plugin_failures=failed,
    )  # fmt: skip
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


def apply_overrides(scenario: Scenario, no_eso: bool = False, fixed_gain: float | None = None) -> Scenario:
    """Scenario copy with the CLI's comparison switches applied."""
    if no_eso:
        scenario = replace(scenario, eso=replace_table(scenario.eso, enabled=False))
    if fixed_gain is not None:
        scenario = replace(
            scenario, leader=replace_table(scenario.leader, adaptive=False, k_rep_fixed=float(fixed_gain), planner="apf")
        )
    return scenario


def run_sim_cli(scenario: Scenario, out: Path, quiet: bool = False, faults: FaultPlan | None = None, full_time: bool = False) -> int:
    """``zenswarm sim``: run, write outputs, print a summary. Exit code 0 on mission success, 1 on
    failure, 4 when a plug-in failed (``plugin_error``; what was flown before it is judged and
    written), 130 when interrupted (Ctrl-C or SIGTERM; what was flown is judged and written)."""
    prog = None if quiet else ProgressPrinter("sim", scenario.timing.dt)
    previous = _interrupt_on_signals()
    try:
        res = simulate(scenario, progress=prog, faults=faults, full_time=full_time)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    write_outputs(out, res.series, res.results)
    for line in closing_lines(res.results, out):
        print(line)
    return exit_code_of(res.results)


def _interrupt_on_signals() -> dict[int, Any]:
    """SIGINT and SIGTERM raise KeyboardInterrupt in the simulator's loop (so the ticks flown are
    judged and written), also when the process was started with SIGINT ignored (a shell's
    background job). Returns the previous handlers. Main thread only; elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {sig: signal.signal(sig, signal.default_int_handler) for sig in (signal.SIGINT, signal.SIGTERM)}

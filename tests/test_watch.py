"""The end-of-flight watch (zenswarm.judge.watch) on synthetic series, without a process: when a
flight ends (a stalled leader, a diverged UAV, --stop-at-goal, a plug-in's failure, the time limit)
and which ticks are judged, each against the tick it must be, in closed form where there is one;
the simulator's way of looking (exact, in blocks) and the supervisor's (a glance, then exact) end
after the same tick."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from zenswarm.judge.metrics import TimeSeries, compute_results
from zenswarm.judge.results import closing_lines, summary_line
from zenswarm.judge.verdict import Criteria, judge
from zenswarm.judge.watch import DECIDE_EVERY, Ending, EndWatch, LiveRecord, Record

DT = 0.01
T = 1000
GOAL = (10.0, 0.0, 1.0)
H = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
OB = SimpleNamespace(center=(5.0, 0.0, 0.0), radius=0.5, height=2.0)


def crit(obstacles=(), **kw) -> Criteria:
    base = dict(
        goal=np.asarray(GOAL, dtype=float), offsets=H, obstacles=tuple(obstacles), dt=DT, goal_tolerance_m=0.05,
        settle_time_s=1.0, vehicle_radius_m=0.06, slot_tolerance_m=0.1, settle_window_s=0.5, stall_speed_m_s=0.045,
        stall_window_s=1.0, divergence_m=1.0, d0=0.3, r_f=1.0,
    )  # fmt: skip
    base.update(kw)
    return Criteria(**base)


def series(x_of_tick: np.ndarray) -> TimeSeries:
    """A flight of T ticks: the leader at (x_k, 0, 1), each UAV exactly in formation on it, its
    reference on its position."""
    ts = TimeSeries.allocate(T, len(H))
    for f in TimeSeries.FIELDS:
        getattr(ts, f)[:] = 0.0
    ts.t[:] = np.arange(T) * DT
    ts.q0[:] = np.stack([x_of_tick, np.zeros(T), np.ones(T)], axis=1)
    ts.q[:] = ts.q0[:, None, :] + H[None]
    ts.qref[:] = ts.q
    return ts


def straight(speed_m_per_tick: float, stop_x: float) -> np.ndarray:
    """The leader's x: from 0 at ``speed_m_per_tick``, holding at ``stop_x``."""
    return np.minimum(np.arange(T) * speed_m_per_tick, stop_x)


class Flying:
    """A synthetic flight as the supervisor sees it while it flies: ticks 0 .. flown - 1 have
    arrived (the :class:`LiveRecord` the swarm's collector is)."""

    def __init__(self, ts: TimeSeries, goal_tol: float = 0.05) -> None:
        self.whole = ts
        self.flown = 0
        self.goal_tol = goal_tol

    @property
    def q0(self) -> np.ndarray:
        return np.where((np.arange(T) < self.flown)[:, None], self.whole.q0, np.nan)

    @property
    def leader_ticks(self) -> int:
        return self.flown

    @property
    def goal_tick(self) -> int | None:
        at = np.flatnonzero(np.linalg.norm(self.whole.q0[: self.flown] - np.asarray(GOAL), axis=1) <= self.goal_tol)
        return int(at[0]) if len(at) else None

    def latest(self, kind: str) -> dict[int, tuple[int, np.ndarray]]:
        if not self.flown:
            return {}
        a = self.whole.q if kind == "state" else self.whole.qref
        return {i + 1: (self.flown - 1, a[self.flown - 1, i]) for i in range(len(H))}

    def complete_ticks(self, upto: int) -> int:
        return min(upto, self.flown)

    def clock_ticks(self) -> int:
        return self.flown

    def series(self, upto_tick: int | None = None, fill: bool = False) -> TimeSeries:
        return self.whole.series(self.flown if upto_tick is None else min(upto_tick, self.flown), fill)


def sim_end(ts: TimeSeries, c: Criteria, full_time: bool = False) -> int:
    """The ticks the simulator flies (compose/sim.py's _Flight): an exact look every DECIDE_EVERY ticks and at the end."""
    w = EndWatch(c, T, full_time=full_time)
    for k in range(T):
        if w.due(k) and (end := w.block(ts, k)) is not None:
            return end.upto
    end = w.block(ts, T)
    return T if end is None else end.upto


def live_end(ts: TimeSeries, c: Criteria, every: int = 7, **kw) -> tuple[int | None, str]:
    """The supervisor's: a look every ``every`` ticks as the flight arrives; (ticks judged, why)
    or (None, "") when it ran its course."""
    w = EndWatch(c, T, **kw)
    f = Flying(ts)
    for flown in range(1, T + 1):
        f.flown = flown
        if flown % every == 0 and (end := w.look(f)) is not None:
            assert w.judged_ticks(f, stopped=False, fill=False) == end.upto
            return end.upto, end.why
    return w.judged_ticks(f, stopped=False, fill=False), ""


def test_both_records_are_what_the_watch_reads() -> None:
    """The simulator's series and the supervisor's collector both satisfy the watch's protocol."""
    from zenswarm.bus import wire
    from zenswarm.process.collector import Collector
    from zenswarm.scenario.config import load_scenario

    from swarmtest import SCENARIOS

    sc = load_scenario(SCENARIOS / "paper_example1.toml")
    assert isinstance(Collector(sc, wire.Keys("watch")), LiveRecord)
    assert isinstance(TimeSeries.allocate(3, 2), Record) and not isinstance(TimeSeries.allocate(3, 2), LiveRecord)


def test_a_leader_stalled_by_an_obstacle_ends_the_flight_after_the_stall_tick() -> None:
    """1 cm a tick, stopped at x = 4.3 (0.2 m from the cylinder at 4.5: within d0 = 0.3) from tick
    430: over the window of W = 100 ticks ending at k the leader moved (430 + W - k) cm, slow below
    0.045 m/s * 1 s = 4.5 cm, so first at k = 430 + 96 = 526; both watches end after it, whatever
    their cadence."""
    ts, c = series(straight(0.01, 4.3)), crit([OB])
    stall = 430 + 96
    assert sim_end(ts, c) == stall + 1
    for every in (1, 7, 50):
        upto, why = live_end(ts, c, every=every)
        assert upto == stall + 1, every
        assert why.startswith(f"at sim time {stall * DT:.2f} s the virtual leader moved ") and "local minimum" in why, why
    assert sim_end(ts, c, full_time=True) == T and live_end(ts, c, full_time=True) == (None, "")
    # stopped as far from every obstacle: no minimum of the field but the goal, flown to the end
    far = crit([SimpleNamespace(center=(50.0, 0.0, 0.0), radius=0.5, height=2.0)])
    assert sim_end(ts, far) == T and live_end(ts, far) == (None, "")


def test_a_uav_that_leaves_its_reference_ends_the_flight_when_it_is_divergence_m_away() -> None:
    """UAV 2 drifts off its reference by 1.3 cm a tick from tick 300: farther than 1 m first at
    tick 300 + 77 (76 * 1.3 = 98.8 cm, 77 * 1.3 = 100.1 cm)."""
    ts, c = series(straight(0.005, 20.0)), crit()
    drift = np.clip(np.arange(T) - 300, 0, None) * 0.013
    ts.q[:, 1, 0] += drift
    assert sim_end(ts, c) == 377 + 1
    for every in (1, 13):
        upto, why = live_end(ts, c, every=every)
        assert upto == 378 and why.startswith("at sim time 3.77 s UAV 2 is 1.00 m from its reference q*_2"), why
    # a state that goes non-finite ends it at that tick
    ts.q[:, 1] = ts.qref[:, 1]
    ts.q[612:, 2, 2] = np.nan
    assert sim_end(ts, c) == 613 and live_end(ts, c)[0] == 613


def test_stop_at_goal_once_every_uav_was_in_its_slot_for_the_settle_window() -> None:
    """The leader flies to the goal at 2 cm a tick with the UAVs in formation: within its 5 cm
    first at tick 498 (9.96 m), when every UAV is 4 cm from its slot (tolerance 10 cm). Looked at
    every tick, the watch counts the settle window (50 ticks) from there and ends the flight after
    tick 547. Without --stop-at-goal it flies its course."""
    ts, c = series(straight(0.02, 10.0)), crit()
    assert live_end(ts, c, every=1, stop_at_goal=True) == (548, "goal reached at sim time 4.98 s and every UAV in its slot for "
                                                             "0.5 s at 5.47 s; stopping (--stop-at-goal)")
    assert live_end(ts, c, every=1) == (None, "") and sim_end(ts, c) == T
    # a UAV that leaves its slot for a tick restarts the settle window
    ts.q[520, 0, 1] += 0.5
    assert live_end(ts, c, every=1, stop_at_goal=True)[0] == 521 + 50


def test_a_plug_in_failure_judges_the_ticks_before_it_unless_the_outcome_was_decided_before() -> None:
    ts, c = series(straight(0.005, 20.0)), crit()
    w = EndWatch(c, T)
    end = w.plugin_failed(ts, 444)
    assert (end.upto, end.plugin_failed) == (444, True) and w.judged_ticks(Flying(ts), stopped=False, fill=False) == 444
    assert EndWatch(c, T).plugin_failed(ts, T + 5).upto == T  # a tick past the limit: the whole flight
    ts.q[200:, 0, 0] += 2.0  # UAV 1 2 m off its reference from tick 200: decided there
    end = EndWatch(c, T).plugin_failed(ts, 444)
    assert (end.upto, end.plugin_failed) == (201, False)
    assert end.why == "the outcome was decided at sim time 2.00 s, before the plug-in failed"
    assert EndWatch(c, T).plugin_failed(ts, 150).plugin_failed  # failed before the decision
    # --full-time, and realtime (held ticks: nothing is waited for), judge the ticks before the failure
    for kw in ({"full_time": True}, {"realtime": True}):
        end = EndWatch(c, T, **kw).plugin_failed(ts, 444)
        assert (end.upto, end.plugin_failed) == (444, True), kw
    # the simulator's blocks already looked at ticks before 200: the same decision
    w = EndWatch(c, T)
    assert w.block(ts, DECIDE_EVERY) is None and w.plugin_failed(ts, 444).upto == 201


def test_a_flight_that_runs_its_course_is_judged_whole_a_timeout_without_the_goal() -> None:
    """Never decided, goal not reached: both watches let it fly to the limit; judged whole, it is a
    ``timeout`` at the last tick's time with the leader's distance to the goal; stopped by a dead
    process or a signal at tick 640 it is judged up to there, ``incomplete``."""
    ts, c = series(straight(0.005, 20.0)), crit()
    assert sim_end(ts, c) == T and live_end(ts, c) == (None, "")
    v = judge(ts.t, ts.q0, ts.q, ts.qref, c, n_ticks=T)
    assert [(f.cause, f.t_s) for f in v.failures] == [("timeout", (T - 1) * DT)]
    assert v.failures[0].detail.endswith(f"({10.0 - (T - 1) * 0.005:.3f} m from it)")
    f = Flying(ts)
    f.flown = 640
    w = EndWatch(c, T)
    assert w.judged_ticks(f, stopped=True, fill=True) == 640 and w.judged_ticks(f, stopped=True, fill=False) == 640
    cut = ts.series(640)
    v = judge(cut.t, cut.q0, cut.q, cut.qref, c, n_ticks=T)
    assert [f.cause for f in v.failures] == ["incomplete"] and v.end_tick == 640


def test_the_simulator_and_the_supervisor_end_after_the_same_tick() -> None:
    """Random drifts and stalls: the exact blocks and the glances end after the same tick (the
    decision is causal; the glance sees a divergence that lasts). A flight whose processes all
    ended before the supervisor's next look ran its course: its results judge the whole series,
    which ends the verdict at that same tick."""
    rng = np.random.default_rng(44)
    seen = {"looked": 0, "ended first": 0}
    for _ in range(30):
        ts = series(straight(0.01, float(rng.uniform(3.0, 12.0))))
        start, rate, uav = int(rng.integers(0, T)), float(rng.uniform(0.001, 0.05)), int(rng.integers(0, len(H)))
        ts.q[:, uav, 1] += np.clip(np.arange(T) - start, 0, None) * rate
        c = crit([OB])
        simulated = sim_end(ts, c)
        supervised = live_end(ts, c, every=int(rng.integers(1, 60)))[0]
        if supervised is None:
            supervised = judge(ts.t, ts.q0, ts.q, ts.qref, c, n_ticks=T).end_tick
            seen["ended first"] += simulated < T
        else:
            seen["looked"] += 1
        assert supervised == simulated, (start, rate, uav)
    assert seen["looked"] >= 5 and seen["ended first"] >= 1, seen


def test_the_closing_lines_are_the_summary_then_where_the_files_are(tmp_path) -> None:
    """results.json's closing lines: a swarm's foreign samples and failsafe intervals first (the
    simulator has none), the summary line, where the files are."""
    ts = series(straight(0.02, 10.0))
    sc = SimpleNamespace(
        name="synthetic", n=len(H), leader=SimpleNamespace(goal=GOAL, d0=0.3), offsets=H, obstacles=(), r_f=1.0,
        vehicle_radius=0.06, timing=SimpleNamespace(dt=DT, goal_tolerance_m=0.05, settle_time_s=1.0, n_ticks=T, control_rate_hz=100.0),
        mission=SimpleNamespace(slot_tolerance_m=0.1, settle_window_s=0.5, stall_speed_m_s=0.045, stall_window_s=1.0, divergence_m=1.0),
    )  # fmt: skip
    res = compute_results(ts, sc, wall_time_s=1.5)
    lines = closing_lines(res, tmp_path)
    assert lines[0] == "synthetic: SUCCESS" and lines[1:3] == summary_line(res).split("\n")[1:]
    assert lines[-1] == f"wrote {tmp_path / 'results.json'} and {tmp_path / 'timeseries.npz'}" and len(lines) == 4
    res["foreign_samples"] = {"a": 2, "b": 3}
    res["failsafe"] = [{"uav": 2, "modes": ["hover", "land"], "from_s": 1.0, "to_s": None}]
    lines = closing_lines(res, tmp_path)
    assert lines[0] == "ignored 5 messages from sessions that are not their key's process (on 2 keys; results.json: foreign_samples)"
    assert lines[1] == ("failsafe: UAV 2 flown by the plant (hover then land) from sim time 1.00 s to the end: "
                        "agent:2's commands were stale")


@pytest.mark.parametrize("fill", [False, True])
def test_a_time_series_gives_its_ticks_as_the_collector_does(fill: bool) -> None:
    """TimeSeries.series: ticks 0 .. k - 1 (views), or filled as the collector fills a realtime series."""
    ts = series(straight(0.01, 5.0))
    ts.q[:3, 1] = np.nan  # UAV 2's first states missing: the filled series starts at tick 3
    ts.q[10, 0] = np.nan  # a skipped tick holds the previous value
    got = ts.series(20, fill=fill)
    if not fill:
        assert len(got.t) == 20 and np.shares_memory(got.q, ts.q) and np.isnan(got.q[10, 0]).all()
        return
    assert got.t[0] == pytest.approx(3 * DT) and len(got.t) == 17
    assert (got.q[10 - 3, 0] == ts.q[9, 0]).all() and not np.shares_memory(got.q, ts.q) and np.isnan(ts.q[10, 0]).all()


def test_the_collector_fed_from_the_bus_ends_as_the_series_it_assembles() -> None:
    """A real Collector (no process: the samples handed to it as the bus would) of a flight whose
    UAV 2 is pushed off its reference by 1.3 cm a tick from tick 40: the supervisor's look ends it
    after the tick the mission's divergence_m is first exceeded, as the simulator's exact look
    on the same series does; the results judge that many ticks; the clock's ticks and the last
    tick flown are read from the clock and the plant's final diagnostics."""
    from zenswarm.bus import wire
    from zenswarm.judge.verdict import criteria_from_scenario
    from zenswarm.process.collector import Collector
    from zenswarm.scenario.config import load_scenario

    from swarmtest import SCENARIOS

    sc = load_scenario(SCENARIOS / "paper_example1.toml")
    keys = wire.Keys("watch")
    col = Collector(sc, keys)
    c = criteria_from_scenario(sc)
    n, dt_ns, z = sc.n, col.dt_ns, (0.0, 0.0, 0.0)
    off = int(np.floor(c.divergence_m / 0.013)) + 1  # ticks past 40 until 1.3 cm a tick is farther than divergence_m
    assert 0.013 * off - c.divergence_m > 1e-4 and c.divergence_m - 0.013 * (off - 1) > 1e-4  # no tie
    q0 = np.asarray(sc.leader.start, dtype=float)
    h = np.asarray(sc.offsets, dtype=float).reshape(n, 3)
    w = EndWatch(c, col.T)
    assert col.clock_ticks() == 0 and w.look(col) is None
    end = None
    for k in range(40 + off + 20):
        t = k * dt_ns
        col.on_sample(keys.leader_ref, wire.encode(wire.Ref(t=t, seq=k, q=tuple(q0), v=z)))
        for i in range(n):
            q = q0 + h[i] + (np.array([0.0, 0.013 * max(0, k - 40), 0.0]) if i == 1 else 0.0)
            col.on_sample(keys.state(i + 1), wire.encode(wire.State(t=t, seq=k, q=tuple(q), v=z, rpy=z, w=z)))
            col.on_sample(keys.ref(i + 1), wire.encode(wire.Ref(t=t, seq=k, q=tuple(q0 + h[i]), v=z)))
            col.on_sample(keys.cmd(i + 1), wire.encode(wire.Cmd(t=t, seq=k, thrust=1.0, rpy=z, u=z, d_hat=z)))
        col.on_sample(keys.clock, wire.encode(wire.Clock(t=(k + 1) * dt_ns, seq=k + 1)))
        if end is None and k % 5 == 4:
            end = w.look(col)
    assert end is not None and end.upto == 40 + off + 1, end
    assert "UAV 2 is" in end.why and w.judged_ticks(col, stopped=False, fill=False) == end.upto
    ts = col.series()
    assert EndWatch(c, col.T).block(ts, 40 + off + 20) == Ending(40 + off + 1)
    assert col.clock_ticks() == 40 + off + 20 and w.judged_ticks(col, stopped=True, fill=False) == 40 + off + 20
    assert col.last_tick_flown() == col.T - 1  # every process ended with 0: the plant flew the whole limit
    col.on_sample(keys.diag("plant"), wire.encode(wire.Diag(t=0, seq=1, process="plant", info={"finished": False})))
    assert col.last_tick_flown() == 40 + off + 20  # stopped early: the clock's last tick
    assert set(col.facts()) == {"failsafe", "diagnostics", "decoder_rejects", "foreign_samples"}

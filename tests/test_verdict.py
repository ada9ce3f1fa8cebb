"""The verdict against closed-form flights: contacts at known ticks, margins, slots, stalls,
divergence, and the pair search against brute force (zenswarm.judge.verdict, zenswarm.vehicle.geometry)."""

from __future__ import annotations

import math
import re
import tracemalloc
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from zenswarm.judge.verdict import CAUSES, Criteria, decide_end, judge
from zenswarm.vehicle.geometry import close_pairs, d_obs_many, obstacle_clearance_many

DT = 0.01
OB = SimpleNamespace(center=(5.0, 0.0, 0.0), radius=0.5, height=1.0)


def crit(offsets, obstacles=(), goal=(10.0, 0.0, 1.0), **kw) -> Criteria:
    base = dict(
        goal=np.asarray(goal, dtype=float),
        offsets=np.asarray(offsets, dtype=float),
        obstacles=tuple(obstacles),
        dt=DT,
        goal_tolerance_m=0.05,
        settle_time_s=1.0,
        vehicle_radius_m=0.06,
        slot_tolerance_m=0.1,
        settle_window_s=0.5,
        stall_speed_m_s=0.01,
        stall_window_s=1.0,
        divergence_m=5.0,
        d0=0.3,
        r_f=float(np.max(np.linalg.norm(np.asarray(offsets, dtype=float), axis=1))),
    )
    base.update(kw)
    return Criteria(**base)


def flight(T: int, offsets, goal=(10.0, 0.0, 1.0), start=(0.0, 0.0, 1.0), arrive_tick: int | None = None):
    """A leader moving on a straight line from start to goal, arriving at ``arrive_tick`` and
    holding; UAVs exactly at q0 + h_i, references equal to the positions."""
    t = np.arange(T) * DT
    s = np.clip(np.arange(T) / float(arrive_tick if arrive_tick else T // 2), 0.0, 1.0)
    q0 = np.asarray(start, dtype=float) + s[:, None] * (np.asarray(goal, dtype=float) - np.asarray(start, dtype=float))
    h = np.asarray(offsets, dtype=float)
    q = q0[:, None, :] + h[None]
    return t, q0, q.copy(), q.copy()


H3 = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]


def causes(v) -> list[str]:
    return [f.cause for f in v.failures]


def test_perfect_flight_succeeds_with_exact_figures() -> None:
    t, q0, q, qref = flight(400, H3)
    v = judge(t, q0, q, qref, crit(H3))
    assert v.success and v.failures == []
    assert v.goal_reached and v.time_to_goal_s == pytest.approx(2.0)
    assert v.max_formation_error_m == 0.0 and v.rms_tracking_error_m == 0.0
    assert v.min_inter_uav_distance_m == pytest.approx(1.0)
    assert v.min_inter_uav_margin_m == pytest.approx(1.0 - 0.12)
    assert v.min_obstacle_clearance_m is None  # no obstacle
    assert v.final_slot_errors_m == [0.0, 0.0, 0.0]


def test_vehicle_formation_error_is_not_the_generator_s() -> None:
    t, q0, q, qref = flight(400, H3)
    q[150:, 1, 2] -= 0.07  # UAV 2 sags 7 cm after 1.5 s; the generator's references do not
    v = judge(t, q0, q, qref, crit(H3))
    assert v.max_formation_error_m == pytest.approx(0.07)
    assert v.max_generator_formation_error_m == 0.0
    assert v.success  # 7 cm is inside the slot tolerance


def test_uav_off_slot_names_the_uav_and_its_error() -> None:
    t, q0, q, qref = flight(400, H3)
    q[:, 2, 0] += 0.25  # UAV 3 a quarter metre behind its slot the whole flight (tracking fine)
    qref[:, 2, 0] += 0.25
    v = judge(t, q0, q, qref, crit(H3))
    assert causes(v) == ["uav_off_slot"] and v.failures[0].uavs == (3,)
    assert v.final_slot_errors_m[2] == pytest.approx(0.25)


def test_ground_contact_after_take_off_only() -> None:
    h = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    t, q0, q, qref = flight(400, h)
    q[:, 0, 2] = np.linspace(0.0, 1.0, 400)  # UAV 1 takes off from the ground: no contact
    q[:, 1, 2] = 1.0
    q[300:, 1, 2] = -0.01  # UAV 2 drops below the ground at tick 300
    v = judge(t, q0, q, qref, crit(h, divergence_m=50.0), early_end=False)
    ground = [f for f in v.failures if f.cause == "collision_ground"]
    assert [(f.uavs, f.t_s) for f in ground] == [((2,), pytest.approx(3.0))]
    assert v.min_altitude_m == pytest.approx(-0.01)


def test_obstacle_contact_below_the_radius_and_margin() -> None:
    h = [[0.0, 0.0, 0.0]]
    t, q0, q, qref = flight(400, h, goal=(10.0, 0.0, 0.5), start=(0.0, 0.0, 0.5))
    # pass beside the cylinder at y = 0.5 + 0.06 + 0.001: 1 mm outside the contact radius
    q[:, 0, 1] = 0.5 + 0.061
    q0[:, 1] = q[:, 0, 1]
    qref[:] = q
    c = crit(h, obstacles=[OB], goal=(10.0, 0.561, 0.5))
    v = judge(t, q0, q, qref, c)
    assert "collision_obstacle" not in causes(v)
    assert v.min_obstacle_clearance_m == pytest.approx(0.061)
    assert v.min_obstacle_margin_m == pytest.approx(0.001)
    q[:, 0, 1] = 0.5 + 0.059  # 1 mm inside
    v = judge(t, q0, q, qref, c)
    f = [f for f in v.failures if f.cause == "collision_obstacle"]
    assert len(f) == 1 and f[0].uavs == (1,) and f[0].obstacle == 0
    # rho = hypot(x - 5, 0.559) < 0.56 only for |x - 5| < 0.0334; x(k) = 0.05 k: tick 100 alone
    assert f[0].t_s == pytest.approx(1.0)


def test_uav_contact_at_the_first_tick_below_twice_the_radius() -> None:
    h = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    t, q0, q, qref = flight(400, h)
    gap = np.linspace(1.0, 0.0, 400)  # UAV 2 slides onto UAV 1
    q[:, 1, 1] = q0[:, 1] + gap
    qref[:] = q
    v = judge(t, q0, q, qref, crit(h, divergence_m=50.0))
    k = int(np.flatnonzero(gap < 0.12)[0])
    f = [f for f in v.failures if f.cause == "collision_uav"]
    assert [(x.uavs, x.t_s) for x in f] == [((1, 2), pytest.approx(k * DT))]
    assert v.min_inter_uav_distance_m == pytest.approx(0.0)


def test_leader_stall_near_an_obstacle_ends_the_run_there() -> None:
    h = [[0.0, 0.0, 0.0]]
    T = 1000
    t = np.arange(T) * DT
    q0 = np.zeros((T, 3))
    q0[:, 0] = np.minimum(np.arange(T) * 0.02, 4.3)  # stops 0.2 m before the cylinder (d0 = 0.3)
    q0[:, 2] = 0.5
    q = q0[:, None, :].copy()
    c = crit(h, obstacles=[OB], goal=(10.0, 0.0, 0.5))
    stopped = int(np.flatnonzero(q0[:, 0] >= 4.3)[0])  # 215
    k = decide_end(q0, q, q, c)
    assert k == stopped + c.stall_ticks  # the first window that starts at the stop: moved 0 m < 0.01 m/s * 1 s
    v = judge(t, q0, q, q, c)
    assert causes(v) == ["leader_stalled"] and v.end_tick == k + 1
    assert v.stall is not None and v.stall["obstacles_within_d0"] == [0]
    assert v.stall["where"] == pytest.approx([4.3, 0.0, 0.5])
    # the same leader stopping far from every obstacle is no AAPF minimum: flown on, a timeout
    far = crit(h, obstacles=[SimpleNamespace(center=(50.0, 0.0, 0.0), radius=0.5, height=1.0)], goal=(10.0, 0.0, 0.5))
    assert decide_end(q0, q, q, far) is None
    assert causes(judge(t, q0, q, q, far)) == ["timeout"]


def test_divergence_from_the_reference_and_non_finite_end_the_run() -> None:
    t, q0, q, qref = flight(400, H3)
    q[:, 1, 2] -= 0.5 * 9.81 * t**2  # UAV 2 falls freely; its reference stays
    k = int(np.flatnonzero(0.5 * 9.81 * t**2 > 5.0)[0])
    v = judge(t, q0, q, qref, crit(H3))
    assert v.end_tick == k + 1
    assert ("uav_diverged", (2,)) in [(f.cause, f.uavs) for f in v.failures]
    full = judge(t, q0, q, qref, crit(H3), early_end=False)  # --full-time: named, not cut
    assert full.end_tick == 400 and "uav_diverged" in causes(full)
    t, q0, q, qref = flight(400, H3)
    q[123:, 0] = np.nan
    v = judge(t, q0, q, qref, crit(H3))
    assert causes(v) == ["non_finite"] and v.failures[0].t_s == pytest.approx(1.23) and not v.finite


def test_a_non_finite_leader_ends_the_run_there() -> None:
    """docs/verdict.md: a non-finite state ends the run early, the leader's reference too."""
    t, q0, q, qref = flight(400, H3)
    q0[120:] = np.nan
    assert decide_end(q0, q, qref, crit(H3)) == 120
    assert decide_end(q0, q, qref, crit(H3), 0, 120) is None and decide_end(q0, q, qref, crit(H3), 130) == 130
    v = judge(t, q0, q, qref, crit(H3))
    assert v.end_tick == 121 and "non_finite" in causes(v)


def test_lagging_formation_is_off_slot_not_diverged() -> None:
    """A formation whose references lag the leader (slow consensus) while the UAVs track them is
    no divergence: it flies to the end and fails with uav_off_slot."""
    t, q0, q, qref = flight(400, H3)
    q[:, 1, 0] -= 8.0
    qref[:, 1, 0] -= 8.0
    v = judge(t, q0, q, qref, crit(H3))
    assert v.end_tick == 400 and causes(v) == ["uav_off_slot"]


def test_stopped_before_the_limit_is_incomplete_not_timeout() -> None:
    t, q0, q, qref = flight(400, H3, arrive_tick=10_000)
    v = judge(t[:100], q0[:100], q[:100], qref[:100], crit(H3), n_ticks=400)
    assert causes(v) == ["incomplete"]
    assert causes(judge(t, q0, q, qref, crit(H3), n_ticks=400)) == ["timeout"]
    v = judge(t[:0], q0[:0], q[:0], qref[:0], crit(H3), n_ticks=400)
    assert causes(v) == ["no_data"] and not v.success
    assert set(causes(v)) <= set(CAUSES)


def test_a_series_that_starts_late_ran_its_course_by_its_last_tick() -> None:
    """A realtime series starts at the first tick every process had produced a value (here 11):
    it is judged by its last tick's time, not its length. Flown to the limit it is a timeout at
    the limit's sim time, never ``incomplete``; stopped early it is incomplete at its last tick."""
    t, q0, q, qref = flight(400, H3, arrive_tick=10_000)
    late = slice(11, None)
    v = judge(t[late], q0[late], q[late], qref[late], crit(H3), n_ticks=400)
    assert causes(v) == ["timeout"] and v.end_tick == 400, (causes(v), v.end_tick)
    assert v.failures[0].t_s == pytest.approx(3.99)
    early = slice(11, 100)
    v = judge(t[early], q0[early], q[early], qref[early], crit(H3), n_ticks=400)
    assert causes(v) == ["incomplete"] and v.end_tick == 100, (causes(v), v.end_tick)
    # reached: success whatever the first tick
    t, q0, q, qref = flight(400, H3, arrive_tick=100)
    v = judge(t[late], q0[late], q[late], qref[late], crit(H3), n_ticks=400)
    assert v.success and v.end_tick == 400 and v.time_to_goal_s == pytest.approx(1.0), (causes(v), v.end_tick)


@pytest.mark.parametrize("seed", range(5))
def test_close_pairs_equals_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-3.0, 3.0, size=(300, 3)) * np.array([1.0, 1.0, 0.1 * seed])
    cutoff = 0.4
    ii, jj, dd = close_pairs(p, cutoff)
    D = np.linalg.norm(p[:, None] - p[None], axis=2)
    bi, bj = np.nonzero(np.triu(D < cutoff, 1))
    assert sorted(zip(ii.tolist(), jj.tolist())) == sorted(zip(bi.tolist(), bj.tolist()))
    np.testing.assert_allclose(np.sort(dd), np.sort(D[bi, bj]))
    # unbounded cutoff: every pair
    ii, _, _ = close_pairs(p[:40], math.inf)
    assert len(ii) == 40 * 39 // 2


@pytest.mark.parametrize("shape", ["cloud", "ring", "grid", "line"])
def test_close_pairs_grid_finds_what_the_sweep_finds_in_its_order(shape: str) -> None:
    """The grid's candidates (issue 42: a 1000-UAV ring made the sweep compare ~30 successors a
    tick) give the sweep's pairs and distances in the sweep's order, bit for bit (so a flight's
    contacts are listed as before), ties and duplicates included."""
    from zenswarm.vehicle.geometry import _sweep_pairs

    rng = np.random.default_rng(7)
    n = 400
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    p = {
        "cloud": rng.uniform(-3.0, 3.0, size=(n, 3)),
        "ring": np.stack([20 * np.cos(a), 20 * np.sin(a), 0.4 + rng.normal(size=n) * 0.01], axis=1),
        "grid": np.round(rng.uniform(-2.0, 2.0, size=(n, 3)), 1),  # on a lattice: ties and duplicates
        "line": rng.normal(size=(n, 3)) * np.array([100.0, 0.01, 0.01]),
    }[shape]
    order = np.argsort(p[:, int(np.argmax(np.ptp(p, axis=0)))], kind="stable")
    for cutoff in (0.05, 0.2, 0.31, 1.0):
        got, want = close_pairs(p, cutoff), _sweep_pairs(p, cutoff, order)
        for x, y in zip(got, want):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), cutoff


@pytest.mark.slow
def test_large_swarm_pairs_match_the_small_swarm_path_with_linear_memory() -> None:
    """N above the all-pairs limit: per-tick sweep. Same minimum and contacts as brute force, and
    peak memory far below a (T, N, N) array."""
    rng = np.random.default_rng(3)
    N, T = 400, 60
    h = np.stack([np.arange(N) % 20 * 0.5, np.arange(N) // 20 * 0.5, np.zeros(N)], axis=1)
    t, q0, q, qref = flight(T, h)
    q += rng.normal(0.0, 0.05, size=q.shape)
    qref[:] = q
    c = crit(h, divergence_m=50.0, slot_tolerance_m=1.0)
    tracemalloc.start()
    v = judge(t, q0, q, qref, c)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < T * N * N * 8 / 40, peak  # a (T, N, N) float array would be 77 MB
    D = np.linalg.norm(q[:, :, None] - q[:, None], axis=3)
    iu = np.triu_indices(N, 1)
    assert v.min_inter_uav_distance_m == pytest.approx(float(D[:, iu[0], iu[1]].min()), abs=1e-12)
    first = {}
    for k in range(T):
        for i, j in zip(*np.nonzero(np.triu(D[k] < 0.12, 1))):
            first.setdefault((int(i) + 1, int(j) + 1), k)
    got = {f.uavs: round(f.t_s / DT) for f in v.failures if f.cause == "collision_uav" and f.uavs}
    assert got == dict(sorted(first.items(), key=lambda x: x[1])[: len(got)])


def test_geometry_against_closed_forms() -> None:
    p = np.array([[5.0, 2.0, 0.5], [5.0, 0.0, 2.5], [5.0, 0.0, -1.0], [5.0, 0.2, 0.5]])
    np.testing.assert_allclose(obstacle_clearance_many(p, OB), [1.5, 1.0, 1.0, -0.3])
    # d_obs: horizontal beside the cylinder, from the cap's centre above it, minus r_o and r_f
    np.testing.assert_allclose(d_obs_many(p[:2], OB, 0.25), [2.0 - 0.75, 1.5 - 0.75])


# ============================================================================ the CLI, sim and up


def _variant(tmp_path, name: str, **sections) -> Path:
    """paper_example1 with whole tables replaced or merged (``leader={...}`` merges)."""
    import tomllib

    from zenswarm.scenario.generate import to_toml

    from swarmtest import SCENARIOS

    d = tomllib.loads((SCENARIOS / "paper_example1.toml").read_text())
    for k, v in sections.items():
        if isinstance(v, dict):
            d.setdefault(k, {}).update(v)
        else:
            d[k] = v
    p = tmp_path / f"{name}.toml"
    p.write_text(to_toml(d))
    return p


def bad_vehicles(tmp_path) -> dict[str, Path]:
    """The issue's cases: no thrust (the UAVs fall), a gale (blown away), the goal straight
    behind a tall obstacle (the AAPF's local minimum)."""
    return {
        "no_thrust": _variant(tmp_path, "no_thrust", vehicle={"max_thrust": 1e-6}),
        "gale": _variant(tmp_path, "gale", disturbance={"wind": [50.0, 0.0, 0.0]}),
        "behind": _variant(
            tmp_path,
            "behind",
            leader={"start": [0.0, 0.0, 0.4], "goal": [2.4, 0.0, 0.4]},
            obstacles=[{"center": [1.2, 0.0, 0.0], "radius": 0.2, "height": 1.5}],
            formation={
                "offsets": [[0.1, 0.0, 0.0], [-0.12, 0.25, 0.0], [-0.12, -0.25, 0.0]],
                "initial_positions": [[0.1, 0.0, 0.4], [-0.12, 0.25, 0.4], [-0.12, -0.25, 0.4]],
            },
        ),
    }


EXPECTED = {
    "no_thrust": ("collision_ground", "uav_diverged"),
    "gale": ("uav_diverged",),
    "behind": ("leader_stalled",),
}


@pytest.fixture(scope="module")
def sim_of(tmp_path_factory):
    """``zenswarm sim CASE.toml --out OUT --quiet`` of a bad-vehicle case, run once per case in
    this process (the sim is deterministic): (scenario file, the completed process, its
    results.json). Both the sim's own test and the swarm's comparison with it read this run."""
    import json

    from swarmtest import zenswarm

    tmp = tmp_path_factory.mktemp("bad_vehicles")
    scens = bad_vehicles(tmp)
    runs: dict = {}

    def get(case: str):
        if case not in runs:
            out = tmp / f"sim_{case}"
            cp = zenswarm("sim", str(scens[case]), "--out", str(out), "--quiet", timeout=120)
            assert cp.returncode == 1, cp.stdout
            runs[case] = (scens[case], cp, json.loads((out / "results.json").read_text()))
        return runs[case]

    return get


@pytest.mark.parametrize("case", sorted(EXPECTED))
@pytest.mark.swarm
def test_sim_names_what_happened_to_the_vehicles(case: str, sim_of) -> None:
    _, cp, res = sim_of(case)
    assert cp.returncode == 1, cp.stdout
    got = {f["cause"] for f in res["failures"]}
    assert set(EXPECTED[case]) <= got, res["failures"]
    assert res["success"] is False and res["ended_early"] is True and res["schema_version"] == 2
    first = "FAILED: " + "; ".join(
        f"{f['cause']}" + (f" uav {f['uavs'][0]}" if len(f["uavs"]) == 1 else "") + f" at {f['t_s']:.2f} s" for f in res["failures"][:2]
    )
    assert first in cp.stdout, cp.stdout
    if case == "behind":  # shortly after the stall, not at the 70 s limit
        stall = res["leader_stall"]
        assert stall["obstacles_within_d0"] == [0] and res["sim_time_s"] < 15.0
        assert stall["where"][0] < 1.2 - 0.2  # in front of the obstacle


@pytest.mark.swarm
def test_sim_full_time_flies_the_whole_limit_and_still_names_the_failure(tmp_path) -> None:
    import json

    from swarmtest import zenswarm

    scen = bad_vehicles(tmp_path)["behind"]
    cp = zenswarm("sim", str(scen), "--out", str(tmp_path / "o"), "--quiet", "--full-time", timeout=120)
    assert cp.returncode == 1
    res = json.loads((tmp_path / "o" / "results.json").read_text())
    assert res["sim_time_s"] == pytest.approx(70.0) and res["ended_early"] is False
    assert [f["cause"] for f in res["failures"]] == ["leader_stalled"]


@pytest.mark.swarm
def test_sim_ctrl_c_writes_what_was_flown(tmp_path) -> None:
    import json
    import signal

    from swarmtest import start_zenswarm

    scen = _variant(tmp_path, "long", timing={"time_limit_s": 3000.0})
    out = tmp_path / "out"
    p = start_zenswarm("sim", str(scen), "--out", str(out))
    try:
        assert p.stdout is not None
        for line in p.stdout:  # progress goes to stderr, merged: wait for the flight to move
            # past its first ticks (a Ctrl-C right after the first progress line, at t = 0.01 s,
            # may leave nothing judged: sim_time_s is the last judged tick's time)
            m = re.search(r"\[sim\] t=\s*([0-9.]+)/", line)
            if m is not None and float(m.group(1)) >= 0.5:
                break
        p.send_signal(signal.SIGINT)
        rest, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 130, rest
    res = json.loads((out / "results.json").read_text())
    assert res["success"] is False and [f["cause"] for f in res["failures"]] == ["interrupted"]
    assert 0.0 < res["sim_time_s"] < 3000.0
    assert (out / "timeseries.npz").stat().st_size > 0
    assert "Traceback" not in rest


@pytest.mark.parametrize("case", sorted(EXPECTED))
@pytest.mark.swarm
def test_swarm_gives_the_simulator_s_verdict_and_ends_as_early(case: str, tmp_path, sim_of) -> None:
    """`zenswarm up` (lockstep) judges the same vehicles the same way: every flight field equal,
    failures included, and the run ends at the same deciding tick; so does `zenswarm report` from
    the run's recording (which holds ticks past the decision: the swarm stops a moment later)."""
    import json

    from zenswarm.judge.metrics import FLIGHT_FIELDS

    from swarmtest import unique_swarm
    from test_swarm import _up

    scen, cp, ref = sim_of(case)  # `zenswarm sim` of the same scenario file
    assert cp.returncode == 1
    up = tmp_path / "up"
    cp = _up(scen, up, unique_swarm("v"), "--quiet-children", "--record", str(up / "f.mcap"), "--report", timeout=300)
    assert cp.returncode == 1, cp.stdout[-3000:]
    assert "ending the run" in cp.stdout
    res = json.loads((up / "results.json").read_text())
    rep = json.loads((up / "report" / "results.json").read_text())  # judged again from the recording
    for k in FLIGHT_FIELDS:
        assert res[k] == ref[k], k
        assert rep[k] == ref[k], k
    assert res["wall_time_s"] > 0 and rep["wall_time_s"] is None

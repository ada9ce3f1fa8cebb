"""The escape planner (zenswarm.leader.escape), leader only: where the paper's AAPF stalls (goal
directly behind an obstacle; two obstacles closer together than the formation passes) it reaches
the goal with the formation sphere clear of every obstacle; on the paper's examples it reaches the
goal too; with nothing on the straight line it is the AAPF bit for bit. Pure, milliseconds to
about a second."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from zenswarm.errors import ScenarioError
from zenswarm.leader.aapf import AapfParams, integrate_leader, total_force
from zenswarm.leader.core import LeaderCore
from zenswarm.leader.escape import (
    EscapeParams,
    _segments_clear,
    escape_velocity,
    inflated_discs,
    integrate_escape,
    plan_path,
)
from zenswarm.scenario.config import Obstacle, load_scenario
from zenswarm.vehicle.geometry import obstacle_clearance_many

SCEN = Path(__file__).resolve().parents[1] / "compose" / "scenarios"
START = np.array([0.0, 0.0, 0.4])
GOAL = np.array([3.0, 0.0, 0.4])
R_F = 0.277  # paper example 1's formation radius, m
D0 = 0.12
BEHIND = [Obstacle(center=(1.5, 0.0, 0.0), radius=0.2, height=1.0)]
# surfaces 0.3 m apart: the formation (2 r_f = 0.55 m) cannot pass between them
PAIR = [Obstacle(center=(1.5, 0.3, 0.0), radius=0.15, height=1.0), Obstacle(center=(1.5, -0.3, 0.0), radius=0.15, height=1.0)]
DT = 0.05  # s: a coarse tick keeps these tests fast; the sub-steps are still 5 ms
T_END = 60.0  # s


def _aapf(goal: np.ndarray, obstacles: list[Obstacle], r_f: float = R_F, d0: float = D0) -> AapfParams:
    return AapfParams(goal, 0.1, 0.05, 0.3, d0, r_f, obstacles)


def _fly(kind: str, p: AapfParams, start: np.ndarray, t_end: float = T_END) -> dict:
    """Leader only, ticks of DT: positions (T, 3), velocities (T, 3), time to goal (0.05 m) or None."""
    q = start.copy()
    E = EscapeParams(p, start) if kind == "escape" else None
    qs, vs = [], []
    for _ in range(int(round(t_end / DT))):
        v = escape_velocity(q, E) if E is not None else total_force(q, p)
        qs.append(q)
        vs.append(v)
        q = integrate_escape(q, DT, E, 10)[0] if E is not None else integrate_leader(q, DT, p, 10)[0]
    Q, V = np.array(qs), np.array(vs)
    near = np.flatnonzero(np.linalg.norm(Q - p.goal, axis=1) < 0.05)
    clear = min((float(np.min(obstacle_clearance_many(Q, ob))) for ob in p.obstacles), default=np.inf)
    return {
        "q": Q,
        "v": V,
        "t_goal": float(near[0] * DT) if len(near) else None,
        "clearance": clear,  # leader to the real obstacle surface, m
        "tv": float(np.sum(np.linalg.norm(np.diff(V, axis=0), axis=1))),
    }


@pytest.mark.parametrize("obstacles", [BEHIND, PAIR], ids=["goal_behind_obstacle", "close_pair"])
def test_aapf_stalls_where_escape_reaches_the_goal(obstacles: list[Obstacle]) -> None:
    p = _aapf(GOAL, obstacles)
    a = _fly("aapf", p, START)
    # the AAPF stalls: far from the goal, no longer moving (a local minimum of eqs 8-14)
    assert a["t_goal"] is None
    assert np.linalg.norm(a["q"][-1] - GOAL) > 1.0
    assert np.linalg.norm(a["q"][-1] - a["q"][-int(5.0 / DT)]) < 1e-3
    e = _fly("escape", p, START)
    assert e["t_goal"] is not None and e["t_goal"] < T_END
    # the formation sphere stays clear of every obstacle, outside the repulsion band even
    assert e["clearance"] >= R_F
    assert e["clearance"] >= R_F + D0


@pytest.mark.parametrize("name", ["paper_example1", "paper_example2"])
def test_escape_flies_the_paper_examples(name: str) -> None:
    sc = load_scenario(SCEN / f"{name}.toml")
    p = AapfParams.from_scenario(sc)
    start = np.asarray(sc.leader.start, dtype=float)
    e = _fly("escape", p, start)
    a = _fly("aapf", p, start)
    assert e["t_goal"] is not None
    assert e["clearance"] >= sc.r_f
    # less chattering than the AAPF: the repulsion band is never entered
    assert e["tv"] < a["tv"]


def test_straight_path_is_the_aapf_bit_for_bit() -> None:
    """An obstacle well off the start-goal line: the path is that line and every tick equals the AAPF's."""
    p = _aapf(GOAL, [Obstacle(center=(1.5, 1.5, 0.0), radius=0.2, height=1.0)])
    E = EscapeParams(p, START)
    assert len(E.path) == 2
    qa, qe = START.copy(), START.copy()
    for _ in range(300):
        np.testing.assert_array_equal(escape_velocity(qe, E), total_force(qa, p))
        qa = integrate_leader(qa, 0.01, p, 10)[0]
        qe = integrate_escape(qe, 0.01, E, 10)[0]
        np.testing.assert_array_equal(qe, qa)


def test_path_is_clear_of_the_inflated_discs_and_deterministic() -> None:
    p = _aapf(GOAL, PAIR)
    path = plan_path(START, GOAL, PAIR, R_F, D0, 0.05, 24)
    np.testing.assert_array_equal(path[0], START)
    np.testing.assert_array_equal(path[-1], GOAL)
    assert len(path) > 2
    discs = inflated_discs(START, GOAL, PAIR, R_F, D0, 0.05)
    assert len(discs) == 2
    assert np.all(_segments_clear(path[:-1, :2], path[1:, :2], discs))
    # the pair is one wall: the path goes round it, not between (|y| beyond the outer disc edge)
    assert np.max(np.abs(path[:, 1])) >= 0.3 + 0.15 + R_F + D0
    np.testing.assert_array_equal(path, EscapeParams(p, START).path)


def test_low_obstacle_is_left_to_the_aapf_and_enclosed_goal_falls_back() -> None:
    low = [Obstacle(center=(1.5, 0.0, 0.0), radius=0.1, height=0.01)]
    high_goal = np.array([3.0, 0.0, 1.2])
    assert len(inflated_discs(np.array([0.0, 0.0, 1.2]), high_goal, low, R_F, D0, 0.05)) == 0
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = [Obstacle(center=(3.0 + 0.8 * np.cos(a), 0.8 * np.sin(a), 0.0), radius=0.3, height=1.0) for a in angles]
    path = plan_path(START, GOAL, ring, R_F, D0, 0.05, 24)
    np.testing.assert_array_equal(path, np.array([START, GOAL]))


def test_bad_parameters_are_rejected() -> None:
    p = _aapf(GOAL, BEHIND)
    for kw, field in (({"margin": -0.1}, "margin"), ({"lookahead": 0.0}, "lookahead"), ({"sides": 2}, "sides")):
        with pytest.raises(ValueError, match=field):
            EscapeParams(p, START, **kw)


def test_selected_by_name_with_typed_params() -> None:
    """``planner = "escape"`` builds the built-in; its ``[leader.params]`` are typed, unknown keys named."""
    from dataclasses import replace

    from msgspec.structs import replace as replace_table

    from zenswarm.leader.planner import EscapePlanner
    from zenswarm.scenario.plugins import check_selection, select

    sc = load_scenario(SCEN / "paper_example1.toml")
    core = LeaderCore.from_scenario(select(sc, planner="escape"))
    assert isinstance(core.planner, EscapePlanner)
    assert len(core.planner.path) > 2  # example 1's straight line crosses obstacle 1's inflated disc
    q0, v0 = core.ref()
    np.testing.assert_array_equal(q0, sc.leader.start)
    assert v0.shape == (3,) and np.linalg.norm(v0) > 0
    core.advance()
    assert core.k == 1 and not np.array_equal(core.q0, q0)
    # the default stays the paper's
    assert type(LeaderCore.from_scenario(sc).planner).__name__ == "AapfPlanner"
    for bad, field in (({"lookahead": 0.0}, "leader.params.lookahead"), ({"sides": 2}, "leader.params.sides"), ({"nope": 1}, "nope")):
        scb = replace(select(sc, planner="escape"), leader=replace_table(select(sc, planner="escape").leader, params=bad))
        with pytest.raises(ScenarioError, match=field):
            check_selection(scb)


def test_sim_escape_flies_goal_behind_obstacle_to_success() -> None:
    """The full in-process simulator (plant, agents, vehicle verdicts): goal 2 m straight behind a
    tall obstacle. The AAPF stalls (``leader_stalled``, the run ends early); the escape planner
    succeeds with no collision. K_att 0.15 and a 2 m leg keep it to 36 s of sim time."""
    import tomllib

    from zenswarm.compose.sim import simulate
    from zenswarm.scenario.config import scenario_from_dict
    from zenswarm.scenario.plugins import select

    d = tomllib.loads((SCEN / "paper_example1.toml").read_text())
    d["scenario"]["name"] = "goal_behind_obstacle"
    d["leader"].update(start=[0.0, 0.0, 0.4], goal=[2.0, 0.0, 0.4], k_att=0.15)
    d["obstacles"] = [{"center": [1.0, 0.0, 0.0], "radius": 0.15, "height": 1.0}]
    d["timing"].update(time_limit_s=36.0, settle_time_s=20.0)
    sc = scenario_from_dict(d)
    a = simulate(select(sc, planner="aapf")).results
    assert not a["success"] and "leader_stalled" in [f["cause"] for f in a["failures"]]
    e = simulate(select(sc, planner="escape")).results
    assert e["failures"] == [] and e["success"], e["failures"]
    assert e["time_to_goal_s"] is not None and e["time_to_goal_s"] < 36.0
    assert e["min_obstacle_margin_m"] > 0.0  # vehicle clearance beyond the vehicle radius

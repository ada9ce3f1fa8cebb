"""Scenario loading and validation (zenswarm.scenario.config).

The paper's numbers are those of its Experiments section (A. Experimental setup). Every rejection
test checks the error's ``field`` (dotted path) and that the message says what is wrong.
"""

from __future__ import annotations

import copy
import math
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from zenswarm.errors import ScenarioError, ZenswarmError
from zenswarm.scenario.config import (
    Scenario,
    formation_radius,
    load_scenario,
    scenario_from_dict,
    scenario_to_dict,
)
from zenswarm.schema import FaultsTable

SCENARIOS = Path(__file__).resolve().parents[1] / "compose" / "scenarios"
EX1 = SCENARIOS / "paper_example1.toml"
EX2 = SCENARIOS / "paper_example2.toml"


def base() -> dict[str, Any]:
    """A fresh parsed copy of paper example 1 to mutate."""
    with open(EX1, "rb") as f:
        return tomllib.load(f)


def reject(d: dict[str, Any], field: str, *needles: str) -> ScenarioError:
    """Assert scenario_from_dict(d) raises ScenarioError naming ``field`` with every needle in the message."""
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict(d)
    e = ei.value
    assert e.field == field, f"field {e.field!r} != {field!r} ({e})"
    msg = str(e)
    assert msg.startswith(field), msg  # the printed form names the field first
    for n in needles:
        assert n.lower() in e.message.lower(), f"{n!r} not in message {e.message!r}"
    return e


# ----------------------------------------------------------------------------- the paper's files


def test_example1_carries_the_papers_numbers() -> None:
    s = load_scenario(EX1)
    assert s.name == "paper_example1"
    assert s.n == 3
    # initial positions q_i(0), m
    assert s.initial_positions == ((0.0, 0.0, 0.4), (0.0, 0.2, 0.4), (0.0, -0.2, 0.4))
    # leader start and goal, m
    assert s.leader.start == (0.0, 0.0, 0.4)
    assert s.leader.goal == (2.4, 1.4, 0.6)
    # obstacles: base centres (1.00, 0.45), (1.75, 1.70) m on the ground, radii 0.14, 0.225 m, heights 0.4, 1 m
    assert [o.center for o in s.obstacles] == [(1.00, 0.45, 0.0), (1.75, 1.70, 0.0)]
    assert [o.radius for o in s.obstacles] == [0.14, 0.225]
    assert [o.height for o in s.obstacles] == [0.4, 1.0]
    # offsets h_i, m
    assert s.offsets == ((0.10, 0.0, 0.0), (-0.12, 0.25, 0.0), (-0.12, -0.25, 0.0))
    # AAPF: K_att, K_rep^min, K_rep^max, d0 (example 1)
    assert (s.leader.k_att, s.leader.k_rep_min, s.leader.k_rep_max) == (0.1, 0.05, 0.3)
    assert s.leader.d0 == 0.12
    assert s.leader.adaptive is True
    # reference generator mu1, mu2; ESO beta; controller K_p, K_d; yaw 0
    assert (s.generator.mu1, s.generator.mu2) == (0.1, 2.0)
    assert s.eso.beta == (15.0, 75.0, 125.0)
    assert s.eso.enabled is True
    assert s.controller.kp == (4.5, 4.5, 5.4)
    assert s.controller.kd == (5.0, 5.0, 3.0)
    assert s.controller.yaw == 0.0
    # r_f = max ||h_i|| = ||h_2|| = sqrt(0.12^2 + 0.25^2)
    assert s.r_f == pytest.approx(math.hypot(0.12, 0.25), abs=1e-12)
    # timing: integer sub-steps
    assert s.timing.substeps == 10 and s.timing.dt == pytest.approx(0.01)


def test_example2_differs_from_example1_only_where_the_paper_says() -> None:
    s1, s2 = load_scenario(EX1), load_scenario(EX2)
    assert s2.name == "paper_example2"
    # obstacle 2 moves to (1.55, 1.70) m; radii and heights remain
    assert [o.center for o in s2.obstacles] == [(1.00, 0.45, 0.0), (1.55, 1.70, 0.0)]
    assert [o.radius for o in s2.obstacles] == [0.14, 0.225]
    assert [o.height for o in s2.obstacles] == [0.4, 1.0]
    # d0 = 0.15 m in example 2
    assert s2.leader.d0 == 0.15
    same = s1.with_changes(
        name=s2.name, description=s2.description, obstacles=s2.obstacles, leader=s2.leader
    )
    assert same == s2
    assert s1.leader.goal == s2.leader.goal and s1.offsets == s2.offsets


@pytest.mark.parametrize("path", [EX1, EX2], ids=["example1", "example2"])
def test_paper_graph_satisfies_lemma1(path: Path) -> None:
    s = load_scenario(path)
    A = np.asarray(s.graph.adjacency)
    M = np.diag(A.sum(1)) - A + np.diag(s.graph.pinning)
    assert np.linalg.eigvalsh(M).min() > 0.1


# ----------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("path", [EX1, EX2], ids=["example1", "example2"])
def test_round_trip(path: Path) -> None:
    s = load_scenario(path)
    d = scenario_to_dict(s)
    assert scenario_from_dict(d) == s
    assert scenario_to_dict(scenario_from_dict(d)) == d


def test_round_trip_with_every_optional_section() -> None:
    d = base()
    d["vehicle"] = {"mass": 0.034, "inertia": [1.6e-5, 1.6e-5, 2.9e-5], "max_thrust": 0.6}
    d["disturbance"] = {"wind": [0.1, 0.0, 0.0], "sine_amplitude": [0.0, 0.2, 0.0], "sine_freq_hz": 0.5,
                        "gust_std": 0.05, "gust_tau_s": 2.0, "attitude_std": 0.1}
    d["faults"] = {"loss": 0.1}
    d["scenario"]["seed"] = 7
    d["leader"]["adaptive"] = False
    s = scenario_from_dict(d)
    assert s.vehicle.inertia == (1.6e-5, 1.6e-5, 2.9e-5) and s.vehicle.max_tilt is None
    assert s.disturbance.active
    s2 = scenario_from_dict(scenario_to_dict(s))
    assert s2 == s
    assert s2.faults == FaultsTable(loss=0.1) and scenario_to_dict(s2)["faults"] == {"loss": 0.1}


def test_defaults_when_optional_sections_are_absent() -> None:
    d = base()
    for k in ("scenario", "timing", "generator", "eso", "controller"):
        del d[k]
    s = scenario_from_dict(d)
    assert s.eso.beta == (15.0, 75.0, 125.0) and s.controller.kp == (4.5, 4.5, 5.4)
    assert scenario_from_dict(scenario_to_dict(s)) == s


def test_integers_are_accepted_as_numbers() -> None:
    d = base()
    d["leader"]["goal"] = [2, 1, 1]
    d["eso"]["beta"] = [15, 75, 125]
    s = scenario_from_dict(d)
    assert s.leader.goal == (2.0, 1.0, 1.0) and all(isinstance(v, float) for v in s.eso.beta)


# ----------------------------------------------------------------------------- rejections

Mutator = Callable[[dict[str, Any]], None]


def _set(path: str, value: Any) -> Mutator:
    """A mutator setting d[a][b]... (keys separated by '/', integer parts index lists)."""

    def f(d: dict[str, Any]) -> None:
        parts = path.split("/")
        cur: Any = d
        for p in parts[:-1]:
            cur = cur[int(p)] if isinstance(cur, list) else cur[p]
        last = parts[-1]
        if isinstance(cur, list):
            cur[int(last)] = value
        else:
            cur[last] = value

    return f


def _del(path: str) -> Mutator:
    def f(d: dict[str, Any]) -> None:
        parts = path.split("/")
        cur: Any = d
        for p in parts[:-1]:
            cur = cur[p]
        del cur[parts[-1]]

    return f


REJECTIONS: list[tuple[str, Mutator, str, tuple[str, ...]]] = [
    # non-positive gains
    ("k_att zero", _set("leader/k_att", 0.0), "leader.k_att", ("> 0", "0.0")),
    ("k_att negative", _set("leader/k_att", -0.1), "leader.k_att", ("> 0", "-0.1")),
    ("d0 zero", _set("leader/d0", 0), "leader.d0", ("> 0",)),
    ("k_rep_min negative", _set("leader/k_rep_min", -0.05), "leader.k_rep_min", ("> 0",)),
    ("mu1 zero", _set("generator/mu1", 0.0), "generator.mu1", ("> 0",)),
    ("mu2 negative", _set("generator/mu2", -2.0), "generator.mu2", ("> 0",)),
    ("kp entry zero", _set("controller/kp", [4.5, 0.0, 5.4]), "controller.kp[1]", ("> 0",)),
    ("kp entry negative", _set("controller/kp", [-4.5, 4.5, 5.4]), "controller.kp[0]", ("> 0", "-4.5")),
    ("kd entry zero", _set("controller/kd", [5.0, 5.0, 0.0]), "controller.kd[2]", ("> 0",)),
    ("eso beta negative", _set("eso/beta", [15.0, 75.0, -125.0]), "eso.beta[2]", ("> 0", "-125")),
    ("eso beta zero", _set("eso/beta", [0.0, 75.0, 125.0]), "eso.beta[0]", ("> 0",)),
    ("k_rep_max < k_rep_min", _set("leader/k_rep_max", 0.01), "leader.k_rep_max", ("k_rep_min", "0.01", "0.05")),
    ("obstacle radius zero", _set("obstacles/1/radius", 0.0), "obstacles[1].radius", ("> 0",)),
    ("time limit negative", _set("timing/time_limit_s", -1.0), "timing.time_limit_s", ("> 0",)),
    # vectors and matrices of the wrong length
    ("offsets row short", _set("formation/offsets/1", [-0.12, 0.25]), "formation.offsets[1]", ("length 3", "got 2")),
    ("offsets row long", _set("formation/offsets/2", [0.0, 0.0, 0.0, 0.0]), "formation.offsets[2]", ("length 3", "got 4")),
    ("goal short", _set("leader/goal", [2.4, 1.4]), "leader.goal", ("length 3", "got 2")),
    ("goal not a list", _set("leader/goal", "far away"), "leader.goal", ("expected a list", "str", "far away")),
    ("eso beta length", _set("eso/beta", [15.0, 75.0]), "eso.beta", ("length 3",)),
    ("too few initial positions", _set("formation/initial_positions", [[0.0, 0.0, 0.4], [0.0, 0.2, 0.4]]),
     "formation.initial_positions", ("3 rows", "got 2")),
    ("too many initial positions", _set("formation/initial_positions", [[0.0, 0.0, 0.4]] * 4),
     "formation.initial_positions", ("3 rows", "got 4")),
    ("pinning length", _set("graph/pinning", [1.0, 0.0]), "graph.pinning", ("length 3", "got 2")),
    ("adjacency rows", _set("graph/adjacency", [[0.0, 1.0, 1.0], [1.0, 0.0, 0.0]]), "graph.adjacency", ("3 rows",)),
    ("no UAVs", lambda d: d["formation"].update(offsets=[], initial_positions=[]), "formation.offsets", ("at least one",)),
    # unknown and missing keys
    ("unknown top-level key", _set("obstacle", []), "obstacle", ("unknown key", "obstacles")),
    ("unknown leader key", _set("leader/katt", 0.1), "leader.katt", ("unknown key", "k_att")),
    ("unknown timing key", _set("timing/dt", 0.01), "timing.dt", ("unknown key", "control_rate_hz")),
    ("unknown obstacle key", _set("obstacles/1/radus", 0.2), "obstacles[1].radus", ("unknown key", "radius")),
    ("missing goal", _del("leader/goal"), "leader.goal", ("missing",)),
    ("missing graph", _del("graph"), "graph", ("missing",)),
    ("section not a table", _set("eso", [1, 2]), "eso", ("expected a table",)),
    # types and non-finite numbers
    ("bool as a number", _set("leader/k_att", True), "leader.k_att", ("expected a number", "bool")),
    ("string as a number", _set("generator/mu1", "0.1"), "generator.mu1", ("expected a number", "str")),
    ("nan gain", _set("leader/k_att", math.nan), "leader.k_att", ("finite", "nan")),
    ("inf in offsets", _set("formation/offsets/0", [math.inf, 0.0, 0.0]), "formation.offsets[0][0]", ("finite", "inf")),
    ("-inf in goal", _set("leader/goal", [2.4, -math.inf, 0.6]), "leader.goal[1]", ("finite",)),
    ("integer too large for a float", _set("leader/k_att", 10**400), "leader.k_att", ("finite", "too large")),
    ("string adaptive", _set("leader/adaptive", "yes"), "leader.adaptive", ("true or false",)),
    ("negative seed", _set("scenario/seed", -1), "scenario.seed", ("non-negative integer",)),
    ("seed of 2**80", _set("scenario/seed", 2**80), "scenario.seed", ("<= 2**63 - 1", str(2**80))),
    ("seed of 2**63", _set("scenario/seed", 2**63), "scenario.seed", ("<= 2**63 - 1",)),
    ("float seed", _set("scenario/seed", 1.5), "scenario.seed", ("expected an integer", "float", "1.5")),
    ("empty name", _set("scenario/name", ""), "scenario.name", ("length >= 1",)),
    # graph
    ("asymmetric adjacency", _set("graph/adjacency", [[0.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
     "graph.adjacency", ("symmetric", "a[0][1]=1.0", "a[1][0]=0.0")),
    ("negative adjacency weight", _set("graph/adjacency", [[0.0, -1.0, 1.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
     "graph.adjacency[0][1]", (">= 0",)),
    ("self loop", _set("graph/adjacency", [[0.0, 1.0, 1.0], [1.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
     "graph.adjacency[1][1]", ("self loop",)),
    ("negative pinning", _set("graph/pinning", [1.0, -1.0, 0.0]), "graph.pinning", (">= 0",)),
    ("pinning all zero", _set("graph/pinning", [0.0, 0.0, 0.0]), "graph.pinning",
     ("spanning tree", "positive definite", "every connected component")),
    ("component without a pinned UAV",
     lambda d: d["graph"].update(adjacency=[[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], pinning=[1.0, 0.0, 0.0]),
     "graph.pinning", ("spanning tree", "every connected component")),
    ("no edges, one pin", lambda d: d["graph"].update(adjacency=[[0.0] * 3] * 3, pinning=[0.0, 0.0, 1.0]),
     "graph.pinning", ("spanning tree",)),
    # timing
    ("physics rate not a multiple", _set("timing/physics_rate_hz", 250.0), "timing.physics_rate_hz",
     ("whole multiple", "control_rate_hz", "2.5")),
    ("physics rate slower than control", _set("timing/physics_rate_hz", 50.0), "timing.physics_rate_hz",
     ("whole multiple",)),
    ("control rate zero", _set("timing/control_rate_hz", 0.0), "timing.control_rate_hz", ("> 0",)),
    # bounds: a valid scenario must be runnable (time_limit_s = 1e12 tried to allocate 728 TiB)
    ("absurd time limit", _set("timing/time_limit_s", 1e12), "timing.time_limit_s",
     ("1e+14 control ticks", "at most 10,000,000", "100000 s")),
    ("time limit of inf ticks", lambda d: d["timing"].update(time_limit_s=1e300, control_rate_hz=1e300, physics_rate_hz=1e300),
     "timing.control_rate_hz", ("<= 1e+06",)),
    ("one tick too many", _set("timing/time_limit_s", 100_000.01), "timing.time_limit_s", ("at most 10,000,000",)),
    ("less than one tick", _set("timing/time_limit_s", 0.001), "timing.time_limit_s", ("less than one control tick",)),
    ("too many sub-steps", _set("timing/physics_rate_hz", 100.0 * 1001), "timing.physics_rate_hz",
     ("at most 1000 physics sub-steps", "1001")),
    ("control rate too fast", lambda d: d["timing"].update(control_rate_hz=2e6, physics_rate_hz=2e6),
     "timing.control_rate_hz", ("<= 1e+06",)),
    ("sim time beyond the wire's 10 days", lambda d: d["timing"].update(control_rate_hz=1.0, physics_rate_hz=100.0,
     time_limit_s=900_000.0), "timing.time_limit_s", ("10 days",)),
    # ESO gains the discrete observer cannot follow at the control rate (issue 43)
    ("eso gains unstable at 100 Hz", _set("eso/beta", [1e6, 1e12, 1e18]), "eso.beta",
     ("unit circle", "got 1e+04", "w < 2/dt = 200 rad/s")),
    ("eso gains unstable at 2 Hz", lambda d: d["timing"].update(control_rate_hz=2.0, physics_rate_hz=200.0), "eso.beta",
     ("dt = 0.5 s", "got 1.5", "w < 2/dt = 4 rad/s")),
    ("eso gains on the bound", _set("eso/beta", [600.0, 120000.0, 8e6]), "eso.beta", ("got 1",)),  # w = 200: |1 - w dt| = 1
    # start or goal inside an obstacle inflated by r_f (obstacle 1: base centre (1.00, 0.45, 0), r_o 0.14, h_o 0.4)
    ("start inside inflated cylinder", _set("leader/start", [1.00 + 0.14 + 0.2, 0.45, 0.2]), "leader.start",
     ("obstacles[0]", "r_f=0.277")),
    ("start inside the solid", _set("leader/start", [1.00, 0.45, 0.2]), "leader.start", ("obstacles[0]",)),
    ("goal inside inflated cap", _set("leader/goal", [1.00, 0.45, 0.4 + 0.14 + 0.2]), "leader.goal",
     ("obstacles[0]", "formation radius")),
    ("goal inside obstacle 2 inflated", _set("leader/goal", [1.75 - 0.225 - 0.1, 1.70, 0.6]), "leader.goal",
     ("obstacles[1]",)),
    ("goal just below the base, inflated", lambda d: d["obstacles"][1].update(center=[1.75, 1.70, 0.7]) or
     d["leader"].update(goal=[1.75, 1.70, 0.6]), "leader.goal", ("obstacles[1]",)),
]


@pytest.mark.parametrize(("mutate", "field", "needles"), [r[1:] for r in REJECTIONS], ids=[r[0] for r in REJECTIONS])
def test_rejects(mutate: Mutator, field: str, needles: tuple[str, ...]) -> None:
    d = base()
    mutate(d)
    reject(d, field, *needles)


def test_eso_bound_is_the_observer_as_stepped() -> None:
    """The bound scenario validation puts on ``eso.beta`` (config.eso_spectral_radius) is the
    observer agents/eso.py runs: its estimation error, stepped by eso_step, shrinks per tick by the
    spectral radius when it is below 1 and grows by it above; bandwidth gains just inside the
    bound w < 2/dt are a valid scenario."""
    from zenswarm.agents.eso import bandwidth_gains, eso_step
    from zenswarm.scenario.config import eso_spectral_radius

    dt, g = 0.01, 9.81
    q, u = np.array([0.3, -0.2, 1.0]), np.array([0.0, 0.0, g])  # a UAV at rest, hovering: d = 0
    for beta in [(15.0, 75.0, 125.0), bandwidth_gains(150.0), (1.0, 1e4, 1e6), (100.0, 100.0, 1e5), (1e6, 1e12, 1e18)]:
        rho = eso_spectral_radius(beta, dt)
        est = (q + 0.01, np.full(3, 0.02), np.full(3, -0.03))  # an initial estimation error
        norms = []
        with np.errstate(all="ignore"):
            for _ in range(60):
                est = eso_step(*est, q, u, beta, dt, g)
                norms.append(float(np.linalg.norm(np.concatenate([est[0] - q, est[1], est[2]]))))
        per_tick = (norms[-1] / norms[-21]) ** (1 / 20) if norms[-21] > 0 else 0.0
        assert (per_tick < 1.0) == (rho < 1.0), (beta, rho, per_tick)
        if 1e-300 < norms[-1] < 1e300:
            assert per_tick == pytest.approx(rho, rel=0.1), (beta, rho, per_tick)
    d = base()
    d["eso"]["beta"] = list(bandwidth_gains(199.0))  # just inside w < 2/dt = 200 rad/s
    assert scenario_from_dict(d).eso.beta == pytest.approx(bandwidth_gains(199.0))


def test_bounds_accept_their_edges() -> None:
    """The largest seed, exactly MAX_CONTROL_TICKS ticks, MAX_SUBSTEPS sub-steps and one tick are valid."""
    from zenswarm.scenario.config import MAX_CONTROL_TICKS, MAX_SEED, MAX_SUBSTEPS

    d = base()
    d["scenario"]["seed"] = MAX_SEED
    d["timing"].update(time_limit_s=MAX_CONTROL_TICKS / 100.0, physics_rate_hz=100.0 * MAX_SUBSTEPS)
    s = scenario_from_dict(d)
    assert (s.seed, s.timing.n_ticks, s.timing.substeps) == (MAX_SEED, MAX_CONTROL_TICKS, MAX_SUBSTEPS)
    d["timing"].update(time_limit_s=0.01)
    assert scenario_from_dict(d).timing.n_ticks == 1


def test_uav_ticks_bound_scales_with_n() -> None:
    """3 UAVs x 10 M ticks fit; the message for a larger product names the time that would fit."""
    from zenswarm.scenario.config import MAX_UAV_TICKS

    d = base()
    d["timing"]["time_limit_s"] = 99_000.0  # 9.9 M ticks x 3 UAVs < 50 M
    assert scenario_from_dict(d).timing.n_ticks * 3 <= MAX_UAV_TICKS
    d["formation"]["offsets"] = [[0.1 * i, 0.0, 0.0] for i in range(6)]
    d["formation"]["initial_positions"] = [[0.1 * i, 0.0, 0.4] for i in range(6)]
    d["graph"] = {"adjacency": [[0.0] * 6] * 6, "pinning": [1.0] * 6}
    reject(d, "timing.time_limit_s", "6 UAVs", "50,000,000 UAV-ticks", "at most 83333.3 s")


def test_rejection_is_a_zenswarm_error() -> None:
    d = base()
    d["leader"]["k_att"] = 0.0
    with pytest.raises(ZenswarmError):
        scenario_from_dict(d)


def test_base_is_not_mutated_between_cases() -> None:
    # guard against a mutator leaking into the shared file's parse (each test re-parses)
    assert scenario_from_dict(base()) == load_scenario(EX1)


@pytest.mark.parametrize(
    "graph",
    [
        # two components, each pinned: M positive definite
        {"adjacency": [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], "pinning": [0.0, 1.0, 1.0]},
        # no edges, every UAV pinned
        {"adjacency": [[0.0] * 3] * 3, "pinning": [1.0, 1.0, 1.0]},
        # weighted complete graph, fractional pinning on the last UAV
        {"adjacency": [[0.0, 0.5, 2.0], [0.5, 0.0, 1.0], [2.0, 1.0, 0.0]], "pinning": [0.0, 0.0, 0.25]},
    ],
)
def test_accepts_graphs_satisfying_lemma1(graph: dict[str, Any]) -> None:
    d = base()
    d["graph"] = graph
    scenario_from_dict(d)


def test_start_just_outside_the_inflated_obstacle_is_accepted() -> None:
    d = base()
    r_f = formation_radius(d["formation"]["offsets"])
    d["leader"]["start"] = [1.00 + 0.14 + r_f + 0.01, 0.45, 0.2]
    scenario_from_dict(d)
    d["leader"]["start"] = [1.00 + 0.14 + r_f - 0.01, 0.45, 0.2]
    reject(d, "leader.start", "obstacles[0]")


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ("\nk_att = 0.1 ", "\nk_att = nan ", "leader.k_att"),
        ("\nmu1 = 0.1 ", "\nmu1 = inf ", "generator.mu1"),
        ("\nd0 = 0.12 ", "\nd0 = -inf ", "leader.d0"),
        ("beta = [15.0, 75.0, 125.0]", "beta = [15.0, nan, 125.0]", "eso.beta[1]"),
        ("radius = 0.225", "radius = +inf", "obstacles[1].radius"),
    ],
)
def test_rejects_toml_nan_and_inf(tmp_path: Path, old: str, new: str, field: str) -> None:
    text = EX1.read_text()
    assert text.count(old) == 1
    p = tmp_path / "bad.toml"
    p.write_text(text.replace(old, new))
    with pytest.raises(ScenarioError) as ei:
        load_scenario(p)
    assert ei.value.field == field
    assert "finite" in ei.value.message


def test_missing_file(tmp_path: Path) -> None:
    p = tmp_path / "nope.toml"
    with pytest.raises(ScenarioError) as ei:
        load_scenario(p)
    assert ei.value.field == "file"
    assert "not found" in ei.value.message and str(p) in ei.value.message


def test_directory_instead_of_file(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError) as ei:
        load_scenario(tmp_path)
    assert ei.value.field == "file" and str(tmp_path) in ei.value.message


@pytest.mark.parametrize(
    "text",
    [
        "[leader\nstart = [0, 0, 0]\n",  # unterminated table header
        "[leader]\nstart = [0, 0, 0\n",  # unterminated array
        "[leader]\nk_att = 0.1\nk_att = 0.2\n",  # duplicate key
        "key = \n",  # missing value
    ],
    ids=["header", "array", "duplicate", "value"],
)
def test_invalid_toml(tmp_path: Path, text: str) -> None:
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ScenarioError) as ei:
        load_scenario(p)
    assert ei.value.field == "file"
    assert "not valid TOML" in ei.value.message and str(p) in ei.value.message
    assert "line" in ei.value.message or "end of document" in ei.value.message  # tomllib's position is kept


def test_not_utf8(tmp_path: Path) -> None:
    p = tmp_path / "latin1.toml"
    p.write_bytes(b'[scenario]\nname = "caf\xe9"\n')
    with pytest.raises(ScenarioError) as ei:
        load_scenario(p)
    assert ei.value.field == "file"


def test_with_changes_revalidates() -> None:
    s = load_scenario(EX1)
    with pytest.raises(ScenarioError) as ei:
        s.with_changes(leader=msgspec.structs.replace(s.leader, k_rep_max=0.01))
    assert ei.value.field == "leader.k_rep_max"


def test_scenario_is_frozen() -> None:
    s: Scenario = load_scenario(EX1)
    with pytest.raises(Exception):  # noqa: B017 - whichever error the frozen type raises
        s.name = "x"  # type: ignore[misc]
    # the parsed document is not retained by reference
    d = base()
    s2 = scenario_from_dict(d)
    d2 = copy.deepcopy(d)
    d["leader"]["goal"][0] = 99.0
    assert s2 == scenario_from_dict(d2)


# ----------------------------------------------------------------------------- subsystem tables (schema)


@pytest.mark.parametrize(
    ("section", "table", "field", "needles"),
    [
        ("network", {"port": 7447}, "network", ("unknown key", "mavlink")),  # no such section
        ("mavlink", {"base_prot": 14540}, "mavlink.base_prot", ("unknown key", "base_port")),  # misspelt key
        ("mavlink", {"rate_hz": 10.0}, "mavlink.rate_hz", (">= 20", "10.0")),
        ("mavlink", {"setpoint": "rates"}, "mavlink.setpoint", ("attitude", "position", "rates")),
        ("mavlink", {"sysids": [1, 2]}, "mavlink.sysids", ("3 system ids", "got 2")),
        ("mavlink", {"takeoff": 1}, "mavlink.takeoff", ("true or false",)),
        ("faults", {"loss": 1.5}, "faults.loss", ("<= 1.0", "1.5")),
        ("faults", {"links": [{"dst": "agent:2", "delay": "5 parsecs"}]}, "faults.links[0].delay", ("5 parsecs",)),
        ("faults", {"links": [{"dst": "agent:9"}]}, "faults.links[0].dst", ("agent:9",)),
        ("failsafe", {"land_speed": -0.3}, "failsafe.land_speed", ("> 0", "-0.3")),
        ("failsafe", {"hover_after_s": 6.0}, "failsafe.land_after_s", ("hover_after_s",)),
        ("failsafe", {"kp": math.nan}, "failsafe.kp", ("finite", "nan")),
        ("restart", {"factor": 0.5}, "restart.factor", (">= 1", "0.5")),
        ("restart", {"max_restarts": True}, "restart.max_restarts", ("integer", "bool")),
        ("restart", {"enabeld": True}, "restart.enabeld", ("unknown key", "enabled")),
    ],
    ids=lambda v: v if isinstance(v, str) else None,
)
def test_subsystem_tables_are_checked_on_load(section: str, table: dict[str, Any], field: str, needles: tuple[str, ...]) -> None:
    d = base()
    d[section] = table
    reject(d, field, *needles)


def test_subsystem_tables_are_typed_and_round_trip() -> None:
    d = base()
    d["mavlink"] = {"base_port": 15000, "setpoint": "position"}
    d["restart"] = {"max_restarts": 5}
    d["failsafe"] = {"land_speed": 0.5}
    s = scenario_from_dict(d)
    assert s.mavlink is not None and s.mavlink.base_port == 15000 and s.mavlink.setpoint == "position"
    assert s.restart is not None and s.restart.enabled and s.restart.max_restarts == 5
    assert s.failsafe is not None and s.failsafe.land_speed == 0.5 and s.failsafe.hover_after_s == 0.5
    assert s.faults is None
    back = scenario_to_dict(s)
    assert (back["mavlink"], back["restart"], back["failsafe"]) == (d["mavlink"], d["restart"], d["failsafe"])
    assert scenario_from_dict(back) == s


def test_unknown_section_in_a_file_exits_2(tmp_path: Path) -> None:
    """`zenswarm scenario check` refuses a file with an unknown [network] section (exit 2)."""
    from zenswarm.compose.cli import main

    p = tmp_path / "net.toml"
    p.write_text(EX1.read_text() + "\n[network]\nport = 7447\n")
    with pytest.raises(ScenarioError) as ei:
        load_scenario(p)
    assert ei.value.field == "network"
    assert main(["scenario", "check", str(p)]) == 2

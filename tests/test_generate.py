"""Scenario generator (zenswarm.scenario.generate): validity, Lemma 1, geometry, determinism, TOML, CLI."""

from __future__ import annotations

import argparse
import itertools
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from zenswarm.errors import ScenarioError
from zenswarm.leader.aapf import d_obs, obstacle_clearance
from zenswarm.scenario import generate
from zenswarm.scenario.config import load_scenario, scenario_from_dict, scenario_to_dict
from zenswarm.scenario.generate import (
    OBSTACLE_GAP,
    PINNINGS,
    SHAPES,
    TOPOLOGIES,
    adjacency_matrix,
    connected_components,
    formation_offsets,
    generate_scenario,
    to_toml,
)

NS = (3, 8, 16, 32)
SEEDS = range(4)
EX1 = Path(__file__).resolve().parents[1] / "compose" / "scenarios" / "paper_example1.toml"


def check_scenario(d: dict[str, Any], n: int, spacing: float, shape: str) -> None:
    """Every invariant a generated scenario promises."""
    s = scenario_from_dict(d)
    assert s.n == n
    h = np.asarray(s.offsets)
    A = s.comm_graph.dense()  # the file names its topology; the scenario builds it
    b = np.asarray(s.graph.pinning)
    assert np.array_equal(A, adjacency_matrix(h, d["graph"]["topology"], d["graph"].get("k", 2)))

    # graph: symmetric 0/1, no self loops, connected; Lemma 1: M = L + B positive definite
    assert np.array_equal(A, A.T) and set(np.unique(A)) <= {0.0, 1.0} and not np.any(np.diag(A))
    assert len(connected_components(A)) == 1
    M = np.diag(A.sum(1)) - A + np.diag(b)
    assert np.linalg.eigvalsh(M).min() > 1e-9
    assert set(np.unique(b)) <= {0.0, 1.0} and b.sum() >= 1

    # formation: planar, centred on the leader, neighbours `spacing` apart; r_f consistent
    assert np.all(h[:, 2] == 0.0)
    assert np.allclose(h.mean(axis=0), 0.0, atol=1e-5)
    r_f = float(np.linalg.norm(h, axis=1).max())
    assert s.r_f == pytest.approx(r_f, abs=1e-12)
    if n >= 2:
        D = np.linalg.norm(h[:, None] - h[None], axis=2) + np.diag(np.full(n, np.inf))
        assert D.min() == pytest.approx(spacing, abs=1e-5)
    if shape == "circle" and n >= 2:
        assert r_f == pytest.approx(spacing / (2 * math.sin(math.pi / n)), abs=1e-5)
        assert np.allclose(np.linalg.norm(h, axis=1), r_f, atol=1e-5)

    # initial positions: start + h_i + a jitter of at most 0.1 spacing per axis
    start, goal = np.asarray(s.leader.start), np.asarray(s.leader.goal)
    q0 = np.asarray(s.initial_positions)
    assert np.abs(q0 - (start + h)).max() <= 0.1 * spacing + 1e-5

    # start and goal far enough apart for the formation
    assert np.linalg.norm((goal - start)[:2]) >= 6 * r_f + 1.0 - 1e-3

    # obstacles: start and goal clear of every obstacle inflated by r_f + d0 (also as AAPF d_obs),
    # between start and goal, and no two overlap
    d0 = s.leader.d0
    seg = (goal - start)[:2]
    for ob in s.obstacles:
        for p in (start, goal):
            assert obstacle_clearance(p, ob) > r_f + d0
            assert d_obs(p, ob, r_f) > d0
        t = float(np.dot(np.asarray(ob.center[:2]) - start[:2], seg) / np.dot(seg, seg))
        assert 0.0 < t < 1.0
        assert ob.center[2] == 0.0 and ob.radius > 0 and ob.height > 0
        for q in q0:  # no UAV starts inside an obstacle's avoidance region
            assert obstacle_clearance(q, ob) > d0
    for o1, o2 in itertools.combinations(s.obstacles, 2):
        gap = math.hypot(o1.center[0] - o2.center[0], o1.center[1] - o2.center[1]) - o1.radius - o2.radius
        assert gap >= OBSTACLE_GAP - 1e-9

    # TOML round trip, and back through the dataclasses
    text = to_toml(d)
    assert tomllib.loads(text) == d
    assert scenario_from_dict(tomllib.loads(text)) == s


@pytest.mark.parametrize(("shape", "topology", "pinning"), list(itertools.product(SHAPES, TOPOLOGIES, PINNINGS)))
@pytest.mark.slow
def test_every_combination_is_valid(shape: str, topology: str, pinning: str) -> None:
    for n in NS:
        for seed in SEEDS:
            d = generate_scenario(n, shape, topology, k=2 + seed % 2, pinning=pinning, n_obstacles=seed + 1, seed=seed)
            check_scenario(d, n, 0.3, shape)
            assert len(d["obstacles"]) == seed + 1
            b = np.asarray(d["graph"]["pinning"])
            if pinning == "first":
                assert b[0] == 1.0 and b.sum() == 1.0
            elif pinning == "all":
                assert np.all(b == 1.0)


@pytest.mark.parametrize("n", [1, 2])
@pytest.mark.parametrize("shape", SHAPES)
def test_tiny_swarms(n: int, shape: str) -> None:
    for topology in TOPOLOGIES:
        d = generate_scenario(n, shape, topology, pinning="random", n_obstacles=2, seed=n)
        check_scenario(d, n, 0.3, shape)


@pytest.mark.parametrize("spacing", [0.15, 0.5, 1.0])
def test_spacing(spacing: float) -> None:
    for shape in SHAPES:
        d = generate_scenario(8, shape, "knn", k=1, n_obstacles=3, spacing=spacing, seed=3)
        check_scenario(d, 8, spacing, shape)


def test_topologies_have_the_expected_edges() -> None:
    h = formation_offsets(6, "circle", 0.3)
    deg = lambda A: A.sum(1)  # noqa: E731
    assert np.all(deg(adjacency_matrix(h, "ring")) == 2)
    A = adjacency_matrix(h, "star")
    assert deg(A)[0] == 5 and np.all(deg(A)[1:] == 1)
    assert np.all(deg(adjacency_matrix(h, "complete")) == 5)
    # knn on a circle with k=2: the two ring neighbours; k >= N-1 clamps to the complete graph
    assert np.array_equal(adjacency_matrix(h, "knn", 2), adjacency_matrix(h, "ring"))
    assert np.array_equal(adjacency_matrix(h, "knn", 100), adjacency_matrix(h, "complete"))
    # N = 2 ring: one edge of weight 1 (not doubled)
    assert np.array_equal(adjacency_matrix(formation_offsets(2), "ring"), [[0, 1], [1, 0]])


def test_knn_is_made_connected() -> None:
    # k = 1 on a circle pairs UAVs up: N/2 components before the repair
    h = formation_offsets(8, "circle", 0.3)
    A = adjacency_matrix(h, "knn", 1)
    assert len(connected_components(A)) == 1
    assert np.array_equal(A, A.T)
    assert np.all(A.sum(1) >= 1)
    # the repair adds N/2 - 1 = 3 edges to the 4 pairs: a tree of 7 edges
    assert A.sum() / 2 == 7
    # two far-apart clusters
    h2 = np.vstack([formation_offsets(4, "grid", 0.3), formation_offsets(4, "grid", 0.3) + [10.0, 0, 0]])
    A2 = adjacency_matrix(h2, "knn", 3)
    assert len(connected_components(A2)) == 1
    assert A2[:4, 4:].sum() == 1  # exactly one bridge


def test_random_pinning_covers_every_component() -> None:
    A = np.zeros((6, 6))
    A[0, 1] = A[1, 0] = A[2, 3] = A[3, 2] = 1.0  # components {0,1}, {2,3}, {4}, {5}
    for seed in range(50):
        b = generate.pinning_vector(A, "random", np.random.default_rng(seed))
        for comp in connected_components(A):
            assert b[comp].sum() >= 1
        M = np.diag(A.sum(1)) - A + np.diag(b)
        assert np.linalg.eigvalsh(M).min() > 0
    b = generate.pinning_vector(A, "first")
    assert list(b) == [1, 0, 1, 0, 1, 1]


def test_same_seed_same_output_different_seed_different_obstacles() -> None:
    kw = dict(n=8, shape="v", topology="knn", pinning="random", n_obstacles=4)
    a = generate_scenario(seed=5, **kw)
    assert generate_scenario(seed=5, **kw) == a
    assert to_toml(generate_scenario(seed=5, **kw)) == to_toml(a)
    layouts = {repr(generate_scenario(seed=s, **kw)["obstacles"]) for s in range(20)}
    assert len(layouts) == 20
    assert generate_scenario(seed=6, **kw)["formation"]["initial_positions"] != a["formation"]["initial_positions"]
    # the obstacles' stream is independent of the UAVs': more obstacles do not move the UAVs
    more = generate_scenario(seed=5, **{**kw, "n_obstacles": 6})
    assert more["formation"] == a["formation"] and more["graph"] == a["graph"]


def test_names_time_limit_and_gains() -> None:
    d = generate_scenario(3, name="my swarm", time_limit_s=123.0)
    s = scenario_from_dict(d)
    assert s.name == "my swarm" and s.timing.time_limit_s == 123.0
    assert d["obstacles"] == [] and s.obstacles == ()
    paper = load_scenario(EX1)
    assert s.leader.k_att == paper.leader.k_att and s.leader.d0 == paper.leader.d0
    assert (s.generator, s.eso, s.controller, s.timing.substeps) == (
        paper.generator, paper.eso, paper.controller, paper.timing.substeps)
    assert generate_scenario(4, "grid", "star", seed=9)["scenario"]["name"] == "gen_grid_star_n4_s9"
    # default time limit grows with the distance to the goal, never below the paper files' 70 s
    t3 = generate_scenario(3)["timing"]["time_limit_s"]
    t32 = generate_scenario(32)["timing"]["time_limit_s"]
    assert 70.0 <= t3 < t32


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(n=0),
        dict(n=2.5),
        dict(n=3, shape="hexagon"),
        dict(n=3, topology="tree"),
        dict(n=3, pinning="none"),
        dict(n=3, topology="knn", k=0),
        dict(n=3, spacing=0.0),
        dict(n=3, spacing=math.nan),
        dict(n=3, seed=-1),
        dict(n=3, seed=2**63),
        dict(n=3, n_obstacles=-1),
    ],
)
def test_bad_arguments(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        generate_scenario(**kwargs)


def test_impossible_obstacles_raise_a_clear_error() -> None:
    with pytest.raises(ScenarioError) as ei:
        generate_scenario(3, n_obstacles=200, seed=1)
    assert ei.value.field == "obstacles"
    assert "cannot place 200" in ei.value.message and "fewer obstacles" in ei.value.message


# ----------------------------------------------------------------------------- to_toml


def test_to_toml_round_trips_awkward_values() -> None:
    d: dict[str, Any] = {
        "top": 1,
        "empty_list": [],
        "s": 'quote " backslash \\ newline \n tab \t bell \x07 del \x7f unicode é ✓',
        "floats": [0.0, -0.0, 1e-300, 1e300, 0.1, -2.5e-7, 1.0, 3.141592653589793],
        "ints": [0, -1, 2**62, -(2**63)],
        "mixed": [1, "a", True, 2.5, [1, [2, []]], {"x": 1, "y": [1, 2]}],
        "bools": [True, False],
        "nested": [[1.0, 2.0], [3.0, 4.0, 5.0], []],
        "a b": {"c.d": 1, "": 2, "ключ": "значение", "x\ny": 3},
        "tab": {"sub": {"deep": {"v": 1}}, "empty": {}, "arr": [{"i": 1}, {"i": 2, "t": {"k": "v"}}]},
        "obstacles": [{"center": [1.0, 2.0, 0.0], "inner": [{"a": 1}]}, {}],
    }
    text = to_toml(d)
    assert tomllib.loads(text) == d
    assert to_toml({}) == ""


def test_to_toml_non_finite_floats() -> None:
    back = tomllib.loads(to_toml({"a": math.inf, "b": -math.inf, "c": [math.nan]}))
    assert back["a"] == math.inf and back["b"] == -math.inf and math.isnan(back["c"][0])


@pytest.mark.parametrize("bad", [{"x": None}, {"x": object()}, {1: 2}, {"x": [None]}])
def test_to_toml_rejects_what_toml_cannot_hold(bad: dict[Any, Any]) -> None:
    with pytest.raises(TypeError):
        to_toml(bad)


def test_to_toml_of_the_paper_scenario() -> None:
    s = load_scenario(EX1)
    d = scenario_to_dict(s)
    assert tomllib.loads(to_toml(d)) == d
    assert scenario_from_dict(tomllib.loads(to_toml(d))) == s


try:
    from hypothesis import given, settings
    from hypothesis import strategies as st
except ImportError:  # pragma: no cover - hypothesis is in the test extras
    pass
else:
    _scalars = (
        st.booleans()
        | st.integers(min_value=-(2**63), max_value=2**63 - 1)
        | st.floats(allow_nan=False)
        | st.text(max_size=8)
    )
    _values = st.recursive(
        _scalars,
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
        max_leaves=20,
    )

    @settings(max_examples=60, deadline=None)
    @given(st.dictionaries(st.text(max_size=5), _values, max_size=5))
    def test_to_toml_round_trip_property(d: dict[str, Any]) -> None:
        assert tomllib.loads(to_toml(d)) == d


# ----------------------------------------------------------------------------- CLI


def _parser() -> argparse.ArgumentParser:
    from zenswarm.compose.scenario_generate import add_parser

    ap = argparse.ArgumentParser(prog="zenswarm scenario")
    sub = ap.add_subparsers(dest="cmd", required=True)
    add_parser(sub)
    return ap


def test_cli_writes_a_loadable_file_and_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "gen.toml"
    argv = ["generate", "--n", "8", "--shape", "grid", "--topology", "knn", "--k", "3", "--pinning", "random",
            "--obstacles", "3", "--seed", "4", "--spacing", "0.4", "--time-limit", "90", "--out", str(out)]
    args = _parser().parse_args(argv)
    assert args.func(args) == 0
    summary = capsys.readouterr().out.strip()
    assert summary.count("\n") == 0 and str(out) in summary and "N=8" in summary and "obstacles=3" in summary

    s = load_scenario(out)
    assert s.n == 8 and len(s.obstacles) == 3 and s.seed == 4 and s.timing.time_limit_s == 90.0
    expected = generate_scenario(8, "grid", "knn", k=3, pinning="random", n_obstacles=3, seed=4, spacing=0.4,
                                 time_limit_s=90.0)
    assert tomllib.loads(out.read_text()) == expected
    before = out.read_bytes()

    # refuses to overwrite
    args = _parser().parse_args(argv[:-2] + ["--seed", "5", "--out", str(out)])
    assert args.func(args) == 2
    assert "exists" in capsys.readouterr().err and "--force" not in capsys.readouterr().out
    assert out.read_bytes() == before

    # --force overwrites
    args = _parser().parse_args(argv[:-2] + ["--seed", "5", "--out", str(out), "--force"])
    assert args.func(args) == 0
    assert out.read_bytes() != before and load_scenario(out).seed == 5


def test_cli_defaults_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "d.toml"
    args = _parser().parse_args(["generate", "--out", str(out)])
    assert (args.n, args.shape, args.topology, args.k, args.pinning, args.obstacles, args.seed, args.spacing) == (
        3, "circle", "ring", 2, "first", 0, 0, 0.3)
    assert args.func(args) == 0
    assert load_scenario(out).n == 3

    # impossible obstacle count: exit 2 with the reason, nothing written
    bad = tmp_path / "bad.toml"
    args = _parser().parse_args(["generate", "--obstacles", "500", "--out", str(bad)])
    assert args.func(args) == 2
    assert "cannot place" in capsys.readouterr().err and not bad.exists()

    # missing directories are created, as for every other output file
    args = _parser().parse_args(["generate", "--out", str(tmp_path / "no" / "such" / "dir.toml")])
    assert args.func(args) == 0
    assert load_scenario(tmp_path / "no" / "such" / "dir.toml").n == 3
    # a file where a directory is needed: exit 2 naming --out, nothing written
    from zenswarm.compose import cli

    assert cli.main(["scenario", "generate", "--out", str(out / "x.toml")]) == 2
    assert "--out" in capsys.readouterr().err

    for argv in (["generate"], ["generate", "--n", "0", "--out", "x"], ["generate", "--shape", "blob", "--out", "x"],
                 ["generate", "--spacing", "-1", "--out", "x"], ["generate", "--obstacles", "-2", "--out", "x"]):
        with pytest.raises(SystemExit) as ei:
            _parser().parse_args(argv)
        assert ei.value.code == 2


def test_cli_help_mentions_units_and_defaults() -> None:
    sub = _parser()._subparsers._group_actions[0]  # type: ignore[union-attr]
    text = " ".join(sub.choices["generate"].format_help().split())
    for needle in ("--spacing", "m (default: 0.3)", "--time-limit", "s (default", "--force", "--out FILE", "knn"):
        assert needle in text, needle


def test_wired_under_the_scenario_command(tmp_path: Path) -> None:
    """``zenswarm scenario generate`` through the real CLI entry point."""
    from zenswarm.compose import cli

    out = tmp_path / "c.toml"
    assert cli.main(["scenario", "generate", "--n", "4", "--obstacles", "1", "--out", str(out)]) == 0
    assert load_scenario(out).n == 4
    assert cli.main(["scenario", "generate", "--n", "4", "--out", str(out)]) == 2

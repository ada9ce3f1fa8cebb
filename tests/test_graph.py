"""The scenario's communication graph (zenswarm.scenario.graph): its three forms in ``[graph]``
(dense adjacency, edge list, topology by name), the same graph and the same flight from each, the
errors naming the field and the entry, and the vectorised generator (16)-(17) equal bit for bit to
the per-agent one."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from zenswarm.agents.core import AgentCore, AgentRow, StackedAgents
from zenswarm.compose.sim import simulate
from zenswarm.errors import ScenarioError
from zenswarm.judge.metrics import FLIGHT_FIELDS, TimeSeries
from zenswarm.scenario.config import scenario_from_dict, scenario_to_dict
from zenswarm.scenario.generate import adjacency_matrix, formation_offsets, generate_scenario, to_toml
from zenswarm.scenario.graph import CommGraph, topology_neighbours

from swarmtest import SCENARIOS, zenswarm

EX1 = SCENARIOS / "paper_example1.toml"


def ex1() -> dict[str, Any]:
    return tomllib.loads(EX1.read_text())


def reject(d: dict[str, Any], field: str, *needles: str) -> None:
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict(d)
    assert ei.value.field == field, f"field {ei.value.field!r} != {field!r} ({ei.value})"
    for n in needles:
        assert n in str(ei.value), f"{n!r} not in {ei.value}"


def _same_series(a: TimeSeries, b: TimeSeries) -> None:
    for f in TimeSeries.FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.shape == y.shape and x.tobytes() == y.tobytes(), f"{f} differs"


# ----------------------------------------------------------------------------- the three forms


def _components(A: np.ndarray) -> list[list[int]]:
    """Connected components of a 0/1 matrix, UAV 1's first (a breadth-first search of its own)."""
    left, comps = set(range(A.shape[0])), []
    while left:
        seen, todo = set(), [min(left)]
        while todo:
            i = todo.pop()
            if i not in seen:
                seen.add(i)
                todo.extend(int(j) for j in np.flatnonzero(A[i]) if j not in seen)
        comps.append(sorted(seen))
        left -= seen
    return comps


def _dense_reference(h: np.ndarray, topology: str, k: int) -> np.ndarray:
    """The named topologies built densely, the way the docs describe them, independent of the
    neighbour-list builder: ring, star, complete; knn = each UAV's k nearest (ties by index, k
    clamped to N - 1), symmetrised, then the closest pair between UAV 1's component and the
    rest joined while the graph is disconnected."""
    n = h.shape[0]
    A = np.zeros((n, n))
    if n == 1:
        return A
    if topology == "ring":
        for i in range(n):
            A[i, (i + 1) % n] = A[(i + 1) % n, i] = 1.0
    elif topology == "star":
        A[0, 1:] = A[1:, 0] = 1.0
    elif topology == "complete":
        A[:] = 1.0
        np.fill_diagonal(A, 0.0)
    else:
        D = np.linalg.norm(h[:, None, :] - h[None, :, :], axis=2)
        np.fill_diagonal(D, np.inf)
        for i in range(n):
            A[i, np.argsort(D[i], kind="stable")[: min(k, n - 1)]] = 1.0
        A = np.maximum(A, A.T)
        while len(comps := _components(A)) > 1:
            inside = np.zeros(n, dtype=bool)
            inside[comps[0]] = True
            sub = D[np.ix_(inside, ~inside)]
            a, b = np.unravel_index(int(np.argmin(sub)), sub.shape)
            i, j = int(np.flatnonzero(inside)[a]), int(np.flatnonzero(~inside)[b])
            A[i, j] = A[j, i] = 1.0
    return A


@pytest.mark.parametrize("n", [1, 2, 3, 5, 16, 40])
@pytest.mark.parametrize("shape", ["circle", "v", "grid"])
def test_topology_by_name_is_the_generators_graph_edge_for_edge(n: int, shape: str) -> None:
    """The neighbour-list builder, its dense form :func:`adjacency_matrix` and the graph of a
    scenario equal a dense reference built here independently (ties, clamping, and the joins of
    a disconnected knn graph included)."""
    rng = np.random.default_rng(n)
    clusters = np.vstack([rng.normal(size=(n // 2, 3)), 50.0 + rng.normal(size=(n - n // 2, 3))])  # knn disconnected
    for h in (formation_offsets(n, shape, 0.3), np.round(rng.normal(size=(n, 3)), 1), clusters):
        for topo, k in [("ring", 2), ("star", 2), ("complete", 2), ("knn", 1), ("knn", 3), ("knn", 4), ("knn", 50)]:
            g = CommGraph.from_topology(topo, k, h, np.ones(n))
            assert np.array_equal(g.dense(), adjacency_matrix(h, topo, k)), (topo, k)
            assert np.array_equal(adjacency_matrix(h, topo, k), _dense_reference(h, topo, k)), (topo, k)
            assert [list(x) for x in g.nbr] == topology_neighbours(h, topo, k)


def test_each_form_is_the_same_graph_and_flies_the_same_bits() -> None:
    """Example 1 with a weighted graph as a dense matrix and as an edge list (one edge given in
    both directions): the same neighbour lists and the same flight, bit for bit."""
    dense = ex1()
    dense["graph"] = {"adjacency": [[0.0, 0.5, 1.5], [0.5, 0.0, 0.0], [1.5, 0.0, 0.0]], "pinning": [1.0, 0.0, 0.0]}
    edges = ex1()
    edges["graph"] = {"edges": [[1, 2, 0.5], [3, 1, 1.5], [1, 3, 1.5]], "pinning": [1.0, 0.0, 0.0]}
    a, b = scenario_from_dict(dense), scenario_from_dict(edges)
    assert np.array_equal(a.comm_graph.dense(), b.comm_graph.dense())
    assert [a.neighbours(i) for i in range(3)] == [b.neighbours(i) for i in range(3)] == [[1, 2], [0], [0]]
    assert b.comm_graph.edge_list() == [(1, 2, 0.5), (1, 3, 1.5)]
    _same_series(simulate(a, n_ticks=400).series, simulate(b, n_ticks=400).series)


def test_generated_file_names_its_topology_and_flies_as_the_dense_matrix() -> None:
    """``scenario generate`` writes the topology by name (a few bytes at any N); the same scenario
    with the dense matrix the generator used to write flies the same bits."""
    d = generate_scenario(12, topology="knn", k=3, n_obstacles=1, seed=3, time_limit_s=3.0)
    assert set(d["graph"]) == {"topology", "k", "pinning"} and d["graph"]["topology"] == "knn"
    dense = {**d, "graph": {"adjacency": adjacency_matrix(np.asarray(d["formation"]["offsets"]), "knn", 3).tolist(),
                            "pinning": d["graph"]["pinning"]}}
    a, b = scenario_from_dict(d), scenario_from_dict(dense)
    res_a, res_b = simulate(a), simulate(b)
    _same_series(res_a.series, res_b.series)
    for k in FLIGHT_FIELDS:
        assert res_a.results[k] == res_b.results[k], k
    # the compact form survives the mission message / TOML round trip
    assert scenario_to_dict(a)["graph"] == d["graph"]
    assert scenario_from_dict(tomllib.loads(to_toml(scenario_to_dict(a)))) == a


def test_a_1000_uav_graph_is_a_few_bytes_and_loads_in_linear_time(tmp_path: Path) -> None:
    """The [graph] table of a generated 1000-UAV knn scenario is a few bytes (the dense matrix
    was 10^6 numbers, 4 MB); the file is dominated by the formation's 2 x 1000 positions."""
    d = generate_scenario(1000, topology="knn", k=4, seed=0, time_limit_s=1.0)
    graph_toml = to_toml({"graph": d["graph"]})
    assert len(graph_toml) < 6000, len(graph_toml)  # pinning: 1000 numbers; the graph itself one line
    text = to_toml(d)
    assert len(text) < 100_000, len(text)
    sc = scenario_from_dict(tomllib.loads(text))
    assert sc.comm_graph.n == 1000 and 2000 <= sc.comm_graph.n_edges <= 4000


# ----------------------------------------------------------------------------- bad input


def _graph(**g: Any) -> dict[str, Any]:
    d = ex1()
    d["graph"] = {"pinning": [1.0, 0.0, 0.0], **g}
    return d


@pytest.mark.parametrize(
    "graph, field, needles",
    [
        ({"edges": [[1, 2, 1.0], [1, 3, 1.0]], "adjacency": [[0.0, 1.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]},
         "graph", ("exactly one form", "adjacency and edges")),
        ({"edges": [[1, 2, 1.0]], "topology": "ring"}, "graph", ("exactly one form", "edges and topology")),
        ({}, "graph", ("exactly one form", "none")),
        ({"edges": [[1, 2, 1.0], [1, 4, 1.0]]}, "graph.edges[1][1]", ("UAV 4 does not exist", "1..3", "[1, 4, 1.0]")),
        ({"edges": [[0, 2, 1.0], [1, 3, 1.0]]}, "graph.edges[0][0]", ("UAV 0 does not exist",)),
        ({"edges": [[1, 2, 1.0], [3, 3, 1.0]]}, "graph.edges[1]", ("self loop", "[3, 3, 1.0]")),
        ({"edges": [[1, 2, -0.5], [1, 3, 1.0]]}, "graph.edges[0][2]", ("finite and > 0", "-0.5")),
        ({"edges": [[1, 2, 0.0], [1, 3, 1.0]]}, "graph.edges[0][2]", ("> 0",)),
        ({"edges": [[1, 2, float("inf")], [1, 3, 1.0]]}, "graph.edges[0][2]", ("finite", "inf")),
        ({"edges": [[1, 2, float("nan")], [1, 3, 1.0]]}, "graph.edges[0][2]", ("finite", "nan")),
        ({"edges": [[1, 2, 1.0], [1, 3, 1.0], [2, 1, 0.5]]}, "graph.edges[2]",
         ("asymmetric", "[2, 1, 0.5]", "graph.edges[0] = [1, 2, 1.0]")),
        ({"edges": [[1, 2]]}, "graph.edges[0]", ("length 3",)),
        ({"edges": [[1.5, 2, 1.0]]}, "graph.edges[0][0]", ("expected an integer",)),
        # no spanning tree from the leader: UAV 3 alone, unpinned
        ({"edges": [[1, 2, 1.0]]}, "graph.pinning", ("spanning tree", "UAV 3", "without a pinned UAV", "positive definite")),
        ({"topology": "mesh"}, "graph.topology", ("expected one of", "knn", "mesh")),
        ({"topology": "knn"}, "graph.k", ("missing", "k")),
        ({"topology": "ring", "k": 2}, "graph.k", ('only with topology = "knn"',)),
        ({"topology": "knn", "k": 0}, "graph.k", (">= 1",)),
    ],
)
def test_bad_graphs_name_the_field_and_the_entry(graph: dict[str, Any], field: str, needles: tuple[str, ...]) -> None:
    reject(_graph(**graph), field, *needles)


def test_unpinned_component_names_the_first_unreached_uav() -> None:
    d = ex1()
    d["formation"]["offsets"] += [[0.0, 0.2, 0.0], [0.0, -0.2, 0.0]]
    d["formation"]["initial_positions"] += [[0.0, 0.2, 0.4], [0.0, -0.2, 0.4]]
    d["graph"] = {"edges": [[1, 2, 1.0], [1, 3, 1.0], [4, 5, 1.0]], "pinning": [1.0, 0.0, 0.0, 0.0, 0.0]}
    reject(d, "graph.pinning", "UAV 4 (pinning[3])", "2 UAVs (4, 5)")
    d["graph"]["pinning"][4] = 0.5  # pin the second component: accepted
    assert scenario_from_dict(d).comm_graph.n_edges == 3


@pytest.mark.swarm
def test_bad_edge_list_exits_2_before_anything_starts(tmp_path: Path) -> None:
    """The command line: exit 2 naming the field and the entry, no output written."""
    d = _graph(edges=[[1, 2, 1.0], [1, 7, 1.0]])
    p = tmp_path / "bad.toml"
    p.write_text(to_toml(d))
    for args in (("scenario", "check", str(p)), ("sim", str(p), "--out", str(tmp_path / "out"))):
        r = zenswarm(*args, timeout=60)
        assert r.returncode == 2, r.stdout
        assert "Traceback" not in r.stdout and "graph.edges[1][1]" in r.stdout and "UAV 7 does not exist" in r.stdout, r.stdout
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- the generator (16)-(17)


@pytest.mark.parametrize("topology", ["ring", "star", "complete", "knn"])
def test_stacked_generator_rates_equal_each_agents_bit_for_bit(topology: str) -> None:
    """:meth:`StackedAgents.rates_all` (vectorised over agents) gives, row for row, the bits of
    :meth:`AgentCore.rates` of each agent (the agent process's), weighted edges and several
    pinned UAVs included, over many random states."""
    n = 23
    d = generate_scenario(n, topology=topology, k=3, pinning="random", seed=5, time_limit_s=1.0)
    rng = np.random.default_rng(1)
    sc = scenario_from_dict(d)
    edges = [[i, j, float(rng.uniform(0.1, 3.0))] for i, j, _ in sc.comm_graph.edge_list()]
    d["graph"] = {"edges": edges, "pinning": [float(rng.uniform(0.2, 2.0)) if b else 0.0 for b in d["graph"]["pinning"]]}
    sc = scenario_from_dict(d)
    rows = [AgentRow.from_scenario(sc, i, 0.027, 9.81) for i in range(n)]
    stacked = StackedAgents(rows)
    singles = [AgentCore(r) for r in rows]
    for _ in range(50):
        q, v = rng.normal(size=(n, 3)) * 10, rng.normal(size=(n, 3))
        q0, v0 = rng.normal(size=3), rng.normal(size=3)
        stacked.reset(q, v)
        stacked.v_ref = v.copy()
        dq, dv = stacked.rates_all(q0, v0)
        for i, (c, r) in enumerate(zip(singles, rows)):
            c.reset(q[i], v[i])
            c.v_ref = v[i].copy()
            nb = list(r.neighbours)
            one = c.rates(q[nb], v[nb], q0 if r.pinned else None, v0 if r.pinned else None)
            assert one[0].tobytes() == dq[i].tobytes() and one[1].tobytes() == dv[i].tobytes(), i

"""Radio links (issue 18, points 1, 2, 5): geometry-dependent delivery, the effective graph,
determinism, bad input. Pure and short in-process runs; the swarm check is marked swarm."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from zenswarm import api
from zenswarm.bus import wire
from zenswarm.compose.sim import simulate
from zenswarm.errors import ScenarioError
from zenswarm.judge.metrics import flight_differences
from zenswarm.link.config import plan_from_scenario, plan_with_radio
from zenswarm.link.decisions import FaultState
from zenswarm.link.plan import FaultPlan, LinkFaultSpec
from zenswarm.link.radio import RadioModel, components, drop_probability, leader_reaches_all, parse_distance, parse_fade, radio_reason
from zenswarm.link.swarm import Box, distance, effective_graph, plan_for
from zenswarm.scenario.config import load_scenario, scenario_from_dict

from swarmtest import SCENARIOS

EX1 = SCENARIOS / "paper_example1.toml"
SHORT = 150  # ticks: 1.5 s of paper example 1


@pytest.mark.parametrize(("text", "m"), [("1.5m", 1.5), ("150cm", 1.5), ("2km", 2000.0), ("0.5", 0.5), (3, 3.0), ("inf", math.inf)])
def test_parse_distance(text, m) -> None:
    assert parse_distance(text) == m


@pytest.mark.parametrize("text", ["0", "0m", "-1m", "-0.5", "nan", "1.5 parsecs", "", True, None, -2.0])
def test_parse_distance_bad(text) -> None:
    with pytest.raises(ValueError, match="distance"):
        parse_distance(text)


def test_parse_fade_and_model_validation() -> None:
    assert parse_fade("1.2m,10cm") == (1.2, 0.1)
    for bad in ("1.2m", "1m,0", "1m,-1m", "inf,1m", "a,b"):
        with pytest.raises(ValueError):
            parse_fade(bad)
    for kw in ({"range_m": 0}, {"range_m": -1.0}, {"fade_50_m": 0.0}, {"fade_width_m": 0.0}, {"fade_width_m": math.inf}, {"range_m": True}):
        with pytest.raises(ValueError):
            RadioModel(**kw)
    assert not RadioModel().active and RadioModel(range_m=1.0).active and RadioModel(fade_50_m=1.0).uses_uniform


def test_logistic_and_range() -> None:
    m = RadioModel(range_m=2.0, fade_50_m=1.0, fade_width_m=0.1)
    assert drop_probability(m, 1.0) == pytest.approx(0.5)
    assert drop_probability(m, 1.1) == pytest.approx(1 / (1 + math.exp(-1)))
    assert drop_probability(m, 0.6) < 0.02 and drop_probability(m, 1.4) > 0.98 and drop_probability(m, 2.01) == 1.0
    assert radio_reason(m, 2.5, 0.99) == "range" and radio_reason(m, 1.0, 0.49) == "fade" and radio_reason(m, 1.0, 0.51) is None
    hard = RadioModel(range_m=1.0)
    assert radio_reason(hard, 1.0, 0.0) is None and radio_reason(hard, math.nextafter(1.0, 2.0), 0.0) == "range"
    assert radio_reason(hard, math.nan, 0.0) == "range"


def test_graph_helpers() -> None:
    assert components(4, []) == 4 and components(4, [(0, 1), (2, 3)]) == 2 and components(3, [(0, 1), (1, 2)]) == 1
    assert leader_reaches_all(2, [(0, 1), (1, 2)]) and not leader_reaches_all(2, [(0, 1), (2, 1)])


def test_distance_is_the_vectorisable_formula() -> None:
    a, b = np.array([0.1, -0.3, 2.0]), np.array([1e-3, 0.7, 1.5])
    d = a - b
    assert distance(a, b) == float(np.sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]))


def test_scenario_and_cli_radio_fields() -> None:
    plan = plan_from_scenario(
        {"range": "1.5m", "fade": {"r50": "1m", "width": "10cm"}, "links": [{"kind": "leader", "range": "inf", "fade": False}]}, 3, 3
    )
    assert plan.radio_for("agent:1", "agent:2", "ref") == RadioModel(1.5, 1.0, 0.1)
    assert plan.radio_for("leader", "agent:1", "leader") is None  # exempted: range inf, no fall-off
    assert plan.radio_for("plant", "agent:1", "state") is None  # on board, never radio
    cli = plan_with_radio(FaultPlan(seed=1), "2m", None)
    assert cli.radio_active and cli.default.radio == RadioModel(range_m=2.0) and cli.active
    assert plan_with_radio(FaultPlan(seed=1)) == FaultPlan(seed=1)


@pytest.mark.parametrize(
    ("section", "field"),
    [
        ({"range": "-1m"}, "faults.range"),
        ({"range": 0}, "faults.range"),
        ({"range": "far"}, "faults.range"),
        ({"fade": {"r50": "0m", "width": "1m"}}, "faults.fade.r50"),
        ({"fade": {"r50": "1m", "width": "-1m"}}, "faults.fade.width"),
        ({"links": [{"kind": "ref", "range": "-3m"}]}, "faults.links[0].range"),
        ({"links": [{"kind": "state", "range": "3m"}]}, "faults.links[0].range"),
        ({"links": [{"kind": "cmd", "fade": {"r50": "1m", "width": "1m"}}]}, "faults.links[0].fade"),
    ],
)
def test_bad_scenario_radio_fields(section, field) -> None:
    d = tomllib.loads(EX1.read_text())
    d["faults"] = section
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict(d)
    assert ei.value.field == field


@pytest.mark.parametrize(("kw", "flag"), [({"link_range": "0"}, "--link-range"), ({"link_range": "-1m"}, "--link-range"),
                                          ({"link_fade": "1m"}, "--link-fade"), ({"link_fade": "1m,0"}, "--link-fade")])
def test_bad_radio_flags_name_the_flag(kw, flag) -> None:
    with pytest.raises(ScenarioError) as ei:
        plan_for(load_scenario(EX1), **kw)
    assert ei.value.field == flag


def test_box_waits_for_the_geometry() -> None:
    """A radio message is decided once the receiver's own position of its geometry tick is
    known; until then due() names it and ready() is False; beyond range it is dropped and the
    box holds the older value."""
    plan = plan_with_radio(FaultPlan(seed=2), "1m")
    box = Box(FaultState(plan), "agent:2", "agent:1", "ref", 0.01)
    box.offer(0, 0, "r0")
    box.own_position(0, (0.0, 0.0, 0.0))
    assert box.ready(0) and box.at(0).value == "r0"
    box.offer(1, 1, "r1", (0.5, 0.0, 0.0))  # ref of tick 1: geometry of tick 0, near
    assert box.ready(1) and box.at(1).value == "r1"
    box.offer(2, 2, "r2", (3.0, 0.0, 0.0))  # geometry tick 1 unknown yet: parked
    assert box.due(2) == 2 and not box.ready(2)
    box.own_position(1, (0.0, 0.0, 0.0))  # now 3 m > 1 m: dropped
    assert box.ready(2) and box.due(2) == 1 and box.at(2).value == "r1"
    assert box.decision(2).reason == "range" and box.counters()["dropped_range"] == 1
    unstamped = Box(FaultState(plan), "agent:2", "agent:1", "ref", 0.01)
    unstamped.own_position(0, (0.0, 0.0, 0.0))
    unstamped.offer(1, 1, "x")
    assert unstamped.decision(1).dropped  # no stamp: as if beyond range


def test_box_stays_ready_through_a_long_outage() -> None:
    """A link out of range for many ticks (more than the box keeps decisions for) still names
    its held message as due and is ready every tick (the lockstep swarm once waited forever)."""
    plan = plan_with_radio(FaultPlan(seed=2), "1m", None)
    box = Box(FaultState(plan), "agent:2", "agent:1", "ref", 0.01)
    for k in range(400):
        box.own_position(k, (0.0, 0.0, 0.0))
        box.offer(k, k, k, (0.5 if k < 5 else 5.0, 0.0, 0.0))  # stamps in range up to tick 4
        assert box.ready(k), k
        assert box.at(k).value == min(k, 4)


def test_ref_wire_stamp_is_optional() -> None:
    """Without a stamp the ref's bytes are the paper's (no "p" key); with one it round-trips; a
    stamp of another length is refused."""
    plain = wire.Ref(t=10, seq=1, q=np.zeros(3), v=np.ones(3))
    assert b"\xa1p" not in wire.encode(plain)
    stamped = wire.Ref(t=10, seq=1, q=np.zeros(3), v=np.ones(3), pos=(1.0, 2.0, 3.0))
    back = wire.decode("ref", wire.encode(stamped))
    assert back.pos == (1.0, 2.0, 3.0) and back == stamped
    assert wire.decode("ref", wire.encode(plain)).pos == ()
    with pytest.raises(wire.MessageError):
        wire.Ref(t=10, seq=1, q=np.zeros(3), v=np.ones(3), pos=(1.0, 2.0))


@pytest.fixture(scope="module")
def ex1():
    return load_scenario(EX1)


@pytest.fixture(scope="module")
def free(ex1):
    return simulate(ex1, n_ticks=SHORT)


def test_range_beyond_the_formation_is_fault_free(ex1, free) -> None:
    """Acceptance: a range well beyond the formation's size equals the fault-free run bit for
    bit; the effective graph is whole at every tick."""
    r = simulate(ex1, n_ticks=SHORT, faults=plan_for(ex1, link_range="100m"))
    assert flight_differences(free.series, free.results, r.series, r.results) == []
    g = r.results["effective_graph"]
    assert g["components"] == [[0, 1]] and g["spanning_tree_fraction"] == 1.0 and set(g["link_up_fraction"].values()) == {1.0}


def test_range_below_the_spacing_disconnects(ex1, free) -> None:
    """Acceptance: with a range below the UAV spacing (0.2 m at the start) nobody hears a
    neighbour after the start-up exchange: the effective graph falls apart, Lemma 1's spanning
    tree holds at tick 0 only, and the flight differs from the fault-free one."""
    r = simulate(ex1, n_ticks=SHORT, faults=plan_for(ex1, link_range="0.1m"))
    g = r.results["effective_graph"]
    ref_links = {k: v for k, v in g["link_up_fraction"].items() if not k.startswith("leader")}
    assert all(v == pytest.approx(1 / SHORT) for v in ref_links.values())
    assert g["max_components"] == ex1.n + 1 and g["spanning_tree_fraction"] == pytest.approx(1 / SHORT)
    assert flight_differences(free.series, free.results, r.series, r.results) != []
    c = r.results["link_counters"]
    assert c["link:agent:2->agent:1:ref.dropped_range"] == SHORT - 1
    # the effective graph (from the series) and the receive boxes agree on every link
    for name, frac in ref_links.items():
        src, dst = name.split("->")
        assert c[f"link:{src}->{dst}:ref.delivered"] == round(frac * SHORT)


def test_fade_is_deterministic_and_matches_the_boxes(ex1) -> None:
    """A logistic fall-off around the spacing: a run repeats exactly, and the effective graph
    recomputed from the series equals what the receive boxes delivered."""
    plan = plan_for(ex1, link_fade="0.25m,0.05m", link_loss="0.1")
    a = simulate(ex1, n_ticks=SHORT, faults=plan)
    b = simulate(ex1, n_ticks=SHORT, faults=plan_for(ex1, link_fade="0.25m,0.05m", link_loss="0.1"))
    assert flight_differences(a.series, a.results, b.series, b.results) == []
    assert a.results["effective_graph"] == b.results["effective_graph"]
    up = a.results["effective_graph"]["link_up_fraction"]
    assert 0.0 < min(up.values()) < 1.0
    c = a.results["link_counters"]
    for name, frac in up.items():
        src, dst = name.split("->")
        kind = "leader" if src == "leader" else "ref"
        assert c[f"link:{src}->{dst}:{kind}.delivered"] == round(frac * SHORT), name
    assert sum(v for k, v in c.items() if k.endswith("dropped_fade")) > 0


def test_effective_graph_of_a_lossless_plan() -> None:
    q = np.zeros((5, 2, 3))
    q[:, 1, 0] = [0.5, 1.5, 1.5, 0.5, 0.5]
    plan = FaultPlan(LinkFaultSpec(radio=RadioModel(range_m=1.0)))
    g = effective_graph(plan, [[1], [0]], [True, False], q, np.zeros((5, 3)), 0.01)
    # a ref of tick k uses the positions of tick k - 1: down at ticks 2 and 3
    assert g["link_up_fraction"] == {"agent:2->agent:1": 0.6, "leader->agent:1": 1.0, "agent:1->agent:2": 0.6}
    assert g["components"] == [[0, 1], [2, 2], [4, 1]] and g["spanning_tree_fraction"] == 0.6


def test_a_series_that_starts_late_is_judged_by_its_own_ticks() -> None:
    """A realtime series starts at the first tick every process had a value (a late joiner): its
    row r is tick s + r. The effective graph of its rows is the whole flight's from tick s on (the
    faults of each tick, not of its row number): loss and the radio's fall-off draw per tick, so a
    graph shifted by s ticks differs. (A ref of tick k is judged at the positions of tick k - 1,
    which a series from tick s has from its second row on.)"""
    from dataclasses import replace

    from zenswarm.compose.sim import radio_results
    from zenswarm.link.swarm import graph_series

    ex1 = load_scenario(SCENARIOS / "paper_example1.toml")
    plan = plan_for(ex1, link_fade="0.25m,0.05m", link_loss="0.3", seed=3)
    flown = simulate(ex1, n_ticks=SHORT, faults=plan)
    ts, s = flown.series, 37
    A = np.asarray(ex1.graph.adjacency, dtype=float)
    nbrs = [[int(j) for j in np.flatnonzero(A[i])] for i in range(ex1.n)]
    pinned = [float(b) > 0 for b in ex1.graph.pinning]
    whole = graph_series(plan, nbrs, pinned, ts.q, ts.q0, ex1.timing.dt)
    late = graph_series(plan, nbrs, pinned, ts.q[s:], ts.q0[s:], ex1.timing.dt, first_tick=s)
    for a, b in zip(whole.links, late.links, strict=True):
        assert a.name == b.name and a.up[s + 1 :].tolist() == b.up[1:].tolist(), a.name
        assert np.array_equal(a.delay_s[s:], b.delay_s)
    assert whole.components[s + 1 :].tolist() == late.components[1:].tolist()
    shifted = graph_series(plan, nbrs, pinned, ts.q[s:], ts.q0[s:], ex1.timing.dt)  # judged as if from tick 0
    assert any(a.up[s + 1 :].tolist() != b.up[1:].tolist() for a, b in zip(whole.links, shifted.links, strict=True))

    # through radio_results, as the supervisor judges a realtime series that starts late
    cut = replace(ts, **{f: getattr(ts, f)[s:] for f in ts.FIELDS})
    graph = radio_results(ex1, plan, cut)["effective_graph"]
    assert graph["first_tick"] == s and graph["ticks"] == SHORT - s and graph["components"][0][0] == s
    for ls in late.links:
        assert graph["link_up_fraction"][ls.name] == float(np.mean(ls.up)), ls.name
    with pytest.raises(ValueError, match="first_tick"):
        graph_series(plan, nbrs, pinned, ts.q, ts.q0, ex1.timing.dt, first_tick=-1)


@pytest.mark.swarm
@pytest.mark.parametrize("rng", ["0.3m"])
def test_radio_swarm_equals_sim(zenswarm_fly, rng: str) -> None:
    """sim equals lockstep up bit for bit with a range that cuts links part of the time and a
    fall-off, on a short flight; the effective graph is the same."""
    kw = dict(link_range=rng, link_fade="0.28m,0.03m", link_delay="30ms", seed=5, duration=2.0, overrides={"faults.hold": "0.04s"})
    swarm = zenswarm_fly(EX1, mode="swarm", **kw)
    assert swarm.exit_code in (0, 1), swarm.log[-3000:]
    sim = api.fly(EX1, **kw)
    assert api.differences(swarm, sim) == []
    assert _expired(sim.results) > 0  # the hold horizon acted
    assert swarm.results["effective_graph"] == sim.results["effective_graph"]
    up = sim.results["effective_graph"]["link_up_fraction"]
    assert min(up.values()) < 1.0  # the radio did act


# ------------------------------------------------------------------------------ hold horizon


def _expired(results: dict) -> int:
    """Ticks beyond the hold horizon, over every link (``link_counters``: ``link:<src>-><dst>:<kind>.<counter>``)."""
    return sum(v for k, v in results["link_counters"].items() if k.endswith(".expired"))


def _box_after_silence(kind: str, hold: str | None) -> list[bool]:
    """A link whose messages of ticks 0..2 arrive and then nothing: is something held at 3..10?"""
    plan = plan_from_scenario({} if hold is None else {"hold": hold}, 0, 3)
    box = Box(FaultState(plan), "agent:2" if kind == "ref" else "plant", "agent:1", kind, 0.01)
    for j in range(3):
        box.offer(j, j, ("value", j))
    return [box.at(k) is not None for k in range(3, 11)]


def test_hold_horizon_expires_references_only() -> None:
    """hold 0.05 s at dt 0.01 s = 5 ticks: the tick-2 message is held while 5 or fewer ticks old
    (ticks 3..7), then not heard; without a horizon it is held forever; a state never expires."""
    assert _box_after_silence("ref", "0.05s") == [True] * 5 + [False] * 3
    assert _box_after_silence("ref", None) == [True] * 8
    assert _box_after_silence("state", "0.05s") == [True] * 8
    plan = plan_from_scenario({"hold": "0.05s"}, 0, 3)
    box = Box(FaultState(plan), "agent:2", "agent:1", "ref", 0.01)
    box.offer(0, 0, "v")
    [box.at(k) for k in range(0, 9)]
    assert box.counters()["expired"] == 3


@pytest.mark.parametrize("bad", ["0s", "-1s", "soon", 5])
def test_hold_horizon_bad_values_name_the_field(bad: object) -> None:
    with pytest.raises(ScenarioError) as e:
        plan_from_scenario({"hold": bad}, 0, 3)
    assert e.value.field == "faults.hold"


def test_hold_horizon_lets_a_cut_neighbour_go() -> None:
    """A range that cuts UAV 3 off its neighbours after take-off: without a horizon the others
    keep its tick-0 reference in (16)-(17) for the whole flight; with one they leave it out, so
    the generator's formation differs (and the link counters say how many ticks expired)."""
    kw = dict(link_range="0.21m", seed=1, duration=3.0)
    forever = api.fly(EX1, **kw)
    held = api.fly(EX1, overrides={"faults.hold": "0.2s"}, **kw)
    assert _expired(held.results) > 0
    assert not any(k.endswith(".expired") for k in forever.results["link_counters"])
    assert not np.array_equal(forever.series.qref, held.series.qref)

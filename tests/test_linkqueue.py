"""Capacity queues (zenswarm.link.queue) and trace replay (zenswarm.link.trace): pure tests, and the
bad-input checks of `zenswarm sim` (exit 2 naming the field or the CSV line)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from zenswarm.bus import wire
from zenswarm.compose.sim import simulate
from zenswarm.errors import ScenarioError
from zenswarm.link.config import plan_from_scenario
from zenswarm.link.decisions import FaultState
from zenswarm.link.queue import LinkQueues, QueueSpec, message_size, parse_capacity, parse_queue
from zenswarm.link.swarm import Box, plan_for, scenario_links
from zenswarm.link.trace import parse_trace
from zenswarm.scenario.config import load_scenario

from swarmtest import SCENARIOS

EX1 = SCENARIOS / "paper_example1.toml"
REPO = Path(__file__).resolve().parents[1]
TRACE = REPO / "docs" / "example_trace.csv"


def test_parse_capacity_and_queue() -> None:
    assert parse_capacity("20kB/s") == 20000.0
    assert parse_capacity("160kbit/s") == 20000.0
    assert parse_capacity("2KiB/s") == 2048.0
    assert parse_capacity(500) == 500.0
    for bad in ("0kB/s", "-1kB/s", "20 furlongs/s", "inf", True, 0):
        with pytest.raises(ValueError):
            parse_capacity(bad)  # type: ignore[arg-type]
    assert parse_queue(8) == (8, "msg")
    assert parse_queue("4kB") == (4000, "B")
    assert parse_queue("4096B") == (4096, "B")
    for bad in (0, -3, "0", "1.5", "x", True):
        with pytest.raises(ValueError):
            parse_queue(bad)  # type: ignore[arg-type]


def test_message_size_is_the_encoded_size_of_what_the_processes_send() -> None:
    """Sizes do not depend on the float values (float64 always), only on t and seq."""
    dt = 0.01
    rng = np.random.default_rng(0)
    for k in (0, 1, 63, 64, 500, 32767, 70000):
        v = [rng.normal(size=3) * 1e3 for _ in range(4)]
        t = k * wire.t_ns(dt)
        assert message_size("ref", k, dt) == len(wire.encode(wire.Ref(t=t, seq=2 * k + 1, q=v[0], v=v[1])))
        assert message_size("cmd", k, dt) == len(wire.encode(wire.Cmd(t=t, seq=2 * k + 2, thrust=9.81, rpy=v[0], u=v[1], d_hat=v[2])))
        assert message_size("state", k, dt) == len(wire.encode(wire.State(t=t, seq=k + 1, q=v[0], v=v[1], rpy=v[2], w=v[3])))
        assert message_size("leader", k, dt) == len(wire.encode(wire.Ref(t=t, seq=k + 1, q=v[0], v=v[1])))


def _const(size: int):
    return lambda kind, tick, dt: size


def test_queue_serialization_wait_and_tail_drop() -> None:
    """One sender, two links of 100 B messages at 10 kB/s (10 ms each), dt 10 ms: the medium
    carries one message per tick, two arrive, so the backlog grows by one per tick until the
    4-message queue is full; then one of the two is dropped every tick."""
    a, b = ("agent:1", "agent:2", "ref"), ("agent:1", "agent:3", "ref")
    spec = QueueSpec(10_000.0, 4, "msg", "sender")
    q = LinkQueues({a: spec, b: spec}, 0.01, size=_const(100))
    assert q.one(a, 0) == (False, 0.0)  # tick 0 is not queued
    da, wa = q.batch(a, np.arange(1, 8))
    db, wb = q.batch(b, np.arange(1, 8))
    np.testing.assert_allclose(wa[:3], [0.01, 0.02, 0.03])
    np.testing.assert_allclose(wb[:3], [0.02, 0.03, 0.04])
    assert not da.any()
    assert db[3:].all() and not db[:2].any()
    # pure: asking out of order, one by one, gives the same
    q2 = LinkQueues({a: spec, b: spec}, 0.01, size=_const(100))
    assert [q2.one(b, k) for k in range(7, 0, -1)] == [(bool(db[k - 1]), float(wb[k - 1])) for k in range(7, 0, -1)]
    # per link: each queue carries one message per tick: serialization only, no wait, no drop
    ql = LinkQueues({a: QueueSpec(10_000.0, 4, "msg", "link"), b: QueueSpec(10_000.0, 4, "msg", "link")}, 0.01, size=_const(100))
    d, w = ql.batch(b, np.arange(1, 500))
    assert not d.any() and np.allclose(w, 0.01)


def test_queue_bound_in_bytes() -> None:
    a = ("plant", "agent:1", "state")
    q = LinkQueues({a: QueueSpec(1000.0, 250, "B", "link")}, 0.01, size=_const(100))
    d, w = q.batch(a, np.arange(1, 6))
    # 100 B take 0.1 s: the queue holds 2 (200 B <= 250 B), the third is dropped
    assert d.tolist() == [False, False, True, True, True]
    np.testing.assert_allclose(w[:2], [0.1, 0.19])


def test_shared_medium_must_agree() -> None:
    a, b = ("agent:1", "agent:2", "ref"), ("agent:1", "plant", "cmd")
    with pytest.raises(ValueError, match="share its medium"):
        LinkQueues({a: QueueSpec(1000.0), b: QueueSpec(2000.0)}, 0.01)


def test_capacity_in_scenario_and_decisions() -> None:
    sc = load_scenario(EX1)
    faults = {"capacity": "20kB/s", "queue": 8, "links": [{"kind": "cmd", "capacity": False}, {"dst": "agent:3", "queue": "2kB"}]}
    plan = plan_from_scenario(faults, 0, sc.n)
    assert plan.spec_for("agent:1", "plant", "cmd").queue is None
    assert plan.spec_for("agent:2", "agent:1", "ref").queue == QueueSpec(20000.0, 8, "msg", "sender")
    assert plan.spec_for("plant", "agent:3", "state").queue == QueueSpec(20000.0, 2000, "B", "sender")
    p = plan_for(sc.with_changes(faults=None), link_capacity="5kB/s", link_queue="3", link_medium="link")
    assert p is not None and p.queues is not None
    assert set(p.queues.links) == set(scenario_links(sc))
    fs = FaultState(p)
    box = Box(fs, "plant", "agent:1", "state", sc.timing.dt)
    for k in (1, 2, 300):
        d = fs.decide("plant", "agent:1", "state", k, k * sc.timing.dt)
        assert d == box.decision(k)
    # 5 kB/s per link: a state message of ~130 B takes ~26 ms > dt, so the queue fills and drops
    drops = [box.decision(k).reason for k in range(1, 200)]
    assert "queue" in drops and "ok" in drops


@pytest.mark.parametrize(
    ("faults", "field"),
    [
        ({"capacity": "0kB/s"}, "faults.capacity"),
        ({"capacity": -5}, "faults.capacity"),
        ({"capacity": "1kB/s", "queue": 0}, "faults.queue"),
        ({"capacity": "1kB/s", "queue": "-2kB"}, "faults.queue"),
        ({"queue": 4}, "faults.queue"),
        ({"capacity": "1kB/s", "medium": "ether"}, "faults.medium"),
        ({"links": [{"src": "agent:1", "capacity": "-1B/s"}]}, "faults.links[0].capacity"),
    ],
)
def test_bad_capacity_names_the_field(faults: dict, field: str) -> None:
    with pytest.raises(ScenarioError) as e:
        plan_from_scenario(faults, 0, 3)
    assert e.value.field == field


def test_trace_semantics() -> None:
    tr = parse_trace(TRACE.read_text(), "t.csv")
    link = ("agent:1", "agent:2", "ref")
    assert tr.lookup(link, 0.0) == (0.02, True)
    assert tr.lookup(link, 0.49) == (0.02, True)
    assert tr.lookup(link, 0.5) == (0.0, False)  # the row in force at the send time
    assert tr.lookup(link, 1.0) == (0.08, True)
    assert tr.lookup(link, 99.0) == (0.02, True)  # the last row holds
    assert tr.lookup(("agent:3", "agent:1", "ref"), 0.0) == (0.15, True)  # before the first row: the first row
    d, ok = tr.lookup_batch(link, np.array([0.0, 0.6, 2.0]))
    assert d.tolist() == [0.02, 0.0, 0.08] and ok.tolist() == [True, False, True]
    sc = load_scenario(EX1)
    plan = plan_for(sc, link_trace=str(TRACE))
    assert plan is not None
    fs = FaultState(plan)
    dt = sc.timing.dt
    assert fs.decide("agent:1", "agent:2", "ref", 60, 0.6).reason == "trace"
    assert fs.decide("agent:1", "agent:2", "ref", 100, 1.0).delay_s == 0.08
    box = Box(fs, "agent:1", "agent:2", "ref", dt)
    assert box.decision(60) == fs.decide("agent:1", "agent:2", "ref", 60, 60 * dt)


@pytest.mark.parametrize(
    ("text", "where", "what"),
    [
        ("tme,link,delay,delivered\n0,agent:1->agent:2,0,1\n", "t.csv:1", "bad header"),
        ("time,link,delay,delivered\nzero,agent:1->agent:2,0,1\n", "t.csv:2", "not a number"),
        ("time,link,delay,delivered\n0,agent:1->agent:2,-0.1,1\n", "t.csv:2", "must be >= 0"),
        ("time,link,delay,delivered\n0,agent:1->agent:2,0.1,2\n", "t.csv:2", "0 or 1"),
        ("time,link,delay,delivered\n# c\n1,agent:1->agent:2,0,1\n0.5,agent:1->agent:2,0,1\n", "t.csv:4", "must not decrease"),
        ("time,link,delay,delivered\n0,agent:1-agent:2,0,1\n", "t.csv:2", "src->dst"),
        ("time,link,delay,delivered\n0,plant->leader,0,1\n", "t.csv:2", "no message kind"),
        ("time,link,delay,delivered\n0,agent:1->agent:2,0\n", "t.csv:2", "4 columns"),
        ("time,link,delay,delivered\n", "t.csv:1", "no rows"),
    ],
)
def test_malformed_trace_names_the_line(text: str, where: str, what: str) -> None:
    with pytest.raises(ScenarioError) as e:
        parse_trace(text, "t.csv")
    assert e.value.field == where and what in e.value.message


def test_trace_of_a_link_not_in_the_graph() -> None:
    sc = load_scenario(EX1)
    tr = parse_trace("time,link,delay,delivered\n0,agent:1->agent:2,0,1\n0,agent:2->agent:3,0,1\n", "t.csv")
    with pytest.raises(ScenarioError) as e:
        tr.check_links(scenario_links(sc))
    assert e.value.field == "t.csv:3" and "agent:2->agent:3" in e.value.message
    tr = parse_trace("time,link,delay,delivered\n0,agent:9->agent:1,0,1\n", "t.csv")
    with pytest.raises(ScenarioError, match="no such UAV"):
        tr.check_links(scenario_links(sc))


def test_scenario_trace_is_relative_to_the_scenario_file(tmp_path: Path) -> None:
    (tmp_path / "tr.csv").write_text(TRACE.read_text())
    text = EX1.read_text() + '\n[faults]\ntrace = "tr.csv"\ncapacity = "40kB/s"\n'
    (tmp_path / "s.toml").write_text(text)
    sc = load_scenario(tmp_path / "s.toml")
    plan = plan_for(sc)
    assert plan is not None and plan.trace is not None and plan.queues is not None
    # the simulator with a trace and a capacity repeats exactly
    a = simulate(sc, n_ticks=120, faults=plan).series
    b = simulate(sc, n_ticks=120, faults=plan_for(sc)).series
    assert np.array_equal(a.q, b.q) and np.array_equal(a.qref, b.qref)


def test_trace_stays_beside_the_scenario_file_under_overrides(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--set` (scenario.overrides.load_file) keeps the file's own relative trace relative to the
    scenario's directory, wherever the command runs from, and a relative one an override names too
    (an absolute one as it is); zenswarm.api.load/fly take the file the same way."""
    from zenswarm import api
    from zenswarm.scenario.overrides import load_file

    (tmp_path / "tr.csv").write_text(TRACE.read_text())
    (tmp_path / "tr2.csv").write_text(TRACE.read_text())
    (tmp_path / "s.toml").write_text(EX1.read_text() + '\n[faults]\ntrace = "tr.csv"\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    plain = load_file(tmp_path / "s.toml", {})
    assert plain.faults is not None and plain.faults.trace == str(tmp_path.absolute() / "tr.csv")
    shorter = load_file(tmp_path / "s.toml", {"timing.time_limit_s": 5.0})
    assert shorter.timing.time_limit_s == 5.0
    assert shorter.faults is not None and shorter.faults.trace == plain.faults.trace
    given = load_file(tmp_path / "s.toml", {"faults.trace": str(tmp_path / "tr2.csv")})  # absolute: as it is
    assert given.faults is not None and given.faults.trace == str(tmp_path / "tr2.csv")
    beside = str(tmp_path.absolute() / "tr2.csv")  # a relative one an override names: beside the file too
    other = load_file(tmp_path / "s.toml", {"faults.trace": "tr2.csv"})
    assert other.faults is not None and other.faults.trace == beside
    # zenswarm.api takes the file the same way: the scenario and the document written for the run
    cases = (({}, plain.faults.trace), ({"timing.time_limit_s": 5.0}, plain.faults.trace), ({"faults.trace": "tr2.csv"}, beside))
    for overrides, want in cases:
        sc, doc = api.load(tmp_path / "s.toml", overrides)
        assert sc.faults is not None and sc.faults.trace == want and doc["faults"]["trace"] == want, overrides


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--link-capacity", "0kB/s"], "--link-capacity"),
        (["--link-capacity", "1kB/s", "--link-queue", "0"], "--link-queue"),
        (["--link-trace", "nonexistent.csv"], "--link-trace"),
        (["--link-trace", "BAD"], "bad.csv:3"),
    ],
)
def test_cli_bad_input_exits_2(args: list[str], needle: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`zenswarm sim` (its main, in this process) refuses bad capacities and traces with exit 2,
    naming the flag or the CSV line, and flies nothing."""
    from zenswarm.compose.cli import main

    bad = tmp_path / "bad.csv"
    bad.write_text("time,link,delay,delivered\n0,agent:1->agent:2,0,1\n0,agent:2->agent:3,0,1\n")
    args = [str(bad) if a == "BAD" else a for a in args]
    out = tmp_path / "out"
    assert main(["sim", str(EX1), "--out", str(out), "--quiet", *args]) == 2
    assert needle in capsys.readouterr().err
    assert not (out / "results.json").exists()


@pytest.mark.swarm
def test_swarm_equals_sim_with_capacity_and_trace(zenswarm_fly) -> None:
    """Lockstep `zenswarm up` equals `zenswarm sim` bit for bit with a per-sender capacity that
    congests (20 kB/s, 3-message queue: queue drops and waits on every link) and the example trace
    on four links; the queue drops are counted per link."""
    faults = dict(link_capacity="20kB/s", link_queue=3, link_trace=TRACE, seed=5)
    swarm = zenswarm_fly(EX1, mode="swarm", duration=2.0, **faults)
    assert swarm.exit_code in (0, 1), swarm.log[-3000:]
    sim = zenswarm_fly(EX1, duration=2.0, **faults)
    from zenswarm import api

    assert api.differences(swarm, sim) == []
    lc = sim.results["link_counters"]
    assert lc["link:plant->agent:3:state.dropped_queue"] > 0
    assert lc["link:agent:1->agent:2:ref.dropped_trace"] > 0
    # the agent process also receives the final state (t = the time limit), one message more
    got = swarm.diagnostics["agent:3"]["link:plant->agent:3:state.dropped_queue"]
    assert got - lc["link:plant->agent:3:state.dropped_queue"] in (0, 1)

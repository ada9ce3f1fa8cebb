"""The swarm as real OS processes over a real Zenoh router on loopback (issue: swarm).

Every test uses its own swarm name and router port and checks that no process is left behind.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from zenswarm.agents.core import AgentRow
from zenswarm.agents.process import subscriptions
from zenswarm.bus import free_port, wire
from zenswarm.compose.sim import simulate
from zenswarm.judge.metrics import FLIGHT_FIELDS, TimeSeries
from zenswarm.scenario.config import load_scenario

from swarmtest import (
    SCENARIOS,
    kill_mentioning,
    processes_mentioning,
    read_results,
    scenario_variant,
    start_zenswarm,
    unique_swarm,
    wait_port_free,
    zenswarm,
)

pytestmark = pytest.mark.swarm  # starts processes: zenoh routers, swarm processes or CLI subprocesses


def _up(scenario: Path, out: Path, swarm: str, *extra: str, timeout: float = 400.0):
    port = free_port()
    try:
        cp = zenswarm(
            "up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
            "--progress-every", "5", *extra, timeout=timeout,
        )
    finally:
        leftovers = processes_mentioning(f"--swarm {swarm}")
        kill_mentioning(f"--swarm {swarm}")
    assert not leftovers, f"processes left behind: {leftovers}"
    assert wait_port_free(port), f"router port {port} still bound after exit"
    return cp


def _assert_equal_to_sim(scenario: Path, out: Path) -> dict:
    sc = load_scenario(scenario)
    ref = simulate(sc)
    got = TimeSeries.load(str(out / "timeseries.npz"))
    for f in TimeSeries.FIELDS:
        a, b = getattr(ref.series, f), getattr(got, f)
        assert a.shape == b.shape, f
        assert not np.any(np.isnan(b)), f"{f}: the swarm run left gaps"
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-9, err_msg=f"{f} differs from the in-process simulator")
    # what the plant model records (the built-in: thrust, torque, rotor thrusts), bit for bit (issue 43)
    assert list(got.plant) == list(ref.series.plant) == ["thrust", "torque", "rotor_thrust"]
    for name, a in ref.series.plant.items():
        assert not np.any(np.isnan(got.plant[name])), f"plant.{name}: the swarm run left gaps"
        assert got.plant[name].tobytes() == a.tobytes(), f"plant.{name} differs from the in-process simulator"
    res = read_results(out)
    for k in FLIGHT_FIELDS:  # bit for bit: the verdict of the same flight, figures and failures
        assert res[k] == ref.results[k], k
    return res


@pytest.mark.parametrize("example", ["paper_example1", "paper_example2"])
def test_lockstep_swarm_equals_in_process_simulator(example: str, tmp_path: Path) -> None:
    """Lockstep: leader, references and UAV states equal the simulator's within 1e-9; same JSON."""
    scenario = SCENARIOS / f"{example}.toml"
    out = tmp_path / "out"
    cp = _up(scenario, out, unique_swarm())
    assert cp.returncode == 0, cp.stdout[-3000:]
    res = _assert_equal_to_sim(scenario, out)
    assert res["success"] and res["goal_reached"] and res["min_obstacle_clearance_m"] > 0
    # contract: every live agent subscribed to exactly its graph row
    sc = load_scenario(scenario)
    keys = wire.Keys("x")
    for i in range(1, sc.n + 1):
        row = AgentRow.from_scenario(sc, i - 1, 0.027, 9.81)
        want = sorted(k.replace("swarm/x/", "") for k, _ in subscriptions(keys, row))
        live = res["diagnostics"][f"agent:{i}"]["subscriptions"].split(",")
        assert sorted(k.split("/", 2)[2] for k in live) == want
    # every swarm process ran zenoh on one thread (bus.use_swarm_runtime, set by the supervisor)
    for name in ["plant", "leader"] + [f"agent:{i}" for i in range(1, sc.n + 1)]:
        threads = res["diagnostics"][name]["zenoh_threads"].split(",")
        assert threads and all(t.startswith("app-") for t in threads), (name, threads)
    # ... and the router kept its sending thread apart (bus.ZENOH_RUNTIME_ROUTER)
    router = {t.split("-")[0] for t in res["supervisor_zenoh_threads"].split(",")}
    assert router == {"app", "tx"}, res["supervisor_zenoh_threads"]


def test_lockstep_swarm_equals_simulator_on_a_sparse_graph(tmp_path: Path) -> None:
    """A scenario whose [graph] is an edge list with weights (issue 42): every process builds its
    row from it, and the lockstep swarm equals the in-process simulator (vectorised generator)."""
    from zenswarm.scenario.config import scenario_from_dict
    from zenswarm.scenario.generate import generate_scenario, to_toml

    d = generate_scenario(6, topology="knn", k=2, pinning="random", n_obstacles=1, seed=4, time_limit_s=4.0)
    graph = scenario_from_dict(d).comm_graph
    weights = [0.5, 1.0, 1.5, 2.0]
    d["graph"] = {
        "edges": [[i, j, weights[x % 4]] for x, (i, j, _) in enumerate(graph.edge_list())],
        "pinning": [1.5 * b for b in d["graph"]["pinning"]],
    }
    p = tmp_path / "sparse.toml"
    p.write_text(to_toml(d))
    out = tmp_path / "out"
    cp = _up(p, out, unique_swarm())
    assert cp.returncode in (0, 1), cp.stdout[-3000:]  # 4 s cannot reach the goal
    _assert_equal_to_sim(p, out)


def test_agent_subscriptions_follow_the_graph(tmp_path: Path) -> None:
    """Contract: subscriptions are the graph row; a different graph gives different ones (live)."""
    import tomllib

    from zenswarm.scenario.generate import to_toml

    d = tomllib.loads((SCENARIOS / "paper_example1.toml").read_text())
    d["timing"].update(time_limit_s=0.5)
    d["graph"] = {"adjacency": [[0, 1, 0], [1, 0, 1], [0, 1, 0]], "pinning": [0.0, 0.0, 1.0]}
    p = tmp_path / "line.toml"
    p.write_text(to_toml(d))
    sc = load_scenario(p)
    keys = wire.Keys("s")
    expected = {
        1: {"uav/1/state", "uav/2/ref"},
        2: {"uav/2/state", "uav/1/ref", "uav/3/ref"},
        3: {"uav/3/state", "uav/2/ref", "leader/ref"},
    }
    for i, want in expected.items():
        row = AgentRow.from_scenario(sc, i - 1, 0.027, 9.81)
        assert {k.replace("swarm/s/", "") for k, _ in subscriptions(keys, row)} == want
    out = tmp_path / "out"
    cp = _up(p, out, unique_swarm())
    assert cp.returncode in (0, 1), cp.stdout[-3000:]  # 0.5 s cannot reach the goal: exit 1 is fine
    diag = read_results(out)["diagnostics"]
    for i, want in expected.items():
        live = {k.split("/", 2)[2] for k in diag[f"agent:{i}"]["subscriptions"].split(",")}
        assert live == want, f"agent:{i}"


def test_process_killed_at_start_fails_naming_it(tmp_path: Path) -> None:
    scenario = scenario_variant(tmp_path, time_limit_s=5.0)
    cp = _up(scenario, tmp_path / "out", unique_swarm(), "--kill", "agent:2@0s", "--lockstep-timeout", "30")
    assert cp.returncode == 3, cp.stdout[-3000:]
    assert "process agent:2 died (killed by SIGKILL)" in cp.stdout
    res = read_results(tmp_path / "out")
    assert res["success"] is False
    assert [(f["cause"], f.get("process")) for f in res["failures"]] == [("process_died", "agent:2")], res["failures"]


def test_ctrl_c_leaves_no_process_behind(tmp_path: Path) -> None:
    swarm = unique_swarm()
    port = free_port()
    out = tmp_path / "out"
    p = start_zenswarm(
        "up", str(SCENARIOS / "paper_example1.toml"), "--out", str(out), "--swarm", swarm,
        "--listen", f"tcp/127.0.0.1:{port}", "--progress-every", "0.2", "--quiet-children",
    )
    try:
        deadline = time.monotonic() + 60
        seen_progress = False
        assert p.stdout is not None
        for line in p.stdout:
            if "t=" in line and "leader->goal" in line and " 0.00/" not in line:
                seen_progress = True
                break
            if time.monotonic() > deadline:
                break
        assert seen_progress, "the swarm never started flying"
        assert len(processes_mentioning(f"--swarm {swarm}")) >= 5
        p.send_signal(signal.SIGINT)
        rest, _ = p.communicate(timeout=30)
        assert p.returncode == 130, rest[-2000:]
        assert "stopping: received SIGINT" in rest
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        leftovers = processes_mentioning(f"--swarm {swarm}")
        kill_mentioning(f"--swarm {swarm}")
    assert not leftovers, f"processes left behind: {leftovers}"
    assert wait_port_free(port), "router port still bound"
    res = read_results(out)  # what was flown is still written
    assert res["success"] is False and res["sim_time_s"] > 0
    assert [f["cause"] for f in res["failures"]] == ["interrupted"], res["failures"]


def test_two_swarms_side_by_side_no_crosstalk(tmp_path: Path) -> None:
    """Two swarms on linked routers (so traffic could cross) both equal the simulator exactly."""
    scenario = scenario_variant(tmp_path, time_limit_s=4.0, settle_time_s=1.0)
    a, b = unique_swarm("a"), unique_swarm("b")
    pa, pb = free_port(), free_port()
    outa, outb = tmp_path / "a", tmp_path / "b"
    common = ("--quiet-children", "--quiet")
    procs = [
        start_zenswarm("up", str(scenario), "--out", str(outa), "--swarm", a, "--listen", f"tcp/127.0.0.1:{pa}", *common),
        start_zenswarm(
            "up", str(scenario), "--out", str(outb), "--swarm", b, "--listen", f"tcp/127.0.0.1:{pb}",
            "--router-connect", f"tcp/127.0.0.1:{pa}", *common,
        ),
    ]
    try:
        outs = [p.communicate(timeout=300)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
        leftovers = processes_mentioning(f"--swarm {a}") + processes_mentioning(f"--swarm {b}")
        kill_mentioning(f"--swarm {a}")
        kill_mentioning(f"--swarm {b}")
    assert not leftovers
    for p, o in zip(procs, outs):
        assert p.returncode in (0, 1), o[-2000:]
    for out in (outa, outb):
        _assert_equal_to_sim(scenario, out)
        res = read_results(out)
        # each supervisor counted only its own swarm's traffic
        assert res["decoder_rejects"]["rejected"] == 0


def test_realtime_example1_reaches_goal(tmp_path: Path) -> None:
    """--realtime: fixed-rate loops on the wall clock, latest value wins; goal, no collision."""
    out = tmp_path / "out"
    cp = _up(SCENARIOS / "paper_example1.toml", out, unique_swarm(), "--realtime", "--stop-at-goal", timeout=200)
    assert cp.returncode == 0, cp.stdout[-3000:]
    res = read_results(out)
    assert res["goal_reached"] and res["success"]
    assert res["min_obstacle_clearance_m"] > 0 and res["min_inter_uav_distance_m"] > 0.05
    assert res["rms_tracking_error_m"] < 0.05
    # each process reported its loop timing
    for name in ("plant", "leader", "agent:1"):
        assert "missed_deadlines" in res["diagnostics"][name], name
    json.dumps(res)


def test_agent_joins_from_elsewhere_and_fetches_the_mission(tmp_path: Path) -> None:
    """`--external agent:3`: agent 3 is started by hand, as on another host, with no scenario file:
    it fetches the mission from the leader's queryable; the run still equals the simulator."""
    scenario = scenario_variant(tmp_path, time_limit_s=3.0, settle_time_s=1.0)
    swarm = unique_swarm("x")
    port = free_port()
    out = tmp_path / "out"
    sup = start_zenswarm(
        "up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
        "--external", "agent:3", "--quiet",
    )
    agent = start_zenswarm("agent", "--id", "3", "--swarm", swarm, "--connect", f"tcp/127.0.0.1:{port}")
    try:
        a_out = agent.communicate(timeout=120)[0]
        s_out = sup.communicate(timeout=120)[0]
    finally:
        for p in (sup, agent):
            if p.poll() is None:
                p.kill()
                p.wait()
        leftovers = processes_mentioning(f"--swarm {swarm}")
        kill_mentioning(f"--swarm {swarm}")
    assert not leftovers
    assert agent.returncode == 0, a_out[-2000:]
    assert sup.returncode in (0, 1), s_out[-2000:]
    _assert_equal_to_sim(scenario, out)


def test_record_and_report_match_the_run(tmp_path: Path) -> None:
    """`--record --report`: the report, from the MCAP alone, gives the run's own results; every
    agent's recorded commands are reproduced bit for bit by `zenswarm verify`."""
    scenario = scenario_variant(tmp_path, time_limit_s=4.0, settle_time_s=1.0)
    out = tmp_path / "out"
    rec = tmp_path / "flight.mcap"
    cp = _up(scenario, out, unique_swarm("r"), "--record", str(rec), "--report")
    assert cp.returncode in (0, 1), cp.stdout[-3000:]
    run = read_results(out)
    rep = json.loads((out / "report" / "results.json").read_text())
    for k in FLIGHT_FIELDS:
        assert rep[k] == run[k], k
    for png in (
        "trajectories_3d.png",
        "formation_errors.png",
        "formation_errors_vehicles.png",
        "tracking_errors.png",
        "clearance.png",
        "links.png",
    ):
        assert (out / "report" / png).stat().st_size > 10_000, png
    v = zenswarm("verify", str(rec), "--agent", "all", timeout=120)
    assert v.returncode == 0, v.stdout
    assert v.stdout.count("verified 400 ticks") == 3, v.stdout
    # the plant model's records are in the recording (issue 43): each state message's "x", read
    # back with the mcap library, is the run's plant.<name> series of that tick and UAV
    from mcap.reader import make_reader

    ts = TimeSeries.load(str(out / "timeseries.npz"))
    seen = 0
    with rec.open("rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages():
            parts = channel.topic.split("/")
            if parts[-1] != "state":
                continue
            d = msgpack.unpackb(message.data)
            k, i = round(d["t"] / 1e7), int(parts[-2]) - 1
            assert list(d["x"]) == ["thrust", "torque", "rotor_thrust"], d
            if k >= len(ts.t):
                continue  # the final state (t = time limit) is past the series' last tick
            for name, vals in d["x"].items():
                assert np.array(vals).tobytes() == ts.plant[name][k, i].tobytes(), (name, k, i)
            seen += 1
    assert seen == 3 * len(ts.t) == 3 * 400, seen
    assert (out / "report" / "plant.png").stat().st_size > 10_000
    info = zenswarm("info", str(rec), timeout=60)
    assert "plant:      records thrust [() N], torque [(3,) N m], rotor_thrust [(4,) N]" in info.stdout, info.stdout


def test_console_says_each_thing_once(tmp_path: Path) -> None:
    """A realtime flight, recorded, with a progress line asked every 0.2 s (issue 43): the start-up
    (processes starting, sim time 0) gives one ``t=  0.00`` line, not one per interval (again
    only after 10 s of the same sim time); the recorder's closing line is printed once; no
    ``joined at tick`` for agents that started with the flight (only a late join says it)."""
    out, rec = tmp_path / "out", tmp_path / "f.mcap"
    scen = scenario_variant(tmp_path, time_limit_s=2.0)
    cp = _up(scen, out, unique_swarm("once"), "--realtime", "--record", str(rec), "--progress-every", "0.2", timeout=200)
    assert cp.returncode in (0, 1), cp.stdout[-3000:]
    lines = cp.stdout.splitlines()
    zero = [ln for ln in lines if "t=  0.00/" in ln]
    assert 1 <= len(zero) <= 2, "\n".join(zero)  # 2: a start-up of more than 10 s on a starved machine
    closing = [ln for ln in lines if "messages on" in ln and str(rec) in ln]
    assert len(closing) == 1, "\n".join(closing)
    assert not [ln for ln in lines if "joined at tick" in ln], cp.stdout[-3000:]

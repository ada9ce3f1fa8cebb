"""Issue 15 items 1-3: the plug-in interfaces, their selection, and one tick everywhere.

Cheap pure tests of the registry and of the paper's scheme behind the interfaces (the simulator's
stacked fast path equals the per-agent plug-in path; the planner shell equals the AAPF functions),
bad names and params (exit 2), and one short lockstep swarm flight of test-only plug-ins
(tests/plugin_fixtures.py: a controller sharing an extra quantity, a planner) with link faults,
bit for bit equal to the simulator, and verified from its recording.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from zenswarm.compose import sim
from zenswarm.errors import ScenarioError
from zenswarm.judge.metrics import FLIGHT_FIELDS, TimeSeries
from zenswarm.leader.aapf import AapfParams, integrate_leader, total_force
from zenswarm.leader.core import LeaderCore
from zenswarm.link.swarm import plan_for
from zenswarm.scenario.config import load_scenario
from zenswarm.scenario.plugins import PluginError, available, check_selection, resolve, select

from swarmtest import SCENARIOS, read_results, scenario_variant, unique_swarm, zenswarm

EX1 = SCENARIOS / "paper_example1.toml"
TESTS = Path(__file__).parent
CTRL = "plugin_fixtures:ConsensusController"
PLAN = "plugin_fixtures:LinePlanner"


def test_builtins_listed_and_resolved() -> None:
    assert [p.name for p in available("controller")] == ["paper"]
    assert [p.name for p in available("planner")] == ["aapf", "apf", "escape"]
    assert resolve("planner", "apf").adaptive is False


def test_bad_names_and_params_are_typed_errors() -> None:
    sc = load_scenario(EX1)
    with pytest.raises(PluginError, match="nosuch") as e:
        check_selection(select(sc, controller="nosuch"))
    assert e.value.field == "agents.controller" and "zenswarm.controllers" in e.value.message
    with pytest.raises(PluginError, match="no_module_xyz"):
        check_selection(select(sc, planner="no_module_xyz:Planner"))
    from msgspec.structs import replace as rt

    with pytest.raises(ScenarioError) as e2:
        check_selection(replace(sc, leader=rt(sc.leader, params={"k_bogus": 1.0})))
    assert "leader.params" in str(e2.value) and "k_bogus" in str(e2.value)
    with pytest.raises(ScenarioError, match="leader.adaptive"):
        check_selection(replace(sc, leader=rt(sc.leader, planner="aapf", adaptive=False)))


@pytest.mark.swarm  # CLI subprocesses
def test_cli_bad_name_and_param_exit_2(tmp_path: Path) -> None:
    cp = zenswarm("sim", str(EX1), "--out", str(tmp_path / "o"), "--controller", "nosuch")
    assert cp.returncode == 2 and "nosuch" in cp.stdout and "--controller: no controller named" in cp.stdout  # the flag it came from
    bad = tmp_path / "bad.toml"
    bad.write_text(EX1.read_text() + "\n[agents.params]\nk_bogus = 1\n")
    cp = zenswarm("up", str(bad), "--out", str(tmp_path / "u"))
    assert cp.returncode == 2 and "agents.params" in cp.stdout and "k_bogus" in cp.stdout, cp.stdout[-2000:]
    assert not (tmp_path / "u").exists()


@pytest.mark.slow  # ~2 s of simulated ticks
def test_paper_stacked_equals_per_agent_plugin_path() -> None:
    """The simulator's fast path (StackedAgents) and the generic per-agent controller path give
    the same bits for the paper's controller (100 ticks of example 1)."""
    sc = load_scenario(EX1)
    series = []
    for stacked in (True, False):
        sw = sim._Swarm(sc, None)
        if not stacked:
            sw.stacked = None
        ts = TimeSeries.allocate(100, sc.n)
        for k in range(100):
            sw.tick(k, ts)
        series.append(ts)
    for f in TimeSeries.FIELDS:
        assert getattr(series[0], f).tobytes() == getattr(series[1], f).tobytes(), f


def test_planner_shell_equals_aapf_functions() -> None:
    sc = load_scenario(EX1)
    core, p = LeaderCore.from_scenario(sc), AapfParams.from_scenario(sc)
    q = np.asarray(sc.leader.start, dtype=float)
    for _ in range(300):
        q0, v0 = core.ref()
        assert q0.tobytes() == q.tobytes() and v0.tobytes() == total_force(q, p).tobytes()
        core.advance()
        q, _info = integrate_leader(q, sc.timing.dt, p, sc.timing.substeps)


@pytest.mark.swarm
def test_plugins_fly_sim_equal_lockstep_up_with_faults(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Test-only controller (sharing an extra quantity) and planner, 3 s, 20 % loss + 30 ms delay:
    the lockstep swarm equals the simulator bit for bit; `verify` recomputes agent 2 from the
    recording (extras included)."""
    from test_swarm import _up

    monkeypatch.syspath_prepend(str(TESTS))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
    scen = scenario_variant(tmp_path, time_limit_s=3.0)
    out, rec = tmp_path / "out", tmp_path / "rec.mcap"
    faults = ("--link-loss", "0.2", "--link-delay", "30ms", "--seed", "5")
    cp = _up(scen, out, unique_swarm("pl"), "--controller", CTRL, "--planner", PLAN, "--record", str(rec), *faults, "--full-time")
    assert cp.returncode in (0, 1), cp.stdout[-3000:]
    sc = replace(select(load_scenario(scen), CTRL, PLAN), seed=5)
    ref = sim.simulate(sc, faults=plan_for(sc, seed=5, link_loss="0.2", link_delay="30ms"), full_time=True)
    got = TimeSeries.load(str(out / "timeseries.npz"))
    for f in TimeSeries.FIELDS:
        np.testing.assert_array_equal(getattr(got, f), getattr(ref.series, f), err_msg=f"{f}: swarm != simulator")
    res = read_results(out)
    for k in FLIGHT_FIELDS:
        assert res[k] == ref.results[k], k
    assert ref.results["link_counters"]  # the faults did act
    cp = zenswarm("verify", str(rec), "--agent", "2")
    assert cp.returncode == 0, cp.stdout[-2000:]

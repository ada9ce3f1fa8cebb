"""The public API (zenswarm.api) and the pytest plugin (zenswarm.pytest_plugin): typed results,
overrides validated and named, the swarm equal to the simulator, nothing left behind."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest
from msgspec.structs import replace as replace_table

from zenswarm import api
from zenswarm.compose.sim import simulate
from zenswarm.errors import ScenarioError
from zenswarm.link.swarm import plan_for
from zenswarm.scenario.config import load_scenario

from swarmtest import SCENARIOS

pytest_plugins = ["pytester"]

EX1 = SCENARIOS / "paper_example1.toml"


# ----------------------------------------------------------------------------- pure


def test_overrides_reach_the_scenario_by_dotted_path() -> None:
    sc, doc = api.load("paper_example1", {"timing.time_limit_s": 3.0, "obstacles[1].radius": 0.05, "leader.goal": (2.0, 1.0, 0.6),
                                          "restart.initial_delay_s": 0.5})
    assert sc.timing.time_limit_s == 3.0 and sc.obstacles[1].radius == 0.05 and sc.leader.goal == (2.0, 1.0, 0.6)
    assert sc.restart is not None and sc.restart.initial_delay_s == 0.5  # a table the file has not: created
    assert doc["timing"]["time_limit_s"] == 3.0
    assert load_scenario(EX1).timing.time_limit_s == 70.0  # the file is untouched


@pytest.mark.parametrize(
    ("overrides", "field", "override", "needle"),
    [
        ({"timing.time_limit_sec": 3.0}, "timing.time_limit_sec", "timing.time_limit_sec", "unknown key"),
        ({"timng.time_limit_s": 3.0}, "timng", "timng.time_limit_s", "unknown key"),
        ({"timing.time_limit_s": "soon"}, "timing.time_limit_s", "timing.time_limit_s", "expected a number"),
        ({"timing.time_limit_s": -1.0}, "timing.time_limit_s", "timing.time_limit_s", ""),
        ({"obstacles[7].radius": 0.1}, "obstacles[7]", "obstacles[7].radius", "no element 7"),
        ({"timing..x": 1}, "timing..x", "timing..x", "dotted path"),
        ({"leader.k_rep_min": 0.5}, "leader.k_rep_max", "leader.k_rep_min", "k_rep_min"),
    ],
)
def test_bad_override_is_a_typed_error_naming_it(overrides: dict, field: str, override: str, needle: str) -> None:
    with pytest.raises(api.OverrideError) as e:
        api.fly("paper_example1", overrides=overrides)
    assert e.value.field == field and e.value.override == override, (e.value.field, e.value.override)
    assert needle in str(e.value)
    assert isinstance(e.value, ScenarioError)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"mode": "cloud"}, "mode"),
        ({"link_loss": 1.5}, "--link-loss"),
        ({"link_delay": -0.05}, "link_delay"),
        ({"link_delay": "50 parsecs"}, "--link-delay"),
        ({"kill": [("agent:2", 1.0)]}, "kill"),
        ({"restart": True}, "restart"),
        ({"mode": "swarm", "kill": ["agent:9@1s"]}, "--kill"),
        ({"mode": "swarm", "kill": [("plane", 1.0)]}, "kill"),
    ],
)
def test_bad_arguments_are_refused_before_anything_flies(kwargs: dict, field: str) -> None:
    with pytest.raises(ScenarioError) as e:
        api.fly("paper_example1", duration=0.5, **kwargs)
    assert e.value.field == field, e.value


def test_unknown_scenario_names_the_built_in_ones(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="paper_example1, paper_example2"):
        api.fly("paper_example9")
    with pytest.raises(ScenarioError, match="not found"):
        api.fly(tmp_path / "none.toml")
    assert api.scenario_path("paper_example2").name == "paper_example2.toml"


# ----------------------------------------------------------------------------- in process


@pytest.mark.slow
def test_sim_flight_is_the_simulator_s_with_typed_results(tmp_path: Path) -> None:
    """fly(mode="sim") is zenswarm sim: the same series and verdict; written to out when asked."""
    f = api.fly(EX1, duration=2.0, seed=7, link_loss=0.2, link_delay=0.05, out=tmp_path / "o")
    base = load_scenario(EX1)
    sc = replace(base, timing=replace_table(base.timing, time_limit_s=2.0), seed=7)
    ref = simulate(sc, faults=plan_for(sc, link_loss="0.2", link_delay="50ms"))
    assert api.differences(f, api._flight("sim", sc, ref.results, ref.series, 1, None)) == []
    assert f.series.q.shape == (200, 3, 3) and f.series.thrust.shape == (200, 3)
    assert not f.success and f.exit_code == 1 and "timeout" in f.causes  # 2 s cannot reach the goal
    assert f.failure("timeout") is not None and f.failures_other_than("timeout", "off_slot") == ()
    assert f.metrics.sim_time_s == 2.0 and f.metrics.min_obstacle_clearance_m is not None
    assert (tmp_path / "o" / "results.json").is_file() and (tmp_path / "o" / "timeseries.npz").is_file()
    assert "FAILED: timeout" in f.summary


def test_differences_name_the_field_and_the_first_tick() -> None:
    a = api.fly("paper_example1", duration=0.5)
    series = replace(a.series, q=a.series.q.copy())
    series.q[20, 1, 2] += 1e-12
    b = replace(a, series=series, results={**a.results, "min_altitude_m": 0.0})
    got = api.differences(a, b)
    assert got[0].startswith("series.q: 1 values differ, first at tick 20") and got[1].startswith("results.min_altitude_m")
    assert "UAV 2)" in got[0], got[0]  # the field, the tick and the UAV
    assert api.differences(a, a) == []


# ----------------------------------------------------------------------------- processes


@pytest.mark.swarm
def test_swarm_flight_takes_its_output_paths_as_text(tmp_path: Path) -> None:
    """``out`` and ``record`` given as str, as a script writes them (once a TypeError after the flight)."""
    out, rec = tmp_path / "o", tmp_path / "f.mcap"
    f = api.fly("paper_example1", mode="swarm", duration=0.5, out=str(out), record=str(rec))
    assert f.out == out and (out / "results.json").is_file() and rec.is_file(), f.log[-2000:]
    assert f.metrics.sim_time_s == 0.5
    # no port given: the supervisor chose a free one, said in results.json and on the flight
    assert f.results["router"] == [f"tcp/127.0.0.1:{f.port}"] and f.port is not None and f.port > 0, f.results.get("router")


@pytest.mark.swarm
def test_swarm_flight_equals_the_sim_flight_and_leaves_nothing(zenswarm_fly) -> None:
    """The fixture flies the lockstep swarm (unique name, a free port its supervisor chose) under loss and delay; the
    flight is the simulator's bit for bit; at teardown nothing of it is left (the fixture checks)."""
    kw = dict(duration=2.0, seed=3, link_loss="20%", link_delay="50ms")
    swarm = zenswarm_fly("paper_example1", mode="swarm", **kw)
    sim = zenswarm_fly("paper_example1", **kw)
    assert api.differences(sim, swarm) == []
    assert swarm.mode == "swarm" and swarm.exit_code == 1 and swarm.leftovers == ()
    assert swarm.out is not None and (swarm.out / "results.json").is_file()
    assert swarm.diagnostics["agent:1"]["link:agent:2->agent:1:ref.dropped"] > 0
    assert swarm.swarm is not None and api.processes_of(swarm.swarm) == []
    assert swarm.port is not None and swarm.results["router"] == [f"tcp/127.0.0.1:{swarm.port}"]


@pytest.mark.swarm
def test_swarm_timeout_stops_every_process(tmp_path: Path) -> None:
    """A flight over its wall-time bound is stopped (its process group), raises FlightError, and
    no process of its swarm survives."""
    name = api.unique_swarm_name("to")
    with pytest.raises(api.FlightError, match="more than 2.5 s"):
        api.fly("paper_example1", mode="swarm", swarm=name, timeout=2.5)
    assert api.processes_of(name) == []


@pytest.mark.swarm
def test_fixture_fails_a_test_that_leaves_a_process_behind(pytester: pytest.Pytester) -> None:
    """A process still carrying the test's swarm name at teardown is killed and fails the test."""
    pytester.makepyfile(
        f"""
        import subprocess, sys

        def test_leaks(zenswarm_swarm):
            subprocess.Popen([{sys.executable!r}, "-c", "import time; time.sleep(60)", "--swarm", zenswarm_swarm])
        """
    )
    r = pytester.runpytest("-p", "no:cacheprovider")
    r.assert_outcomes(passed=1, errors=1)
    r.stdout.fnmatch_lines(["*process left behind and killed*--swarm pt*"])


def test_plugin_is_registered_by_entry_point() -> None:
    from importlib.metadata import entry_points

    assert [ep.value for ep in entry_points(group="pytest11") if ep.name == "zenswarm"] == ["zenswarm.pytest_plugin"]

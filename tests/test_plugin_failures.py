"""The sim == swarm contract for plug-ins that misbehave (issue 27): an exception, a non-finite or
a wrongly shaped output of a controller or a planner is the named failure ``plugin_error`` (the
plug-in, its process and UAV, the tick, the call, the exception or the bad field) at the sim time
it happened; the run ends there, results are written, and the exit status is 4, the same in
``zenswarm sim``, the lockstep ``zenswarm up`` and ``api.fly``; the two modes judge the same
flight bit for bit. The plug-ins are tests/plugin_fixtures.py's ``Misbehaving*``."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from zenswarm import api
from zenswarm.compose.sim import summary_line
from zenswarm.errors import EXIT_PLUGIN_FAILED

from swarmtest import SCENARIOS, zenswarm

TESTS = Path(__file__).parent
CTRL = "plugin_fixtures:MisbehavingController"
PLAN = "plugin_fixtures:MisbehavingPlanner"
DT = 0.01  # paper example 1: 100 Hz control


@pytest.fixture
def on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """tests/ importable here and in the swarm's processes (the fixtures' plug-ins)."""
    monkeypatch.syspath_prepend(str(TESTS))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))


def _fly(mode: str, kind: str, params: dict[str, Any], **kw: Any) -> api.Flight:
    name, table = (CTRL, "agents") if kind == "controller" else (PLAN, "leader")
    ov = {f"{table}.params.{k}": v for k, v in params.items()}
    pick = {"controller": name} if kind == "controller" else {"planner": name}
    return api.fly("paper_example1", mode=mode, duration=1.0, overrides=ov, **pick, **kw)  # type: ignore[arg-type]


def _named(f: api.Flight) -> list[dict[str, Any]]:
    return [x for x in f.results["failures"] if x["cause"] == "plugin_error"]


# (kind, params, expected: (process, uavs, tick, call, field, text in the detail) of each failure)
CASES = {
    "raise": ("controller", {"how": "raise", "tick": 50, "uav": 2},
              [("agent:2", [2], 50, "finish", None, "RuntimeError: misbehaving controller: deliberate error at tick 50")]),
    "nan-thrust": ("controller", {"how": "nan", "tick": 37, "uav": 3},
                   [("agent:3", [3], 37, "finish", "thrust", "thrust: nan is not finite")]),
    "wrong-shape": ("controller", {"how": "shape", "tick": 20, "uav": 1},
                    [("agent:1", [1], 20, "finish", "rpy", "rpy: shape (2,) != (3,)")]),
    "share-inf": ("controller", {"how": "share", "tick": 30, "uav": 2}, [("agent:2", [2], 30, "share", "v", "is not finite")]),
    "every-uav": ("controller", {"how": "raise", "tick": 25, "uav": 0},
                  [(f"agent:{i}", [i], 25, "finish", None, "deliberate error at tick 25") for i in (1, 2, 3)]),
    "constructor": ("controller", {"how": "init", "uav": 3}, [("agent:3", [3], 0, "__init__", None, "ValueError: misbehaving controller")]),
    # not Exceptions: a plug-in that exits or unwinds is as failed as one that raises (issue 43)
    "sys-exit": ("controller", {"how": "exit", "tick": 45, "uav": 2}, [("agent:2", [2], 45, "finish", None, "raised SystemExit: 3")]),
    "generator-exit": ("controller", {"how": "generator-exit", "tick": 15, "uav": 1},
                       [("agent:1", [1], 15, "finish", None, "raised GeneratorExit: misbehaving controller")]),
    "base-exception": ("controller", {"how": "base", "tick": 33, "uav": 3},
                       [("agent:3", [3], 33, "finish", None, "raised PluginAbort: misbehaving controller")]),
    "planner-nan": ("planner", {"how": "nan", "tick": 40}, [("leader", [], 40, "ref", "q0", "q0: [nan nan nan] is not finite")]),
    "planner-raise": ("planner", {"how": "raise", "tick": 60},
                      [("leader", [], 60, "advance", None, "ZeroDivisionError: misbehaving planner")]),
}


def _check_named(f: api.Flight, kind: str, expected: list[tuple]) -> None:
    got = _named(f)
    assert [(x["process"], x["uavs"], x["tick"], x["call"], x["field"]) for x in got] == [e[:5] for e in expected], got
    for x, e in zip(got, expected, strict=True):
        assert x["kind"] == kind and x["plugin"] == (CTRL if kind == "controller" else PLAN)
        assert x["t_s"] == pytest.approx(e[2] * DT, abs=1e-12), x  # the exact sim time of the failed tick
        assert e[5] in x["detail"], x["detail"]
    assert not f.success and f.exit_code == EXIT_PLUGIN_FAILED
    assert f.results["sim_time_s"] == pytest.approx(expected[0][2] * DT)  # the run ended at the failed tick
    assert len(f.series.t) == expected[0][2]  # the ticks before it, judged
    assert np.isfinite(f.series.q).all() and np.isfinite(f.series.qref).all()  # nothing non-finite reached the vehicles


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_misbehaving_plug_in_is_named_in_sim(case: str, on_path: None) -> None:
    kind, params, expected = CASES[case]
    f = _fly("sim", kind, params)
    _check_named(f, kind, expected)
    assert "plugin_error" in summary_line(f.results)


@pytest.mark.swarm
@pytest.mark.parametrize("case", sorted(CASES))
def test_the_swarm_names_the_same_failure_as_the_simulator(case: str, on_path: None) -> None:
    """The lockstep swarm: the same failures, exit status and flight, bit for bit."""
    kind, params, expected = CASES[case]
    sim, swarm = _fly("sim", kind, params), _fly("swarm", kind, params)
    _check_named(swarm, kind, expected)
    assert swarm.results["failures"] == sim.results["failures"]
    assert api.differences(sim, swarm) == []
    assert not swarm.leftovers
    assert "Traceback" not in swarm.log, swarm.log[-3000:]


@pytest.mark.swarm
def test_with_link_faults_too(on_path: None) -> None:
    """Through the links' receive boxes (20 % loss, 30 ms delay): still the same flight and failure."""
    kw = {"link_loss": 0.2, "link_delay": "30ms", "seed": 3}
    bad = {"how": "nan", "tick": 60, "uav": 1}
    sim, swarm = _fly("sim", "controller", bad, **kw), _fly("swarm", "controller", bad, **kw)
    _check_named(sim, "controller", [("agent:1", [1], 60, "finish", "thrust", "not finite")])
    assert swarm.results["failures"] == sim.results["failures"] and api.differences(sim, swarm) == []


@pytest.mark.swarm
def test_realtime_names_it_too(on_path: None) -> None:
    """Realtime: no bit equality, but the same named failure at its tick, exit 4, results written."""
    f = _fly("swarm", "controller", {"how": "raise", "tick": 30, "uav": 2}, realtime=True)
    got = _named(f)
    assert f.exit_code == EXIT_PLUGIN_FAILED and [x["process"] for x in got] == ["agent:2"], f.results["failures"]
    # its 31st step, at the sim time of the state it stepped on (realtime skips ticks: not before tick 30)
    assert got[0]["tick"] >= 30 and got[0]["t_s"] == pytest.approx(got[0]["tick"] * DT) and "at tick 30" in got[0]["detail"]
    assert f.results["sim_time_s"] <= got[0]["t_s"] + 1e-9 and len(f.series.t) > 0


@pytest.mark.swarm
def test_command_lines_exit_4_with_results_and_no_traceback(tmp_path: Path) -> None:
    """``zenswarm sim`` and ``zenswarm up``: exit 4, results.json written, the failure in the
    summary line, no traceback; --set and --duration as api.fly's overrides."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    args = [str(SCENARIOS / "paper_example1.toml"), "--controller", CTRL, "--duration", "1",
            "--set", "agents.params.how=nan", "--set", "agents.params.tick=42"]
    outs = {}
    for cmd in ("sim", "up"):
        out = tmp_path / cmd
        cp = zenswarm(cmd, *args, "--out", str(out), env=env, timeout=120)
        assert cp.returncode == EXIT_PLUGIN_FAILED, cp.stdout[-3000:]
        assert "Traceback" not in cp.stdout and "plugin_error uav 2 at 0.42 s" in cp.stdout, cp.stdout[-3000:]
        outs[cmd] = json.loads((out / "results.json").read_text())["failures"]
    assert outs["sim"] == outs["up"] and outs["sim"][0]["field"] == "thrust"


def test_sim_command_line_a_plug_in_calling_sys_exit_is_plugin_error(tmp_path: Path) -> None:
    """``zenswarm sim`` with a controller that calls ``sys.exit(3)`` in its step: not exit 3 with
    nothing written, but the plug-in's failure, named (UAV, tick, cause), exit 4, results written."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "sim"
    cp = zenswarm("sim", str(SCENARIOS / "paper_example1.toml"), "--controller", CTRL, "--duration", "1",
                  "--set", "agents.params.how=exit", "--set", "agents.params.tick=12", "--out", str(out), env=env, timeout=120)
    assert cp.returncode == EXIT_PLUGIN_FAILED, cp.stdout[-3000:]
    assert "Traceback" not in cp.stdout and "plugin_error uav 2 at 0.12 s" in cp.stdout, cp.stdout[-3000:]
    (f,) = json.loads((out / "results.json").read_text())["failures"]
    assert (f["cause"], f["uavs"], f["tick"]) == ("plugin_error", [2], 12) and "raised SystemExit: 3" in f["detail"], f


def test_badly_tuned_built_in_gains_are_bad_input_or_a_divergence_not_a_plugin_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """ESO gains the discrete observer cannot follow at the control rate are bad input (exit 2
    naming eso.beta, nothing flown, no numpy warning); gains inside that bound that still fly
    badly are judged as the flight they give (here: a UAV diverges), never as a failure of the
    built-in controller ``paper``."""
    import warnings

    from zenswarm.agents.eso import bandwidth_gains
    from zenswarm.compose.cli import main

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy overflow warning would fail the test
        rc = main(["sim", str(SCENARIOS / "paper_example1.toml"), "--set", "eso.beta=[1e6,1e12,1e18]", "--out", "/nonexistent/x"])
        err = capsys.readouterr().err
        assert rc == 2 and "eso.beta" in err and "200 rad/s" in err, err
        f = api.fly("paper_example1", mode="sim", duration=2.0, overrides={"eso.beta": list(bandwidth_gains(199.0))})
    causes = {x["cause"] for x in f.results["failures"]}
    assert "uav_diverged" in causes and "plugin_error" not in causes and f.exit_code == 1, f.results["failures"]


def test_scenario_check_validates_plug_in_parameters_as_a_flight(tmp_path: Path, on_path: None) -> None:
    """`scenario check` refuses what `sim` refuses: an unknown or bad plug-in parameter, exit 2
    naming the field, before anything is flown."""
    from zenswarm.compose.cli import main

    text = (SCENARIOS / "paper_example1.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text + "\n[agents.params]\nk2 = -1.0\n")
    for argv in (["scenario", "check", str(bad)], ["sim", str(bad), "--out", str(tmp_path / "o")]):
        assert main(argv) == 2
    assert not (tmp_path / "o").exists()
    assert main(["scenario", "check", str(SCENARIOS / "paper_example1.toml"), "--planner", "escape", "--set", "leader.params.sides=2"]) == 2
    assert main(["scenario", "check", str(SCENARIOS / "paper_example1.toml"), "--planner", "escape", "--set", "leader.params.sides=8"]) == 0


def test_every_override_error_is_an_override_error(on_path: None) -> None:
    with pytest.raises(api.OverrideError) as e:
        api.fly("paper_example1", overrides={"agents.params.k9": 0.2}, duration=0.1)
    assert e.value.override == "agents.params.k9" and e.value.field == "agents.params.k9"
    with pytest.raises(api.OverrideError) as e:
        api.fly("paper_example1", controller=CTRL, overrides={"agents.params.tick": "soon"}, duration=0.1)
    assert e.value.override == "agents.params.tick"


def test_unknown_names_say_did_you_mean_and_the_flag(capsys: pytest.CaptureFixture[str]) -> None:
    from zenswarm.compose.cli import main

    ex1 = str(SCENARIOS / "paper_example1.toml")
    assert main(["sim", ex1, "--planner", "escpae", "--out", "/nonexistent/never"]) == 2
    err = capsys.readouterr().err
    assert "--planner: no planner named 'escpae'; did you mean 'escape'?" in err, err
    assert main(["scenario", "check", ex1, "--controller", "aapf"]) == 2
    err = capsys.readouterr().err
    assert "--controller" in err and "'aapf' (a planner)" in err, err


def test_formation_error_is_a_time_series_whose_late_maximum_is_the_verdict_s() -> None:
    f = api.fly("paper_example1", duration=3.0, overrides={"timing.settle_time_s": 1.0})
    e = f.formation_error
    assert e.shape == (len(f.series.t), f.scenario.n) and np.isfinite(e).all()
    late = f.series.t >= 1.0
    assert float(e[late].max()) == f.metrics.max_formation_error_m
    h = np.asarray(f.scenario.offsets)
    k, i = 123, 1  # one value by hand
    assert e[k, i] == pytest.approx(float(np.linalg.norm(f.series.q[k, i] - f.series.q0[k] - h[i])), rel=0, abs=0)

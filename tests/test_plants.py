"""Issue 28: plant models as the third plug-in kind, and RotorPy's multirotor as one.

Cheap in-process tests of the registry, the scenario's ``[plant]`` table, the built-in model
behind the interface (bit for bit the old plant step), bad input (exit 2, named, before any
work), a model that returns NaN or raises (PluginFailure naming the model, the tick and the
field; exit 4), the conformance check on broken models, and the RotorPy model's mapping of
zenswarm's thrust + attitude command (hover, roll sign, wind); then one short lockstep swarm flight
on RotorPy with link faults, bit for bit equal to the simulator and verified from its recording,
and paper example 1 flown to the goal on RotorPy.
"""

from __future__ import annotations

import sys
import time
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from msgspec.structs import replace as replace_table

from zenswarm.compose import sim
from zenswarm.compose.cli import main
from zenswarm.compose.plugcheck import check_plugin
from zenswarm.errors import ScenarioError
from zenswarm.judge.metrics import FLIGHT_FIELDS, TimeSeries
from zenswarm.link.swarm import plan_for
from zenswarm.plant.api import QuadrotorModel
from zenswarm.plant.core import PlantCore
from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.quadrotor import initial_state, step_held
from zenswarm.scenario.config import load_scenario, scenario_from_dict, scenario_to_dict
from zenswarm.scenario.generate import to_toml
from zenswarm.scenario.plugins import DEFAULTS, GROUPS, KINDS, STAGE_PLANT, available, check_selection, plant_vehicle, resolve, select
from zenswarm.vehicle.params import QuadParams

from plant_fixtures import TickCounting
from swarmtest import SCENARIOS, read_results, scenario_variant, unique_swarm, zenswarm

EX1 = SCENARIOS / "paper_example1.toml"
SC = load_scenario(EX1)

# ----------------------------------------------------------------------------- test-only models


class NanPlant(TickCounting):
    """The built-in, but UAV 2's velocity turns NaN at tick 5."""

    name = "nan"
    description = "the built-in; UAV 2's velocity is NaN from tick 5"

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Any) -> None:
        super().step(thrust, rpy, disturbance)
        if self.k > 5:
            self.state.v[1, 2] = np.nan


class SlowExitPlant(NanPlant):
    """NanPlant whose process is slow to leave after its failure, without handling signals any
    more (as late in an interpreter's exit, once Python's signal handlers are gone and zenoh's
    runtime is being torn down): a SIGTERM then kills it, and its status would be -15."""

    name = "slow-exit"
    description = "NanPlant; its process takes 2 s to exit, deaf to signals"

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Any) -> None:
        super().step(thrust, rpy, disturbance)
        if self.k == 6:  # the NaN is in: the failure is reported once this step returns
            import atexit
            import signal

            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            atexit.register(time.sleep, 2.0)


class RaisingPlant(TickCounting):
    name = "raising"
    description = "raises at tick 3"

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Any) -> None:
        if self.k == 3:
            raise ZeroDivisionError("the model's own bug")
        super().step(thrust, rpy, disturbance)


class ExitingPlant(TickCounting):
    name = "exiting"
    description = "calls sys.exit(5) at tick 4"

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Any) -> None:
        if self.k == 4:
            sys.exit(5)
        super().step(thrust, rpy, disturbance)


class ClockPlant(QuadrotorModel):
    name = "clock"
    description = "reads the clock in its step"

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Any) -> None:
        time.monotonic()
        super().step(thrust, rpy, disturbance)


# ----------------------------------------------------------------------------- registry, scenario


def test_plants_are_the_third_kind_listed_and_resolved() -> None:
    assert KINDS == ("controller", "planner", "plant") and GROUPS["plant"] == "zenswarm.plants"
    assert DEFAULTS["plant"] == "quadrotor" and SC.plant.model == "quadrotor"
    names = {p.name: p for p in available("plant")}
    assert names["quadrotor"].origin == names["rotorpy"].origin == "builtin"
    assert resolve("plant", "quadrotor") is QuadrotorModel
    assert resolve("plant", "test_plants:NanPlant") is NanPlant
    assert main(["plugins"]) == 0


def test_plant_table_in_scenarios_and_on_the_command_line() -> None:
    d = tomllib.loads(EX1.read_text())
    assert "plant" not in scenario_to_dict(SC)  # the default is not written: old recordings' scenarios unchanged
    d["plant"] = {"model": "rotorpy", "params": {"steps_per_tick": 2, "wind": [0.5, 0.0, 0.0]}}
    sc = scenario_from_dict(d)
    assert sc.plant.model == "rotorpy" and scenario_to_dict(sc)["plant"] == d["plant"]
    check_selection(sc)
    assert select(sc, plant_model="quadrotor").plant.model == "quadrotor"
    assert select(sc, plant_model="quadrotor").plant.params == d["plant"]["params"]  # the params table stays
    # the agents fly the model's vehicle: RotorPy's Crazyflie weighs 30 g, zenswarm's 27 g
    assert plant_vehicle(sc).mass == 0.03 and plant_vehicle(SC) == QuadParams.from_vehicle(SC.vehicle)


def test_scenario_check_names_the_plant_model(capsys: pytest.CaptureFixture[str]) -> None:
    """`scenario check`'s OK line names what would fly: controller, planner and plant model."""
    assert main(["scenario", "check", str(EX1)]) == 0
    assert "controller paper  planner aapf  plant model quadrotor" in capsys.readouterr().out
    assert main(["scenario", "check", str(EX1), "--plant-model", "test_plants:NanPlant"]) == 0
    assert "plant model test_plants:NanPlant" in capsys.readouterr().out


def test_the_built_in_model_is_the_old_plant_step_bit_for_bit() -> None:
    """PlantCore with the built-in model == step_held on a PlantState, with gusts and attitude noise."""
    sc = replace(SC, disturbance=replace_table(SC.disturbance, wind=(0.2, -0.1, 0.0), gust_std=0.3, attitude_std=0.5))
    core = PlantCore(sc)
    ref = initial_state(np.asarray(sc.initial_positions, dtype=float))
    p = QuadParams.from_vehicle(sc.vehicle)
    dist = DisturbanceModel(sc.disturbance, sc.n, np.random.default_rng(sc.seed))
    h, nsub = sc.timing.dt / sc.timing.substeps, sc.timing.substeps
    for k in range(60):
        f = p.hover_thrust * (1 + 0.1 * np.sin(0.1 * k + np.arange(sc.n)))
        r = 0.05 * np.cos(0.07 * k + np.arange(3 * sc.n)).reshape(sc.n, 3)
        core.hold_all(f, r, k)
        core.step(k)
        step_held(ref, f, r, p, h, nsub, dist.sampler(k * sc.timing.dt, h))
        for name in ("q", "v", "rpy", "w"):
            assert getattr(core.state, name).tobytes() == getattr(ref, name).tobytes(), (k, name)


# ----------------------------------------------------------------------------- bad input, failures


def _scenario_file(tmp: Path, plant: dict[str, Any]) -> Path:
    d = tomllib.loads(EX1.read_text())
    d["plant"] = plant
    p = tmp / "scenario.toml"
    p.write_text(to_toml(d))
    return p


@pytest.mark.parametrize(
    ("plant", "flags", "needle"),
    [
        ({}, ["--plant-model", "nosuch"], "--plant-model: no plant named 'nosuch'"),
        ({"model": "no_module_xyz:Model"}, [], "plant.model: plant 'no_module_xyz:Model': cannot load"),
        ({"model": "rotorpy", "params": {"bogus": 1}}, [], "plant.params"),
        ({"model": "rotorpy", "params": {"steps_per_tick": 3}}, [],
         "plant.params.steps_per_tick: must be >= 1 and divide timing.substeps (10)"),
        ({"params": {"tau": 1}}, [], "plant.params"),  # the built-in takes no parameters
    ],
)
def test_bad_plant_input_is_exit_2_naming_it_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], plant: dict[str, Any], flags: list[str], needle: str
) -> None:
    scen = _scenario_file(tmp_path, plant)
    for cmd in (["sim", str(scen), "--out", str(tmp_path / "sim")], ["up", str(scen), "--out", str(tmp_path / "up")]):
        assert main([*cmd, *flags]) == 2
        assert needle in capsys.readouterr().err
    assert not (tmp_path / "sim").exists() and not (tmp_path / "up").exists()


def test_mavlink_vehicles_refuse_another_plant_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["up", str(EX1), "--plant", "mavlink", "--plant-model", "rotorpy", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--plant-model: plant model 'rotorpy' cannot fly with --plant mavlink" in err


def test_rotorpy_not_installed_is_named_with_the_remedy(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rotorpy.vehicles.crazyflie_params", None)  # import fails
    with pytest.raises(ScenarioError, match=r"plant\.model: plant model 'rotorpy' needs RotorPy.*pip install 'zenswarm\[rotorpy\]'"):
        check_selection(select(SC, plant_model="rotorpy"))


def test_a_model_that_returns_nan_or_raises_is_a_named_plugin_failure(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The plug-in failure contract (issue 27) with kind plant: the run ends at the failed tick,
    the failure ``plugin_error`` names the model, the process, the tick, the field and the UAV;
    results are written and ``zenswarm sim`` exits 4."""
    res = sim.simulate(select(SC, plant_model="test_plants:NanPlant"), n_ticks=50)
    (f,) = [f for f in res.results["failures"] if f["cause"] == "plugin_error"]
    assert {k: f[k] for k in ("plugin", "kind", "process", "tick", "stage", "call", "field", "uavs")} == {
        "plugin": "test_plants:NanPlant", "kind": "plant", "process": "plant", "tick": 5, "stage": STAGE_PLANT, "call": "step",
        "field": "state.v", "uavs": [2],
    }  # fmt: skip
    assert "not finite for UAV 2" in f["detail"] and f["t_s"] == 5 * SC.timing.dt
    assert len(res.series.t) == 5 and not res.results["success"]  # the ticks before the failed one are judged
    res = sim.simulate(select(SC, plant_model="test_plants:RaisingPlant"), n_ticks=50)
    (f,) = [f for f in res.results["failures"] if f["cause"] == "plugin_error"]
    assert (f["tick"], f["call"], f["field"], f["uavs"]) == (3, "step", None, [1, 2, 3])
    assert "raised ZeroDivisionError: the model's own bug" in f["detail"]
    res = sim.simulate(select(SC, plant_model="test_plants:ExitingPlant"), n_ticks=50)  # not an Exception: the same
    (f,) = [f for f in res.results["failures"] if f["cause"] == "plugin_error"]
    assert (f["tick"], f["call"], f["uavs"]) == (4, "step", [1, 2, 3]) and "raised SystemExit: 5" in f["detail"]
    out = tmp_path / "o"
    assert main(["sim", str(EX1), "--plant-model", "test_plants:NanPlant", "--out", str(out), "--quiet"]) == 4
    assert "plugin_error" in capsys.readouterr().out
    assert read_results(out)["failures"][0]["kind"] == "plant"


@pytest.mark.swarm
def test_a_failing_plant_model_fails_the_lockstep_swarm_as_the_simulator(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`zenswarm up --plant-model test_plants:NanPlant`: exit 4, the same plugin_error and the
    same flight as the simulator, bit for bit."""
    import os

    from test_swarm import _up

    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]))
    scen = scenario_variant(tmp_path, time_limit_s=1.0)
    out = tmp_path / "out"
    cp = _up(scen, out, unique_swarm("np"), "--plant-model", "test_plants:NanPlant")
    assert cp.returncode == 4, cp.stdout[-3000:]
    ref = sim.simulate(select(load_scenario(scen), plant_model="test_plants:NanPlant"))
    got = TimeSeries.load(str(out / "timeseries.npz"))
    for name in TimeSeries.FIELDS:
        np.testing.assert_array_equal(getattr(got, name), getattr(ref.series, name), err_msg=f"{name}: swarm != simulator")
    assert list(got.plant) == list(ref.series.plant) == ["thrust", "torque", "rotor_thrust"]  # its records (issue 43)
    for name, a in ref.series.plant.items():
        np.testing.assert_array_equal(got.plant[name], a, err_msg=f"plant.{name}: swarm != simulator")
    res = read_results(out)
    for k in FLIGHT_FIELDS:
        assert res[k] == ref.results[k], k
    assert res["failures"][0]["cause"] == "plugin_error" and res["failures"][0]["kind"] == "plant"
    assert res["processes"]["plant"] == 4, res["processes"]


@pytest.mark.swarm
def test_a_failed_plant_exits_4_even_when_slow_to_leave(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After its plug-in failed, the plant leaves by itself with status 4 (docs/architecture.md);
    the supervisor stops the others and waits for it before any signal, so results.json's
    ``processes.plant`` is 4, not the SIGTERM (-15) that caught it on its way out."""
    import os

    from test_swarm import _up

    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]))
    out = tmp_path / "out"
    cp = _up(scenario_variant(tmp_path, time_limit_s=1.0), out, unique_swarm("se"), "--plant-model", "test_plants:SlowExitPlant")
    assert cp.returncode == 4, cp.stdout[-3000:]
    res = read_results(out)
    assert res["failures"][0]["kind"] == "plant" and res["processes"]["plant"] == 4, res["processes"]


@pytest.mark.parametrize(("name", "check", "needle"), [
    ("test_plants:NanPlant", "outputs", "state.v: not finite for UAV 2"),
    ("test_plants:ClockPlant", "pure ticks", "time.monotonic()"),
])
def test_plugins_check_fails_a_broken_plant_model(name: str, check: str, needle: str) -> None:
    kind, _, checks = check_plugin(name, SC, swarm=False)
    got = {c.name: f"{c.status} {c.detail}" for c in checks}
    assert kind == "plant" and got[check].startswith("FAIL") and needle in got[check], got


# ----------------------------------------------------------------------------- RotorPy's vehicle


def _rotorpy(sc: Any = SC, **params: Any) -> PlantCore:
    return PlantCore(replace(select(sc, plant_model="rotorpy"), plant=replace_table(sc.plant, model="rotorpy", params=params)))


def test_rotorpy_hovers_tracks_a_roll_setpoint_with_zenswarm_signs_and_feels_wind() -> None:
    core = _rotorpy()
    p = core.params
    assert (p.mass, p.g, p.inertia) == (0.03, 9.81, (1.43e-5, 1.43e-5, 2.89e-5)) and abs(p.max_thrust - 0.575) < 1e-12
    q0 = np.asarray(SC.initial_positions, dtype=float)
    hover, level = np.full(SC.n, p.mass * p.g), np.zeros((SC.n, 3))
    for k in range(100):  # 1 s of hover: the rotors start at hover speed
        core.hold_all(hover, level, k)
        core.step(k)
    assert np.abs(core.state.q - q0).max() < 1e-3 and np.abs(core.state.rpy).max() < 1e-6
    roll = level.copy()
    roll[:, 0] = 0.1
    for k in range(100, 200):  # +0.1 rad roll, ZYX, ENU/FLU: the thrust tilts towards -y
        core.hold_all(hover / np.cos(0.1), roll, k)
        core.step(k)
    assert np.allclose(core.state.rpy[:, 0], 0.1, atol=0.01), core.state.rpy
    assert np.all(core.state.v[:, 1] < -0.3) and np.abs(core.state.q[:, 2] - q0[:, 2]).max() < 0.05
    windy, still = _rotorpy(wind=(3.0, 0.0, 0.0)), _rotorpy()
    for k in range(100):  # air wind along +x drags the vehicles along +x (rotor drag)
        for c in (windy, still):
            c.hold_all(hover, level, k)
            c.step(k)
    assert np.all(windy.state.v[:, 0] > 0.1) and np.abs(still.state.v[:, 0]).max() < 1e-6


@pytest.mark.swarm
def test_rotorpy_sim_equals_lockstep_up_with_faults_and_verify(tmp_path: Path) -> None:
    """3 s of paper example 1 on RotorPy, 20 % loss + 30 ms delay: the lockstep swarm equals the
    simulator bit for bit (states, verdict and figures); `verify` recomputes agent 2 from the
    recording with the plant model's vehicle mass."""
    from test_swarm import _up

    scen = scenario_variant(tmp_path, time_limit_s=3.0)
    out, rec = tmp_path / "out", tmp_path / "rec.mcap"
    faults = ("--link-loss", "0.2", "--link-delay", "30ms", "--seed", "5")
    cp = _up(scen, out, unique_swarm("rp"), "--plant-model", "rotorpy", "--record", str(rec), *faults, "--full-time")
    assert cp.returncode in (0, 1), cp.stdout[-3000:]
    sc = replace(select(load_scenario(scen), plant_model="rotorpy"), seed=5)
    ref = sim.simulate(sc, faults=plan_for(sc, seed=5, link_loss="0.2", link_delay="30ms"), full_time=True)
    got = TimeSeries.load(str(out / "timeseries.npz"))
    for f in TimeSeries.FIELDS:
        np.testing.assert_array_equal(getattr(got, f), getattr(ref.series, f), err_msg=f"{f}: swarm != simulator")
    # RotorPy's records (rotor speeds, their command, rotor thrusts: issue 43), bit for bit, and in the recording
    assert list(got.plant) == list(ref.series.plant) == ["rotor_speed", "rotor_speed_cmd", "rotor_thrust"]
    for name, a in ref.series.plant.items():
        assert got.plant[name].tobytes() == a.tobytes(), f"plant.{name}: swarm != simulator"
    from zenswarm.bridge.reports.report import flight_from_recording, load_recording

    from_rec = flight_from_recording(load_recording(rec)).series
    for name, a in ref.series.plant.items():
        np.testing.assert_array_equal(from_rec.plant[name], a, err_msg=f"plant.{name}: recording != simulator")
    res = read_results(out)
    for k in FLIGHT_FIELDS:
        assert res[k] == ref.results[k], k
    builtin = sim.simulate(replace(load_scenario(scen), seed=5), faults=plan_for(sc, seed=5, link_loss="0.2", link_delay="30ms"))
    assert not np.array_equal(builtin.series.q, ref.series.q)  # it did fly RotorPy's vehicle
    cp = zenswarm("verify", str(rec), "--agent", "2")
    assert cp.returncode == 0, cp.stdout[-2000:]


@pytest.mark.slow
def test_paper_example_1_reaches_the_goal_on_rotorpy(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`zenswarm sim paper_example1 --plant-model rotorpy`, cut to 52 s (the goal is reached at
    44.9 s, then the 3 s settle window): SUCCESS."""
    scen = scenario_variant(tmp_path, time_limit_s=52.0)
    assert main(["sim", str(scen), "--plant-model", "rotorpy", "--out", str(tmp_path / "o"), "--quiet"]) == 0
    r = read_results(tmp_path / "o")
    assert r["success"] and r["time_to_goal_s"] < 50.0 and r["rms_tracking_error_m"] < 0.02, r

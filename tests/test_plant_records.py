"""Issue 43: a plant model records its internal signals (``records`` / ``record()``), as a
controller's ``shares`` travel: into ``timeseries.npz`` (``plant.<name>``), into each state message
(``State.extra``, so the MCAP recording holds them), checked at the plug-in boundary and by
``zenswarm plugins check``.

In-process and cheap: the built-in quadrotor's records against closed-form and independent
computations (the rotor thrusts sum to the applied thrust and mix back to the wrench; the torque
is the one eq. (5) applied in the tick's last sub-step), RotorPy's rotor speeds against the
first-order motor model (the rotor thrusts sum to the commanded thrust once the motor lag has
settled), the series in the simulator's ``timeseries.npz``, the wire and the collector (the
swarm's path), bad declarations (exit 2 naming the field) and bad ``record()`` values
(``plugin_error`` of call ``record``) in the simulator and in ``plugins check``. The swarm's
flights with these series are in tests/test_swarm.py and tests/test_plants.py.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from msgspec.structs import replace as replace_table

from zenswarm.bus import wire
from zenswarm.compose import sim
from zenswarm.compose.cli import main
from zenswarm.compose.plugcheck import check_plugin
from zenswarm.errors import PluginFailure, ScenarioError
from zenswarm.judge.metrics import TimeSeries, flight_differences
from zenswarm.plant.api import QuadrotorModel, Signal, rotor_mixer
from zenswarm.plant.core import PlantCore
from zenswarm.plant.quadrotor import initial_state, step, step_held
from zenswarm.process.collector import Collector
from zenswarm.scenario.config import load_scenario
from zenswarm.scenario.plugins import STAGE_BUILD, STAGE_PLANT, plant_records, records_of, resolve, select
from zenswarm.vehicle.params import ARM_LENGTH, KM_OVER_KF, QuadParams

from plant_fixtures import TickCounting
from swarmtest import SCENARIOS

EX1 = SCENARIOS / "paper_example1.toml"
SC = load_scenario(EX1)

# ----------------------------------------------------------------------------- test-only models


class BadShapeDecl(QuadrotorModel):
    name = "bad-shape-decl"
    description = "declares a shape with a zero"
    records = {"rotor_thrust": Signal((0,), "N")}


class BadUnitDecl(QuadrotorModel):
    name = "bad-unit-decl"
    description = "declares no unit"
    records = {"thrust": Signal((), "")}


class NotSignalDecl(QuadrotorModel):
    name = "not-signal-decl"
    description = "declares a bare shape"
    records = {"thrust": (4,)}  # type: ignore[dict-item]


class RaisingRecord(TickCounting):
    name = "raising-record"
    description = "record() raises after tick 2"

    def record(self) -> Any:
        if self.k > 2:
            raise KeyError("no such rotor")
        return super().record()


class WrongShapeRecord(QuadrotorModel):
    name = "wrong-shape-record"
    description = "returns 3 rotor thrusts"

    def record(self) -> Any:
        got = dict(super().record())
        got["rotor_thrust"] = got["rotor_thrust"][:, :3]
        return got


class UndeclaredRecord(QuadrotorModel):
    name = "undeclared-record"
    description = "returns a signal it did not declare"

    def record(self) -> Any:
        return {**super().record(), "secret": np.zeros((self.ctx.n, 2))}


class NanRecord(TickCounting):
    name = "nan-record"
    description = "UAV 3's torque record is NaN from tick 4"

    def record(self) -> Any:
        got = {k: np.array(v) for k, v in super().record().items()}
        if self.k >= 4:
            got["torque"][2, 1] = np.nan
        return got


# ----------------------------------------------------------------------------- the built-in quadrotor


def _hold_and_step(core: PlantCore, k: int, thrust: np.ndarray, rpy: np.ndarray) -> dict[str, np.ndarray]:
    core.hold_all(thrust, rpy, k)
    core.step(k)
    return {name: np.array(a) for name, a in core.recorded.items()}


def test_the_quadrotor_declares_its_records_with_shapes_and_units() -> None:
    recs = plant_records(SC)
    assert {n: (s.shape, s.unit) for n, s in recs.items()} == {
        "thrust": ((), "N"), "torque": ((3,), "N m"), "rotor_thrust": ((4,), "N"),
    }  # fmt: skip
    assert all(s.description for s in recs.values())


def test_quadrotor_rotor_thrusts_are_the_applied_wrench_mixed() -> None:
    """The records of every tick: ``thrust`` is the command clamped to [0, max_thrust] (exactly:
    the model has no motor lag), the four rotor thrusts sum to it and the X layout maps them back
    onto (thrust, torque); at tick 0 (before any step) the vehicles hold hover thrust, no torque."""
    core = PlantCore(SC)
    p = core.params
    n = SC.n
    rec0 = core.recorded
    np.testing.assert_array_equal(rec0["thrust"], np.full(n, p.mass * p.g))
    np.testing.assert_array_equal(rec0["torque"], np.zeros((n, 3)))
    np.testing.assert_allclose(rec0["rotor_thrust"], np.full((n, 4), p.mass * p.g / 4), rtol=1e-12)
    # the layout, independently: rotor positions (x, y) and spin (+1: its drag torque is +z)
    a = ARM_LENGTH / np.sqrt(2)
    pos = np.array([[a, -a], [-a, -a], [-a, a], [a, a]])  # M1 front right, M2 back right, M3 back left, M4 front left
    spin = np.array([-1.0, 1.0, -1.0, 1.0])
    for k in range(80):
        thrust = p.mass * p.g * (1.0 + 0.3 * np.sin(0.2 * k + np.arange(n)))
        thrust[0] = 2.0 * p.max_thrust if k == 40 else thrust[0]  # over the bound: clamped
        rpy = np.zeros((n, 3))
        rpy[:, 0] = 0.2 * np.sin(0.15 * k + np.arange(n))
        rpy[:, 1] = -0.15 * np.cos(0.1 * k + np.arange(n))
        rpy[:, 2] = 0.3
        rec = _hold_and_step(core, k, thrust, rpy)
        np.testing.assert_array_equal(rec["thrust"], np.clip(thrust, 0.0, p.max_thrust))
        f = rec["rotor_thrust"]
        np.testing.assert_allclose(f.sum(axis=1), rec["thrust"], rtol=1e-12)
        tau = np.stack([f @ pos[:, 1], -(f @ pos[:, 0]), KM_OVER_KF * (f @ spin)], axis=1)
        np.testing.assert_allclose(tau, rec["torque"], rtol=1e-9, atol=1e-15)
        assert np.all(np.abs(rec["torque"]) <= np.asarray(p.max_torque) + 1e-18)
    assert np.abs(rec["torque"]).max() > 1e-6  # the attitude commands did ask for torque


def test_quadrotor_torque_record_is_what_eq5_applied_in_the_last_sub_step() -> None:
    """Independent of the PID code: step the same vehicles one physics sub-step at a time and
    read the torque eq. (5) applied in the tick's last sub-step off the body rates,
    tau = J ((w1 - w0) / h + c o (w_y w_z, w_z w_x, w_x w_y)), c = ((Jz - Jy)/Jx, ...)."""
    core = PlantCore(SC)
    p = core.params
    n, nsub, h = SC.n, SC.timing.substeps, SC.timing.dt / SC.timing.substeps
    ref = initial_state(np.asarray(SC.initial_positions, dtype=float))
    J = np.asarray(p.inertia)
    c = np.array([(J[2] - J[1]) / J[0], (J[0] - J[2]) / J[1], (J[1] - J[0]) / J[2]])
    for k in range(30):
        thrust = np.full(n, p.mass * p.g * 1.05)
        rpy = np.zeros((n, 3))
        rpy[:, 0] = 0.1 * (1 + np.arange(n)) * (1 if k < 15 else -1)
        rpy[:, 2] = 0.2
        rec = _hold_and_step(core, k, thrust, rpy)
        for _ in range(nsub - 1):
            step(ref, thrust, rpy, p, h)
        w0 = ref.w.copy()
        step(ref, thrust, rpy, p, h)
        gyro = np.stack([w0[:, 1] * w0[:, 2], w0[:, 2] * w0[:, 0], w0[:, 0] * w0[:, 1]], axis=1)
        tau = J * ((ref.w - w0) / h + c * gyro)
        np.testing.assert_allclose(rec["torque"], tau, rtol=1e-6, atol=1e-12, err_msg=f"tick {k}")
        np.testing.assert_array_equal(core.state.w, ref.w)


@pytest.mark.parametrize("n", [3, 12])  # the scalar path (N <= 10) and numpy's
def test_step_held_writes_the_last_sub_steps_wrench_as_step_does(n: int) -> None:
    """step_held's wrench (both paths) is bit for bit the loop of step() with wrench_out on the last sub-step."""
    p = QuadParams()
    rng = np.random.default_rng(3)
    q0 = rng.normal(size=(n, 3))
    a, b = initial_state(q0), initial_state(q0)
    for k in range(20):
        f = p.hover_thrust * (1 + 0.4 * rng.normal(size=n))
        r = 0.3 * rng.normal(size=(n, 3))
        step_held(a, f, r, p, 1e-3, 10)
        for j in range(10):
            step(b, f, r, p, 1e-3, wrench_out=j == 9)
        assert a.wrench.tobytes() == b.wrench.tobytes(), k
        assert a.w.tobytes() == b.w.tobytes(), k
    np.testing.assert_array_equal(a.wrench[:, 0], np.clip(f, 0, p.max_thrust))


def test_rotor_mixer_inverts_the_x_layout() -> None:
    M = rotor_mixer(0.04, 0.02)
    a, c = 0.04 / np.sqrt(2), 0.02
    B = np.array([[1, 1, 1, 1], [-a, -a, a, a], [-a, a, a, -a], [-c, c, -c, c]])  # (F, tau) = B f
    np.testing.assert_allclose(B @ M, np.eye(4), atol=1e-12)


# ----------------------------------------------------------------------------- RotorPy


def _rotorpy() -> PlantCore:
    return PlantCore(replace(select(SC, plant_model="rotorpy"), plant=replace_table(SC.plant, model="rotorpy", params={})))


def test_rotorpy_rotor_speeds_follow_the_first_order_motor_model() -> None:
    """RotorPy's records: the rotor speeds relax to the commanded ones with its motor time
    constant, omega(k+1) = cmd + (omega(k) - cmd) exp(-dt / tau_m) (the solver's tolerance);
    after the lag settles (7 tau_m) the rotor thrusts k_eta omega^2 sum to the commanded thrust."""
    from zenswarm.plant.rotorpy_model import crazyflie_params

    qp = crazyflie_params()
    core = _rotorpy()
    n, p, dt = SC.n, core.params, SC.timing.dt
    assert set(core.recorded) == {"rotor_speed", "rotor_speed_cmd", "rotor_thrust"}
    hover = np.sqrt(qp["mass"] * 9.81 / (4 * qp["k_eta"]))
    np.testing.assert_allclose(core.recorded["rotor_speed"], hover, rtol=1e-12)
    level = np.zeros((n, 3))
    thrust = np.full(n, 1.2 * p.mass * p.g)  # a step up in thrust, level
    decay = np.exp(-dt / qp["tau_m"])
    before = core.recorded["rotor_speed"].copy()
    for k in range(50):
        rec = _hold_and_step(core, k, thrust, level)
        cmd = rec["rotor_speed_cmd"]
        want = cmd + (before - cmd) * decay
        np.testing.assert_allclose(rec["rotor_speed"], want, rtol=2e-4, err_msg=f"tick {k}")
        np.testing.assert_allclose(rec["rotor_thrust"], qp["k_eta"] * rec["rotor_speed"] ** 2, rtol=1e-12)
        before = rec["rotor_speed"]
    assert np.all(rec["rotor_speed"] > hover * 1.05)  # it did spin up
    np.testing.assert_allclose(rec["rotor_thrust"].sum(axis=1), thrust, rtol=2e-3)


# ----------------------------------------------------------------------------- the simulator's series


def test_the_simulators_series_holds_the_records_with_the_state_they_belong_to(tmp_path: Path) -> None:
    """``zenswarm sim``: timeseries.npz has ``plant.<name>`` (T, N, *shape), tick k holding the
    records of the state of tick k; save and load keep them; two flights that differ in them
    differ (flight_differences names the series, tick and UAV)."""
    out = tmp_path / "o"
    assert main(["sim", str(EX1), "--out", str(out), "--quiet", "--duration", "2"]) in (0, 1)
    with np.load(out / "timeseries.npz") as z:
        assert {"plant.thrust", "plant.torque", "plant.rotor_thrust"} <= set(z.files)
        T = len(z["t"])
        assert z["plant.thrust"].shape == (T, 3) and z["plant.rotor_thrust"].shape == (T, 3, 4)
        assert z["plant.torque"].shape == (T, 3, 3) and np.isfinite(z["plant.rotor_thrust"]).all()
        np.testing.assert_allclose(z["plant.rotor_thrust"].sum(axis=2), z["plant.thrust"], rtol=1e-12)
        # tick k + 1 holds the thrust applied during tick k: the agents' command of tick k, clamped
        np.testing.assert_array_equal(z["plant.thrust"][1:], np.clip(z["thrust"][:-1], 0.0, QuadParams().max_thrust))
    ts = TimeSeries.load(str(out / "timeseries.npz"))
    assert list(ts.plant) == ["thrust", "torque", "rotor_thrust"]
    other = TimeSeries.from_arrays({k: np.array(a) for k, a in ts.arrays().items()})
    assert flight_differences(ts, {}, other, {}) == []
    other.plant["torque"][7, 1, 2] += 1e-9
    (diff,) = flight_differences(ts, {}, other, {})
    assert diff.startswith("series.plant.torque: 1 values differ, first at tick 7") and "UAV 2" in diff, diff
    del other.plant["torque"]
    assert flight_differences(ts, {}, other, {}) == ["series.plant.torque: only in the first flight"]


def test_a_flight_of_no_tick_has_no_plant_series() -> None:
    """Nothing flown (here: record() failed after the constructor): no plant series, as the
    swarm's collector has it (a series comes with its first value)."""
    res = sim.simulate(select(SC, plant_model="test_plant_records:WrongShapeRecord"), n_ticks=10)
    assert len(res.series.t) == 0 and res.series.plant == {}


# ----------------------------------------------------------------------------- the swarm's path


def test_a_state_message_carries_the_records_bit_for_bit() -> None:
    q, v = np.array([1.0, 2.0, 3.0]), np.array([0.1, -0.2, 0.3])
    rpy, w = np.array([0.01, -0.02, 0.5]), np.zeros(3)
    extra = {"rotor_thrust": [0.066, 0.0661, -0.0, 1e-300], "thrust": [0.2648]}
    data = wire.encode_state(100, 3, q, v, rpy, w, extra)
    assert data == wire.encode(wire.State(t=100, seq=3, q=q, v=v, rpy=rpy, w=w, extra=extra))
    msg = wire.decode("state", data)
    assert msg.extra == {k: tuple(x) for k, x in extra.items()} and np.signbit(msg.extra["rotor_thrust"][2])
    assert wire.encode_state(100, 3, q, v, rpy, w) == wire.encode_state(100, 3, q, v, rpy, w, {})  # none: no "x"
    assert b"\xa1x" not in wire.encode_state(100, 3, q, v, rpy, w)
    with pytest.raises(wire.MessageError):
        wire.encode_state(100, 3, q, v, rpy, w, {"thrust": [float("nan")]})


def test_the_collector_rebuilds_the_records_with_their_declared_shapes() -> None:
    """What ``zenswarm up`` and ``zenswarm report`` build the series with: each UAV's state
    message's records, reshaped as the plant model declares them; a signal the model does not
    declare (or a model that cannot be loaded) stays flat."""
    keys = wire.Keys("rec")
    col = Collector(SC, keys)
    z = np.zeros(3)
    for k in range(3):
        for i in range(1, SC.n + 1):
            extra = {"torque": [float(k), float(i), 0.5], "rotor_thrust": [0.25 * i, 0.2, 0.3, float(k)], "other": [1.0, 2.0],
                     "thrust": [0.5 * k + i]}
            col.on_sample(keys.state(i), wire.encode_state(wire.t_ns(k * SC.timing.dt), k + 1, z, z, z, z, extra))
    ts = col.series(3)
    assert list(ts.plant) == ["torque", "rotor_thrust", "other", "thrust"]
    assert ts.plant["torque"].shape == (3, 3, 3) and ts.plant["other"].shape == (3, 3, 2)
    assert ts.plant["thrust"].shape == (3, 3) and ts.plant["thrust"][2].tolist() == [2.0, 3.0, 4.0]  # a scalar per UAV
    assert ts.plant["torque"][2, 1].tolist() == [2.0, 2.0, 0.5] and ts.plant["rotor_thrust"][1, 2].tolist() == [0.75, 0.2, 0.3, 1.0]
    col.close()
    unknown = Collector(select(SC, plant_model="no_module_xyz:Model"), keys)  # not loadable here: flat
    unknown.on_sample(keys.state(1), wire.encode_state(0, 1, z, z, z, z, {"torque": [1.0, 2.0, 3.0]}))
    assert unknown.series(1).plant["torque"].shape == (1, 3, 3)
    unknown.close()


# ----------------------------------------------------------------------------- bad declarations and values


@pytest.mark.parametrize(("model", "field"), [
    ("test_plant_records:BadShapeDecl", "records.rotor_thrust.shape"),
    ("test_plant_records:BadUnitDecl", "records.thrust.unit"),
    ("test_plant_records:NotSignalDecl", "records.thrust"),
])
def test_a_bad_declaration_is_exit_2_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], model: str, field: str
) -> None:
    """Before any work: sim, up and plugins check refuse the model, exit 2, naming the field."""
    with pytest.raises(ScenarioError) as e:
        records_of(resolve("plant", model))
    assert e.value.field == field
    for cmd in (["sim", str(EX1), "--out", str(tmp_path / "s")], ["up", str(EX1), "--out", str(tmp_path / "u")]):
        assert main([*cmd, "--plant-model", model]) == 2
        assert f"{field}: " in capsys.readouterr().err
    assert not (tmp_path / "s").exists() and not (tmp_path / "u").exists()
    assert main(["plugins", "check", model, "--no-swarm"]) == 2
    assert f"{field}: " in capsys.readouterr().err
    with pytest.raises(ScenarioError):
        check_plugin(model, SC, swarm=False)


def test_more_bad_declarations_are_named() -> None:
    class Many(QuadrotorModel):
        records = {f"s{i}": Signal((2,), "N") for i in range(65)}

    class Big(QuadrotorModel):
        records = {"image": Signal((40, 40), "1")}

    class BadName(QuadrotorModel):
        records = {"rotor thrust": Signal((4,), "N")}

    class NotMapping(QuadrotorModel):
        records = [Signal((4,), "N")]  # type: ignore[assignment]

    for cls, field, needle in [(Many, "records", "at most 64 signals"), (Big, "records", "at most 1024 values per UAV"),
                               (BadName, "records", "'rotor thrust'"), (NotMapping, "records", "must map names")]:
        with pytest.raises(ScenarioError) as e:
            records_of(cls)
        assert e.value.field == field and needle in e.value.message, e.value


@pytest.mark.parametrize(("model", "tick", "stage", "field", "uavs", "needle"), [
    ("test_plant_records:RaisingRecord", 2, STAGE_PLANT, None, [1, 2, 3], "raised KeyError: 'no such rotor'"),
    ("test_plant_records:WrongShapeRecord", 0, STAGE_BUILD, "record.rotor_thrust", [1, 2, 3], "shape (3, 3) != (3, 4)"),
    ("test_plant_records:UndeclaredRecord", 0, STAGE_BUILD, "record.secret", [1, 2, 3], "not declared in records"),
    ("test_plant_records:NanRecord", 3, STAGE_PLANT, "record.torque", [3], "record.torque: not finite for UAV 3"),
])
def test_a_bad_record_is_a_named_plugin_failure(model: str, tick: int, stage: int, field: str | None, uavs: list[int], needle: str) -> None:
    """record() raising or returning a wrong value: ``plugin_error`` of call ``record`` (kind
    plant, process plant), at the tick whose step it followed (tick 0, stage build: after the
    constructor); the ticks before are judged; ``plugins check`` fails its outputs with it."""
    res = sim.simulate(select(SC, plant_model=model), n_ticks=20)
    (f,) = [f for f in res.results["failures"] if f["cause"] == "plugin_error"]
    got = {k: f[k] for k in ("kind", "process", "tick", "stage", "call", "field", "uavs")}
    assert got == {"kind": "plant", "process": "plant", "tick": tick, "stage": stage, "call": "record", "field": field, "uavs": uavs}
    assert needle in f["detail"], f["detail"]
    assert len(res.series.t) == (tick if stage == STAGE_PLANT else 0)
    _, _, checks = check_plugin(model, SC, swarm=False)
    outputs = next(c for c in checks if c.name == "outputs")
    assert outputs.status == "FAIL" and "record()" in outputs.detail and needle in outputs.detail, outputs
    with pytest.raises(PluginFailure):
        core = PlantCore(select(SC, plant_model=model))
        for k in range(10):
            core.step(k)


def test_plugins_check_compares_the_records_between_runs() -> None:
    """The conformance check's outputs include the records, so its deterministic check sees them."""
    _, _, checks = check_plugin("quadrotor", SC, swarm=False)
    by = {c.name: c for c in checks}
    assert all(c.status == "PASS" for n, c in by.items() if n != "sim == swarm"), by
    assert "records thrust () N, torque (3,) N m, rotor_thrust (4,) N" in by["interface"].detail

"""The plant's tick (numpy only): THE plant step of the plant process and the in-process
simulator alike.

:class:`PlantCore` holds the scenario's plant model (:class:`zenswarm.plant.api.PlantModel`, a
plug-in: ``[plant] model``, default ``quadrotor``), the commands every UAV holds (zero-order hold,
with the tick each was sent at), the failsafe and the disturbance model. Step 7 of a control tick
(see :mod:`zenswarm.compose.sim`) is :meth:`PlantCore.step`: the failsafe decides, from each
command's age, what is applied (:mod:`zenswarm.plant.failsafe`), then the model advances one
control period with it held (the built-in: ``timing.substeps`` physics sub-steps of
:func:`zenswarm.plant.quadrotor.step_held`), and its state is checked (shapes, finite), then what
the model records (:meth:`zenswarm.plant.api.PlantModel.record`: :attr:`PlantCore.recorded`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from zenswarm.errors import PluginFailure
from zenswarm.plant.api import PlantContext, PlantModel, VehicleStates
from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.failsafe import FailsafeState, failsafe_config
from zenswarm.scenario.plugins import (
    PLANT_ROLE,
    STAGE_BUILD,
    STAGE_PLANT,
    Boundary,
    Signal,
    plant_selection,
    plant_vehicle,
    plugin_rng,
    records_of,
)

__all__ = ["PlantCore", "make_plant_model", "STATE_FIELDS"]

_F64 = np.dtype(np.float64)
_PY_SUM_MAX = 48
"""A record of at most this many values is checked on Python floats, a larger one with numpy."""

STATE_FIELDS = ("q", "v", "rpy", "w")
"""The state arrays a plant model exposes, each (N, 3) (:class:`zenswarm.plant.api.VehicleStates`)."""


def make_plant_model(scenario: Any) -> PlantModel:
    """The scenario's plant model (``[plant] model``, ``[plant.params]``), built with its
    :class:`zenswarm.plant.api.PlantContext`; PluginError naming the field for a bad name or
    parameter; :class:`zenswarm.errors.PluginFailure` (kind ``plant``, process ``plant``, stage
    build, call ``__init__``) when constructing it raises."""
    cls, params = plant_selection(scenario)
    tm = scenario.timing
    vehicle = plant_vehicle(scenario)
    ctx = PlantContext(
        n=scenario.n, dt=tm.dt, substeps=tm.substeps, h=tm.dt / tm.substeps,
        initial_positions=np.asarray(scenario.initial_positions, dtype=float).copy(), yaw=scenario.controller.yaw,
        vehicle=vehicle, rng=plugin_rng(scenario.seed, PLANT_ROLE), scenario=scenario,
    )  # fmt: skip
    model: PlantModel = boundary(scenario).call(0, STAGE_BUILD, "__init__", cls, ctx, params)
    return model


def boundary(scenario: Any) -> Boundary:
    """Where the plant model is called (:class:`zenswarm.scenario.plugins.Boundary`): kind ``plant``, the
    name it was selected by, process ``plant``, every UAV."""
    return Boundary("plant", str(scenario.plant.model), "plant", tuple(range(1, scenario.n + 1)))


class PlantCore:
    """N simulated vehicles (the scenario's plant model) and the commands they hold.

    ``thrust`` (N,) N and ``rpy_cmd`` (N, 3) rad: the held commands (hover thrust, level, yaw =
    controller.yaw before the first); ``last_cmd_tick`` (N,): the tick each was sent at.
    ``state``: the model's :class:`zenswarm.plant.api.VehicleStates` (q, v, rpy, w: (N, 3) each).
    ``params``: the model's vehicle (:meth:`zenswarm.plant.api.PlantModel.vehicle`).
    ``records``: the signals the model declares (name -> :class:`zenswarm.scenario.plugins.Signal`);
    ``recorded``: their values with the current state, name -> float64 (N, *shape), checked
    (read them before the next :meth:`step`: they may be the model's own arrays).
    """

    def __init__(self, scenario: Any) -> None:
        n = scenario.n
        tm = scenario.timing
        self.n = n
        self.model = make_plant_model(scenario)
        self.bound = boundary(scenario)
        self.params = self.model.ctx.vehicle
        self.dt = tm.dt
        self.nsub = tm.substeps
        self.h = tm.dt / tm.substeps
        self.yaw = scenario.controller.yaw
        self.dist = DisturbanceModel(scenario.disturbance, n, np.random.default_rng(scenario.seed))
        self._shape = (n, 3)
        self._check_state(0, STAGE_BUILD)
        self.records: dict[str, Signal] = records_of(type(self.model), f"plant {scenario.plant.model!r}")
        self._rec_shapes = {name: (n, *sig.shape) for name, sig in self.records.items()}
        self.recorded: dict[str, np.ndarray] = self._record(0, STAGE_BUILD)
        self.failsafe = FailsafeState(n, failsafe_config(scenario.failsafe))
        self.thrust = np.full(n, self.params.mass * self.params.g)
        self.rpy_cmd = np.zeros((n, 3))
        self.rpy_cmd[:, 2] = self.yaw
        self.last_cmd_tick = [0] * n

    @property
    def state(self) -> VehicleStates:
        """The model's state (q, v, rpy, w: (N, 3) each; read it, do not write it)."""
        return self.model.state

    def hold(self, i: int, thrust: float, rpy: np.ndarray, k_cmd: int) -> None:
        """UAV i (0-based) holds this command (thrust N, rpy (3,) rad), sent at tick ``k_cmd``."""
        self.thrust[i] = thrust
        self.rpy_cmd[i] = rpy
        self.last_cmd_tick[i] = k_cmd

    def hold_all(self, thrust: np.ndarray, rpy: np.ndarray, k_cmd: int) -> None:
        """Every UAV holds its command of tick ``k_cmd``: thrust (N,) N, rpy (N, 3) rad."""
        self.thrust = thrust
        self.rpy_cmd = rpy
        self.last_cmd_tick = [k_cmd] * self.n

    def step(self, k: int) -> list[tuple[int, int, str, str]]:
        """Step 7 of tick k: failsafe on the commands' ages, then the model's control period to
        tick k + 1 (in place). Returns the failsafe events of this tick (tick, UAV 1-based, from,
        to). A model that raises, or leaves a state that is not (N, 3) and finite, raises
        :class:`zenswarm.errors.PluginFailure` (kind ``plant``, process ``plant``, tick k, stage
        :data:`zenswarm.scenario.plugins.STAGE_PLANT`, call ``step``; the field ``state.<name>`` and the
        UAVs whose rows are not finite)."""
        p = self.params
        fs = self.failsafe
        before = len(fs.events)
        ages = [(k - self.last_cmd_tick[i]) * self.dt for i in range(self.n)]
        st = self.model.state
        f_app, r_app = fs.apply(k, ages, st.q, st.v, self.thrust, self.rpy_cmd, p.mass, p.g, self.yaw)
        self.bound.call(k, STAGE_PLANT, "step", self.model.step, f_app, r_app, self.dist.sampler(k * self.dt, self.h))
        self._check_state(k)
        if self.records:
            self.recorded = self._record(k)
        return fs.events[before:]

    def _record(self, k: int, stage: int = STAGE_PLANT) -> dict[str, np.ndarray]:
        """The model's :meth:`~zenswarm.plant.api.PlantModel.record` after its constructor or its
        step of tick k, checked: every declared name and no other, each a float array of shape
        (N, *shape), finite; else :class:`zenswarm.errors.PluginFailure` (call ``record``, field
        ``record.<name>``, the UAVs whose values are not finite)."""
        if not self.records:
            return {}
        got = self.bound.call(k, stage, "record", self.model.record)
        shapes = self._rec_shapes
        try:  # the fast path: the declared names, float64 arrays of the declared shapes, a finite sum
            if got.keys() == shapes.keys():
                out: dict[str, np.ndarray] = {}
                total = 0.0
                for name, shape in shapes.items():
                    a = got[name]
                    if type(a) is not np.ndarray or a.dtype != _F64 or a.shape != shape:
                        break
                    out[name] = a  # a few values: summed as Python floats (cheaper than numpy's reduction)
                    total += sum(a.ravel().tolist()) if a.size <= _PY_SUM_MAX else float(a.sum())
                else:
                    if math.isfinite(total):
                        return out
        except (AttributeError, TypeError, ValueError):
            pass  # not a mapping of arrays: the slow path names what is wrong
        return self._record_slow(k, stage, got)

    def _record_slow(self, k: int, stage: int, got: Any) -> dict[str, np.ndarray]:
        b = self.bound
        if not hasattr(got, "keys") or not hasattr(got, "__getitem__"):
            raise b.fail(k, stage, "record", "record", f"{type(got).__name__} is not a mapping of names to arrays")
        for name in got.keys():
            if name not in self.records:
                raise b.fail(k, stage, "record", f"record.{name}", f"not declared in records ({', '.join(self.records)})")
        out: dict[str, np.ndarray] = {}
        for name, shape in self._rec_shapes.items():
            if name not in got:
                raise b.fail(k, stage, "record", f"record.{name}", "missing (declared in records)")
            try:
                a = np.asarray(got[name], dtype=float)
            except (TypeError, ValueError):
                raise b.fail(k, stage, "record", f"record.{name}", f"{type(got[name]).__name__} is not an array of numbers") from None
            if a.shape != shape:
                raise b.fail(k, stage, "record", f"record.{name}", f"shape {a.shape} != {shape}")
            ok = np.isfinite(a.reshape(self.n, -1)).all(axis=1)
            if not ok.all():
                bad = tuple(int(i) + 1 for i in np.flatnonzero(~ok))
                detail = f"record.{name}: not finite for UAV {', '.join(map(str, bad))} ({a[bad[0] - 1].tolist()} for UAV {bad[0]})"
                raise PluginFailure(b.kind, b.plugin, b.process, bad, k, stage, "record", detail, f"record.{name}")
            out[name] = a
        return out

    def _check_state(self, k: int, stage: int = STAGE_PLANT) -> None:
        st = self.model.state
        try:  # the fast path: four (N, 3) arrays whose sum is finite (a sum that overflows takes the slow one)
            if all(getattr(st, f).shape == self._shape for f in STATE_FIELDS) and math.isfinite(
                float(st.q.sum()) + float(st.v.sum()) + float(st.rpy.sum()) + float(st.w.sum())
            ):
                return
        except (AttributeError, TypeError, ValueError):
            pass  # not arrays: the slow path names what is wrong
        call = "step" if stage == STAGE_PLANT else "__init__"
        for name in STATE_FIELDS:
            a = getattr(st, name, None)
            shape = np.shape(a) if a is not None else None
            if a is None or shape != (self.n, 3):
                raise self.bound.fail(k, stage, call, f"state.{name}", f"shape {shape} != ({self.n}, 3)")
            ok = np.isfinite(a).all(axis=1)
            if not ok.all():
                b = self.bound
                bad = tuple(int(i) + 1 for i in np.flatnonzero(~ok))
                i = bad[0] - 1
                detail = f"state.{name}: not finite for UAV {', '.join(map(str, bad))} ({np.asarray(a)[i].tolist()} for UAV {bad[0]})"
                raise PluginFailure(b.kind, b.plugin, b.process, bad, k, stage, call, detail, f"state.{name}")

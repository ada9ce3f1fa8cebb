"""The plant model interface: the dynamics N vehicles fly, one control tick at a time.

A plant model is the third plug-in kind (beside :class:`zenswarm.agents.api.Controller` and
:class:`zenswarm.leader.planner.Planner`; :mod:`zenswarm.scenario.plugins`, entry-point group
``zenswarm.plants``). It is chosen by ``[plant] model = "NAME"`` in the scenario (parameters in
``[plant.params]``) or ``--plant-model NAME`` on ``zenswarm sim`` and ``zenswarm up``; the
built-in :class:`QuadrotorModel` (name ``quadrotor``, :mod:`zenswarm.plant.quadrotor`) is the
default, and ``rotorpy`` (:mod:`zenswarm.plant.rotorpy_model`, extra ``rotorpy``) flies RotorPy's
multirotor.

The model is driven by :class:`zenswarm.plant.core.PlantCore`, THE plant step of the in-process
simulator and of the plant process alike, so any deterministic model flies bit for bit the same
in ``zenswarm sim`` and in the lockstep swarm (``zenswarm up``). Around the model the core keeps
what every model shares: the commands each UAV holds (zero-order hold), the command-loss
failsafe (:mod:`zenswarm.plant.failsafe`, which hovers and lands with the model's
:meth:`PlantModel.vehicle` mass and g) and the scenario's seeded ``[disturbance]``
(:class:`zenswarm.plant.disturbance.DisturbanceModel`).

Frames and units, as everywhere in zenswarm: inertial ENU (z up), body FLU (x forward, z along
the thrust); positions m, velocities m/s, Euler angles [roll, pitch, yaw] (ZYX, paper eq. 2) rad,
body angular velocity rad/s, thrust N, times s.

One control tick k (step 7 of :mod:`zenswarm.compose.sim`): the core hands the model the
commands the failsafe let through, ``thrust`` (N,) N (collective, along body z) and ``rpy``
(N, 3) rad (the attitude setpoint of the inversion after eq. 28, the same commands the agents
send on ``uav/<i>/cmd``), and :meth:`PlantModel.step` advances every vehicle by one control
period ``ctx.dt``. Afterwards the core checks :attr:`PlantModel.state`: every array (N, 3) and
finite, else the flight ends with the plug-in failure ``plugin_error``
(:class:`zenswarm.errors.PluginFailure`: kind ``plant``, process ``plant``, stage
:data:`zenswarm.scenario.plugins.STAGE_PLANT`, the tick, the field, the UAVs; docs/plugins.md); a model
that raises (constructor or step) is reported the same way.

A model must be deterministic (no clock, no I/O, randomness only from ``ctx.rng``), as
``zenswarm plugins check`` verifies.

Recording internal signals (rotor thrusts, a motor-lag state, ...): declare ``records = {"name":
Signal(shape, unit, description), ...}`` and return the values of the current tick from
:meth:`PlantModel.record`, name -> (N, *shape) array. The runner calls it once after the
constructor and once after every :meth:`PlantModel.step` (the same calls in ``zenswarm sim`` and
``zenswarm up``), checks it (every declared name, nothing else, the shapes, finite), and records
the values with the state they belong to: ``plant.<name>`` (T, N, *shape) in ``timeseries.npz``,
and in each ``uav/<i>/state`` message (:attr:`zenswarm.bus.wire.State.extra`), so the flight's
MCAP recording holds them. A bad declaration is refused before any work (exit 2, naming
``records.<name>``); a ``record()`` that raises or returns a wrong value is the plug-in failure
``plugin_error`` (call ``record``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import msgspec
import numpy as np

from zenswarm.plant.quadrotor import PlantState, initial_state, step_held
from zenswarm.scenario.plugins import Signal
from zenswarm.vehicle.params import ARM_LENGTH, KM_OVER_KF, QuadParams

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = ["NoParams", "PlantContext", "VehicleStates", "Disturbance", "PlantModel", "QuadrotorModel", "Signal", "rotor_mixer"]

_NO_RECORDS: Mapping[str, np.ndarray] = MappingProxyType({})

Disturbance = Callable[[int], tuple[Any, Any]]
"""``disturbance(j) -> (d_p, d_a)`` for physics sub-step j = 0 .. ctx.substeps - 1 of the tick:
d_p (N, 3) m/s^2 ENU, a translational acceleration (eq. 1), and d_a (N, 3) rad/s^2 body, an
angular acceleration (eq. 5), each held over the sub-step of ``ctx.h`` s (either may be None: 0)."""


class NoParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A plant model without parameters: its ``[plant.params]`` table must be empty."""


class VehicleStates(Protocol):
    """The vehicles' state a model exposes (the rows of UAV i, 0-based), each (N, 3) float64:
    ``q`` position m ENU, ``v`` velocity m/s ENU, ``rpy`` Euler angles [phi, theta, psi] rad
    (ZYX, each wrapped to (-pi, pi]), ``w`` body angular velocity rad/s FLU. These are what the
    plant publishes on ``uav/<i>/state``, what the agents measure and what the verdict judges."""

    q: np.ndarray
    v: np.ndarray
    rpy: np.ndarray
    w: np.ndarray


@dataclass(frozen=True)
class PlantContext:
    """What a plant model is built from.

    n: number of vehicles N. dt: control tick, s (one :meth:`PlantModel.step`). substeps: physics
    sub-steps per tick (``timing.substeps``; a model may integrate differently, but the
    disturbance is sampled per sub-step). h: dt / substeps, s. initial_positions: (N, 3) m ENU
    (every vehicle starts there at rest, level, yaw 0). yaw: the commanded yaw, rad
    (``controller.yaw``). vehicle: the model's own :meth:`PlantModel.vehicle`. rng: its seeded
    stream (:func:`zenswarm.scenario.plugins.plugin_rng` with role :data:`zenswarm.scenario.plugins.PLANT_ROLE`).
    scenario: the whole scenario.
    """

    n: int
    dt: float
    substeps: int
    h: float
    initial_positions: np.ndarray
    yaw: float
    vehicle: QuadParams
    rng: np.random.Generator
    scenario: Scenario


class PlantModel(ABC):
    """The dynamics of N vehicles. Class attributes: ``name`` (listed under), ``description``
    (one line), ``Params`` (a frozen :class:`msgspec.Struct` with ``forbid_unknown_fields=True``:
    the scenario's ``[plant.params]`` decoded, unknown keys rejected naming the field),
    ``records`` (internal signals recorded with the flight: name -> :class:`Signal`, returned by
    :meth:`record`)."""

    name: ClassVar[str] = ""
    description: ClassVar[str] = ""
    Params: ClassVar[type[msgspec.Struct]] = NoParams
    records: ClassVar[Mapping[str, Signal]] = MappingProxyType({})

    def __init__(self, ctx: PlantContext, params: Any) -> None:
        self.ctx = ctx
        self.params = params

    @classmethod
    def vehicle(cls, scenario: Scenario, params: Any) -> QuadParams:
        """The vehicle this model flies, as :class:`zenswarm.vehicle.params.QuadParams`: ``mass`` kg and
        ``g`` m/s^2 (the agents' controllers compute thrust = m |u|, eq. 28, and the failsafe
        hovers with them), ``inertia`` kg m^2 and ``max_thrust`` N (for the record). Called
        before any work starts (a model that cannot run, e.g. a missing package, raises
        :class:`zenswarm.scenario.plugins.PluginError` naming ``plant.model`` here). Default: zenswarm's
        Crazyflie 2.1 with the scenario's ``[vehicle]`` overrides."""
        return QuadParams.from_vehicle(scenario.vehicle)

    @property
    @abstractmethod
    def state(self) -> VehicleStates:
        """The vehicles' current state (:class:`VehicleStates`). The runner reads it after each
        :meth:`step` (and copies what it keeps); it never writes it."""

    @abstractmethod
    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Disturbance | None) -> None:
        """Advance every vehicle by one control tick, ``ctx.dt`` s, with the command held.

        thrust: (N,) N, collective thrust along body z (finite, >= 0 from the built-in
        controller; clamp to what the vehicle can do). rpy: (N, 3) rad, attitude setpoint
        [phi_d, theta_d, psi_d] (ZYX), tracked by the vehicle's own attitude control.
        disturbance: the scenario's ``[disturbance]`` for this tick (:data:`Disturbance`), None
        when it is inactive; call it for j = 0 .. ctx.substeps - 1, in order, once each (its
        gusts are a seeded random process: the draws must not depend on the model)."""

    def record(self) -> Mapping[str, np.ndarray]:
        """The declared :attr:`records` of the current tick (the state :attr:`state` holds now):
        name -> float array (N, *shape), finite, every declared name and no other. Called once
        after the constructor (tick 0) and once after every :meth:`step`; the runner copies what
        it keeps before the next :meth:`step`, so views of arrays the model updates in place are
        fine. Default: nothing (a model without ``records``)."""
        return _NO_RECORDS


def rotor_mixer(arm_length: float, km_over_kf: float) -> np.ndarray:
    """The (4, 4) matrix M with f = M [F, tau_x, tau_y, tau_z]: the four rotor thrusts f (N) of
    an X-configuration quadrotor that produce the collective thrust F (N) and the body torque tau
    (N m, FLU). Rotors as the Crazyflie numbers them: 1 front right, 2 back right, 3 back left,
    4 front left (seen from above, clockwise from the front right), each at arm_length (m) from
    the centre on the diagonals, 1 and 3 turning counter-clockwise, 2 and 4 clockwise (seen from
    above), a rotor's drag torque km_over_kf (m) times its thrust. The inverse of::

        F     = f1 + f2 + f3 + f4
        tau_x = a (-f1 - f2 + f3 + f4)        a = arm_length / sqrt(2)
        tau_y = a (-f1 + f2 + f3 - f4)
        tau_z = c (-f1 + f2 - f3 + f4)        c = km_over_kf
    """
    a = arm_length / np.sqrt(2.0)
    c = km_over_kf
    sx = np.array([-1.0, -1.0, 1.0, 1.0])
    sy = np.array([-1.0, 1.0, 1.0, -1.0])
    sz = np.array([-1.0, 1.0, -1.0, 1.0])
    return np.stack([np.full(4, 0.25), sx / (4.0 * a), sy / (4.0 * a), sz / (4.0 * c)], axis=1)


class QuadrotorModel(PlantModel):
    """zenswarm's own quadrotor: paper eqs 1-5, onboard attitude PID, semi-implicit Euler at the physics rate."""

    name = "quadrotor"
    description = "zenswarm's own quadrotor: paper eqs 1-5, onboard attitude PID, semi-implicit Euler at the physics rate"
    records = MappingProxyType({
        "thrust": Signal((), "N", "collective thrust applied over the tick's last physics sub-step (the command clamped "
                         "to [0, max_thrust])"),
        "torque": Signal((3,), "N m", "body torque (FLU) of the onboard attitude PID over that sub-step (clamped to max_torque)"),
        "rotor_thrust": Signal((4,), "N", "the rotor thrusts of that wrench (rotor_mixer: Crazyflie X layout, M1 front right "
                               "clockwise to M4 front left), unclipped: outside [0, max_thrust / 4] the rotors could not"),
    })  # fmt: skip

    def __init__(self, ctx: PlantContext, params: Any) -> None:
        super().__init__(ctx, params)
        self.quad = ctx.vehicle
        self._state: PlantState = initial_state(ctx.initial_positions)
        # tick 0: the wrench that holds the vehicles at rest, level (hover thrust, as the runner holds it)
        self._state.wrench[:, 0] = self.quad.mass * self.quad.g
        self._mix_t = np.ascontiguousarray(rotor_mixer(ARM_LENGTH, KM_OVER_KF).T)
        self._rotor = np.zeros((ctx.n, 4))

    @property
    def state(self) -> PlantState:
        """:class:`zenswarm.plant.quadrotor.PlantState` (q, v, rpy, w and the attitude PID's internals)."""
        return self._state

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Disturbance | None) -> None:
        """``ctx.substeps`` sub-steps of :func:`zenswarm.plant.quadrotor.step` (via
        :func:`~zenswarm.plant.quadrotor.step_held`), the command held."""
        c = self.ctx
        step_held(self._state, thrust, rpy, self.quad, c.h, c.substeps, disturbance)

    def record(self) -> Mapping[str, np.ndarray]:
        """``thrust`` (N,) N and ``torque`` (N, 3) N m: the wrench of the last physics sub-step
        (:attr:`zenswarm.plant.quadrotor.PlantState.wrench`; at tick 0 hover thrust, no torque);
        ``rotor_thrust`` (N, 4) N: that wrench through :func:`rotor_mixer` (the model applies the
        wrench itself, it has no rotors: these are the thrusts the Crazyflie's rotors would need)."""
        wr = self._state.wrench
        np.matmul(wr, self._mix_t, out=self._rotor)
        return {"thrust": wr[:, 0], "torque": wr[:, 1:], "rotor_thrust": self._rotor}

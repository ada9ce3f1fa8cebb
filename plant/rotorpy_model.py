"""RotorPy's multirotor as a zenswarm plant model (name ``rotorpy``; ``pip install -e '.[rotorpy]'``).

The vehicles are RotorPy's :class:`rotorpy.vehicles.multirotor.Multirotor` with its Crazyflie
parameters (:data:`rotorpy.vehicles.crazyflie_params.quad_params`: 30 g, arm 43 mm, thrust and yaw
moment coefficients, motor time constant 72 ms), flown through RotorPy's own collective thrust +
attitude control abstraction, ``cmd_ctatt``: each vehicle gets zenswarm's command unchanged in
meaning (thrust F N along body z; the attitude setpoint [phi_d, theta_d, psi_d], ZYX, as a unit
quaternion), RotorPy's attitude controller (``kp_att``, ``kd_att``) turns it into a moment, its
allocation into four rotor speeds, and its dynamics (:meth:`Multirotor._s_dot_fn`: rigid body,
first-order rotor dynamics, rotor drag and induced inflow with ``aero`` on) are integrated by
:func:`scipy.integrate.solve_ivp` (RotorPy's integrator, RK45 by default). Nothing of RotorPy is
copied: the model calls its functions.

Per control tick of ``dt`` the model takes ``steps_per_tick`` RotorPy steps (default 1: RotorPy's
usual 100 Hz at zenswarm's 100 Hz control rate); RotorPy's controller computes the rotor speed
command once per step and holds it, as :meth:`Multirotor.step` does. The model calls the pieces of
``Multirotor.step`` rather than ``step`` itself: ``step`` draws motor noise from numpy's global
generator on every call (even at zero noise), which a plug-in must not touch (determinism), and
takes no external disturbance.

Frames: RotorPy's world frame is z up and its body frame has z along the thrust, as zenswarm's
(ENU / FLU); quaternions are [x, y, z, w] (scalar last, :mod:`scipy.spatial.transform`).

Disturbances:

* the scenario's ``[disturbance]`` (:class:`zenswarm.plant.disturbance.DisturbanceModel`, the
  paper's lumped d_p of eq. 1 and d_a of eq. 5, accelerations, seeded) acts on the RotorPy vehicles
  as on the built-in ones: the same draws, added to RotorPy's state derivative (d_p to dv/dt, d_a
  to dw/dt), each RotorPy step holding the mean of the sub-steps it covers. So ``[disturbance]
  wind`` is an acceleration here too.
* air wind (a velocity, m/s, ENU), which only RotorPy models (it enters its rotor drag, the
  built-in model has no aerodynamics): ``[plant.params] wind`` (:class:`rotorpy.wind.default_winds.ConstantWind`)
  and ``wind_amplitude`` / ``wind_freq_hz`` (:class:`rotorpy.wind.default_winds.SinusoidWind`),
  summed. RotorPy's Dryden gusts draw from numpy's global generator, so they are not offered.

Records (:attr:`RotorPyModel.records`, in ``timeseries.npz`` as ``plant.<name>`` and in each state
message): ``rotor_speed`` (RotorPy's first-order motor state, rad/s), ``rotor_speed_cmd`` (what its
controller commanded for the last step, rad/s: what the motors lag behind, time constant
``tau_m`` = 72 ms) and ``rotor_thrust`` (k_eta omega^2 of each rotor, N: RotorPy's rotor thrust,
its translational lift ``k_h`` being 0 for the Crazyflie), rotors in RotorPy's order r1 .. r4:
front left, front right, back right, back left.

The vehicle the agents fly (:meth:`RotorPyModel.vehicle`) is RotorPy's: mass 0.030 kg (zenswarm's
Crazyflie 2.1 is 0.027 kg), inertia (1.43e-5, 1.43e-5, 2.89e-5) kg m^2, max thrust 4 k_eta
omega_max^2 = 0.575 N, g = 9.81 m/s^2: the paper's controller computes its thrust with this mass.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

import msgspec
import numpy as np

from zenswarm.plant.api import Disturbance, PlantContext, PlantModel, Signal
from zenswarm.scenario.plugins import PluginError
from zenswarm.vehicle.params import QuadParams

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = ["RotorPyModel", "RotorPyStates", "crazyflie_params"]

_INSTALL = "pip install 'zenswarm[rotorpy]' (from a checkout: pip install -e '.[rotorpy]')"
_STATE_LEN = 20  # RotorPy's state vector: x (3), v (3), q (4), w (3), wind (3), rotor speeds (4)


def crazyflie_params() -> dict[str, Any]:
    """RotorPy's Crazyflie parameters (a copy of its dict); PluginError naming ``plant.model`` when
    RotorPy is not installed."""
    try:
        from rotorpy.vehicles.crazyflie_params import quad_params
    except ImportError as e:
        raise PluginError("plant.model", f"plant model 'rotorpy' needs RotorPy, which is not installed ({e}): {_INSTALL}") from None
    return dict(quad_params)


class RotorPyStates:
    """The vehicles' state in zenswarm's terms (:class:`zenswarm.plant.api.VehicleStates`), (N, 3)
    each: q m, v m/s (ENU), rpy rad (ZYX, from RotorPy's quaternion), w rad/s (body)."""

    def __init__(self, n: int) -> None:
        self.q = np.zeros((n, 3))
        self.v = np.zeros((n, 3))
        self.rpy = np.zeros((n, 3))
        self.w = np.zeros((n, 3))


class RotorPyModel(PlantModel):
    """RotorPy's multirotor, Crazyflie parameters: rotor dynamics, aerodynamic drag, air wind; thrust + attitude (cmd_ctatt)."""

    name = "rotorpy"
    description = "RotorPy's multirotor, Crazyflie parameters: rotor dynamics, aerodynamic drag, air wind; thrust + attitude (cmd_ctatt)"
    records = MappingProxyType({
        "rotor_speed": Signal((4,), "rad/s", "RotorPy's rotor speeds, its first-order motor state (r1..r4: front left, front right, "
                              "back right, back left)"),
        "rotor_speed_cmd": Signal((4,), "rad/s", "the rotor speeds RotorPy's controller commanded for the last step (clipped), "
                                  "which the motors follow with time constant tau_m"),
        "rotor_thrust": Signal((4,), "N", "each rotor's thrust k_eta * rotor_speed^2"),
    })  # fmt: skip

    class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
        """``[plant.params]`` of the ``rotorpy`` model.

        steps_per_tick: RotorPy steps per control tick (>= 1, dividing ``timing.substeps``);
        RotorPy's attitude controller runs once per step. aero: RotorPy's aerodynamic wrench
        (rotor drag, induced inflow, parasitic drag). wind: constant air wind, m/s ENU.
        wind_amplitude, wind_freq_hz: sinusoidal air wind per axis, m/s and Hz.
        integrator: the :func:`scipy.integrate.solve_ivp` method of each step.
        """

        steps_per_tick: int = 1
        aero: bool = True
        wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
        wind_amplitude: tuple[float, float, float] = (0.0, 0.0, 0.0)
        wind_freq_hz: tuple[float, float, float] = (0.0, 0.0, 0.0)
        integrator: Literal["RK45", "RK23", "DOP853"] = "RK45"

    @classmethod
    def vehicle(cls, scenario: Scenario, params: Any) -> QuadParams:
        """RotorPy's Crazyflie (module docstring); the parameters checked against the scenario."""
        qp = crazyflie_params()
        if params.steps_per_tick < 1 or scenario.timing.substeps % params.steps_per_tick:
            raise PluginError(
                "plant.params.steps_per_tick",
                f"must be >= 1 and divide timing.substeps ({scenario.timing.substeps}), got {params.steps_per_tick}",
            )
        for key in ("wind", "wind_amplitude", "wind_freq_hz"):
            x = np.asarray(getattr(params, key), dtype=float)
            if not np.all(np.isfinite(x)) or (key == "wind_freq_hz" and np.any(x < 0)):
                what = "3 finite numbers >= 0" if key == "wind_freq_hz" else "3 finite numbers"
                raise PluginError(f"plant.params.{key}", f"must be {what}, got {x.tolist()}")
        base = QuadParams()
        max_thrust = float(qp["num_rotors"] * qp["k_eta"] * qp["rotor_speed_max"] ** 2)
        # the command clamp of the built-in (max_tilt) is kept; the rest is RotorPy's vehicle
        return QuadParams(
            mass=float(qp["mass"]), inertia=(float(qp["Ixx"]), float(qp["Iyy"]), float(qp["Izz"])), max_thrust=max_thrust,
            max_tilt=base.max_tilt if scenario.vehicle.max_tilt is None else float(scenario.vehicle.max_tilt), g=9.81,
        )  # fmt: skip

    def __init__(self, ctx: PlantContext, params: Any) -> None:
        super().__init__(ctx, params)
        from rotorpy.vehicles.multirotor import Multirotor
        from rotorpy.wind.default_winds import ConstantWind, SinusoidWind
        from scipy.integrate import solve_ivp
        from scipy.spatial.transform import Rotation

        self._solve_ivp = solve_ivp
        self._Rotation = Rotation
        qp = crazyflie_params()
        n = ctx.n
        self.quad = ctx.vehicle
        hover = float(np.sqrt(qp["mass"] * 9.81 / (qp["num_rotors"] * qp["k_eta"])))  # rad/s
        self.vehicles = [
            Multirotor(qp, control_abstraction="cmd_ctatt", aero=bool(params.aero), integrator_kwargs={"method": params.integrator})
            for _ in range(n)
        ]
        self.winds: list[Any] = []
        if any(params.wind):
            self.winds.append(ConstantWind(*params.wind))
        if any(params.wind_amplitude) and any(params.wind_freq_hz):
            self.winds.append(SinusoidWind(np.asarray(params.wind_amplitude, float), np.asarray(params.wind_freq_hz, float)))
        # RotorPy's state vectors, one per vehicle: at rest, level, rotors at hover speed
        self.s = np.zeros((n, _STATE_LEN))
        self.s[:, 0:3] = ctx.initial_positions
        self.s[:, 9] = 1.0  # q = [0, 0, 0, 1]
        self.s[:, 16:] = hover
        self.k_eta = float(qp["k_eta"])
        self.cmd_speeds = np.full((n, 4), hover)  # the last step's commanded rotor speeds (hover before the first)
        self.steps = int(params.steps_per_tick)
        self.t_step = ctx.dt / self.steps
        self.sub_per_step = ctx.substeps // self.steps
        self.tick = 0
        self._states = RotorPyStates(n)
        self._publish()

    @property
    def state(self) -> RotorPyStates:
        return self._states

    def _publish(self) -> None:
        """zenswarm's (q, v, rpy, w) from RotorPy's state vectors."""
        st, s = self._states, self.s
        st.q[...] = s[:, 0:3]
        st.v[...] = s[:, 3:6]
        st.rpy[...] = self._Rotation.from_quat(s[:, 6:10]).as_euler("ZYX")[:, ::-1]
        st.w[...] = s[:, 10:13]

    def _commands(self, thrust: np.ndarray, rpy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The built-in's command clamp (thrust to [0, max_thrust], roll and pitch to +-max_tilt,
        a NaN to the lower bound), then the setpoint as quaternions [x, y, z, w], (N, 4)."""
        p = self.quad
        f = np.fmin(np.fmax(np.asarray(thrust, dtype=float), 0.0), p.max_thrust)
        a = np.array(np.broadcast_to(np.asarray(rpy, dtype=float), (self.ctx.n, 3)))
        lim = np.array([p.max_tilt, p.max_tilt, 1e6])
        a = np.fmin(np.fmax(a, -lim), lim)
        quat = self._Rotation.from_euler("ZYX", a[:, ::-1]).as_quat()
        return f, quat

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Disturbance | None) -> None:
        """``steps_per_tick`` RotorPy steps of every vehicle with the command held (module docstring)."""
        from rotorpy.vehicles.multirotor import Multirotor

        n, c = self.ctx.n, self.ctx
        f, quat = self._commands(thrust, rpy)
        d_p = np.zeros((c.substeps, n, 3))
        d_a = np.zeros((c.substeps, n, 3))
        if disturbance is not None:
            for j in range(c.substeps):  # every sub-step's draw, in order, as the built-in model
                p_j, a_j = disturbance(j)
                if p_j is not None:
                    d_p[j] = p_j
                if a_j is not None:
                    d_a[j] = a_j
        t0 = self.tick * c.dt
        for k in range(self.steps):
            lo, hi = k * self.sub_per_step, (k + 1) * self.sub_per_step
            dp, da = d_p[lo:hi].mean(axis=0), d_a[lo:hi].mean(axis=0)
            t = t0 + k * self.t_step
            for i, veh in enumerate(self.vehicles):
                s = self.s[i]
                if self.winds:
                    s[13:16] = sum(w.update(t, s[0:3]) for w in self.winds)
                state = Multirotor._unpack_state(s)
                cmd = veh.get_cmd_motor_speeds(state, {"cmd_thrust": f[i], "cmd_q": quat[i]})
                cmd = np.clip(cmd, veh.rotor_speed_min, veh.rotor_speed_max)
                self.cmd_speeds[i] = cmd
                extra = np.zeros(_STATE_LEN)
                extra[3:6] = dp[i]
                extra[10:13] = da[i]

                def rhs(tt: float, ss: np.ndarray, veh: Any = veh, cmd: np.ndarray = cmd, extra: np.ndarray = extra) -> np.ndarray:
                    out: np.ndarray = veh._s_dot_fn(tt, ss, cmd) + extra
                    return out

                sol = self._solve_ivp(rhs, (0.0, self.t_step), s, **veh.integrator_kwargs)
                s_new = sol["y"][:, -1]
                # as Multirotor.step after its integration: the quaternion renormalised, the rotor
                # speeds clipped to their range (its motor noise and ground contact left out)
                s_new[6:10] /= np.linalg.norm(s_new[6:10])
                s_new[16:] = np.clip(s_new[16:], veh.rotor_speed_min, veh.rotor_speed_max)
                self.s[i] = s_new
        self.tick += 1
        self._publish()

    def record(self) -> dict[str, np.ndarray]:
        """``rotor_speed`` (N, 4) rad/s, ``rotor_speed_cmd`` (N, 4) rad/s, ``rotor_thrust`` (N, 4) N (module docstring)."""
        w = self.s[:, 16:20].copy()
        return {"rotor_speed": w, "rotor_speed_cmd": self.cmd_speeds.copy(), "rotor_thrust": self.k_eta * (w * w)}

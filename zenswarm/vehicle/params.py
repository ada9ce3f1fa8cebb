"""Crazyflie 2.1 physical parameters and onboard attitude-controller gains.

Pure data: imports the standard library only (``zenswarm.schema`` is imported lazily for type
hints). Units are SI; every default names its source.

The onboard attitude controller is a cascade like the Crazyflie firmware's (``controller_pid``):
angle error -> P -> body-rate setpoint (clamped to ``max_rate``) -> rate PID -> torque (clamped to
``max_torque``); see :func:`zenswarm.plant.quadrotor.step`. The firmware's gains act on PWM-scaled units, so
the gains below are ours, chosen in SI for these inertias and a 1 kHz update:

* rate loop: ``rate_kp = 200 J /s`` (rate bandwidth 200 rad/s), ``rate_ki = 800 J /s^2``
  (integral zero at 4 rad/s), ``rate_kd = 0.05 J`` (adds 5 % effective inertia: a little damping
  for the one-sample delay of the backward-difference derivative);
* angle loop: ``att_kp = 40 /s``.

Linearised per axis (no saturation, continuous time) the closed angle loop is
(J + Kd) s^3 + (Kp + Kd Ka) s^2 + (Kp Ka + Ki) s + Ki Ka = 0, whose roots for these numbers are
-129, -59 and -4.0 rad/s; the slow one is almost cancelled by the integral zero at -Ki/Kp = -4,
so a step settles to 2 % in about 0.08 s with under 1 % overshoot, and a constant disturbance
torque is removed with a time constant of about 0.25 s. These are normalised by J, so the loop
behaves the same on every axis. The discrete loop is designed for a 1 kHz update; it stays well
damped up to dt = 5 ms and degrades beyond (at 10 ms it rings). ``tests/test_plant.py`` checks
the step response of the nonlinear, saturated loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, cast

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.schema import VehicleConfig

__all__ = ["QuadParams", "THRUST_TO_WEIGHT", "ARM_LENGTH", "KM_OVER_KF"]

G: float = 9.81
"""Standard gravity used throughout, m/s^2."""

THRUST_TO_WEIGHT: float = 2.25
"""Crazyflie 2.x thrust-to-weight ratio, as in gym-pybullet-drones' ``cf2x.urdf``
(``thrust2weight="2.25"``)."""

_MASS = 0.027
# Bitcraze Crazyflie 2.1 datasheet: take-off weight 27 g.

_INERTIA = (1.657171e-5, 1.6655602e-5, 2.9261652e-5)
# Diagonal of J identified in J. Foerster, "System Identification of the Crazyflie 2.0 Nano
# Quadrocopter", BSc thesis, ETH Zurich 2015 (kg m^2; off-diagonal terms < 1e-6 neglected).

_MAX_THRUST = THRUST_TO_WEIGHT * _MASS * G
# 2.25 * m * g = 0.5959 N (thrust-to-weight 2.25, gym-pybullet-drones cf2x).

_ARM = 0.0397
# Motor arm length L, m (gym-pybullet-drones cf2x.urdf, arm="0.0397").

_KM_OVER_KF = 7.94e-12 / 3.16e-10
# Rotor drag-to-thrust coefficient ratio km/kf, m (gym-pybullet-drones cf2x.urdf: kf=3.16e-10,
# km=7.94e-12).

ARM_LENGTH: float = _ARM
"""Motor arm length L of the Crazyflie 2.x, m (gym-pybullet-drones cf2x.urdf): the X layout's
torque bounds below, and the rotor thrusts the built-in plant model records
(:func:`zenswarm.plant.api.rotor_mixer`)."""

KM_OVER_KF: float = _KM_OVER_KF
"""A rotor's drag torque per unit of its thrust, km/kf, m (gym-pybullet-drones cf2x.urdf)."""

_MAX_TORQUE = (
    2.0 * _ARM * (_MAX_THRUST / 4.0) / 2.0**0.5,
    2.0 * _ARM * (_MAX_THRUST / 4.0) / 2.0**0.5,
    2.0 * _KM_OVER_KF * (_MAX_THRUST / 4.0),
)
# Per-axis torque limits, N m, as gym-pybullet-drones computes them for the X configuration
# (BaseAviary: MAX_XY_TORQUE = 2 L kf w_max^2 / sqrt(2), MAX_Z_TORQUE = 2 km w_max^2, with
# kf w_max^2 = max_thrust / 4): (8.36e-3, 8.36e-3, 7.49e-3) N m.

# Normalised attitude-loop design (ours, see the module docstring).
_RATE_BW = 200.0  # rate-loop proportional gain / J, 1/s
_RATE_KI_N = 800.0  # rate-loop integral gain / J, 1/s^2
_RATE_KD_N = 0.05  # rate-loop derivative gain / J, dimensionless (extra effective inertia)
_ATT_KP = 40.0  # angle-loop gain, 1/s


@dataclass(frozen=True)
class QuadParams:
    """Physical and onboard-controller parameters of one quadrotor (all UAVs share them).

    Attributes
    ----------
    mass : float
        m, kg; eq. (1). Default 0.027 (Crazyflie 2.1 datasheet).
    inertia : (3,) tuple
        diag(J) = (J_xx, J_yy, J_zz), kg m^2, body FLU; eq. (5). Default from Foerster (2015).
    max_thrust : float
        Upper bound of the collective thrust F, N; eq. (1). Default 2.25 m g.
    max_tilt : float
        Bound on the commanded roll and pitch, rad (ours).
    g : float
        Gravity, m/s^2; G = [0, 0, g] in eq. (1).
    att_kp : (3,) tuple
        Angle-loop P gain, (rad/s) per rad (ours).
    rate_kp, rate_ki, rate_kd : (3,) tuples
        Body-rate PID gains, N m per (rad/s), N m per rad, N m per (rad/s^2) (ours).
    max_rate : float
        Clamp on the body-rate setpoint, rad/s (ours; the Crazyflie gyro range is 2000 deg/s).
    max_torque : (3,) tuple
        Per-axis clamp on the commanded torque tau, N m; eq. (5).
    """

    mass: float = _MASS
    inertia: tuple[float, float, float] = _INERTIA
    max_thrust: float = _MAX_THRUST
    max_tilt: float = 0.6  # rad, ours (~34 deg)
    g: float = G
    att_kp: tuple[float, float, float] = (_ATT_KP, _ATT_KP, _ATT_KP)  # 1/s, ours
    rate_kp: tuple[float, float, float] = cast("tuple[float, float, float]", tuple(_RATE_BW * j for j in _INERTIA))  # N m s/rad, ours
    rate_ki: tuple[float, float, float] = cast("tuple[float, float, float]", tuple(_RATE_KI_N * j for j in _INERTIA))  # N m/rad, ours
    rate_kd: tuple[float, float, float] = cast("tuple[float, float, float]", tuple(_RATE_KD_N * j for j in _INERTIA))  # N m s^2/rad, ours
    max_rate: float = 10.0  # rad/s (~570 deg/s), ours
    max_torque: tuple[float, float, float] = _MAX_TORQUE  # N m, gym-pybullet-drones cf2x

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ValueError:
            return ValueError(f"QuadParams.{name} {why}, got {getattr(self, name)!r}")

        for name in ("mass", "max_thrust", "g", "max_rate"):
            x = getattr(self, name)
            if not (math.isfinite(x) and x > 0):
                raise bad(name, "must be a positive finite number")
        if not (0 < self.max_tilt < math.pi / 2):
            raise bad("max_tilt", "must be in (0, pi/2) rad")
        for name in ("inertia", "att_kp", "rate_kp", "rate_ki", "rate_kd", "max_torque"):
            x = getattr(self, name)
            if len(x) != 3 or not all(math.isfinite(v) for v in x):
                raise bad(name, "must be 3 finite numbers")
            strict = name in ("inertia", "max_torque")  # zero gains: open loop (tests)
            if any((v <= 0) if strict else (v < 0) for v in x):
                raise bad(name, "must be > 0" if strict else "must be >= 0")

    @property
    def thrust_to_weight(self) -> float:
        """max_thrust / (m g), dimensionless."""
        return self.max_thrust / (self.mass * self.g)

    @property
    def hover_thrust(self) -> float:
        """m g, N."""
        return self.mass * self.g

    @classmethod
    def from_vehicle(cls, vehicle: VehicleConfig | None) -> QuadParams:
        """Defaults with the scenario's ``[vehicle]`` overrides applied.

        ``None`` fields keep the default. If ``mass`` is overridden and ``max_thrust`` is not,
        ``max_thrust`` is scaled to keep the thrust-to-weight ratio 2.25. The onboard controller
        is rescaled so the attitude loop keeps its designed dynamics: rate gains scale with the
        per-axis inertia (they are torques per unit rate error) and ``max_torque`` scales with
        ``max_thrust`` (both come from the same rotors).
        """
        p = cls()
        if vehicle is None:
            return p
        mass = p.mass if vehicle.mass is None else float(vehicle.mass)
        inertia = p.inertia if vehicle.inertia is None else tuple(float(x) for x in vehicle.inertia)
        if vehicle.max_thrust is not None:
            max_thrust = float(vehicle.max_thrust)
        elif vehicle.mass is not None:
            max_thrust = THRUST_TO_WEIGHT * mass * p.g
        else:
            max_thrust = p.max_thrust
        max_tilt = p.max_tilt if vehicle.max_tilt is None else float(vehicle.max_tilt)
        js = tuple(n / d for n, d in zip(inertia, p.inertia, strict=True))
        ts = max_thrust / p.max_thrust
        return replace(
            p,
            mass=mass,
            inertia=inertia,  # type: ignore[arg-type]
            max_thrust=max_thrust,
            max_tilt=max_tilt,
            rate_kp=tuple(k * s for k, s in zip(p.rate_kp, js, strict=True)),  # type: ignore[arg-type]
            rate_ki=tuple(k * s for k, s in zip(p.rate_ki, js, strict=True)),  # type: ignore[arg-type]
            rate_kd=tuple(k * s for k, s in zip(p.rate_kd, js, strict=True)),  # type: ignore[arg-type]
            max_torque=tuple(t * ts for t in p.max_torque),  # type: ignore[arg-type]
        )

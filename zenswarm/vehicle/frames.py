"""Frame conversions between the swarm (ENU / FLU, the paper's ZYX Euler angles) and MAVLink
(NED / FRD, quaternions, normalised thrust). This module is the only place where ENU/FLU <->
NED/FRD conversion happens; the MAVLink bridge and the simulated MAVLink vehicle both call it.

Pure numerics: numpy and the standard library only. Every function works on one vector or on a
stack (leading dimensions broadcast), returns new float64 arrays and never mutates its input.

Frames
------
* Swarm, as in the paper: inertial ENU (x east, y north, z up); body FLU (x forward, y left,
  z up along the thrust). Attitude: ZYX Euler angles Theta = [phi, theta, psi] with
  R(Theta) = Rz(psi) Ry(theta) Rx(phi), body -> inertial (eq. 2).
* MAVLink (PX4, ArduPilot): inertial NED (x north, y east, z down) in ``LOCAL_POSITION_NED``
  and ``SET_POSITION_TARGET_LOCAL_NED``; body FRD (x forward, y right, z down) for body rates.
  Attitude: the quaternion q = (w, x, y, z) that rotates NED into FRD (``SET_ATTITUDE_TARGET.q``,
  ``ATTITUDE_QUATERNION``; its rotation matrix maps FRD vectors to NED), or ZYX Euler angles
  (roll, pitch, yaw) of the same rotation (``ATTITUDE``), yaw measured from north towards east.

The fixed maps are the permutation/reflection matrices

    T = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]    v_ned = T v_enu     (T = T^T = T^-1)
    F = diag(1, -1, -1)                       v_frd = F v_flu     (F = F^T = F^-1)

so the body-to-inertial rotation in MAVLink frames is R_ned = T R_enu F. For ZYX Euler angles
this is, in closed form (checked in ``tests/test_mavlink.py`` against the matrix product):

    roll = phi,    pitch = -theta,    yaw = pi/2 - psi   (wrapped to (-pi, pi])

and, since the map is an involution, the same formula converts back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "T_ENU_NED",
    "F_FLU_FRD",
    "wrap_pi",
    "enu_to_ned",
    "ned_to_enu",
    "flu_to_frd",
    "frd_to_flu",
    "euler_enu_to_ned",
    "euler_ned_to_enu",
    "euler_to_quat",
    "quat_to_euler",
    "quat_to_rotation",
    "rotation_to_quat",
    "quat_normalize",
    "attitude_to_quat_ned",
    "quat_ned_to_attitude",
    "ThrustMap",
]

T_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""v_ned = T v_enu (and v_enu = T v_ned): swap x and y, negate z."""
T_ENU_NED.setflags(write=False)

F_FLU_FRD = np.diag([1.0, -1.0, -1.0])
"""v_frd = F v_flu (and back): negate y and z."""
F_FLU_FRD.setflags(write=False)

_PI = math.pi
_TWO_PI = 2.0 * math.pi


def _vec3(x: Any, name: str) -> np.ndarray:
    a = np.array(x, dtype=float)  # a copy
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {a.shape}")
    return a


def wrap_pi(a: Any) -> np.ndarray:
    """Wrap angles to (-pi, pi], rad (same formula as :func:`zenswarm.plant.quadrotor.wrap_angle`)."""
    a = np.asarray(a, dtype=float)
    w: np.ndarray = _PI - np.remainder(_PI - a, _TWO_PI)
    return w


# --------------------------------------------------------------------------- vectors


def enu_to_ned(v: Any) -> np.ndarray:
    """Inertial vector ENU -> NED: (x, y, z) -> (y, x, -z).

    v: (..., 3) position (m), velocity (m/s) or acceleration (m/s^2), ENU -> same shape, NED.
    """
    a = _vec3(v, "v")
    out = np.empty_like(a)
    out[..., 0] = a[..., 1]
    out[..., 1] = a[..., 0]
    out[..., 2] = -a[..., 2]
    return out


def ned_to_enu(v: Any) -> np.ndarray:
    """Inertial vector NED -> ENU: (x, y, z) -> (y, x, -z) (the same involution).

    v: (..., 3) m, m/s or m/s^2, NED -> same shape, ENU.
    """
    return enu_to_ned(v)


def flu_to_frd(w: Any) -> np.ndarray:
    """Body vector FLU -> FRD: (x, y, z) -> (x, -y, -z).

    w: (..., 3), e.g. body rates (p, q, r) rad/s -> same shape, FRD.
    """
    a = _vec3(w, "w")
    a[..., 1] = -a[..., 1]
    a[..., 2] = -a[..., 2]
    return a


def frd_to_flu(w: Any) -> np.ndarray:
    """Body vector FRD -> FLU: (x, y, z) -> (x, -y, -z) (the same involution)."""
    return flu_to_frd(w)


# --------------------------------------------------------------------------- attitude


def euler_enu_to_ned(rpy: Any) -> np.ndarray:
    """Paper ZYX Euler angles (phi, theta, psi) in ENU/FLU -> (roll, pitch, yaw) in NED/FRD.

    rpy: (..., 3) rad. Returns (phi, -theta, wrap(pi/2 - psi)), rad; yaw in (-pi, pi].
    Exact for every attitude (the rotation matrices agree: R_ned = T R_enu F).
    """
    a = _vec3(rpy, "rpy")
    a[..., 1] = -a[..., 1]
    a[..., 2] = wrap_pi(0.5 * _PI - a[..., 2])
    return a


def euler_ned_to_enu(rpy: Any) -> np.ndarray:
    """MAVLink (roll, pitch, yaw) in NED/FRD -> paper (phi, theta, psi) in ENU/FLU.

    rpy: (..., 3) rad (e.g. ``ATTITUDE.roll/pitch/yaw``). Returns (roll, -pitch,
    wrap(pi/2 - yaw)), rad.
    """
    return euler_enu_to_ned(rpy)


def euler_to_quat(rpy: Any) -> np.ndarray:
    """ZYX Euler angles -> unit quaternion (w, x, y, z) of R = Rz(yaw) Ry(pitch) Rx(roll).

    rpy: (..., 3) rad -> (..., 4), w >= 0 (the sign is chosen so; q and -q are one rotation).
    Frame-agnostic: give NED angles to get the MAVLink quaternion (see
    :func:`attitude_to_quat_ned`).
    """
    a = _vec3(rpy, "rpy")
    h = 0.5 * a
    cr, cp, cy = np.cos(h[..., 0]), np.cos(h[..., 1]), np.cos(h[..., 2])
    sr, sp, sy = np.sin(h[..., 0]), np.sin(h[..., 1]), np.sin(h[..., 2])
    q = np.empty(a.shape[:-1] + (4,))
    q[..., 0] = cr * cp * cy + sr * sp * sy
    q[..., 1] = sr * cp * cy - cr * sp * sy
    q[..., 2] = cr * sp * cy + sr * cp * sy
    q[..., 3] = cr * cp * sy - sr * sp * cy
    return _canonical(q)


def _canonical(q: np.ndarray) -> np.ndarray:
    neg = q[..., 0] < 0
    if np.any(neg):
        q[neg] = -q[neg]
    return q


def quat_normalize(q: Any) -> np.ndarray:
    """Unit quaternion with w >= 0. q: (..., 4), (w, x, y, z). Raises ValueError if some q has
    norm below 1e-9 or is not finite (it does not describe a rotation)."""
    a = np.array(q, dtype=float)
    if a.ndim == 0 or a.shape[-1] != 4:
        raise ValueError(f"q must have shape (..., 4), got {a.shape}")
    n = np.linalg.norm(a, axis=-1, keepdims=True)
    if not np.all(np.isfinite(n)) or np.any(n < 1e-9):
        raise ValueError("quaternion is zero or not finite")
    return _canonical(a / n)


def quat_to_euler(q: Any) -> np.ndarray:
    """Quaternion (w, x, y, z) -> ZYX Euler angles (roll, pitch, yaw), rad.

    q: (..., 4), normalised here. roll, yaw in (-pi, pi]; pitch in [-pi/2, pi/2] (at
    pitch = +-pi/2 the split between roll and yaw is arbitrary; this returns a valid one).
    """
    u = quat_normalize(q)
    w, x, y, z = u[..., 0], u[..., 1], u[..., 2], u[..., 3]
    out = np.empty(u.shape[:-1] + (3,))
    out[..., 0] = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    out[..., 1] = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    out[..., 2] = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return out


def quat_to_rotation(q: Any) -> np.ndarray:
    """Quaternion (w, x, y, z) -> rotation matrix (..., 3, 3) (body -> inertial); normalised here."""
    u = quat_normalize(q)
    w, x, y, z = u[..., 0], u[..., 1], u[..., 2], u[..., 3]
    R = np.empty(u.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotation_to_quat(R: Any) -> np.ndarray:
    """Rotation matrix (..., 3, 3) -> unit quaternion (..., 4), w >= 0 (Shepperd's method: the
    largest of 4w^2, 4x^2, 4y^2, 4z^2 is taken as pivot, so it is accurate for every rotation)."""
    M = np.array(R, dtype=float)
    if M.ndim < 2 or M.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {M.shape}")
    flat = M.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for k, m in enumerate(flat):  # small stacks only (telemetry, tests); not a hot path
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        cands = (tr, m[0, 0], m[1, 1], m[2, 2])
        i = int(np.argmax(cands))
        if i == 0:
            s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
            q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
        elif i == 1:
            s = 2.0 * math.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
            q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
        elif i == 2:
            s = 2.0 * math.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0))
            q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
        else:
            s = 2.0 * math.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0))
            q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
        out[k] = q
    return quat_normalize(out.reshape(M.shape[:-2] + (4,)))


def attitude_to_quat_ned(rpy_enu: Any) -> np.ndarray:
    """Paper attitude (phi, theta, psi), ENU/FLU, rad -> MAVLink quaternion (w, x, y, z), NED/FRD.

    rpy_enu: (..., 3) -> (..., 4), unit, w >= 0. This is what ``SET_ATTITUDE_TARGET.q`` carries
    for the agent's attitude command (eq. 28 and the inversion after it).
    """
    return euler_to_quat(euler_enu_to_ned(rpy_enu))


def quat_ned_to_attitude(q_ned: Any) -> np.ndarray:
    """MAVLink quaternion (w, x, y, z), NED/FRD -> paper attitude (phi, theta, psi), ENU/FLU, rad.

    q_ned: (..., 4), normalised here -> (..., 3). Inverse of :func:`attitude_to_quat_ned` (up to
    angle wrapping, and away from pitch = +-pi/2).
    """
    return euler_ned_to_enu(quat_to_euler(q_ned))


# --------------------------------------------------------------------------- thrust


@dataclass(frozen=True)
class ThrustMap:
    """Collective thrust, newtons <-> normalised throttle 0..1 (``SET_ATTITUDE_TARGET.thrust``).

    Linear through zero. By default ``u = F / max_thrust`` (hover then maps to
    ``1 / thrust_to_weight``, 0.444 for the Crazyflie). With ``hover_throttle`` set (PX4
    ``MPC_THR_HOVER``, ArduPilot ``MOT_THST_HOVER``: the throttle at which the real vehicle
    hovers) the slope is chosen so that ``hover_thrust`` maps to it: ``u = F hover_throttle /
    hover_thrust``. Results are clipped to [0, 1] (thrust to [0, thrust at u = 1]).

    Attributes: max_thrust (N, > 0); hover_thrust (N, > 0; needed with hover_throttle);
    hover_throttle (in (0, 1), or None for the default map).
    """

    max_thrust: float
    hover_thrust: float | None = None
    hover_throttle: float | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.max_thrust, (int, float)) and math.isfinite(self.max_thrust) and self.max_thrust > 0):
            raise ValueError(f"ThrustMap.max_thrust must be a positive finite number of newtons, got {self.max_thrust!r}")
        if self.hover_throttle is not None:
            h = self.hover_throttle
            if not (isinstance(h, (int, float)) and math.isfinite(h) and 0.0 < h < 1.0):
                raise ValueError(f"ThrustMap.hover_throttle must be in (0, 1), got {h!r}")
            ht = self.hover_thrust
            if not (isinstance(ht, (int, float)) and math.isfinite(ht) and ht > 0):
                raise ValueError(
                    f"ThrustMap.hover_thrust must be a positive finite number of newtons when hover_throttle is set, got {ht!r}"
                )

    @property
    def slope(self) -> float:
        """Normalised throttle per newton, 1/N."""
        if self.hover_throttle is None:
            return 1.0 / self.max_thrust
        return self.hover_throttle / float(self.hover_thrust)  # type: ignore[arg-type]

    def to_normalized(self, thrust_n: Any) -> np.ndarray | float:
        """Thrust F, N (scalar or array) -> throttle in [0, 1] (NaN -> 0)."""
        u = np.clip(np.nan_to_num(np.asarray(thrust_n, dtype=float) * self.slope, nan=0.0), 0.0, 1.0)
        return float(u) if u.ndim == 0 else u

    def to_newtons(self, throttle: Any) -> np.ndarray | float:
        """Throttle (scalar or array; clipped to [0, 1], NaN -> 0) -> thrust F, N."""
        u = np.clip(np.nan_to_num(np.asarray(throttle, dtype=float), nan=0.0), 0.0, 1.0)
        f = u / self.slope
        return float(f) if f.ndim == 0 else f

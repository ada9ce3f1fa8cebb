"""Quadrotor rigid-body model (paper eqs 1-5) with the onboard attitude PID, vectorised over N UAVs.

Pure numerics: numpy and the standard library's ``math`` only; no I/O, no clock, no globals that
change. Frames as in the paper: inertial ENU (z up), body FLU (x forward, z along the thrust).

State of UAV i (rows of :class:`PlantState`): position q_i and velocity v_i (inertial, eq. 1/3),
Euler angles Theta_i = [phi, theta, psi] (ZYX, eq. 2) and body angular velocity omega_i (eq. 5).

Input of one physics sub-step (:func:`step`): collective thrust F_i (eq. 1) and the attitude
setpoint [phi_d, theta_d, psi_d] of the inversion after eq. (28); the onboard attitude controller
turns the setpoint into the body torque tau_i of eq. (5), as the Crazyflie firmware does.

Performance: :func:`step` is the simulator's inner loop (1 kHz per UAV), so it uses whole-array
numpy operations with preallocated scratch buffers and precomputed constants (a small
``_Compiled`` object cached on the state, rebuilt when ``params``, ``dt`` or N change); it has
no Python loop over UAVs. It is not thread-safe for one state shared between threads.

:func:`step_held` runs the sub-steps of one control period (the command held) and is what the
simulator and the plant process call. For a few UAVs (N <= :data:`SCALAR_MAX_N`) it runs them on
Python floats, UAV by UAV, with the very same operations in the same order as :func:`step`: a
numpy ufunc costs about 0.4 us whatever the size of a (3, 3) operand, so at N = 3 ten numpy
sub-steps cost about 3.5x the scalar ones. Both paths give bit-identical states
(``tests/test_plant.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from zenswarm.vehicle.params import QuadParams

__all__ = [
    "rotation_matrix",
    "euler_rate_matrix",
    "PlantState",
    "initial_state",
    "step",
    "step_held",
    "SCALAR_MAX_N",
    "wrap_angle",
    "COS_THETA_MIN",
    "YAW_CMD_MAX",
]

COS_THETA_MIN = 1e-6
"""Guard on |cos(theta)| in the Euler kinematics (4); see :func:`step`."""

YAW_CMD_MAX = 1e6
"""Yaw setpoints are clamped to +-YAW_CMD_MAX rad before wrapping (keeps the state finite for
any command, including inf and NaN)."""

SCALAR_MAX_N = 10
"""Largest N for which :func:`step_held` integrates on Python floats rather than with numpy
(measured on the project's 2-core machine: ten sub-steps cost the same both ways at N = 12)."""

_PI = math.pi
_TWO_PI = 2.0 * math.pi
_INV_TWO_PI = 1.0 / _TWO_PI


def wrap_angle(a: Any) -> np.ndarray:
    """Wrap angles to (-pi, pi], rad: a - 2 pi ceil(a / (2 pi) - 1/2) (the formula :func:`step`
    applies to the Euler angles).

    a: array_like, rad -> ndarray of the same shape. Values inside (-pi, pi) are returned
    bit-exactly; within one rounding of +-pi the result may be off the interval by an ulp.
    """
    a = np.asarray(a, dtype=float)
    w: np.ndarray = a - _TWO_PI * np.ceil(a * (1.0 / _TWO_PI) - 0.5)
    return w


def rotation_matrix(rpy: Any) -> np.ndarray:
    """Rotation matrix R(Theta) of eq. (2), ZYX Euler angles, body (FLU) -> inertial (ENU).

    Parameters
    ----------
    rpy : (N, 3) or (3,) array_like
        [phi, theta, psi] roll, pitch, yaw, rad.

    Returns
    -------
    R : (N, 3, 3) or (3, 3) ndarray
        R = Rz(psi) Ry(theta) Rx(phi); eq. (2) entry by entry. A body vector b maps to R @ b.
    """
    a = np.asarray(rpy, dtype=float)
    single = a.ndim == 1
    a = np.atleast_2d(a)
    if a.shape[-1] != 3:
        raise ValueError(f"rpy must have shape (N, 3) or (3,), got {np.shape(rpy)}")
    s = np.sin(a)
    c = np.cos(a)
    sf, st, sp = s[:, 0], s[:, 1], s[:, 2]
    cf, ct, cp = c[:, 0], c[:, 1], c[:, 2]
    R = np.empty((a.shape[0], 3, 3))
    R[:, 0, 0] = ct * cp
    R[:, 0, 1] = cp * st * sf - sp * cf
    R[:, 0, 2] = cp * st * cf + sp * sf
    R[:, 1, 0] = ct * sp
    R[:, 1, 1] = sp * st * sf + cp * cf
    R[:, 1, 2] = sp * st * cf - cp * sf
    R[:, 2, 0] = -st
    R[:, 2, 1] = sf * ct
    R[:, 2, 2] = cf * ct
    return R[0] if single else R


def euler_rate_matrix(rpy: Any) -> np.ndarray:
    """Euler-rate matrix T(Theta) of eq. (4): d/dt [phi, theta, psi] = T(Theta) omega.

    Parameters
    ----------
    rpy : (N, 3) or (3,) array_like
        [phi, theta, psi], rad. Singular at cos(theta) = 0 (gimbal lock); no guard here.

    Returns
    -------
    T : (N, 3, 3) or (3, 3) ndarray
        Maps body rates omega (rad/s, FLU; eq. 5) to Euler-angle rates (rad/s).
    """
    a = np.asarray(rpy, dtype=float)
    single = a.ndim == 1
    a = np.atleast_2d(a)
    if a.shape[-1] != 3:
        raise ValueError(f"rpy must have shape (N, 3) or (3,), got {np.shape(rpy)}")
    sf, cf = np.sin(a[:, 0]), np.cos(a[:, 0])
    tt, ct = np.tan(a[:, 1]), np.cos(a[:, 1])
    T = np.zeros((a.shape[0], 3, 3))
    T[:, 0, 0] = 1.0
    T[:, 0, 1] = tt * sf
    T[:, 0, 2] = tt * cf
    T[:, 1, 1] = cf
    T[:, 1, 2] = -sf
    T[:, 2, 1] = sf / ct
    T[:, 2, 2] = cf / ct
    return T[0] if single else T


@dataclass(eq=False)
class PlantState:
    """State of N quadrotors, updated in place by :func:`step`.

    :func:`step` writes ``q``, ``v``, ``rpy``, ``w`` and ``rate_int`` in place (views stay valid)
    and rebinds ``rate_err_prev`` to a fresh array. Arrays are converted to float64 on
    construction; all must have shape (N, 3).

    Attributes
    ----------
    q : (N, 3) ndarray
        Position, m, ENU; eq. (1).
    v : (N, 3) ndarray
        Velocity, m/s, ENU; eq. (3).
    rpy : (N, 3) ndarray
        Euler angles [phi, theta, psi] (ZYX, eq. 2), rad, each wrapped to (-pi, pi] by
        :func:`step` (pitch leaves [-pi/2, pi/2] only if the vehicle tumbles over).
    w : (N, 3) ndarray
        Body angular velocity omega, rad/s, FLU; eq. (5).
    rate_int : (N, 3) ndarray
        Onboard controller: integral of the body-rate error, rad (clamped, anti-windup).
    rate_err_prev : (N, 3) ndarray
        Onboard controller: body-rate error of the previous sub-step, rad/s (derivative term).
    wrench : (N, 4) ndarray
        The wrench applied over the last sub-step :func:`step_held` ran (written at its last
        sub-step, in place): [F, tau_x, tau_y, tau_z], the clamped collective thrust F (N) and the
        onboard controller's clamped body torque tau (N m, FLU). Zeros unless given; :func:`step`
        writes it only when asked (``wrench_out``). Not part of the dynamics: a record.
    """

    q: np.ndarray
    v: np.ndarray
    rpy: np.ndarray
    w: np.ndarray
    rate_int: np.ndarray
    rate_err_prev: np.ndarray
    _cache: Any = field(default=None, repr=False, compare=False)
    wrench: Any = field(default=None, compare=False)

    def __post_init__(self) -> None:
        n = np.shape(self.q)[0] if np.ndim(self.q) == 2 else -1
        for name in ("q", "v", "rpy", "w", "rate_int", "rate_err_prev"):
            a = np.asarray(getattr(self, name), dtype=float)
            if a.shape != (n, 3):
                raise ValueError(f"PlantState.{name} must have shape (N, 3) with N = len(q), got {a.shape}")
            object.__setattr__(self, name, a)
        wr = np.zeros((n, 4)) if self.wrench is None else np.array(self.wrench, dtype=float)
        if wr.shape != (n, 4):
            raise ValueError(f"PlantState.wrench must have shape (N, 4) with N = len(q), got {wr.shape}")
        self.wrench = wr

    @property
    def n(self) -> int:
        """Number of UAVs N."""
        n: int = self.q.shape[0]
        return n

    def copy(self) -> PlantState:
        """A deep copy (own arrays; scratch buffers are not shared)."""
        return PlantState(
            q=self.q.copy(),
            v=self.v.copy(),
            rpy=self.rpy.copy(),
            w=self.w.copy(),
            rate_int=self.rate_int.copy(),
            rate_err_prev=self.rate_err_prev.copy(),
            wrench=self.wrench.copy(),
        )


def initial_state(q0: Any) -> PlantState:
    """At rest, level, yaw 0, controller internals zero.

    q0: (N, 3) array_like, m, ENU -> :class:`PlantState` with N rows.
    """
    q = np.array(q0, dtype=float, copy=True)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"q0 must have shape (N, 3), got {q.shape}")
    n = q.shape[0]

    def z() -> np.ndarray:
        return np.zeros((n, 3))

    return PlantState(q=q, v=z(), rpy=z(), w=z(), rate_int=z(), rate_err_prev=z())


def _full(x: Any, n: int) -> np.ndarray:
    """x broadcast to a C-contiguous (n, 3) float array."""
    return np.ascontiguousarray(np.broadcast_to(np.asarray(x, dtype=float), (n, 3)))


class _Compiled:
    """Constants of :func:`step` for one (params, dt, N), pre-broadcast to (N, 3) (numpy
    broadcasting a (3,) operand costs about 3x a same-shape operation), plus scratch buffers;
    grouped by the phase of :func:`step` that reads them (``ctl``, ``body``) and
    as Python floats for :func:`_step_held_scalar` (``scalars``)."""

    def __init__(self, p: QuadParams, dt: float, n: int) -> None:
        self.params = p
        self.dt = dt
        self.n = n
        self._constants(p, dt, n)
        self._scratch(n)
        self.ctl = (
            *(self.zero, self.fmax, self.cmd_lo, self.cmd_hi, self.pi, self.two_pi, self.att_kp, self.rate_lo, self.rate_hi),
            *(self.dt0, self.int_lo, self.int_hi, self.k_e, self.k_prev, self.ki, self.tau_lo, self.tau_hi, self.tmp, self.Fb),
        )
        self.body = (
            *(self.G, self.G0, self.G1, self.G2, self.jinv_dt, self.gyro_dt, self.dt0, self.tmp, self.S, self.C),
            *(self.sf, self.st, self.sp, self.cf, self.ct, self.cp, self.cos_min, self.E, self.e0, self.e1, self.e2),
            *(self.t1, self.t2, self.t3, self.t4, self.inv_two_pi, self.half, self.two_pi, self.fdt_m, self.g_dt),
        )
        self.scalars = self._scalars(dt)

    def _constants(self, p: QuadParams, dt: float, n: int) -> None:
        J = np.asarray(p.inertia, dtype=float)
        kp = np.asarray(p.rate_kp, dtype=float)
        ki = np.asarray(p.rate_ki, dtype=float)
        kd = np.asarray(p.rate_kd, dtype=float)
        tmax = np.asarray(p.max_torque, dtype=float)
        tilt = float(p.max_tilt)
        # scalars as 0-d arrays (faster than Python floats as ufunc operands)
        self.zero = np.array(0.0)
        self.dt0 = np.array(dt)
        self.pi = np.array(_PI)
        self.two_pi = np.array(_TWO_PI)
        self.inv_two_pi = np.array(1.0 / _TWO_PI)
        self.half = np.array(0.5)
        self.fmax = np.full(n, float(p.max_thrust))
        self.fdt_m = np.array(dt / p.mass)
        self.cos_min = np.array(COS_THETA_MIN)
        # attitude command bounds: roll, pitch within +-max_tilt; yaw within +-YAW_CMD_MAX (then
        # wrapped), a finite bound so that no command can make the state non-finite
        self.cmd_lo = _full([-tilt, -tilt, -YAW_CMD_MAX], n)
        self.cmd_hi = _full([tilt, tilt, YAW_CMD_MAX], n)
        self.att_kp = _full(p.att_kp, n)
        self.rate_hi = _full(p.max_rate, n)
        self.rate_lo = -self.rate_hi
        # rate PID, derivative on the error by backward difference:
        # tau = kp e + ki I + kd (e - e_prev)/dt = (kp + kd/dt) e - (kd/dt) e_prev + ki I
        self.k_e = _full(kp + kd / dt, n)
        self.k_prev = _full(kd / dt, n)
        self.ki = _full(ki, n)
        # anti-windup: the integral term alone never exceeds the torque limit
        with np.errstate(divide="ignore"):
            ilim = np.where(ki > 0, tmax / np.where(ki > 0, ki, 1.0), 0.0)
        self.int_hi = _full(ilim, n)
        self.int_lo = -self.int_hi
        self.tau_hi = _full(tmax, n)
        self.tau_lo = -self.tau_hi
        # eq. (5), diagonal J: w' = tau/J - c * (w_y w_z, w_z w_x, w_x w_y) + d_a,
        # c = ((Jz - Jy)/Jx, (Jx - Jz)/Jy, (Jy - Jx)/Jz); pre-multiplied by dt
        self.jinv_dt = _full(dt / J, n)
        self.gyro_dt = _full(dt * np.array([(J[2] - J[1]) / J[0], (J[0] - J[2]) / J[1], (J[1] - J[0]) / J[2]]), n)
        self.g_dt = _full([0.0, 0.0, -p.g * dt], n)

    def _scratch(self, n: int) -> None:
        # C-contiguous (numpy is ~3x slower on 2-D strided views); column views
        self.G = np.zeros((n, 3))  # gyroscopic products (w_y w_z, w_z w_x, w_x w_y)
        self.G0, self.G1, self.G2 = self.G[:, 0], self.G[:, 1], self.G[:, 2]
        self.S = np.zeros((n, 3))
        self.C = np.zeros((n, 3))
        self.sf, self.st, self.sp = self.S[:, 0], self.S[:, 1], self.S[:, 2]
        self.cf, self.ct, self.cp = self.C[:, 0], self.C[:, 1], self.C[:, 2]
        self.E = np.zeros((n, 3))  # Euler rates, then thrust direction
        self.e0, self.e1, self.e2 = self.E[:, 0], self.E[:, 1], self.E[:, 2]
        self.t1 = np.zeros(n)
        self.t2 = np.zeros(n)
        self.t3 = np.zeros(n)
        self.t4 = np.zeros(n)
        self.Fb = np.zeros(n)  # clamped thrust
        self.tmp = np.zeros((n, 3))

    def _scalars(self, dt: float) -> tuple[Any, ...]:
        """The same constants as Python floats, per axis, for :func:`_step_held_scalar`."""

        def row(a: np.ndarray) -> tuple[float, ...]:
            return tuple(float(x) for x in a[0])

        per_axis = (self.cmd_lo, self.cmd_hi, self.att_kp, self.rate_hi, self.int_hi, self.k_e, self.k_prev, self.ki, self.tau_hi)
        return (
            *(row(a) for a in (*per_axis, self.jinv_dt, self.gyro_dt)),
            float(self.g_dt[0, 0]),
            float(self.g_dt[0, 2]),
            float(self.fdt_m),
            float(self.cos_min),
            float(self.fmax[0]),
            dt,
        )


def _compile(state: PlantState, params: QuadParams, dt: float) -> _Compiled:
    if not isinstance(params, QuadParams):
        raise TypeError(f"params must be a QuadParams, got {type(params).__name__}")
    try:
        dtf = float(dt)
    except (TypeError, ValueError):
        dtf = math.nan
    if not (math.isfinite(dtf) and dtf > 0):
        raise ValueError(f"dt must be a positive finite number of seconds, got {dt!r}")
    c = _Compiled(params, dtf, state.q.shape[0])
    state._cache = c
    return c


_mul = np.multiply
_add = np.add
_sub = np.subtract
_div = np.divide
_rem = np.remainder
_fmin = np.fmin
_fmax = np.fmax
_sin = np.sin
_cos = np.cos
_abs = np.absolute
_copysign = np.copysign
_ceil = np.ceil


def step(
    state: PlantState,
    thrust_cmd: Any,
    rpy_cmd: Any,
    params: QuadParams,
    dt: float,
    d_p: Any = None,
    d_a: Any = None,
    wrench_out: bool = False,
) -> None:
    """Advance N quadrotors by one physics sub-step, in place.

    Parameters
    ----------
    state : PlantState
        Updated in place (the arrays ``q``, ``v``, ``rpy``, ``w`` are written, not replaced).
    thrust_cmd : (N,) array_like
        Collective thrust F, N; eq. (1). Clamped to [0, max_thrust] (NaN -> 0).
    rpy_cmd : (N, 3) array_like
        Attitude setpoint [phi_d, theta_d, psi_d], rad. Roll and pitch are clamped to
        +-max_tilt, yaw to +-YAW_CMD_MAX (a NaN becomes the lower bound): no command, finite or
        not, can make the state non-finite. (Decoders upstream reject non-finite commands.)
    params : QuadParams
    dt : float
        Sub-step, s (1e-3 typically; the controller gains are designed for 1 kHz).
    d_p : (N, 3) array_like or None
        Translational lumped disturbance as an acceleration, m/s^2, ENU; eq. (1). None = 0.
    d_a : (N, 3) array_like or None
        Attitude disturbance as an angular acceleration, rad/s^2, body; eq. (5) with the
        disturbance torque J d_a. None = 0.
    wrench_out : bool
        Also write the sub-step's clamped thrust and torque into ``state.wrench`` (what
        :func:`step_held` asks of its last sub-step).

    Notes
    -----
    Onboard attitude controller (cascade as in the Crazyflie firmware), per axis::

        e      = wrap(Theta_d - Theta)                          angle error, rad
        w_d    = clamp(att_kp * e, +-max_rate)                   body-rate setpoint, rad/s
        e_w    = w_d - omega
        I      = clamp(I + e_w dt, +-max_torque / rate_ki)     anti-windup
        tau    = clamp(rate_kp e_w + rate_ki I + rate_kd (e_w - e_w_prev)/dt, +-max_torque)

    Integrator: semi-implicit (symplectic) Euler, in this order:

    1. omega_{k+1} = omega_k + dt J^-1 (tau - omega_k x J omega_k) + dt d_a          eq. (5)
    2. Theta_{k+1} = Theta_k + dt T(Theta_k) omega_{k+1}, wrapped to (-pi, pi]      eq. (4)
    3. v_{k+1} = v_k + dt (R(Theta_{k+1}) [0, 0, F]/m - [0, 0, g] + d_p)             eq. (1)
    4. q_{k+1} = q_k + dt v_{k+1}                                                     eq. (3)

    T(Theta) is singular at cos(theta) = 0; there |cos(theta)| is floored at ``COS_THETA_MIN``
    (sign kept) so the state stays finite; the Euler angles are meaningless for that step only.
    Deterministic: identical inputs give bit-identical results.
    """
    c = state._cache
    if c is None or c.params is not params or c.dt != dt or c.n != state.q.shape[0]:
        c = _compile(state, params, dt)
    # two phases, two Python calls a sub-step (each call costs: four phases cost 2.5% more
    # instructions in the simulator at N = 16, measured with callgrind)
    F, tau = _attitude_controller(state, c, thrust_cmd, rpy_cmd, wrench_out)
    _rigid_body(state, c, F, tau, d_a, d_p)  # 1.-4., eqs. (5), (4), (1), (3)


def _attitude_controller(state: PlantState, c: _Compiled, thrust_cmd: Any, rpy_cmd: Any, wrench_out: bool) -> tuple[np.ndarray, np.ndarray]:
    """The commands clamped, then the onboard attitude controller of :func:`step` (angle P -> rate
    PID): the clamped thrust F (N,) N and body torque tau (N, 3) N m; advances the controller's
    state (``rate_int``, ``rate_err_prev``) and writes ``state.wrench`` when asked. F and tau are
    scratch buffers of ``c`` (valid until the next sub-step)."""
    zero, fmaxv, cmd_lo, cmd_hi, pi, two_pi, att_kp, rate_lo, rate_hi, dt0, int_lo, int_hi, k_e, k_prev, ki, tau_lo, tau_hi, tmp, Fb = c.ctl
    mul, add, sub, fmin, fmax = _mul, _add, _sub, _fmin, _fmax
    # ---- commands (fmin/fmax map NaN to a bound, so no NaN reaches the state)
    F = fmin(fmax(thrust_cmd, zero, Fb), fmaxv, Fb)  # (N,) N
    e = fmax(rpy_cmd, cmd_lo)
    fmin(e, cmd_hi, e)  # (N, 3) rad, attitude setpoint
    # ---- angle P -> rate PID -> torque
    sub(e, state.rpy, e)
    sub(pi, e, e)  # wrap to (-pi, pi]: pi - ((pi - e) mod 2 pi)
    _rem(e, two_pi, e)
    sub(pi, e, e)
    mul(e, att_kp, e)
    fmin(fmax(e, rate_lo, e), rate_hi, e)  # body-rate setpoint w_d
    ew = sub(e, state.w, e)  # rate error e_w
    I = state.rate_int
    add(I, mul(ew, dt0, tmp), I)
    fmin(fmax(I, int_lo, I), int_hi, I)
    tau = mul(ew, k_e)
    sub(tau, mul(state.rate_err_prev, k_prev, tmp), tau)
    add(tau, mul(I, ki, tmp), tau)
    fmin(fmax(tau, tau_lo, tau), tau_hi, tau)
    state.rate_err_prev = ew  # a fresh array each call
    if wrench_out:  # before tau is overwritten by the attitude dynamics
        wr = state.wrench
        wr[:, 0] = F
        wr[:, 1:] = tau
    return F, tau


def _rigid_body(state: PlantState, c: _Compiled, F: np.ndarray, tau: np.ndarray, d_a: Any, d_p: Any) -> None:
    """Steps 1-4 of :func:`step` (semi-implicit Euler), in place, given the clamped thrust F (N,)
    N and the body torque tau (N, 3) N m (overwritten) of :func:`_attitude_controller`."""
    G, G0, G1, G2, jinv_dt, gyro_dt, dt0, tmp, S, C, sf, st, sp, cf, ct, cp, cos_min, E, e0, e1, e2 = c.body[:21]
    t1, t2, t3, t4, inv_two_pi, half, two_pi, fdt_m, g_dt = c.body[21:]
    mul, add, sub = _mul, _add, _sub
    q, v, rpy, w = state.q, state.v, state.rpy, state.w

    # ---- 1. attitude dynamics, eq. (5): omega += dt (J^-1 (tau - omega x J omega) + d_a)
    wx, wy, wz = w.T  # column views of the state; they see the in-place update below
    mul(wy, wz, G0)  # G = (w_y w_z, w_z w_x, w_x w_y)
    mul(wz, wx, G1)
    mul(wx, wy, G2)
    dw = mul(tau, jinv_dt, tau)
    sub(dw, mul(G, gyro_dt, G), dw)
    if d_a is not None:
        add(dw, mul(d_a, dt0, tmp), dw)
    add(w, dw, w)

    # ---- 2. Euler kinematics, eq. (4), T at Theta_k times the new omega
    _sin(rpy, S)
    _cos(rpy, C)
    # guard cos(theta) away from 0, keeping its sign (a no-op when |cos(theta)| >= cos_min)
    _copysign(_fmax(_abs(ct, t1), cos_min, t1), ct, ct)
    # a = s_phi w_y + c_phi w_z;  phi' = w_x + tan(theta) a;  theta' = c_phi w_y - s_phi w_z;
    # psi' = a / cos(theta)
    add(mul(sf, wy, t1), mul(cf, wz, t2), t3)
    sub(mul(cf, wy, t1), mul(sf, wz, t2), e1)
    _div(t3, ct, e2)
    add(wx, mul(st, e2, t1), e0)
    add(rpy, mul(E, dt0, E), rpy)
    # wrap to (-pi, pi], bit-exact inside: Theta -= 2 pi ceil(Theta / (2 pi) - 1/2)
    k = sub(mul(rpy, inv_two_pi, tmp), half, tmp)
    _ceil(k, k)
    sub(rpy, mul(k, two_pi, k), rpy)

    # ---- 3. translational dynamics, eq. (1), with R(Theta_{k+1}):
    # v += dt (F/m R e3 - g e3 + d_p),  R e3 = (c_psi s_th c_phi + s_psi s_phi,
    #                                           s_psi s_th c_phi - c_psi s_phi,  c_phi c_th)
    _sin(rpy, S)
    _cos(rpy, C)
    fdm = mul(F, fdt_m, t4)  # F dt / m
    cfF = mul(cf, fdm, t3)
    sfF = mul(sf, fdm, t4)
    stcf = mul(st, cfF, t1)
    add(mul(cp, stcf, e0), mul(sp, sfF, t2), e0)
    sub(mul(sp, stcf, e1), mul(cp, sfF, t2), e1)
    mul(cfF, ct, e2)
    add(v, E, v)
    add(v, g_dt, v)
    if d_p is not None:
        add(v, mul(d_p, dt0, tmp), v)

    # ---- 4. position, eq. (3)
    add(q, mul(v, dt0, tmp), q)


def step_held(
    state: PlantState,
    thrust_cmd: Any,
    rpy_cmd: Any,
    params: QuadParams,
    dt: float,
    nsub: int,
    disturbance: Callable[[int], tuple[Any, Any]] | None = None,
) -> None:
    """Advance N quadrotors by ``nsub`` physics sub-steps of ``dt`` with the command held (one
    control period, zero-order hold), in place. Bit for bit the same as::

        for j in range(nsub):
            d_p, d_a = disturbance(j) if disturbance is not None else (None, None)
            step(state, thrust_cmd, rpy_cmd, params, dt, d_p, d_a, wrench_out=j == nsub - 1)

    Parameters
    ----------
    state, thrust_cmd, rpy_cmd, params, dt
        As for :func:`step` (thrust_cmd (N,) N, rpy_cmd (N, 3) rad, dt s).
    nsub : int
        Number of sub-steps (>= 0).
    disturbance : callable or None
        ``disturbance(j) -> (d_p, d_a)`` for sub-step j = 0 .. nsub - 1, each an (N, 3) array or
        None (see :func:`step`); called once per sub-step, in order (so a seeded sampler draws
        the same numbers as the loop above). None: no disturbance.

    For N <= :data:`SCALAR_MAX_N` the sub-steps run on Python floats (faster for a few UAVs);
    a state that is not finite takes the numpy path, which never raises.
    """
    c = state._cache
    if c is None or c.params is not params or c.dt != dt or c.n != state.q.shape[0]:
        c = _compile(state, params, dt)
    nsub = int(nsub)
    if nsub < 0:
        raise ValueError(f"nsub must be >= 0, got {nsub}")
    samples = [disturbance(j) for j in range(nsub)] if disturbance is not None else None
    if c.n <= SCALAR_MAX_N:
        try:
            _step_held_scalar(state, c, thrust_cmd, rpy_cmd, nsub, samples)
            return
        except (ValueError, OverflowError):  # math.sin(inf), ceil(nan): a non-finite state
            pass  # nothing was written: the numpy path takes it from the same state
    for j in range(nsub):
        d_p, d_a = samples[j] if samples is not None else (None, None)
        step(state, thrust_cmd, rpy_cmd, params, dt, d_p, d_a, j == nsub - 1)


def _rows(x: Any, n: int, shape: tuple[int, ...]) -> list[Any]:
    return np.broadcast_to(np.asarray(x, dtype=float), shape).tolist() if x is not None else [None] * n


def _scalar_inputs(state: PlantState, n: int, thrust_cmd: Any, rpy_cmd: Any, samples: list[Any] | None) -> tuple[list[Any], ...]:
    """The state, the commands and the disturbance samples of :func:`_step_held_scalar` as lists
    of Python floats: Q, V, R, W, IN, PR (rows of the state), T (thrust, N), C (attitude setpoint
    rows, rad), DP, DA ([j][i] -> [x, y, z] or None; empty without samples)."""
    Q, V, R, W = state.q.tolist(), state.v.tolist(), state.rpy.tolist(), state.w.tolist()
    IN, PR = state.rate_int.tolist(), state.rate_err_prev.tolist()
    T = np.broadcast_to(np.asarray(thrust_cmd, dtype=float), (n,)).tolist()
    C = np.broadcast_to(np.asarray(rpy_cmd, dtype=float), (n, 3)).tolist()
    DP = [_rows(d_p, n, (n, 3)) for d_p, _ in samples] if samples is not None else []
    DA = [_rows(d_a, n, (n, 3)) for _, d_a in samples] if samples is not None else []
    return Q, V, R, W, IN, PR, T, C, DP, DA


def _scalar_write(state: PlantState, rows: tuple[list[Any], ...], WR: list[list[float]]) -> None:
    """Write the rows (Q, V, R, W, IN, PR) :func:`_step_held_scalar` advanced, and the last
    sub-step's wrench WR, into ``state``."""
    Q, V, R, W, IN, PR = rows
    state.wrench[...] = WR
    state.q[...] = Q
    state.v[...] = V
    state.rpy[...] = R
    state.w[...] = W
    state.rate_int[...] = IN
    state.rate_err_prev = np.array(PR, dtype=float)  # a fresh array, as step() leaves it


def _wrap_far(r: float) -> float:
    """The wrap of eq. (4) in :func:`_step_held_scalar` for |r| >= 3 rad: r - 2 pi ceil(r / (2 pi) - 1/2),
    with np.ceil's -0.0 on (-1, 0]."""
    x = r * _INV_TWO_PI - 0.5
    return r - (math.ceil(x) or math.copysign(0.0, x)) * _TWO_PI


def _step_held_scalar(state: PlantState, c: _Compiled, thrust_cmd: Any, rpy_cmd: Any, nsub: int, samples: list[Any] | None) -> None:
    """:func:`step_held` on Python floats, UAV by UAV: every operation of :func:`step`, in its
    order (``fmax(a, b)`` = ``a if a >= b else b`` as numpy's for a non-NaN bound, ``%`` as
    ``np.remainder``, ``np.ceil``'s signed zero kept). Writes the state only at the end.

    Skipped where they provably give the same bits: sin/cos of (phi, theta) at the start of a
    sub-step are those of the previous sub-step's eq. (1) (same angles); the wrap of eq. (4) is
    Theta + 0.0 for |Theta| < 3 rad (the ceil is -0.0 there); the cos(theta) guard is a no-op
    for |cos(theta)| >= COS_THETA_MIN.

    Reads better whole (issue 44's exception to 80 lines): the sub-step loop is :func:`step`'s
    phases line by line on floats, and it is the simulator's inner loop for N <= SCALAR_MAX_N; a
    helper per phase would pass some 30 floats a call (about 0.4 us, measured) on a sub-step of
    about 2.5 us per UAV."""
    (lo0, lo1, lo2), (hi0, hi1, hi2), (ak0, ak1, ak2), (rh0, rh1, rh2), (ih0, ih1, ih2) = c.scalars[:5]
    (ke0, ke1, ke2), (kp0, kp1, kp2), (ki0, ki1, ki2), (th0, th1, th2), (jd0, jd1, jd2) = c.scalars[5:10]
    (gd0, gd1, gd2), gxy, gz, fdt_m, cos_min, fmx, dt = c.scalars[10:]
    n = c.n
    pi, two_pi = _PI, _TWO_PI
    # negated bounds, once (negation is exact)
    nrh0, nrh1, nrh2, nih0, nih1, nih2, nth0, nth1, nth2 = -rh0, -rh1, -rh2, -ih0, -ih1, -ih2, -th0, -th1, -th2
    ncos_min = -cos_min
    sin, cos, copysign, fabs, wrap_far = math.sin, math.cos, math.copysign, math.fabs, _wrap_far
    Q, V, R, W, IN, PR, T, C, DP, DA = _scalar_inputs(state, n, thrust_cmd, rpy_cmd, samples)
    WR = [[0.0, 0.0, 0.0, 0.0]] * n  # the last sub-step's wrench per UAV
    for i in range(n):
        # ---- commands (held: clamped once; fmin/fmax map NaN to a bound)
        f = T[i]
        f = f if f >= 0.0 else 0.0
        F = f if f <= fmx else fmx
        c0, c1, c2 = C[i]
        c0 = c0 if c0 >= lo0 else lo0
        c0 = c0 if c0 <= hi0 else hi0
        c1 = c1 if c1 >= lo1 else lo1
        c1 = c1 if c1 <= hi1 else hi1
        c2 = c2 if c2 >= lo2 else lo2
        c2 = c2 if c2 <= hi2 else hi2
        q0, q1, q2 = Q[i]
        v0, v1, v2 = V[i]
        r0, r1, r2 = R[i]
        w0, w1, w2 = W[i]
        i0, i1, i2 = IN[i]
        p0, p1, p2 = PR[i]
        fdm = F * fdt_m  # F dt / m
        # sin/cos of (phi, theta) at Theta_k: those of step 3 of the previous sub-step (same angles)
        sf, st, cf, ct = sin(r0), sin(r1), cos(r0), cos(r1)
        for j in range(nsub):
            # ---- onboard attitude controller: angle P -> rate PID -> torque
            e0 = (pi - ((pi - (c0 - r0)) % two_pi)) * ak0
            e0 = e0 if e0 >= nrh0 else nrh0
            e0 = e0 if e0 <= rh0 else rh0
            e1 = (pi - ((pi - (c1 - r1)) % two_pi)) * ak1
            e1 = e1 if e1 >= nrh1 else nrh1
            e1 = e1 if e1 <= rh1 else rh1
            e2 = (pi - ((pi - (c2 - r2)) % two_pi)) * ak2
            e2 = e2 if e2 >= nrh2 else nrh2
            e2 = e2 if e2 <= rh2 else rh2
            e0 = e0 - w0  # rate error e_w
            e1 = e1 - w1
            e2 = e2 - w2
            i0 = i0 + e0 * dt
            i0 = i0 if i0 >= nih0 else nih0
            i0 = i0 if i0 <= ih0 else ih0
            i1 = i1 + e1 * dt
            i1 = i1 if i1 >= nih1 else nih1
            i1 = i1 if i1 <= ih1 else ih1
            i2 = i2 + e2 * dt
            i2 = i2 if i2 >= nih2 else nih2
            i2 = i2 if i2 <= ih2 else ih2
            t0 = e0 * ke0 - p0 * kp0 + i0 * ki0
            t0 = t0 if t0 >= nth0 else nth0
            t0 = t0 if t0 <= th0 else th0
            t1 = e1 * ke1 - p1 * kp1 + i1 * ki1
            t1 = t1 if t1 >= nth1 else nth1
            t1 = t1 if t1 <= th1 else th1
            t2 = e2 * ke2 - p2 * kp2 + i2 * ki2
            t2 = t2 if t2 >= nth2 else nth2
            t2 = t2 if t2 <= th2 else th2
            p0, p1, p2 = e0, e1, e2
            # ---- 1. attitude dynamics, eq. (5)
            d0 = t0 * jd0 - (w1 * w2) * gd0
            d1 = t1 * jd1 - (w2 * w0) * gd1
            d2 = t2 * jd2 - (w0 * w1) * gd2
            if samples is not None and (da := DA[j][i]) is not None:
                d0 = d0 + da[0] * dt
                d1 = d1 + da[1] * dt
                d2 = d2 + da[2] * dt
            w0 = w0 + d0
            w1 = w1 + d1
            w2 = w2 + d2
            # ---- 2. Euler kinematics, eq. (4), T at Theta_k times the new omega
            # guard |cos(theta)| >= cos_min, sign kept (a no-op unless |ct| < cos_min or NaN)
            if not (ct >= cos_min or ct <= ncos_min):
                a = fabs(ct)
                a = a if a >= cos_min else cos_min
                ct = copysign(a, ct)
            E2 = (sf * w1 + cf * w2) / ct
            E1 = cf * w1 - sf * w2
            E0 = w0 + st * E2
            r0 = r0 + E0 * dt
            r1 = r1 + E1 * dt
            r2 = r2 + E2 * dt
            # wrap to (-pi, pi]: Theta -= 2 pi ceil(Theta / (2 pi) - 1/2); np.ceil gives -0.0 on (-1, 0].
            # For |Theta| < 3 that ceil is -0.0, so the wrap is Theta - (-0.0) = Theta + 0.0 exactly.
            r0 = r0 + 0.0 if -3.0 < r0 < 3.0 else wrap_far(r0)
            r1 = r1 + 0.0 if -3.0 < r1 < 3.0 else wrap_far(r1)
            r2 = r2 + 0.0 if -3.0 < r2 < 3.0 else wrap_far(r2)
            # ---- 3. translational dynamics, eq. (1), with R(Theta_{k+1})
            sf, st, sp, cf, ct, cp = sin(r0), sin(r1), sin(r2), cos(r0), cos(r1), cos(r2)
            cfF = cf * fdm
            sfF = sf * fdm
            stcf = st * cfF
            v0 = (v0 + (cp * stcf + sp * sfF)) + gxy
            v1 = (v1 + (sp * stcf - cp * sfF)) + gxy
            v2 = (v2 + cfF * ct) + gz
            if samples is not None and (dp := DP[j][i]) is not None:
                v0 = v0 + dp[0] * dt
                v1 = v1 + dp[1] * dt
                v2 = v2 + dp[2] * dt
            # ---- 4. position, eq. (3)
            q0 = q0 + v0 * dt
            q1 = q1 + v1 * dt
            q2 = q2 + v2 * dt
        Q[i] = [q0, q1, q2]
        V[i] = [v0, v1, v2]
        R[i] = [r0, r1, r2]
        W[i] = [w0, w1, w2]
        IN[i] = [i0, i1, i2]
        PR[i] = [p0, p1, p2]
        if nsub:
            WR[i] = [F, t0, t1, t2]
    if nsub:
        _scalar_write(state, (Q, V, R, W, IN, PR), WR)

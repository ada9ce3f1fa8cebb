"""Tests of the quadrotor plant (paper eqs 1-5), its onboard attitude PID and the disturbances.

Closed forms with stated tolerances. Timing figures are not asserted here (see bench/).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.quadrotor import (
    SCALAR_MAX_N,
    PlantState,
    euler_rate_matrix,
    initial_state,
    rotation_matrix,
    step,
    step_held,
    wrap_angle,
)
from zenswarm.scenario.config import DisturbanceConfig, VehicleConfig
from zenswarm.vehicle.params import THRUST_TO_WEIGHT, QuadParams

DT = 1e-3
P = QuadParams()


def run(state: PlantState, n_steps: int, thrust, rpy_cmd, params=P, dt=DT, d_p=None, d_a=None, record=None):
    """Step n_steps times with constant inputs; optionally record a state attribute per step."""
    out = []
    for _ in range(n_steps):
        step(state, thrust, rpy_cmd, params, dt, d_p, d_a)
        if record is not None:
            out.append(getattr(state, record).copy())
    return np.array(out) if record is not None else None


def random_angles(rng, n):
    """Random Euler angles away from gimbal lock: roll, yaw in (-pi, pi), pitch in (-1.4, 1.4)."""
    return np.column_stack([rng.uniform(-3.1, 3.1, n), rng.uniform(-1.4, 1.4, n), rng.uniform(-3.1, 3.1, n)])


def skew(w):
    x, y, z = w
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


# ----------------------------------------------------------------------------- eq. (2)


def test_rotation_matrix_is_eq2_entry_by_entry():
    rng = np.random.default_rng(0)
    a = random_angles(rng, 50)
    R = rotation_matrix(a)
    assert R.shape == (50, 3, 3)
    for (f, t, p), Ri in zip(a, R):
        c, s = math.cos, math.sin
        expected = np.array(
            [
                [c(t) * c(p), c(p) * s(t) * s(f) - s(p) * c(f), c(p) * s(t) * c(f) + s(p) * s(f)],
                [c(t) * s(p), s(p) * s(t) * s(f) + c(p) * c(f), s(p) * s(t) * c(f) - c(p) * s(f)],
                [-s(t), s(f) * c(t), c(f) * c(t)],
            ]
        )
        np.testing.assert_allclose(Ri, expected, rtol=0, atol=1e-15)


def test_rotation_matrix_orthonormal_det1_and_zyx():
    rng = np.random.default_rng(1)
    a = random_angles(rng, 100)
    R = rotation_matrix(a)
    eye = np.broadcast_to(np.eye(3), R.shape)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), eye, atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    # ZYX composition, body -> inertial: R = Rz(psi) Ry(theta) Rx(phi)
    f, t, p = a[7]
    Rx = np.array([[1, 0, 0], [0, math.cos(f), -math.sin(f)], [0, math.sin(f), math.cos(f)]])
    Ry = np.array([[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]])
    Rz = np.array([[math.cos(p), -math.sin(p), 0], [math.sin(p), math.cos(p), 0], [0, 0, 1]])
    np.testing.assert_allclose(R[7], Rz @ Ry @ Rx, atol=1e-15)
    # (3,) input -> (3, 3)
    np.testing.assert_array_equal(rotation_matrix(a[7]), R[7])


def test_rotation_maps_e3_to_thrust_direction():
    e3 = np.array([0.0, 0.0, 1.0])
    # level: thrust straight up, whatever the yaw
    np.testing.assert_allclose(rotation_matrix([0.0, 0.0, 1.234]) @ e3, e3, atol=1e-15)
    # positive roll (about body x, FLU) tilts the thrust towards -y
    phi = 0.3
    np.testing.assert_allclose(rotation_matrix([phi, 0.0, 0.0]) @ e3, [0.0, -math.sin(phi), math.cos(phi)], atol=1e-15)
    # positive pitch (about body y) tilts it towards +x
    th = 0.25
    np.testing.assert_allclose(rotation_matrix([0.0, th, 0.0]) @ e3, [math.sin(th), 0.0, math.cos(th)], atol=1e-15)
    # pitch then yaw 90 deg: towards +y
    np.testing.assert_allclose(
        rotation_matrix([0.0, th, math.pi / 2]) @ e3, [0.0, math.sin(th), math.cos(th)], atol=1e-15
    )


# ----------------------------------------------------------------------------- eq. (4)


def test_euler_rate_matrix_matches_rotation_kinematics():
    """d/dt R(Theta) = R [omega]_x when Theta' = T(Theta) omega (central difference, h = 1e-6)."""
    rng = np.random.default_rng(2)
    a = random_angles(rng, 40)
    w = rng.normal(size=(40, 3))
    T = euler_rate_matrix(a)
    assert T.shape == (40, 3, 3)
    h = 1e-6
    rate = np.einsum("nij,nj->ni", T, w)
    dR = (rotation_matrix(a + h * rate) - rotation_matrix(a - h * rate)) / (2 * h)
    expected = rotation_matrix(a) @ np.array([skew(x) for x in w])
    scale = 1.0 / np.cos(a[:, 1])[:, None, None] ** 2  # conditioning near gimbal lock
    assert np.all(np.abs(dR - expected) <= 1e-7 * scale * (1 + np.abs(w).max()))
    # and T is the inverse of the body-rate map at a hand-checked point: level -> identity
    np.testing.assert_allclose(euler_rate_matrix([0.0, 0.0, 0.7]), np.eye(3), atol=1e-15)


def open_loop_params(**kw):
    """Onboard controller switched off (zero gains): tau = 0, the rigid body alone."""
    z = (0.0, 0.0, 0.0)
    return replace(P, att_kp=z, rate_kp=z, rate_ki=z, rate_kd=z, **kw)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_step_attitude_kinematics_follow_rotation_about_principal_axis(axis):
    """Torque-free spin at rate w about a body axis (principal, so omega stays constant):
    R(t) = R0 expm(t [omega]_x). Exercises every column of T (eq. 4) inside :func:`step`.

    The semi-implicit Euler attitude update is first order: error <= 2 dt w^2 t over 1 s."""
    p0 = open_loop_params()
    s = initial_state(np.zeros((1, 3)))
    s.rpy[0] = [0.3, -0.4, 0.5]
    w = np.zeros(3)
    w[axis] = 0.8
    s.w[0] = w
    R0 = rotation_matrix(s.rpy[0])
    run(s, 1000, 0.0, s.rpy.copy(), params=p0)
    t = 1.0
    np.testing.assert_array_equal(s.w[0], w)  # principal axis: omega constant
    K = skew(w / 0.8)
    ang = 0.8 * t
    expm = np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K  # Rodrigues
    err = np.abs(rotation_matrix(s.rpy[0]) - R0 @ expm).max()
    assert err < 2 * DT * 0.8**2 * t
    assert err < 0.01 * np.abs(rotation_matrix(s.rpy[0]) - R0).max()  # and it did rotate


def test_one_step_update_order():
    """omega, then Theta with the new omega (T at the old Theta), then v with R at the new
    Theta, then q with the new v: eqs (5), (4), (1), (3), to rounding."""
    p0 = open_loop_params()
    rng = np.random.default_rng(12)
    n = 5
    s = initial_state(rng.normal(size=(n, 3)))
    s.v[:] = rng.normal(size=(n, 3))
    s.rpy[:] = random_angles(rng, n) * [0.3, 0.3, 1.0]
    s.w[:] = rng.normal(size=(n, 3))
    F = rng.uniform(0.0, P.max_thrust, n)
    d_p = rng.normal(size=(n, 3))
    d_a = rng.normal(size=(n, 3))
    q0, v0, a0, w0 = s.q.copy(), s.v.copy(), s.rpy.copy(), s.w.copy()
    dt = 0.01
    step(s, F, np.zeros((n, 3)), p0, dt, d_p, d_a)
    J = np.array(P.inertia)
    w1 = w0 + dt * (-np.cross(w0, J * w0) / J + d_a)
    a1 = wrap_angle(a0 + dt * np.einsum("nij,nj->ni", euler_rate_matrix(a0), w1))
    v1 = v0 + dt * (rotation_matrix(a1)[:, :, 2] * (F / P.mass)[:, None] - [0.0, 0.0, P.g] + d_p)
    q1 = q0 + dt * v1
    for got, want in ((s.w, w1), (s.rpy, a1), (s.v, v1), (s.q, q1)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)


def test_thrust_along_body_z_at_fixed_attitude():
    """Held attitude (no rates, no torque): v = k dt (R(Theta) e3 F/m - g e3) exactly, eq. (1)."""
    p0 = open_loop_params()
    rng = np.random.default_rng(13)
    n = 6
    s = initial_state(np.zeros((n, 3)))
    s.rpy[:] = random_angles(rng, n)
    a = s.rpy.copy()
    F = rng.uniform(0.0, P.max_thrust, n)
    run(s, 100, F, np.zeros((n, 3)), params=p0)
    np.testing.assert_array_equal(s.rpy, a)
    acc = rotation_matrix(a)[:, :, 2] * (F / P.mass)[:, None] - [0.0, 0.0, P.g]
    np.testing.assert_allclose(s.v, 100 * DT * acc, rtol=0, atol=1e-12)


def test_step_rigid_body_eq5_one_step():
    """omega_1 = omega_0 + dt (-J^-1 (omega_0 x J omega_0) + d_a) exactly, with tau = 0."""
    p0 = open_loop_params()
    rng = np.random.default_rng(3)
    s = initial_state(np.zeros((4, 3)))
    s.w[:] = rng.normal(scale=5.0, size=(4, 3))
    d_a = rng.normal(scale=10.0, size=(4, 3))
    w0 = s.w.copy()
    J = np.array(P.inertia)
    step(s, 0.0, np.zeros((4, 3)), p0, DT, None, d_a)
    expected = w0 + DT * (-np.cross(w0, J * w0) / J + d_a)
    np.testing.assert_allclose(s.w, expected, rtol=1e-13, atol=1e-15)


# ----------------------------------------------------------------------------- eq. (1)


def test_hover_level_stays_put():
    q0 = np.array([[0.0, 0.0, 0.4], [0.0, 0.2, 0.4], [1.0, -0.2, 2.0]])
    s = initial_state(q0)
    run(s, 1000, np.full(3, P.mass * P.g), np.zeros((3, 3)))
    assert np.abs(s.q - q0).max() <= 1e-9
    assert np.abs(s.v).max() <= 1e-9
    assert np.abs(s.rpy).max() == 0.0


def test_free_fall_matches_semi_implicit_euler_closed_form():
    """Zero thrust: v_k = -g k dt, z_k = z0 - g dt^2 k (k + 1) / 2 -> z0 - g t^2 / 2 as dt -> 0."""
    z0 = 10.0
    s = initial_state([[1.0, 2.0, z0]])
    k = 1000
    run(s, k, 0.0, np.zeros((1, 3)))
    z_expected = z0 - P.g * DT**2 * k * (k + 1) / 2
    assert abs(s.q[0, 2] - z_expected) <= 1e-12
    assert abs(s.v[0, 2] + P.g * k * DT) <= 1e-12
    # the continuous closed form, within the first-order integrator error g t dt / 2
    t = k * DT
    assert abs(s.q[0, 2] - (z0 - P.g * t**2 / 2)) <= P.g * t * DT / 2 + 1e-12
    np.testing.assert_array_equal(s.q[0, :2], [1.0, 2.0])


def test_constant_disturbance_acceleration_is_integrated():
    """Hover thrust cancels gravity; d_p = a const gives q = q0 + a dt^2 k (k + 1) / 2."""
    a = np.array([[0.3, -0.2, 0.1], [-1.0, 0.5, 0.0]])
    q0 = np.array([[0.0, 0.0, 1.0], [2.0, 2.0, 1.0]])
    s = initial_state(q0)
    k = 1000
    run(s, k, np.full(2, P.mass * P.g), np.zeros((2, 3)), d_p=a)
    np.testing.assert_allclose(s.q, q0 + a * DT**2 * k * (k + 1) / 2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.v, a * k * DT, rtol=0, atol=1e-12)


def test_thrust_clamped_to_max_thrust_and_zero():
    s = initial_state(np.zeros((3, 3)))
    step(s, np.array([10 * P.max_thrust, -5.0, P.max_thrust]), np.zeros((3, 3)), P, DT)
    a_max = P.max_thrust / P.mass - P.g
    np.testing.assert_allclose(s.v[:, 2], [a_max * DT, -P.g * DT, a_max * DT], rtol=1e-14)
    assert a_max == pytest.approx((THRUST_TO_WEIGHT - 1) * P.g, rel=1e-12)


def test_tilt_clamped_to_max_tilt():
    s = initial_state(np.zeros((2, 3)))
    cmd = np.array([[1.4, 0.0, 0.0], [0.0, -1.5, 0.0]])
    roll = run(s, 1000, np.full(2, P.mass * P.g), cmd, record="rpy")
    assert np.abs(roll[:, :, :2]).max() <= P.max_tilt * 1.02  # never tilts past the clamp (2 %)
    np.testing.assert_allclose(s.rpy[:, :2], [[P.max_tilt, 0.0], [0.0, -P.max_tilt]], atol=1e-3)


def test_torque_clamped_to_max_torque():
    """A huge step saturates the torque: the first sub-step's omega is dt max_torque / J."""
    s = initial_state(np.zeros((1, 3)))
    step(s, P.mass * P.g, np.array([[0.6, -0.6, 3.0]]), P, DT)
    J = np.array(P.inertia)
    np.testing.assert_allclose(s.w[0], DT * np.array(P.max_torque) * np.array([1, -1, 1]) / J, rtol=1e-12)


# ----------------------------------------------------------------------------- attitude PID


@pytest.mark.parametrize("axis,amp", [(0, 0.2), (1, -0.2), (2, 0.5), (2, -2.5)])
def test_attitude_step_tracked(axis, amp):
    """Within 2 % from 0.5 s on (checked to 1 s), overshoot < 20 %."""
    s = initial_state(np.zeros((1, 3)))
    cmd = np.zeros((1, 3))
    cmd[0, axis] = amp
    y = run(s, 1000, P.mass * P.g, cmd, record="rpy")[:, 0, axis]
    assert np.abs(y[499:] - amp).max() <= 0.02 * abs(amp)
    assert np.max(y / amp) - 1.0 < 0.20
    # the other axes stay put
    others = [i for i in range(3) if i != axis]
    assert np.abs(s.rpy[0, others]).max() < 1e-9


def test_yaw_error_takes_the_short_way_round():
    s = initial_state(np.zeros((1, 3)))
    s.rpy[0, 2] = 3.0
    y = run(s, 1000, P.mass * P.g, np.array([[0.0, 0.0, -3.0]]), record="rpy")[:, 0, 2]
    # -3.0 is 0.283 rad away through +pi: yaw increases, wraps, and settles at -3.0
    assert y[0] > 3.0 and np.abs(y[499:] + 3.0).max() < 0.02 * (2 * math.pi - 6.0)
    assert np.all(np.abs(y) <= math.pi)


@pytest.mark.parametrize("axis", [0, 2])
def test_integral_removes_constant_torque_disturbance(axis):
    d_a = np.zeros((1, 3))
    d_a[0, axis] = 50.0  # rad/s^2 (a torque J d_a, ~17 % of the roll authority)
    s = initial_state(np.zeros((1, 3)))
    run(s, 3000, P.mass * P.g, np.zeros((1, 3)), d_a=d_a)
    # without the integral the angle loop leaves e = J d_a / (att_kp rate_kp) (closed form)
    p_only = replace(P, rate_ki=(0.0, 0.0, 0.0))
    s2 = initial_state(np.zeros((1, 3)))
    run(s2, 3000, P.mass * P.g, np.zeros((1, 3)), params=p_only, d_a=d_a)
    e_p = P.inertia[axis] * 50.0 / (P.att_kp[axis] * P.rate_kp[axis])
    assert s2.rpy[0, axis] == pytest.approx(e_p, rel=0.01)
    assert abs(s.rpy[0, axis]) < 1e-3 * e_p


def test_integral_anti_windup_bounds_the_integral_and_speeds_recovery():
    """A roll disturbance beyond the torque authority (600 > max_torque/J_xx = 505 rad/s^2) for
    0.3 s: the integral term stays within +-max_torque, and 0.7 s after the disturbance ends
    the roll is back within 0.01 rad (without the clamp it is still ~0.25 rad off)."""
    s = initial_state(np.zeros((1, 3)))
    d_a = np.array([[600.0, 0.0, 0.0]])
    worst = 0.0
    for k in range(1000):
        step(s, P.mass * P.g, np.zeros((1, 3)), P, DT, None, d_a if k < 300 else None)
        worst = max(worst, float(np.max(np.abs(s.rate_int[0] * P.rate_ki) / P.max_torque)))
    assert worst <= 1.0 + 1e-12
    assert abs(s.rpy[0, 0]) < 0.01


# ----------------------------------------------------------------------------- robustness


def test_extreme_finite_and_nonfinite_commands_keep_state_finite():
    rng = np.random.default_rng(4)
    n = 8
    s = initial_state(rng.normal(size=(n, 3)))
    big = [1e300, -1e300, 1e30, -1e30, 0.0, 5e-324]
    with np.errstate(over="raise", invalid="raise", divide="raise"):  # none anywhere either
        for k in range(2000):
            thrust = rng.choice(big, n)
            cmd = rng.choice(big, (n, 3))
            step(s, thrust, cmd, P, DT)
            for name in ("q", "v", "rpy", "w", "rate_int", "rate_err_prev"):
                assert np.isfinite(getattr(s, name)).all(), (k, name)
        for bad in (np.inf, -np.inf, np.nan):
            run(s, 200, np.full(n, bad), np.full((n, 3), bad))
    for name in ("q", "v", "rpy", "w", "rate_int", "rate_err_prev"):
        assert np.isfinite(getattr(s, name)).all(), name
    assert np.abs(s.rpy).max() <= math.pi
    assert np.abs(s.w).max() <= 1e3  # bounded by the torque clamp and the rate clamp


def test_pitch_through_gimbal_lock_stays_finite():
    p0 = open_loop_params()
    s = initial_state(np.zeros((1, 3)))
    s.w[0] = [0.0, 3.0, 0.0]  # tumble through theta = pi/2
    run(s, 1000, 0.0, np.zeros((1, 3)), params=p0)
    assert np.isfinite(s.rpy).all() and np.abs(s.rpy).max() <= math.pi


def test_deterministic_and_copy_is_independent():
    rng = np.random.default_rng(5)
    n = 3
    q0 = rng.normal(size=(n, 3))
    F = rng.uniform(0.2, 0.4, (500, n))
    cmd = rng.uniform(-0.5, 0.5, (500, n, 3))
    d_p = rng.normal(size=(500, n, 3))
    d_a = rng.normal(size=(500, n, 3))

    def go(s):
        for k in range(500):
            step(s, F[k], cmd[k], P, DT, d_p[k], d_a[k])
        return s

    a = go(initial_state(q0))
    b0 = initial_state(q0)
    b = go(b0.copy())
    for name in ("q", "v", "rpy", "w", "rate_int", "rate_err_prev"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(b0.q, q0)  # stepping the copy left the original alone
    assert np.abs(b0.v).max() == 0.0


@pytest.mark.slow
def test_scales_to_32_rows_independent():
    """Each row of an N = 32 run equals an N = 1 run with the same inputs (to 1e-12)."""
    rng = np.random.default_rng(6)
    n = 32
    s = initial_state(rng.normal(size=(n, 3)))
    singles = [initial_state(s.q[i : i + 1]) for i in range(n)]
    F = rng.uniform(0.0, 0.6, n)
    cmd = rng.uniform(-1.0, 1.0, (n, 3))
    d_p = rng.normal(size=(n, 3))
    for _ in range(200):
        step(s, F, cmd, P, DT, d_p)
        for i in range(n):
            step(singles[i], F[i : i + 1], cmd[i : i + 1], P, DT, d_p[i : i + 1])
    for i in (0, 13, 31):
        np.testing.assert_allclose(s.q[i], singles[i].q[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(s.rpy[i], singles[i].rpy[0], rtol=0, atol=1e-12)


STATE_FIELDS = ("q", "v", "rpy", "w", "rate_int", "rate_err_prev")


def random_state(rng, n):
    """A state anywhere on the attitude sphere, spinning, with controller memory; the first UAV
    at signed-zero angles and rates (the scalar path must keep numpy's signed zeros)."""
    s = initial_state(rng.normal(size=(n, 3)))
    s.v[:] = rng.normal(size=(n, 3))
    s.rpy[:] = rng.uniform(-math.pi, math.pi, (n, 3))
    s.w[:] = rng.normal(scale=3.0, size=(n, 3))
    s.rate_int[:] = rng.normal(scale=1e-3, size=(n, 3))
    s.rate_err_prev = rng.normal(size=(n, 3))
    s.rpy[0] = [0.0, -0.0, 0.0]
    s.w[0] = [-0.0, 0.0, -0.0]
    return s


def assert_bitwise_equal(a: PlantState, b: PlantState, ctx) -> None:
    for name in STATE_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        np.testing.assert_array_equal(x, y, err_msg=f"{ctx} {name}")
        np.testing.assert_array_equal(np.signbit(x), np.signbit(y), err_msg=f"{ctx} {name} (sign of zero)")


@pytest.mark.parametrize("n", [1, 2, 3, SCALAR_MAX_N, SCALAR_MAX_N + 1, 16])
def test_step_held_equals_step_bit_for_bit(n):
    """step_held (Python floats for N <= SCALAR_MAX_N, numpy above) is, bit for bit and sign of
    zero included, nsub calls of step: random states, commands beyond every clamp, NaN, inf."""
    rng = np.random.default_rng(100 + n)
    for trial in range(40):
        a = random_state(rng, n)
        b = a.copy()
        thrust = rng.uniform(-0.2, 1.0, n)
        cmd = rng.normal(scale=1.5, size=(n, 3))
        if trial % 4 == 0:
            thrust[0], cmd[0, 1], cmd[-1, 2] = np.nan, np.nan, np.inf
        if trial % 5 == 0:
            cmd[0] = [0.0, -0.0, 0.0]
            thrust[-1] = -0.0
        nsub = int(rng.integers(0, 12))
        for _ in range(nsub):
            step(a, thrust, cmd, P, DT)
        step_held(b, thrust, cmd, P, DT, nsub)
        assert_bitwise_equal(a, b, (n, trial, nsub))


def test_step_held_equals_step_at_the_edges_of_its_fast_paths():
    """The scalar path skips the angle wrap for |angle| < 3 rad and the cos(theta) guard for
    |cos(theta)| >= COS_THETA_MIN; at and around those edges (angles at +-3, +-pi and one ulp
    inside, signed zeros; pitch at +-pi/2) it still equals step bit for bit."""
    rng = np.random.default_rng(7)
    edges = [3.0, -3.0, np.nextafter(3.0, 0.0), np.nextafter(-3.0, 0.0), np.nextafter(3.0, 4.0),
             np.nextafter(-3.0, -4.0), math.pi, -math.pi, np.nextafter(math.pi, 0.0),
             np.nextafter(-math.pi, 0.0), math.pi / 2, -math.pi / 2, 0.0, -0.0]
    n = 3
    for trial in range(60):
        a = random_state(rng, n)
        a.rpy[:] = rng.choice(edges, size=(n, 3))
        a.w[:] = rng.normal(scale=rng.choice([1e-9, 1.0, 50.0]), size=(n, 3))
        b = a.copy()
        thrust = rng.uniform(0.0, 0.6, n)
        cmd = a.rpy + rng.choice([0.0, 1e-12, 3.0, -3.0, 6.0], size=(n, 3))
        nsub = int(rng.integers(1, 12))
        for _ in range(nsub):
            step(a, thrust, cmd, P, DT)
        step_held(b, thrust, cmd, P, DT, nsub)
        assert_bitwise_equal(a, b, (trial, nsub))


@pytest.mark.parametrize("n", [3, SCALAR_MAX_N + 2])
def test_step_held_with_disturbances_draws_and_applies_them_as_the_loop(n):
    """A seeded disturbance sampler is called once per sub-step, in order: the generator ends
    in the same place and the states are bit-identical; None entries mean no disturbance."""
    cfg = DisturbanceConfig(wind=(0.1, -0.2, 0.05), gust_std=0.3, gust_tau_s=0.5, attitude_std=2.0,
                            sine_amplitude=(0.1, 0.0, 0.2), sine_freq_hz=0.7)
    rng = np.random.default_rng(7)
    a = random_state(rng, n)
    b = a.copy()
    da = DisturbanceModel(cfg, n, np.random.default_rng(3))
    db = DisturbanceModel(cfg, n, np.random.default_rng(3))
    h = 1e-3
    for k in range(30):
        thrust = rng.uniform(0.1, 0.5, n)
        cmd = rng.normal(scale=0.3, size=(n, 3))
        t = k * 10 * h
        for j in range(10):
            d_p, d_a = da.sample(t + j * h, h)
            if k % 3 == 1:
                d_a = None
            step(a, thrust, cmd, P, h, d_p, d_a)

        def dist(j, t=t, k=k):
            d_p, d_a = db.sample(t + j * h, h)
            return d_p, (None if k % 3 == 1 else d_a)

        step_held(b, thrust, cmd, P, h, 10, dist)
        assert_bitwise_equal(a, b, k)
    assert da.rng.standard_normal() == db.rng.standard_normal()


def test_step_held_nonfinite_state_takes_the_numpy_path_without_raising():
    s = initial_state(np.zeros((2, 3)))
    s.rpy[1, 2] = np.inf
    ref = s.copy()
    with np.errstate(invalid="ignore"):
        for _ in range(3):
            step(ref, np.full(2, 0.3), np.zeros((2, 3)), P, DT)
        step_held(s, np.full(2, 0.3), np.zeros((2, 3)), P, DT, 3)
    np.testing.assert_array_equal(s.q, ref.q)  # NaN == NaN here
    assert np.isfinite(s.q[0]).all()
    with pytest.raises(ValueError, match="nsub"):
        step_held(s, np.full(2, 0.3), np.zeros((2, 3)), P, DT, -1)


def test_params_or_dt_change_recompiles():
    s = initial_state(np.zeros((1, 3)))
    step(s, 0.0, np.zeros((1, 3)), P, DT)
    heavy = replace(P, mass=2 * P.mass)
    v0 = s.v[0, 2]
    step(s, heavy.max_thrust, np.zeros((1, 3)), heavy, 2 * DT)
    assert s.v[0, 2] - v0 == pytest.approx(2 * DT * (heavy.max_thrust / heavy.mass - P.g), rel=1e-12)
    with pytest.raises(ValueError):
        step(s, 0.0, np.zeros((1, 3)), P, 0.0)


def test_wrap_angle():
    x = np.array([0.0, 1.0, math.pi, -math.pi, 3 * math.pi + 0.5, -7.0, 1e6])
    y = wrap_angle(x)
    assert np.all((y > -math.pi) & (y <= math.pi))
    np.testing.assert_allclose(np.sin(y), np.sin(x), atol=1e-9)
    np.testing.assert_allclose(np.cos(y), np.cos(x), atol=1e-9)
    assert y[2] == math.pi and y[3] == math.pi
    np.testing.assert_array_equal(y[:2], x[:2])  # bit-exact inside the interval
    inside = np.random.default_rng(14).uniform(-3.14159, 3.14159, 1000)
    np.testing.assert_array_equal(wrap_angle(inside), inside)


# ----------------------------------------------------------------------------- disturbance


def test_disturbance_inactive_fast_path_returns_zeros_without_rng():
    rng = np.random.default_rng(7)
    before = rng.bit_generator.state
    m = DisturbanceModel(DisturbanceConfig(), 3, rng)
    d_p, d_a = m.sample(0.0, DT)
    d_p2, d_a2 = m.sample(0.001, DT)
    assert d_p.shape == d_a.shape == (3, 3)
    assert not d_p.any() and not d_a.any()
    assert d_p is d_p2 and d_a is d_a2  # cached
    assert rng.bit_generator.state == before


def test_disturbance_seeded_reproducible():
    cfg = DisturbanceConfig(wind=(0.1, 0.0, 0.0), gust_std=0.3, gust_tau_s=0.5, attitude_std=2.0)

    def seq(seed):
        m = DisturbanceModel(cfg, 3, np.random.default_rng(seed))
        return [m.sample(k * DT, DT) for k in range(100)]

    a, b, c = seq(11), seq(11), seq(12)
    for (pa, aa), (pb, ab) in zip(a, b):
        np.testing.assert_array_equal(pa, pb)
        np.testing.assert_array_equal(aa, ab)
    assert not np.array_equal(a[50][0], c[50][0])
    # the gust starts from 0: the first sample is the wind alone
    np.testing.assert_array_equal(a[0][0], np.tile([0.1, 0.0, 0.0], (3, 1)))


def test_gust_stationary_std_and_correlation():
    std, tau, dt = 0.3, 0.5, 0.01
    m = DisturbanceModel(DisturbanceConfig(gust_std=std, gust_tau_s=tau), 32, np.random.default_rng(8))
    k = 10000
    g = np.empty((k, 32, 3))
    for i in range(k):
        g[i] = m.sample(i * dt, dt)[0]
    g = g[500:]  # started from 0: drop 10 tau of transient
    assert abs(g.std() / std - 1.0) < 0.10
    assert abs(g.mean()) < 0.05 * std
    # lag-tau autocorrelation of a Gauss-Markov process is exp(-1)
    lag = int(round(tau / dt))
    rho = np.mean(g[lag:] * g[:-lag]) / np.mean(g * g)
    assert rho == pytest.approx(math.exp(-1.0), abs=0.05)


def test_attitude_noise_std():
    m = DisturbanceModel(DisturbanceConfig(attitude_std=3.0), 4, np.random.default_rng(9))
    d_a = np.array([m.sample(i * DT, DT)[1] for i in range(5000)])
    assert abs(d_a.std() / 3.0 - 1.0) < 0.05
    # white: consecutive samples uncorrelated
    assert abs(np.mean(d_a[1:] * d_a[:-1]) / 9.0) < 0.05


def test_sine_and_wind_match_closed_form():
    wind = (0.05, -0.1, 0.02)
    amp = (0.2, 0.0, -0.1)
    f = 0.7
    rng = np.random.default_rng(10)
    before = rng.bit_generator.state
    m = DisturbanceModel(DisturbanceConfig(wind=wind, sine_amplitude=amp, sine_freq_hz=f), 3, rng)
    for t in (0.0, 0.123, 1.0, 13.37):
        d_p, d_a = m.sample(t, DT)
        expected = np.array(wind) + np.array(amp) * math.sin(2 * math.pi * f * t)
        np.testing.assert_allclose(d_p, np.tile(expected, (3, 1)), rtol=0, atol=1e-15)
        assert not d_a.any()
    assert rng.bit_generator.state == before  # no randomness configured, none drawn


# ----------------------------------------------------------------------------- params


def test_params_defaults_and_from_vehicle_overrides():
    assert P.mass == 0.027
    assert P.inertia == (1.657171e-5, 1.6655602e-5, 2.9261652e-5)
    assert P.max_thrust == pytest.approx(2.25 * 0.027 * 9.81, rel=1e-12)
    assert QuadParams.from_vehicle(VehicleConfig()) == P
    assert QuadParams.from_vehicle(None) == P

    heavy = QuadParams.from_vehicle(VehicleConfig(mass=0.054))
    assert heavy.mass == 0.054
    assert heavy.thrust_to_weight == pytest.approx(2.25, rel=1e-12)
    assert heavy.inertia == P.inertia and heavy.max_tilt == P.max_tilt

    both = QuadParams.from_vehicle(VehicleConfig(mass=0.054, max_thrust=0.9))
    assert both.max_thrust == 0.9

    j2 = tuple(2 * j for j in P.inertia)
    other = QuadParams.from_vehicle(VehicleConfig(inertia=j2, max_tilt=0.3))
    assert other.inertia == j2 and other.max_tilt == 0.3 and other.mass == P.mass
    # rate gains follow the inertia so the loop keeps its dynamics
    np.testing.assert_allclose(np.array(other.rate_kp) / j2, np.array(P.rate_kp) / P.inertia, rtol=1e-12)

    with pytest.raises(ValueError):
        QuadParams(mass=-1.0)
    with pytest.raises(ValueError):
        QuadParams(max_tilt=2.0)


def test_overridden_vehicle_still_tracks_attitude():
    p2 = QuadParams.from_vehicle(VehicleConfig(mass=0.035, inertia=(2.5e-5, 2.5e-5, 4e-5)))
    s = initial_state(np.zeros((1, 3)))
    y = run(s, 700, p2.mass * p2.g, np.array([[0.2, 0.0, 0.0]]), params=p2, record="rpy")[:, 0, 0]
    assert np.abs(y[499:] - 0.2).max() <= 0.004

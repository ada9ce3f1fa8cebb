"""The simulated vehicles' onboard position controller: the loop a PX4 / ArduCopter autopilot
(:mod:`zenswarm.plant.mavlink.autopilot`) and a Crazyflie's firmware
(:mod:`zenswarm.plant.crazyflie.firmware`) close around a position or velocity setpoint, before
their attitude controller (the plant's onboard PID, :func:`zenswarm.plant.quadrotor.step`).

Pure numerics (numpy + math). Frame: the swarm's ENU (positions m, velocities m/s), Euler angles
ZYX (roll phi, pitch theta, yaw psi, rad) of the body frame FLU; thrust in N.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["position_loop"]


def position_loop(
    q: np.ndarray,
    v: np.ndarray,
    p_ref: np.ndarray | None,
    v_ref: np.ndarray,
    yaw: float,
    *,
    kp: np.ndarray,
    kd: np.ndarray,
    max_pos_err: float,
    mass: float,
    g: float,
    max_tilt: float,
    max_thrust: float,
) -> tuple[float, np.ndarray]:
    """a = Kp (p* - p) + Kd (v* - v), then the thrust and attitude of that acceleration.

    q, v: the vehicle's position (m) and velocity (m/s), (3,) ENU. p_ref: the position setpoint
    (m), None for none (velocity control), a NaN axis not position-controlled; the position error
    is clipped to the norm ``max_pos_err`` (m; it limits the approach speed). v_ref: the velocity
    setpoint, m/s. yaw: the yaw setpoint, rad. kp (1/s^2), kd (1/s): (3,) gains per axis. The
    acceleration is limited to the tilt envelope (horizontal at most 0.9 g tan ``max_tilt``) and
    the thrust envelope (vertical in [-0.7 g, 0.9 (``max_thrust`` / ``mass`` - g)]); then F = m
    |a + g e_z| and the attitude of that thrust direction at ``yaw`` (the inversion after eq. 28).
    Returns (F, N; [phi, theta, psi], rad).
    """
    a = kd * (v_ref - v)
    if p_ref is not None:
        e = np.where(np.isnan(p_ref), 0.0, p_ref - q)
        n = float(np.linalg.norm(e))
        if n > max_pos_err:
            e *= max_pos_err / n
        a += kp * e
    axy_max = 0.9 * g * math.tan(max_tilt)
    nxy = math.hypot(a[0], a[1])
    if nxy > axy_max:
        a[0:2] *= axy_max / nxy
    a[2] = min(max(a[2], -0.7 * g), 0.9 * (max_thrust / mass - g))
    ux, uy, uz = a[0], a[1], a[2] + g
    norm = math.sqrt(ux * ux + uy * uy + uz * uz)
    s, c = math.sin(yaw), math.cos(yaw)
    phi = math.asin(min(max((ux * s - uy * c) / norm, -1.0), 1.0))
    theta = math.atan2(ux * c + uy * s, uz)
    return mass * norm, np.array([phi, theta, yaw])

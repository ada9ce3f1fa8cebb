"""Thrust and attitude from a virtual acceleration, and back (after eq. 28; definition under eq. 2).

The agents' controller turns its virtual control u (eq. 28) into a total thrust and desired
roll/pitch with :func:`invert_thrust_attitude`; the vehicle's command-loss failsafe does the same
with its hold loop. Pure numerics (numpy + math); (3,) vectors or (N, 3) stacks; SI units,
inertial frame ENU, Euler angles ZYX (roll phi, pitch theta, yaw psi) of the body frame FLU.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["invert_thrust_attitude", "virtual_control_from_attitude"]


def invert_thrust_attitude(
    u: np.ndarray, mass: float, yaw: float = 0.0, min_uz: float = 0.1
) -> tuple[np.ndarray | np.float64, np.ndarray | np.float64, np.ndarray | np.float64]:
    """Total thrust and desired roll/pitch from u (after eq. 28).

    F = m ||u||, phi_d = arcsin(m/F (u_x sin psi_d - u_y cos psi_d)),
    theta_d = arctan((u_x cos psi_d + u_y sin psi_d) / u_z).

    u: (3,) or (N, 3) m/s^2. mass: kg. yaw: desired yaw psi_d, rad. u_z is floored at
    ``min_uz`` (m/s^2) so the inversion is defined when the command asks to accelerate downward
    faster than gravity (the thrust cannot point down); the arcsin argument is clipped to [-1, 1].
    Returns (F (N,) or scalar, N; phi_d; theta_d) in rad. Tilt limits are the plant's job.
    """
    u = np.asarray(u, dtype=float)
    if u.shape == (3,):
        return _invert_one(u, mass, yaw, min_uz)
    return _invert_many(u, mass, yaw, min_uz)


def _invert_many(u: np.ndarray, mass: float, yaw: float, min_uz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`invert_thrust_attitude` of stacked u (..., 3), m/s^2 (float)."""
    ux = u[..., 0]
    uy = u[..., 1]
    uz = np.maximum(u[..., 2], min_uz)
    norm = np.sqrt(ux * ux + uy * uy + uz * uz)
    F = mass * norm
    s, c = np.sin(yaw), np.cos(yaw)
    phi = np.arcsin(np.clip((ux * s - uy * c) / norm, -1.0, 1.0))
    theta = np.arctan2(ux * c + uy * s, uz)
    return F, phi, theta


def _invert_one(u: np.ndarray, mass: float, yaw: float, min_uz: float) -> tuple[np.float64, np.float64, np.float64]:
    """:func:`invert_thrust_attitude` of one (3,) u on Python floats (an agent's every tick): the
    same operations in the same order as the stacked form, so the same bits (np.maximum and
    np.clip pass NaN through, and so do these; sin/cos of the yaw are the same as numpy's;
    arcsin and arctan2 stay numpy's, whose results differ from the math module's)."""
    ux, uy, uz = u.tolist()
    if not uz >= min_uz and uz == uz:
        uz = min_uz
    norm = math.sqrt(ux * ux + uy * uy + uz * uz)
    if norm == 0.0:  # only with min_uz <= 0: numpy's 0/0 and x/0, with its warnings
        F, phi, theta = _invert_many(u[None, :], mass, yaw, min_uz)
        return F[0], phi[0], theta[0]
    s, c = math.sin(yaw), math.cos(yaw)
    a = (ux * s - uy * c) / norm
    if a < -1.0:
        a = -1.0
    elif a > 1.0:
        a = 1.0
    return np.float64(mass * norm), np.arcsin(a), np.arctan2(ux * c + uy * s, uz)


def virtual_control_from_attitude(F: np.ndarray, rpy: np.ndarray, mass: float) -> np.ndarray:
    """u = R(phi, theta, psi) [0, 0, F]^T / m, the definition under eq. (2); the inverse check."""
    rpy = np.asarray(rpy, dtype=float)
    phi, theta, psi = rpy[..., 0], rpy[..., 1], rpy[..., 2]
    cphi, sphi = np.cos(phi), np.sin(phi)
    cth, sth = np.cos(theta), np.sin(theta)
    cps, sps = np.cos(psi), np.sin(psi)
    a = np.asarray(F, dtype=float) / mass
    return np.stack(
        [a * (cps * sth * cphi + sps * sphi), a * (sps * sth * cphi - cps * sphi), a * (cphi * cth)], axis=-1
    )

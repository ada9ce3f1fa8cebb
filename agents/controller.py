"""Composite tracking controller, paper eq. (28), and the thrust/attitude inversion after it.

Pure numerics (numpy + math). Works on (3,) vectors or (N, 3) stacks. The inversion lives in the
base layer (:mod:`zenswarm.vehicle.inversion`: the vehicle's failsafe uses it too) and is re-exported.
"""

from __future__ import annotations

import numpy as np

from zenswarm.vehicle.inversion import invert_thrust_attitude, virtual_control_from_attitude

__all__ = ["composite_control", "invert_thrust_attitude", "virtual_control_from_attitude"]


def composite_control(
    q_ref: np.ndarray,
    v_ref: np.ndarray,
    vdot_ref: np.ndarray,
    q: np.ndarray,
    v: np.ndarray,
    d_hat: np.ndarray,
    kp: np.ndarray,
    kd: np.ndarray,
    g: float = 9.81,
) -> np.ndarray:
    """u_i = G - d_hat + K_p (q* - q) + K_d (v* - v) + v*', eq. (28).

    q_ref, v_ref, vdot_ref: generator output q*_i (m), v*_i (m/s) and v*_i' (m/s^2, eq. 17).
    q, v: measured position and velocity. d_hat: ESO disturbance estimate (m/s^2; zeros when
    the ESO is disabled). kp, kd: (3,) diagonals of K_p (1/s^2) and K_d (1/s).
    Returns the virtual control u (same shape as q), m/s^2.
    """
    u: np.ndarray = kp * (q_ref - q) + kd * (v_ref - v) + vdot_ref - d_hat
    u[..., 2] += g
    return u

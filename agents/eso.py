"""Extended state observer of the position loop, paper eq. (27).

Pure numerics (numpy only). The observer estimates (q_i, v_i, d_i^p) from the measured position
q_i and the applied virtual control u_i. Discretisation: explicit Euler at the control period
dt, using the estimate and input of tick k to produce the estimate of tick k+1
(:func:`eso_step`). Works on (3,) or (N, 3) arrays alike.
"""

from __future__ import annotations

import numpy as np

__all__ = ["G_VEC", "eso_rates", "eso_step", "eso_matrix", "bandwidth_gains"]

G_VEC = np.array([0.0, 0.0, 9.81])
"""Default gravity vector G = [0, 0, g], m/s^2 (eq. 1). Functions take g explicitly."""


def eso_rates(
    q_hat: np.ndarray,
    v_hat: np.ndarray,
    d_hat: np.ndarray,
    q_meas: np.ndarray,
    u: np.ndarray,
    beta: tuple[float, float, float],
    g: float = 9.81,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Right-hand side of eq. (27).

    q_hat, v_hat, d_hat: estimates, m, m/s, m/s^2. q_meas: measured position, m.
    u: virtual control u_i = R F_b / m, m/s^2 (eq. 3). beta = (beta1, beta2, beta3) > 0.
    Returns (q_hat', v_hat', d_hat').
    """
    b1, b2, b3 = beta
    e = q_meas - q_hat
    acc = u + d_hat + b2 * e
    acc[..., 2] -= g
    return v_hat + b1 * e, acc, b3 * e


def eso_step(
    q_hat: np.ndarray,
    v_hat: np.ndarray,
    d_hat: np.ndarray,
    q_meas: np.ndarray,
    u: np.ndarray,
    beta: tuple[float, float, float],
    dt: float,
    g: float = 9.81,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One explicit-Euler step of eq. (27) over dt (s). Returns the new (q_hat, v_hat, d_hat)."""
    dq, dv, dd = eso_rates(q_hat, v_hat, d_hat, q_meas, u, beta, g)
    return q_hat + dt * dq, v_hat + dt * dv, d_hat + dt * dd


def eso_matrix(beta: tuple[float, float, float]) -> np.ndarray:
    """A_e of eq. (31), (9, 9)."""
    b1, b2, b3 = beta
    I = np.eye(3)
    Z = np.zeros((3, 3))
    return np.block([[-b1 * I, I, Z], [-b2 * I, Z, I], [-b3 * I, Z, Z]])


def bandwidth_gains(omega_o: float) -> tuple[float, float, float]:
    """beta = (3 w, 3 w^2, w^3): all eigenvalues of A_e at -omega_o (after eq. 32)."""
    w = float(omega_o)
    return 3.0 * w, 3.0 * w * w, w * w * w

"""Delay margin of the distributed reference generator, paper eqs (16)-(17) (pure numpy).

The derivation is in ``docs/delay_margin.md``; this module is its formulas. Notation (paper,
section Graph theory notions): A (N, N) symmetric adjacency, b (N,) pinning weights, L the
Laplacian, B = diag(b), M = L + B (eq. 20; positive definite by Lemma 1 when the graph is
connected and B != 0). Write M = Delta - A with Delta = diag(delta), delta_i = sum_j a_ij + b_i
(the diagonal of M).

Two delay models, never to be mixed up:

* **zenswarm's** ("own state current"): agent i integrates (16)-(17) with its OWN generator
  state (q*_i, v*_i) of the current tick and the neighbours' (q*_j, v*_j) and the leader's
  (q0, v0) received with a uniform link delay tau. Per axis and per loop (mu = mu1 for the
  position loop (16), mu = mu2 for the velocity loop (17); the error system (19)-(20) is block
  triangular, so its spectrum is the union of the two loops'), the error obeys

      continuous:  x'(t) = -mu Delta x(t) + mu A x(t - tau)                       (D1)
      Euler at dt, delay of d ticks (what the swarm computes):
                   x(k+1) = (I - a Delta) x(k) + a A x(k - d),   a = mu dt        (D2)

  (D1) is stable for EVERY tau >= 0 (delay-independent) and (D2) for every d >= 0 as soon as
  rho(Delta^-1 A) < 1 (true whenever M is positive definite, Lemma 1) and, for (D2),
  a max_i delta_i <= 1 (:func:`delay_independent`). Otherwise the exact test of (D2) is the
  spectral radius of its lifted (companion) matrix (:func:`lifted_matrix`).

* **the classical, fully delayed** model, for comparison only (NOT what zenswarm runs): the
  whole consensus term delayed, own state included,

      x'(t) = -mu M x(t - tau):  stable iff tau < pi / (2 mu lambda_max(M))         (F1)
      x(k+1) = x(k) - a M x(k - d):  stable iff a lambda_max(M) < 2 cos(d pi / (2 d + 1))  (F2)

  (F2) is the Levin-May condition, applied per eigenvalue of the symmetric M.

A link delay tau becomes an integer number of ticks d = ceil(tau / dt - 1e-9)
(:func:`delay_ticks`, the same as :func:`zenswarm.link.units.delivery_tick`): the receiver holds the
message of tick k - d at tick k.

Units: dt, tau in s; mu1, mu2 in 1/s (with unit weights a_ij, b_i).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "degrees",
    "graph_matrix",
    "delay_ticks",
    "delay_independent",
    "lifted_matrix",
    "spectral_radius",
    "mode_roots",
    "modal_spectral_radius",
    "discrete_margin_ticks",
    "generator_margin_ticks",
    "continuous_scalar_margin",
    "fully_delayed_bound",
    "levin_may_bound",
    "fully_delayed_discrete_margin_ticks",
    "steady_lag_factors",
]

_EPS_TICK = 1e-9


def _check(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float).reshape(-1)
    n = A.shape[0]
    if A.shape != (n, n) or b.shape != (n,):
        raise ValueError(f"A must be (N, N) and b (N,), got {A.shape} and {b.shape}")
    if np.any(A < 0) or np.any(b < 0) or np.any(np.diag(A) != 0):
        raise ValueError("A must be non-negative with a zero diagonal and b non-negative")
    return A, b


def degrees(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """delta (N,): delta_i = sum_j a_ij + b_i, the diagonal of M = L + B (Delta = D + B)."""
    A, b = _check(A, b)
    d: np.ndarray = A.sum(axis=1) + b
    return d


def graph_matrix(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """M = L + B = Delta - A (N, N), eq. (20)."""
    A, b = _check(A, b)
    M: np.ndarray = np.diag(degrees(A, b)) - A
    return M


def delay_ticks(tau: float, dt: float) -> int:
    """Ticks of delay d a link delay tau (s) becomes at control period dt (s):
    ceil(tau / dt - 1e-9) (as :func:`zenswarm.link.units.delivery_tick`)."""
    if not dt > 0 or not (tau >= 0 and math.isfinite(tau)):
        raise ValueError(f"need dt > 0 and a finite tau >= 0, got dt={dt!r}, tau={tau!r}")
    return max(0, math.ceil(tau / dt - _EPS_TICK))


def delay_independent(A: np.ndarray, b: np.ndarray, mu: float, dt: float | None = None) -> bool:
    """True when (D1) (``dt`` None) or (D2) (Euler at ``dt``) is stable for every delay.

    Sufficient condition proved in docs/delay_margin.md: every delta_i > 0,
    rho(Delta^-1 A) < 1 (Delta - A = M a nonsingular M-matrix; with A symmetric this is M
    positive definite, Lemma 1), and for (D2) also mu dt max_i delta_i <= 1.
    """
    A, b = _check(A, b)
    if not mu > 0:
        raise ValueError(f"mu must be > 0, got {mu!r}")
    delta = degrees(A, b)
    if np.any(delta <= 0):
        return False
    if float(np.max(np.abs(np.linalg.eigvals(A / delta[:, None])))) >= 1.0:
        return False
    return dt is None or mu * dt * float(np.max(delta)) <= 1.0


def lifted_matrix(A: np.ndarray, b: np.ndarray, mu: float, dt: float, d: int) -> np.ndarray:
    """The companion matrix of (D2), (N (d+1), N (d+1)), on X(k) = [x(k); x(k-1); ...; x(k-d)]:
    X(k+1) = F X(k). d = 0 gives F = I - a M (the delay-free Euler step), a = mu dt."""
    A, b = _check(A, b)
    if d < 0:
        raise ValueError(f"d must be >= 0, got {d!r}")
    n = A.shape[0]
    a = mu * dt
    top = np.eye(n) - a * np.diag(degrees(A, b))
    if d == 0:
        F0: np.ndarray = top + a * A
        return F0
    F = np.zeros((n * (d + 1), n * (d + 1)))
    F[:n, :n] = top
    F[:n, n * d :] = a * A
    F[n:, :-n] = np.eye(n * d)
    return F


def spectral_radius(A: np.ndarray, b: np.ndarray, mu: float, dt: float, d: int) -> float:
    """rho of :func:`lifted_matrix`: (D2) is asymptotically stable iff it is < 1 (exact, any graph)."""
    return float(np.max(np.abs(np.linalg.eigvals(lifted_matrix(A, b, mu, dt, d)))))


def mode_roots(alpha: float, delta: float, mu: float, dt: float, d: int) -> np.ndarray:
    """Roots z of z^(d+1) - (1 - a delta) z^d - a alpha = 0, a = mu dt: one mode of (D2) when
    Delta = delta I (alpha an eigenvalue of A). (d+1,) complex."""
    a = mu * dt
    coeffs = np.zeros(d + 2)
    coeffs[0] = 1.0
    coeffs[1] = -(1.0 - a * delta)
    coeffs[-1] += -a * alpha
    r: np.ndarray = np.roots(coeffs)
    return r


def modal_spectral_radius(A: np.ndarray, b: np.ndarray, mu: float, dt: float, d: int) -> float:
    """rho of (D2) mode by mode, when Delta = delta I (e.g. a complete or ring graph with uniform
    pinning): the max over the eigenvalues alpha of A of the largest root of :func:`mode_roots`.
    Equal to :func:`spectral_radius` (which needs no such structure). ValueError otherwise."""
    A, b = _check(A, b)
    delta = degrees(A, b)
    if not np.allclose(delta, delta[0]):
        raise ValueError("Delta = D + B is not a multiple of the identity: the modes do not decouple (use spectral_radius)")
    alphas = np.linalg.eigvalsh(A)
    return float(max(np.max(np.abs(mode_roots(float(al), float(delta[0]), mu, dt, d))) for al in alphas))


def discrete_margin_ticks(A: np.ndarray, b: np.ndarray, mu: float, dt: float, d_max: int) -> float:
    """Largest d such that (D2) is stable for every delay 0..d ticks; ``math.inf`` when
    :func:`delay_independent` proves it for every d; -1 if unstable without delay. Otherwise a scan
    of :func:`spectral_radius` for d = 0..d_max (returns d_max if all of them are stable: a lower
    bound only)."""
    if delay_independent(A, b, mu, dt):
        return math.inf
    for d in range(d_max + 1):
        if spectral_radius(A, b, mu, dt, d) >= 1.0:
            return float(d - 1)
    return float(d_max)


def generator_margin_ticks(A: np.ndarray, b: np.ndarray, mu1: float, mu2: float, dt: float, d_max: int) -> float:
    """Delay margin in ticks of the generator (16)-(17) in zenswarm's model (D2): the smaller of
    the position loop's (mu1) and the velocity loop's (mu2) (block-triangular error system (21))."""
    return min(discrete_margin_ticks(A, b, mu1, dt, d_max), discrete_margin_ticks(A, b, mu2, dt, d_max))


def continuous_scalar_margin(a: float, c: float) -> float:
    """Exact delay margin (s) of the scalar x'(t) = -a x(t) + c x(t - tau).

    * a + |c| ... : unstable at tau = 0 if c - a >= 0 (returns -1.0);
    * |c| <= a: stable for every tau (``math.inf``; the scalar form of (D1), |alpha| < delta);
    * otherwise (c < -|a|): stable iff tau < arccos(a / c) / sqrt(c^2 - a^2) (the root crosses the
      imaginary axis at s = i w, w = sqrt(c^2 - a^2)); a = 0 gives pi / (2 |c|), i.e. (F1).
    """
    if c - a >= 0.0:
        return -1.0
    if abs(c) <= a:
        return math.inf
    w = math.sqrt(c * c - a * a)
    return math.acos(a / c) / w


def fully_delayed_bound(M: np.ndarray, mu: float) -> float:
    """(F1): pi / (2 mu lambda_max(M)) s, the exact margin of x' = -mu M x(t - tau), M symmetric
    positive definite. A DIFFERENT delay model from zenswarm's (own state delayed too)."""
    lam = float(np.max(np.linalg.eigvalsh(np.asarray(M, dtype=float))))
    return math.pi / (2.0 * mu * lam)


def levin_may_bound(d: int) -> float:
    """2 cos(d pi / (2 d + 1)): x(k+1) = x(k) - q x(k - d) is asymptotically stable iff
    0 < q < this (Levin and May, 1976)."""
    return 2.0 * math.cos(d * math.pi / (2 * d + 1))


def fully_delayed_discrete_margin_ticks(M: np.ndarray, mu: float, dt: float) -> int:
    """(F2): the largest d with mu dt lambda_max(M) < 2 cos(d pi / (2 d + 1)) (-1 if none).
    The Euler form of (F1): d dt -> pi / (2 mu lambda_max) - dt / 2 as dt -> 0."""
    q = mu * dt * float(np.max(np.linalg.eigvalsh(np.asarray(M, dtype=float))))
    if not q > 0:
        raise ValueError("need mu dt lambda_max(M) > 0")
    d = -1
    while q < levin_may_bound(d + 1):
        d += 1
    return d


def steady_lag_factors(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """c (N,) = M^-1 Delta 1: with a constant leader velocity v0 (Assumption 1) and delay tau
    (continuous) or d ticks (tau = d dt, discrete), the position error of (16) settles at
    q*_i - q0 - h_i = -tau c_i v0 and v*_i = v0 (section Steady lag of docs/delay_margin.md).
    c_i >= 1; c = 1 for a single pinned agent."""
    M = graph_matrix(A, b)
    c: np.ndarray = np.linalg.solve(M, degrees(A, b))
    return c

"""Closed-form checks of the pure math: generator (16-21), ESO (27, 31), controller (28) and the
inversion after it, AAPF (8-15). Tolerances are stated per test."""

from __future__ import annotations

import ast
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from zenswarm.agents.controller import composite_control, invert_thrust_attitude, virtual_control_from_attitude
from zenswarm.agents.eso import bandwidth_gains, eso_matrix, eso_step
from zenswarm.agents.generator import error_matrix, generator_rates, generator_rates_all, graph_matrix
from zenswarm.leader import aapf
from zenswarm.scenario.config import Obstacle

ROOT = Path(__file__).resolve().parents[1]
PURE_MODULES = [
    "leader/aapf.py",
    "leader/escape.py",
    "agents/generator.py",
    "agents/eso.py",
    "agents/controller.py",
    "agents/core.py",
    "zenswarm/vehicle/params.py",
    "plant/quadrotor.py",
    "plant/disturbance.py",
    "plant/failsafe.py",
    "plant/position_control.py",
    "zenswarm/vehicle/frames.py",
    "zenswarm/vehicle/crazyflie.py",
    "zenswarm/judge/metrics.py",
    "zenswarm/judge/verdict.py",
    "zenswarm/judge/watch.py",
    "zenswarm/vehicle/geometry.py",
    "zenswarm/vehicle/inversion.py",
    "zenswarm/campaign/delaymargin.py",
]
ALLOWED_IMPORTS = {"numpy", "math", "dataclasses", "typing", "__future__", "zenswarm"}


def _module_name(rel: str) -> str:
    """Installed module name of a repository file: ``agents/eso.py`` -> ``zenswarm.agents.eso``."""
    name = rel.removesuffix(".py").replace("/", ".")
    return name if name.startswith("zenswarm.") else "zenswarm." + name


# A math module may import another math module, and these (types and the obstacle geometry) only.
ALLOWED_ZENSWARM = {
    "zenswarm.scenario.config", "zenswarm.schema", "zenswarm.errors", "zenswarm.vehicle.geometry", *map(_module_name, PURE_MODULES),
}  # fmt: skip
# the scenario and its tables are allowed (types only); anything that touches I/O, the clock or the network is not.
FORBIDDEN_NAMES = {"open", "print", "input", "perf_counter", "monotonic", "sleep"}


# --------------------------------------------------------------------------- purity


@pytest.mark.parametrize("rel", PURE_MODULES)
def test_math_module_imports_numpy_only(rel: str) -> None:
    tree = ast.parse((ROOT / rel).read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name.split(".")[0] for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative import inside the same package
                mod = (node.module or "").split(".")[0]
                assert mod not in {"bus", "wire", "cli", "sim", "process"}, f"{rel}: relative import of {node.module}"
                continue
            if node.module == "collections.abc":  # abstract types for annotations only
                continue
            names = [node.module.split(".")[0]]
            if node.module.startswith("zenswarm") and node.module not in ALLOWED_ZENSWARM:
                pytest.fail(
                    f"{rel} imports {node.module}: math modules may use other math modules, the scenario's types, errors and geometry only"
                )
        else:
            if isinstance(node, ast.Name) and node.id in FORBIDDEN_NAMES:
                pytest.fail(f"{rel} uses {node.id} (I/O or clock) at line {node.lineno}")
            continue
        for n in names:
            assert n in ALLOWED_IMPORTS, f"{rel} imports {n}: math modules import numpy only"


def test_math_modules_load_no_io_libraries() -> None:
    code = (
        "import sys\n"
        "import zenswarm.leader.aapf, zenswarm.agents.core, zenswarm.plant.quadrotor, zenswarm.plant.disturbance\n"
        "import zenswarm.judge.metrics, zenswarm.judge.verdict\n"
        "bad = [m for m in ('zenoh', 'mcap', 'pymavlink', 'msgpack', 'socket') if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "", f"math modules pulled in I/O libraries: {out.stdout}"


# --------------------------------------------------------------------------- generator


def _random_graph(rng: np.random.Generator, n: int) -> np.ndarray:
    A = (rng.random((n, n)) < 0.4).astype(float) * rng.uniform(0.5, 2.0, (n, n))
    A = np.triu(A, 1)
    return A + A.T


def test_D_hurwitz_iff_M_positive_definite() -> None:
    """D of (21) is Hurwitz exactly when M = L + B is positive definite (Lemma 1, Prop. 1)."""
    rng = np.random.default_rng(1)
    seen = {True: 0, False: 0}
    for _ in range(300):
        n = int(rng.integers(2, 7))
        A = _random_graph(rng, n)
        b = (rng.random(n) < 0.3) * rng.uniform(0.5, 2.0, n)
        M = graph_matrix(A, b)
        pd = bool(np.min(np.linalg.eigvalsh(M)) > 1e-9)
        D = error_matrix(M, 0.1, 2.0)
        hurwitz = bool(np.max(np.linalg.eigvals(D).real) < -1e-12)
        assert pd == hurwitz
        seen[pd] += 1
    assert seen[True] > 20 and seen[False] > 20  # both cases exercised


def test_generator_rates_match_matrix_form() -> None:
    """Per-agent (16)-(17) equals the stacked error dynamics (20) with M = L + B (1e-12)."""
    rng = np.random.default_rng(2)
    n = 5
    A = _random_graph(rng, n)
    b = np.array([1.0, 0, 0, 0.5, 0])
    h = rng.normal(size=(n, 3))
    qs, vs = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    q0, v0 = rng.normal(size=3), rng.normal(size=3)
    dq, dv = generator_rates_all(qs, vs, h, A, b, q0, v0, 0.1, 2.0)
    M = graph_matrix(A, b)
    qt = qs - q0 - h
    vt = vs - v0
    # (19): q~' = v~ - mu1 M q~ ; with q~' = q*' - v0 (q0' = v0)
    np.testing.assert_allclose(dq - v0, vt - 0.1 * M @ qt, atol=1e-12)
    np.testing.assert_allclose(dv, -2.0 * M @ vt, atol=1e-12)
    # and the single-agent form for agent 3 (pinned with weight 0.5)
    nbr = np.flatnonzero(A[3])
    dq3, dv3 = generator_rates(qs[3], vs[3], h[3], qs[nbr], vs[nbr], h[nbr], A[3, nbr], 0.5, q0, v0, 0.1, 2.0)
    np.testing.assert_array_equal(dq3, dq[3])
    np.testing.assert_array_equal(dv3, dv[3])


@pytest.mark.slow
def test_generator_converges_to_leader_plus_offsets_with_constant_v0() -> None:
    """Prop. 1: with constant v0, q*_i - q0 - h_i -> 0 and v*_i -> v0 (exponentially)."""
    A = np.array([[0, 1, 1], [1, 0, 0], [1, 0, 0]], float)
    b = np.array([1.0, 0, 0])
    h = np.array([[0.1, 0, 0], [-0.12, 0.25, 0], [-0.12, -0.25, 0]])
    qs = np.array([[0, 0, 0.4], [0, 0.2, 0.4], [0, -0.2, 0.4]])
    vs = np.zeros((3, 3))
    q0 = np.array([0, 0, 0.4])
    v0 = np.array([0.2, -0.1, 0.05])
    dt = 0.01
    M = graph_matrix(A, b)
    rate = 0.5 * np.min(np.linalg.eigvalsh(M))  # mu1 = 0.5 here: slowest mode exp(-mu1 lam_min t)
    errs = []
    for k in range(12000):
        dq, dv = generator_rates_all(qs, vs, h, A, b, q0, v0, 0.5, 2.0)
        qs, vs = qs + dt * dq, vs + dt * dv
        q0 = q0 + dt * v0
        if k % 1000 == 999:
            errs.append(np.max(np.linalg.norm(qs - q0 - h, axis=1)))
    assert errs[-1] < 1e-6
    np.testing.assert_allclose(vs, np.tile(v0, (3, 1)), atol=1e-9)
    # decays at least as fast as the slowest mode predicts (with slack for the transient)
    assert errs[-1] < errs[0] * math.exp(-rate * 100.0) * 100


# --------------------------------------------------------------------------- ESO


@pytest.mark.parametrize("w", [1.0, 5.0, 12.5])
def test_eso_matrix_eigenvalues_at_minus_omega(w: float) -> None:
    """A_e of (31) with beta = (3w, 3w^2, w^3) has all eigenvalues at -w."""
    Ae = eso_matrix(bandwidth_gains(w))
    # triple eigenvalue: compare the characteristic polynomial (exact) rather than eigvals
    poly = np.poly(Ae[np.ix_([0, 3, 6], [0, 3, 6])])
    np.testing.assert_allclose(poly, [1, 3 * w, 3 * w * w, w**3], rtol=1e-12)
    ev = np.linalg.eigvals(Ae)
    np.testing.assert_allclose(ev.real, -w, atol=1e-3 * w)  # triple root: eigvals are ill-conditioned


def test_paper_eso_gains_are_bandwidth_5() -> None:
    assert bandwidth_gains(5.0) == (15.0, 75.0, 125.0)


def test_eso_estimates_constant_disturbance_open_loop() -> None:
    """Double integrator with a constant d and zero input: d_hat -> d (Remark 6)."""
    d = np.array([0.3, -0.2, 0.5])
    g = 9.81
    dt = 0.001
    q, v = np.zeros(3), np.zeros(3)
    u = np.array([0.0, 0.0, g])  # cancels gravity
    qh, vh, dh = q.copy(), v.copy(), np.zeros(3)
    for _ in range(8000):
        qh, vh, dh = eso_step(qh, vh, dh, q, u, (15.0, 75.0, 125.0), dt, g)
        v = v + dt * (u - np.array([0, 0, g]) + d)
        q = q + dt * v
    np.testing.assert_allclose(dh, d, atol=1e-3)


def _closed_loop_point_mass(d: np.ndarray, use_eso: bool) -> float:
    """Track a fixed reference with (27)+(28) on the translational model (3); returns |e_q| at end."""
    g, dt = 9.81, 0.01
    kp, kd = np.array([4.5, 4.5, 5.4]), np.array([5.0, 5.0, 3.0])
    q, v = np.zeros(3), np.zeros(3)
    qh, vh, dh = q.copy(), v.copy(), np.zeros(3)
    q_ref, v_ref = np.array([1.0, -0.5, 0.3]), np.zeros(3)
    for _ in range(2000):
        dh_used = dh if use_eso else np.zeros(3)
        u = composite_control(q_ref, v_ref, np.zeros(3), q, v, dh_used, kp, kd, g)
        qh, vh, dh = eso_step(qh, vh, dh, q, u, (15.0, 75.0, 125.0), dt, g)
        for _ in range(10):
            v = v + 0.001 * (u - np.array([0, 0, g]) + d)
            q = q + 0.001 * v
    return float(np.linalg.norm(q_ref - q))


def test_eso_rejects_constant_disturbance_in_closed_loop() -> None:
    d = np.array([0.8, -0.6, 1.0])
    with_eso = _closed_loop_point_mass(d, True)
    without = _closed_loop_point_mass(d, False)
    assert with_eso < 1e-3
    # without the ESO the steady-state error is |d_j| / kp_j per axis (PD on a double integrator)
    expected = np.linalg.norm(d / np.array([4.5, 4.5, 5.4]))
    assert without == pytest.approx(expected, rel=0.02)


# --------------------------------------------------------------------------- controller


def test_hover_needs_thrust_mg() -> None:
    m = 0.027
    u = composite_control(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3), np.ones(3), np.ones(3), 9.81)
    F, phi, theta = invert_thrust_attitude(u, m, 0.0)
    assert float(F) == pytest.approx(m * 9.81, rel=1e-15)
    assert float(phi) == 0.0 and float(theta) == 0.0


def test_inversion_then_rotation_reproduces_u() -> None:
    """F, phi_d, theta_d from u, then u = R(phi, theta, psi) [0,0,F]/m (eq. 2) gives u back."""
    rng = np.random.default_rng(3)
    m = 0.027
    for _ in range(200):
        psi = rng.uniform(-math.pi, math.pi)
        u = rng.normal(size=3) * 3.0
        u[2] = abs(u[2]) + 5.0
        F, phi, theta = invert_thrust_attitude(u, m, psi)
        back = virtual_control_from_attitude(F, np.array([phi, theta, psi]), m)
        np.testing.assert_allclose(back, u, atol=1e-12)


def test_inversion_of_one_u_equals_its_row_of_the_stacked_form_bit_for_bit() -> None:
    """An agent inverts its own (3,) u on Python floats; the simulator inverts the (N, 3) stack.
    Every output must be the same bits (sign included) and a numpy float64, for downward u
    (u_z floor), NaN, inf and u = 0 with a zero floor (numpy's 0/0 path)."""
    rng = np.random.default_rng(11)
    U = rng.normal(scale=5.0, size=(3000, 3))
    U[::7, 2] = -3.0
    U[::11] = [np.nan, 1.0, 2.0]
    U[::13, 2] = np.nan
    U[::17] = [0.0, -0.0, 0.1]
    U[::19, 0] = np.inf
    for yaw, min_uz in ((0.0, 0.1), (0.3, 0.1), (-2.0, 0.1), (0.5, 0.0)):
        if min_uz == 0.0:
            U[::5] = 0.0
        with np.errstate(all="ignore"):
            stacked = invert_thrust_attitude(U, 0.027, yaw, min_uz)
            for i in range(len(U)):
                one = invert_thrust_attitude(U[i], 0.027, yaw, min_uz)
                for a, b in zip(one, (x[i] for x in stacked)):
                    assert type(a) is np.float64, (i, yaw)
                    assert (a == b or (math.isnan(a) and math.isnan(b))) and np.signbit(a) == np.signbit(b), (i, yaw, a, b)


def test_inversion_matches_plant_rotation_matrix() -> None:
    from zenswarm.plant.quadrotor import rotation_matrix

    rng = np.random.default_rng(4)
    m = 0.03
    u = np.array([1.2, -0.7, 10.5])
    psi = 0.4
    F, phi, theta = invert_thrust_attitude(u, m, psi)
    R = rotation_matrix(np.array([phi, theta, psi]))
    np.testing.assert_allclose(R @ np.array([0, 0, F]) / m, u, atol=1e-12)
    del rng


# --------------------------------------------------------------------------- AAPF

OB = Obstacle(center=(1.0, 0.45, 0.0), radius=0.14, height=0.4)


def _params(adaptive: bool = True) -> aapf.AapfParams:
    return aapf.AapfParams(
        goal=(2.4, 1.4, 0.6), k_att=0.1, k_rep_min=0.05, k_rep_max=0.3, d0=0.12, r_f=0.2773, obstacles=[OB], adaptive=adaptive
    )


def _U(q: np.ndarray, p: aapf.AapfParams) -> float:
    return aapf.repulsive_potential(aapf.d_obs(q, OB, p.r_f), p.d0)


@pytest.mark.parametrize(
    "q",
    [
        np.array([1.0 + 0.48, 0.45 + 0.02, 0.2]),  # beside the cylinder part
        np.array([1.0 - 0.3, 0.45 - 0.3, 0.35]),
        np.array([1.0 + 0.2, 0.45 + 0.1, 0.4 + 0.4]),  # above: cap region
        np.array([1.0, 0.45 - 0.1, 0.4 + 0.46]),
    ],
)
def test_repulsive_force_is_minus_gain_times_grad_U(q: np.ndarray) -> None:
    """Gamma_rep = -K* grad U_rep (13) by central finite differences (rel 1e-5)."""
    p = _params()
    d = aapf.d_obs(q, OB, p.r_f)
    assert 0.0 < d < p.d0, "test point must lie inside the avoidance region"
    eps = 1e-7
    grad = np.array([(_U(q + eps * e, p) - _U(q - eps * e, p)) / (2 * eps) for e in np.eye(3)])
    expected = -aapf.adaptive_gain(d, p) * grad
    np.testing.assert_allclose(aapf.repulsive_force(q, p), expected, rtol=1e-5)


def test_attractive_force_is_minus_grad_U_att() -> None:
    p = _params()
    q = np.array([0.3, -0.2, 0.9])
    Uatt = lambda x: 0.5 * p.k_att * float(np.sum((x - p.goal) ** 2))  # noqa: E731  eq. (8)
    eps = 1e-6
    grad = np.array([(Uatt(q + eps * e) - Uatt(q - eps * e)) / (2 * eps) for e in np.eye(3)])
    np.testing.assert_allclose(aapf.attractive_force(q, p.goal, p.k_att), -grad, rtol=1e-7)


def test_equivalent_center_regions() -> None:
    """Eq. (10): [xc, yc, z0] up to the cylinder top, the cap centre above it."""
    np.testing.assert_array_equal(aapf.equivalent_center(np.array([0, 0, 0.3]), OB), [1.0, 0.45, 0.3])
    np.testing.assert_array_equal(aapf.equivalent_center(np.array([0, 0, 0.4]), OB), [1.0, 0.45, 0.4])
    np.testing.assert_array_equal(aapf.equivalent_center(np.array([0, 0, 0.9]), OB), [1.0, 0.45, 0.4])


def test_adaptive_gain_endpoints_and_linearity() -> None:
    """Eq. (12): K_min at d0, K_max at 0, linear between, 0 outside."""
    p = _params()
    assert aapf.adaptive_gain(0.12, p) == pytest.approx(0.05)
    assert aapf.adaptive_gain(0.0, p) == pytest.approx(0.3)
    assert aapf.adaptive_gain(0.06, p) == pytest.approx(0.175)
    assert aapf.adaptive_gain(0.13, p) == 0.0
    assert aapf.adaptive_gain(0.06, _params(adaptive=False)) == 1.0


def test_force_finite_at_and_inside_boundary() -> None:
    """d_obs <= 0 (sphere touching or inside): finite force pointing out of the obstacle."""
    p = _params()
    for q in [
        np.array([1.0 + 0.14 + 0.2773, 0.45, 0.2]),
        np.array([1.0 + 0.2, 0.45, 0.2]),
        np.array([1.0, 0.45, 0.2]),
        np.array([1.0, 0.45, 0.4]),
    ]:
        f = aapf.repulsive_force(q, p)
        assert np.all(np.isfinite(f))
        r, n = aapf.obstacle_distance(q, OB)
        assert float(f @ n) > 0.0


def test_integrate_leader_never_enters_inflated_obstacle() -> None:
    """Head straight at the obstacle: the adaptive sub-steps keep d_obs > 0 and values finite."""
    ob = Obstacle(center=(1.0, 0.0, 0.0), radius=0.14, height=2.0)
    p = aapf.AapfParams(goal=(3.0, 0.0, 0.5), k_att=0.5, k_rep_min=0.05, k_rep_max=0.3, d0=0.12, r_f=0.28, obstacles=[ob])
    q = np.array([0.0, 0.0, 0.5])
    dmin = math.inf
    for _ in range(3000):
        q, info = aapf.integrate_leader(q, 0.01, p, 10)
        assert not info.capped
        assert np.all(np.isfinite(q))
        dmin = min(dmin, aapf.d_obs(q, ob, p.r_f))
    assert dmin > 0.0


def test_obstacle_clearance_surfaces() -> None:
    """Signed distance to the real solid: side, cap, base rim, inside."""
    assert aapf.obstacle_clearance(np.array([1.5, 0.45, 0.2]), OB) == pytest.approx(0.5 - 0.14)
    assert aapf.obstacle_clearance(np.array([1.0, 0.45, 0.9]), OB) == pytest.approx(0.5 - 0.14)
    assert aapf.obstacle_clearance(np.array([1.3, 0.45, 0.7]), OB) == pytest.approx(math.hypot(0.3, 0.3) - 0.14)
    assert aapf.obstacle_clearance(np.array([1.0, 0.45, 0.2]), OB) == pytest.approx(-0.14)
    assert aapf.obstacle_clearance(np.array([1.0, 0.45, -0.1]), OB) == pytest.approx(0.1)
    pts = np.random.default_rng(5).uniform([0.5, 0.0, -0.2], [1.5, 0.9, 1.0], size=(500, 3))
    many = aapf.obstacle_clearance_many(pts, OB)
    one = np.array([aapf.obstacle_clearance(x, OB) for x in pts])
    np.testing.assert_allclose(many, one, atol=1e-15)

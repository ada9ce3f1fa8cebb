"""Delay margin of the generator (16)-(17): closed-form checks of zenswarm.campaign.delaymargin, the
generator-only simulation against the full simulator, the bisection, and the CLI's bad input.
All cheap (no process is started)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from zenswarm.campaign.delaymargin import (
    continuous_scalar_margin,
    delay_independent,
    delay_ticks,
    discrete_margin_ticks,
    fully_delayed_bound,
    fully_delayed_discrete_margin_ticks,
    graph_matrix,
    levin_may_bound,
    lifted_matrix,
    modal_spectral_radius,
    mode_roots,
    spectral_radius,
    steady_lag_factors,
)
from zenswarm.compose import margin
from zenswarm.compose.sim import simulate
from zenswarm.link.units import delivery_tick
from zenswarm.scenario.config import load_scenario

ROOT = Path(__file__).resolve().parents[1]
EX1 = ROOT / "compose" / "scenarios" / "paper_example1.toml"


def _ring(n: int) -> np.ndarray:
    A = np.zeros((n, n))
    for i in range(n):
        A[i, (i + 1) % n] = A[(i + 1) % n, i] = 1.0
    return A


def _complete(n: int) -> np.ndarray:
    return np.ones((n, n)) - np.eye(n)


# ----------------------------------------------------------------------------- continuous time


def test_scalar_continuous_margin_closed_forms() -> None:
    # x' = -c x(t - tau) (a = 0): the classical pi / (2 c)
    assert continuous_scalar_margin(0.0, -3.0) == pytest.approx(math.pi / 6.0)
    # x' = -x - 2 x(t - tau): crossing at w = sqrt(3), cos(w tau) = -1/2 -> tau = (2 pi / 3) / sqrt(3)
    assert continuous_scalar_margin(1.0, -2.0) == pytest.approx((2.0 * math.pi / 3.0) / math.sqrt(3.0))
    # |c| <= a: delay-independent (the scalar form of zenswarm's model, |alpha| < delta)
    assert continuous_scalar_margin(2.0, 1.5) == math.inf
    assert continuous_scalar_margin(2.0, -2.0) == math.inf
    # unstable without delay
    assert continuous_scalar_margin(1.0, 1.0) == -1.0


def test_scalar_continuous_margin_is_where_the_root_crosses() -> None:
    # at the margin s = i w solves s = -a + c exp(-s tau)
    a, c = 0.7, -2.5
    tau = continuous_scalar_margin(a, c)
    w = math.sqrt(c * c - a * a)
    s = 1j * w
    assert abs(s - (-a + c * np.exp(-s * tau))) < 1e-12


def test_single_pinned_agent_fully_delayed_bound() -> None:
    # one agent pinned with weight b: M = [b]; fully delayed x' = -mu b x(t - tau): pi / (2 mu b)
    mu, b = 2.0, 1.5
    assert fully_delayed_bound(np.array([[b]]), mu) == pytest.approx(math.pi / (2 * mu * b))
    assert fully_delayed_bound(np.array([[b]]), mu) == pytest.approx(continuous_scalar_margin(0.0, -mu * b))


# ----------------------------------------------------------------------------- discrete time


def test_delay_ticks_is_the_receivers_rule() -> None:
    for tau in (0.0, 0.001, 0.01, 0.0100000001, 0.05, 0.123, 2.0):
        assert delay_ticks(tau, 0.01) == delivery_tick(0, tau, 0.01)


def test_mode_roots_d0_and_d1_closed_form() -> None:
    mu, dt, delta, alpha = 2.0, 0.1, 3.0, -1.0
    a = mu * dt
    (z,) = mode_roots(alpha, delta, mu, dt, 0)
    assert z == pytest.approx(1 - a * delta + a * alpha)
    # d = 1: z^2 - p z - c with p = 1 - a delta, c = a alpha; Schur-Cohn/Jury: stable iff |c| < 1 and |p| < 1 - c
    rng = np.random.default_rng(1)
    for p, c in rng.uniform(-2.0, 2.0, size=(300, 2)):
        rho = float(np.max(np.abs(np.roots([1.0, -p, -c]))))
        jury = abs(c) < 1 and abs(p) < 1 - c
        if abs(rho - 1.0) > 1e-9:
            assert (rho < 1.0) == jury, (p, c, rho)
    # mode_roots builds the same polynomial
    r = np.sort_complex(mode_roots(0.5, 2.0, 1.0, 0.3, 1))
    assert np.allclose(r, np.sort_complex(np.roots([1.0, -(1 - 0.6), -0.15])))


@pytest.mark.parametrize("A,b", [(_complete(5), np.full(5, 1.0)), (_ring(6), np.full(6, 0.5))])
@pytest.mark.parametrize("d", [0, 1, 3, 7])
def test_modal_equals_lifted_where_delta_is_scalar(A: np.ndarray, b: np.ndarray, d: int) -> None:
    for mu, dt in ((2.0, 0.01), (2.0, 0.2), (0.5, 0.6)):
        assert modal_spectral_radius(A, b, mu, dt, d) == pytest.approx(spectral_radius(A, b, mu, dt, d), abs=1e-6)


def test_modal_refuses_a_non_scalar_delta() -> None:
    with pytest.raises(ValueError, match="not a multiple of the identity"):
        modal_spectral_radius(_ring(5), np.array([1.0, 0, 0, 0, 0]), 2.0, 0.01, 2)


def test_lifted_without_delay_is_the_euler_step() -> None:
    A, b = _ring(5), np.array([1.0, 0, 0, 0, 0])
    M = graph_matrix(A, b)
    assert np.allclose(lifted_matrix(A, b, 2.0, 0.01, 0), np.eye(5) - 0.02 * M)
    rho = spectral_radius(A, b, 2.0, 0.01, 0)
    assert rho == pytest.approx(float(np.max(np.abs(1 - 0.02 * np.linalg.eigvalsh(M)))))


def test_delay_independent_certificate_holds_numerically() -> None:
    # paper example 1's graph and gains: certified, and the lifted spectral radius agrees
    A = np.array([[0.0, 1, 1], [1, 0, 0], [1, 0, 0]])
    b = np.array([1.0, 0, 0])
    for mu in (0.1, 2.0):
        assert delay_independent(A, b, mu, 0.01) and delay_independent(A, b, mu)
        assert discrete_margin_ticks(A, b, mu, 0.01, 10) == math.inf
        for d in (0, 1, 5, 20):
            assert spectral_radius(A, b, mu, 0.01, d) < 1.0
    # an unpinned graph (M singular): not certified
    assert not delay_independent(A, np.zeros(3), 2.0, 0.01)


def test_beyond_the_certificate_the_scan_is_exact() -> None:
    # a dt mu delta > 1 (coarse Euler): no certificate; the scan must agree with the modal roots
    A, b = _complete(3), np.full(3, 1.0)  # delta = 3 I, alpha in {2, -1, -1}
    mu, dt = 1.0, 0.45  # a delta = 1.35: delay-free roots 1 - 1.35 + 0.45 * alpha = 0.55, -0.8
    assert not delay_independent(A, b, mu, dt)
    got = discrete_margin_ticks(A, b, mu, dt, 30)
    want = -1
    for d in range(31):
        if modal_spectral_radius(A, b, mu, dt, d) >= 1.0:
            break
        want = d
    assert got == want
    assert 0 <= got < 30  # it does lose stability at some finite delay


def test_levin_may_bound_is_where_the_roots_cross() -> None:
    # x(k+1) = x(k) - q x(k - d): z^(d+1) - z^d + q = 0 stable iff 0 < q < 2 cos(d pi / (2d + 1))
    for d in range(0, 9):
        qc = levin_may_bound(d)
        for q, stable in ((qc * (1 - 1e-6), True), (qc * (1 + 1e-6), False)):
            poly = np.zeros(d + 2)
            poly[0], poly[1] = 1.0, -1.0
            poly[-1] += q
            assert (float(np.max(np.abs(np.roots(poly)))) < 1.0) == stable, (d, q)


def test_fully_delayed_discrete_tends_to_continuous() -> None:
    M = graph_matrix(np.array([[0.0, 1, 1], [1, 0, 0], [1, 0, 0]]), np.array([1.0, 0, 0]))
    mu = 2.0
    cont = fully_delayed_bound(M, mu)
    for dt in (0.01, 0.002, 0.0005):
        d = fully_delayed_discrete_margin_ticks(M, mu, dt)
        assert abs((d + 0.5) * dt - cont) <= 1.5 * dt, (dt, d, cont)


def test_steady_lag_factors() -> None:
    assert steady_lag_factors(np.zeros((1, 1)), np.array([2.0])) == pytest.approx([1.0])
    A, b = np.array([[0.0, 1, 1], [1, 0, 0], [1, 0, 0]]), np.array([1.0, 0, 0])
    assert steady_lag_factors(A, b) == pytest.approx([5.0, 6.0, 6.0])


# ----------------------------------------------------------------------------- generator simulation


def test_lag_of_a_single_pinned_agent_is_tau_v0() -> None:
    dt, d = 0.01, 30
    v0 = np.array([0.2, -0.1, 0.05])
    q0, v0s = margin.constant_leader(np.zeros(3), v0, 4000, dt)
    h = np.array([[0.1, 0.0, 0.0]])
    Q, V = margin.simulate_generator(np.zeros((1, 1)), np.array([1.0]), h, np.array([[0.3, 0.0, 0.0]]), 0.5, 2.0, dt, d, q0, v0s)
    assert np.allclose(Q[-1, 0] - q0[-1] - h[0], -d * dt * v0, atol=1e-6)
    assert np.allclose(V[-1, 0], v0, atol=1e-9)


def test_lag_of_paper_graph_matches_formula() -> None:
    sc = load_scenario(EX1)
    A, b, h = np.asarray(sc.graph.adjacency), np.asarray(sc.graph.pinning), np.asarray(sc.offsets)
    dt, d, v0 = 0.01, 20, np.array([0.1, 0.05, 0.0])
    q0, v0s = margin.constant_leader(np.zeros(3), v0, 6000, dt)
    Q, _ = margin.simulate_generator(A, b, h, np.asarray(sc.initial_positions), 2.0, 2.0, dt, d, q0, v0s)
    lag = -(d * dt) * steady_lag_factors(A, b)[:, None] * v0[None, :]
    assert np.allclose(Q[-1] - q0[-1] - h, lag, atol=1e-5)


def test_generator_only_equals_the_full_simulator() -> None:
    """The references of compose.sim.simulate under the margin's fault plan (ref and leader links
    delayed, plant links not) are those of simulate_generator with the same leader."""
    sc = load_scenario(EX1)
    delay = 0.05
    res = simulate(sc, n_ticks=120, faults=margin.fault_plan(delay), full_time=True)
    ts = res.series
    d = delay_ticks(delay, sc.timing.dt)
    Q, V = margin.simulate_generator(
        np.asarray(sc.graph.adjacency),
        np.asarray(sc.graph.pinning),
        np.asarray(sc.offsets),
        np.asarray(sc.initial_positions),
        sc.generator.mu1,
        sc.generator.mu2,
        sc.timing.dt,
        d,
        np.asarray(ts.q0),
        np.asarray(ts.v0),
    )
    assert np.allclose(Q, ts.qref, rtol=0, atol=1e-12)
    assert np.allclose(V, ts.vref, rtol=0, atol=1e-12)
    # and the delay matters (the test can fail): without it the references differ
    Q0, _ = margin.simulate_generator(
        np.asarray(sc.graph.adjacency), np.asarray(sc.graph.pinning), np.asarray(sc.offsets),
        np.asarray(sc.initial_positions), sc.generator.mu1, sc.generator.mu2, sc.timing.dt, 0,
        np.asarray(ts.q0), np.asarray(ts.v0),
    )  # fmt: skip
    assert not np.allclose(Q0, ts.qref, rtol=0, atol=1e-9)


def test_judge() -> None:
    T, n, w = 200, 2, 20
    q0 = np.zeros((T, 3))
    v0 = np.zeros((T, 3))
    h = np.zeros((n, 3))
    lag = np.zeros((n, 3))
    decay = np.exp(-np.arange(T) / 20.0)[:, None, None] * np.ones((T, n, 3))
    assert margin.judge(decay, 0.0 * decay, q0, v0, h, lag, w).converged
    grow = np.exp(np.arange(T) / 50.0)[:, None, None] * np.ones((T, n, 3)) * 1e-3
    j = margin.judge(grow, 0.0 * grow, q0, v0, h, lag, w)
    assert not j.converged and "position" in j.reason
    # slowly decaying: not below 5 % of the peak by the end
    slow = np.exp(-np.arange(T) / 400.0)[:, None, None] * np.ones((T, n, 3))
    assert not margin.judge(slow, 0.0 * slow, q0, v0, h, lag, w).converged
    nan = decay.copy()
    nan[-1] = np.nan
    assert margin.judge(nan, decay, q0, v0, h, lag, w).reason.startswith("diverged")


# ----------------------------------------------------------------------------- bisection


def test_find_margin_monotone() -> None:
    calls: list[int] = []

    def conv(d: int) -> bool:
        calls.append(d)
        return d <= 37

    r = margin.find_margin(conv, 200, 1)
    assert r.margin_ticks == 37 and r.monotone and not r.at_least
    assert len(calls) == len(set(calls)) and len(calls) <= 8 + 6
    assert margin.find_margin(conv, 200, 5).margin_ticks in range(33, 38)


def test_find_margin_edges_and_non_monotone() -> None:
    assert margin.find_margin(lambda d: True, 50).at_least
    assert margin.find_margin(lambda d: True, 50).margin_ticks == 50
    assert margin.find_margin(lambda d: False, 50).margin_ticks == -1
    # fails only in a window [20, 40], passes again above: reported, margin below the first failure
    r = margin.find_margin(lambda d: not (20 <= d <= 40), 140, 1)
    assert not r.monotone and r.margin_ticks == 19


def test_empirical_margin_short_run() -> None:
    sc = load_scenario(EX1)
    res, info = margin.empirical_margin(sc, 0.05, tol_ticks=1, duration_s=3.0, scan=3)
    assert res.margin_ticks <= 5 and info["duration_s"] == pytest.approx(3.0)
    assert all(d in info["judgements"] for d, _ in res.tried)


# ----------------------------------------------------------------------------- command line


@pytest.mark.parametrize(
    "argv,field",
    [
        (["no_such_scenario"], "scenario"),
        ([str(EX1), "--max-delay", "-1s"], "--max-delay"),
        ([str(EX1), "--max-delay", "2"], "--max-delay"),
        ([str(EX1), "--tol", "0tick"], "--tol"),
        ([str(EX1), "--tol", "fast"], "--tol"),
        ([str(EX1), "--duration", "0.01s"], "--duration"),
        ([str(EX1), "--speed", "-1"], "--speed"),
        ([str(EX1), "--scan", "1"], "--scan"),
    ],
)
def test_cli_bad_input_exit_2(argv: list[str], field: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert margin.cli(argv) == 2
    err = capsys.readouterr().err
    assert field in err, err


def test_cli_help_and_a_short_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert margin.cli(["--help"]) == 0
    assert "delay margin" in capsys.readouterr().out
    out = tmp_path / "m.json"
    assert margin.cli(["paper_example1", "--max-delay", "30ms", "--duration", "2s", "--scan", "2", "--json", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "analytic" in text and "empirical" in text and "fully delayed" in text
    doc = json.loads(out.read_text())
    assert doc["analytic"]["margin_s"] == "inf" and doc["analytic"]["delay_independent"] is True
    assert doc["empirical"]["max_delay_s"] == pytest.approx(0.03)

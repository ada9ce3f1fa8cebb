"""``zenswarm sweep margin``: the empirical delay margin of the reference generator (16)-(17),
beside the analytic one (:mod:`zenswarm.campaign.delaymargin`). Derivation, criterion and table:
docs/delay_margin.md.

What is simulated
-----------------
Only the generator, in lockstep, with a uniform link delay on every ``agent:j -> agent:i``
(``ref``) and ``leader -> agent:i`` (``leader``) link and none on the plant's links. This is
faithful, not an approximation: in zenswarm the generator of agent i reads its own (q*_i, v*_i),
its neighbours' and the leader's references and nothing else (not the measured state,
:meth:`zenswarm.agents.core.AgentCore.rates`), and the leader does not read the UAVs, so the
references the swarm computes under such a delay do not depend on the plant at all. The delay
becomes d = ceil(tau / dt - 1e-9) ticks (:func:`zenswarm.link.delivery_tick`) and each
receiver holds the message of tick max(0, k - d) at tick k (:class:`zenswarm.link.swarm.Box`:
the tick-0 message is there at once), so agent i integrates, by explicit Euler at dt,

    q*_i(k+1) = q*_i(k) + dt [v*_i(k) - mu1 (delta_i (q*_i(k) - h_i) - sum_j a_ij (q*_j(k-d) - h_j) - b_i q0(k-d))]
    v*_i(k+1) = v*_i(k) - dt mu2 (delta_i v*_i(k) - sum_j a_ij v*_j(k-d) - b_i v0(k-d))

from q*_i(0) = q_i(0) (the UAV's start), v*_i(0) = 0 (:meth:`~zenswarm.agents.core.AgentCore.reset`).
:func:`simulate_generator` computes this vectorised over agents; a test checks it against the
full simulator (:func:`zenswarm.compose.sim.simulate` with the same fault plan, :func:`fault_plan`).

The leader: Assumption 1
------------------------
The leader moves at a constant velocity v0 (``--speed`` along the scenario's start -> goal
direction) from its start: the setting of the paper's stability analysis (Assumption 1). With a
delay the position error then settles at a known constant lag, q*_i - q0 - h_i -> -tau c_i v0,
c = M^-1 Delta 1 (:func:`zenswarm.campaign.delaymargin.steady_lag_factors`), which is subtracted: what is
judged is convergence, not the lag. (A hovering leader would leave eq. (17) unexcited: v* starts
at 0 = v0. The scenario's own AAPF leader has a varying v0, whose lag cannot be separated from
a slow divergence.)

Criterion
---------
e_q(k) = max_i ||q*_i(k) - q0(k) - h_i + tau c_i v0||, e_v(k) = max_i ||v*_i(k) - v0||. The
formation *converges* at a delay when, over the run (``--duration``), every value is finite and,
for e_q and for e_v: the maximum over the final window (the last 10 %, at least 1 s) is at most
``REL_TOL`` (5 %) of the peak of the delay-free run (a fixed scale), and is not above the maximum over the window before it (not
growing). Values below ``ABS_FLOOR`` count as converged (rounding).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm.campaign.delaymargin import (
    degrees,
    delay_independent,
    fully_delayed_bound,
    fully_delayed_discrete_margin_ticks,
    generator_margin_ticks,
    graph_matrix,
    steady_lag_factors,
)
from zenswarm.errors import ScenarioError, run_command
from zenswarm.link import FaultPlan, LinkFaultSpec, delivery_tick, parse_duration
from zenswarm.process.paths import check_output_file
from zenswarm.scenario.config import Scenario, load_scenario

__all__ = [
    "REL_TOL",
    "ABS_FLOOR",
    "Judgement",
    "MarginResult",
    "fault_plan",
    "simulate_generator",
    "constant_leader",
    "judge",
    "find_margin",
    "analytic_summary",
    "empirical_margin",
    "default_duration",
    "cli",
    "json_safe",
]

REL_TOL = 0.05
"""Final-window maximum of the error as a fraction of its peak over the run, at most."""
ABS_FLOOR = 1e-9
"""Errors below this (m, m/s) count as converged whatever their history (rounding)."""
DEFAULT_SPEED = 0.1
"""Leader speed (m/s) of the constant-velocity leader by default (the paper's examples fly ~0.1 m/s)."""


def fault_plan(delay_s: float, seed: int = 0) -> FaultPlan:
    """The fault plan of the margin runs: ``delay_s`` on every ``ref`` and ``leader`` link, the
    plant's ``state`` and ``cmd`` links undelayed (``--link-delay`` of ``zenswarm sim`` would
    delay those too: it sets the default of every link)."""
    spec = LinkFaultSpec(delay_s=delay_s)
    return FaultPlan(
        LinkFaultSpec(),
        {("agent:*", "agent:*", "ref"): spec, ("leader", "agent:*", "leader"): spec},
        seed,
    )


def constant_leader(q_start: np.ndarray, v0: np.ndarray, n_ticks: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Leader of Assumption 1: q0(k) = q_start + k dt v0, v0 constant. ((T, 3), (T, 3))."""
    k = np.arange(n_ticks, dtype=float)[:, None]
    q0 = np.asarray(q_start, dtype=float)[None, :] + k * dt * np.asarray(v0, dtype=float)[None, :]
    return q0, np.broadcast_to(np.asarray(v0, dtype=float), (n_ticks, 3)).copy()


def simulate_generator(
    A: np.ndarray,
    b: np.ndarray,
    h: np.ndarray,
    q_init: np.ndarray,
    mu1: float,
    mu2: float,
    dt: float,
    d: int,
    q0: np.ndarray,
    v0: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The references (q*, v*) of all agents, ticks 0..T-1, with the neighbours' and the
    leader's values d ticks old (module docstring). A (N, N), b (N,), h and q_init (N, 3) m,
    q0 and v0 (T, 3) the leader's reference per tick. Returns ((T, N, 3) m, (T, N, 3) m/s);
    stops early (the rest NaN) once a value is not finite."""
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)
    h = np.asarray(h, dtype=float)
    T, n = q0.shape[0], A.shape[0]
    delta = degrees(A, b)[:, None]
    bb = b[:, None]
    Q = np.full((T, n, 3), np.nan)
    V = np.full((T, n, 3), np.nan)
    Q[0] = np.asarray(q_init, dtype=float)
    V[0] = 0.0
    P = np.full((T, n, 3), np.nan)  # q* - h, what the neighbours' terms need
    P[0] = Q[0] - h
    for k in range(T - 1):
        j = k - d if k >= d else 0
        eq = delta * P[k] - A @ P[j] - bb * q0[j]
        ev = delta * V[k] - A @ V[j] - bb * v0[j]
        Q[k + 1] = Q[k] + dt * (V[k] - mu1 * eq)
        V[k + 1] = V[k] + dt * (-mu2 * ev)
        P[k + 1] = Q[k + 1] - h
        if k % 256 == 0 and not (np.all(np.isfinite(Q[k + 1])) and np.all(np.isfinite(V[k + 1]))):
            break
    return Q, V


@dataclass(frozen=True)
class Judgement:
    """The criterion's figures for one run: converged, and per error (q: m, v: m/s) its peak
    over the run and maxima over the final and the previous window."""

    converged: bool
    reason: str
    peak_q: float
    final_q: float
    previous_q: float
    peak_v: float
    final_v: float
    previous_v: float


def _windows(e: np.ndarray, w: int) -> tuple[float, float, float]:
    return float(np.max(e)), float(np.max(e[-w:])), float(np.max(e[-2 * w : -w]))


def judge(
    Q: np.ndarray,
    V: np.ndarray,
    q0: np.ndarray,
    v0: np.ndarray,
    h: np.ndarray,
    lag: np.ndarray,
    window: int,
    ref_q: float | None = None,
    ref_v: float | None = None,
) -> Judgement:
    """Apply the criterion (module docstring) to a run of :func:`simulate_generator`.
    lag (N, 3): the steady position error to subtract (-tau c_i v0). window: ticks (>= 1; the
    run must be at least 2 windows long). ref_q, ref_v: the peaks the final window is compared
    with (default: this run's; :func:`empirical_margin` passes the delay-free run's, so that the
    threshold does not grow with the delay)."""
    T = Q.shape[0]
    w = max(1, int(window))
    if T < 2 * w:
        raise ValueError(f"run of {T} ticks is shorter than two windows of {w}")
    if not (np.all(np.isfinite(Q)) and np.all(np.isfinite(V))):
        return Judgement(False, "diverged (not finite)", math.inf, math.inf, math.inf, math.inf, math.inf, math.inf)
    eq = np.max(np.linalg.norm(Q - q0[:, None, :] - h[None] - lag[None], axis=2), axis=1)
    ev = np.max(np.linalg.norm(V - v0[:, None, :], axis=2), axis=1)
    pq, fq, bq = _windows(eq, w)
    pv, fv, bv = _windows(ev, w)
    reasons = []
    rq = pq if ref_q is None else ref_q
    rv = pv if ref_v is None else ref_v
    for name, peak, fin, prev in (("position", rq, fq, bq), ("velocity", rv, fv, bv)):
        if fin <= ABS_FLOOR:
            continue
        if fin > REL_TOL * peak:
            reasons.append(f"{name} error {fin:.3g} in the final window > {REL_TOL:g} x peak {peak:.3g} (delay-free run)")
        elif fin > prev:
            reasons.append(f"{name} error growing ({prev:.3g} -> {fin:.3g})")
    ok = not reasons
    return Judgement(ok, "converged" if ok else "; ".join(reasons), pq, fq, bq, pv, fv, bv)


@dataclass
class MarginResult:
    """Outcome of :func:`find_margin`: the largest delay in ticks found to converge (-1: not
    even without delay), whether every delay scanned up to ``max_ticks`` converged
    (``at_least``: the margin is then only a lower bound), whether the pre-scan was monotone
    (all passes before all failures), and every (ticks, converged) tried, in order."""

    margin_ticks: int
    max_ticks: int
    at_least: bool
    monotone: bool
    tried: list[tuple[int, bool]] = field(default_factory=list)


def find_margin(converges: Callable[[int], bool], max_ticks: int, tol_ticks: int = 1, scan: int = 8) -> MarginResult:
    """Largest delay d in [0, max_ticks] (ticks) with ``converges(d)``, to within ``tol_ticks``.

    First a scan of ``scan`` delays evenly spaced over [0, max_ticks] (0 and max_ticks included):
    if they are not all passes followed by all failures the result says ``monotone=False`` and
    the search continues below the FIRST failing delay scanned (a conservative margin: every
    scanned delay below it converged). Then bisection between the last passing and the first
    failing delay. Each d is evaluated at most once.
    """
    if max_ticks < 0 or tol_ticks < 1 or scan < 2:
        raise ValueError("need max_ticks >= 0, tol_ticks >= 1, scan >= 2")
    seen: dict[int, bool] = {}
    tried: list[tuple[int, bool]] = []

    def ok(d: int) -> bool:
        if d not in seen:
            seen[d] = bool(converges(d))
            tried.append((d, seen[d]))
        return seen[d]

    points = sorted({round(i * max_ticks / (scan - 1)) for i in range(scan)})
    results = [ok(d) for d in points]
    first_fail = next((i for i, r in enumerate(results) if not r), None)
    monotone = first_fail is None or not any(results[first_fail:])
    if first_fail is None:
        return MarginResult(max_ticks, max_ticks, True, monotone, tried)
    if first_fail == 0:
        return MarginResult(-1, max_ticks, False, monotone, tried)
    lo, hi = points[first_fail - 1], points[first_fail]  # lo converges, hi does not
    while hi - lo > tol_ticks:
        mid = (lo + hi) // 2
        if ok(mid):
            lo = mid
        else:
            hi = mid
    return MarginResult(lo, max_ticks, False, monotone, tried)


def _lambda(M: np.ndarray) -> tuple[float, float]:
    ev = np.linalg.eigvalsh(M)
    return float(ev[0]), float(ev[-1])


def default_duration(scenario: Scenario, max_delay_s: float) -> float:
    """Run length (s) by default: 6 of the slowest delay-free time constants,
    1 / (min(mu1, mu2) lambda_min(M)), plus twice the largest delay, at least 30 s, at most 1200 s."""
    M = graph_matrix(scenario.comm_graph.dense(), scenario.comm_graph.b)
    lam_min, _ = _lambda(M)
    g = scenario.generator
    slow = 1.0 / (min(g.mu1, g.mu2) * lam_min)
    return float(min(1200.0, max(30.0, 6.0 * slow + 2.0 * max_delay_s)))


def analytic_summary(scenario: Scenario, max_ticks: int) -> dict[str, Any]:
    """The analytic figures of :mod:`zenswarm.campaign.delaymargin` for a scenario's graph and gains."""
    A = scenario.comm_graph.dense()
    b = np.asarray(scenario.graph.pinning, dtype=float)
    g, dt = scenario.generator, scenario.timing.dt
    M = graph_matrix(A, b)
    lam_min, lam_max = _lambda(M)
    delta = degrees(A, b)
    indep = delay_independent(A, b, g.mu1, dt) and delay_independent(A, b, g.mu2, dt)
    ticks = generator_margin_ticks(A, b, g.mu1, g.mu2, dt, max_ticks)
    mu = max(g.mu1, g.mu2)
    fd_ticks = fully_delayed_discrete_margin_ticks(M, mu, dt)
    return {
        "n": int(A.shape[0]),
        "dt_s": dt,
        "mu1": g.mu1,
        "mu2": g.mu2,
        "lambda_min_M": lam_min,
        "lambda_max_M": lam_max,
        "rho_Delta_inv_A": float(np.max(np.abs(np.linalg.eigvals(A / delta[:, None])))),
        "a_delta_max": max(g.mu1, g.mu2) * dt * float(np.max(delta)),
        "delay_independent": bool(indep),
        "margin_ticks": None if math.isinf(ticks) else int(ticks),
        "margin_s": math.inf if math.isinf(ticks) else ticks * dt,
        "fully_delayed_bound_s": fully_delayed_bound(M, mu),
        "fully_delayed_discrete_margin_s": fd_ticks * dt,
        "lag_factors": [float(x) for x in steady_lag_factors(A, b)],
    }


def empirical_margin(
    scenario: Scenario,
    max_delay_s: float,
    tol_ticks: int = 1,
    duration_s: float | None = None,
    speed: float = DEFAULT_SPEED,
    scan: int = 8,
    progress: Callable[[int, bool], None] | None = None,
) -> tuple[MarginResult, dict[str, Any]]:
    """Bisect the uniform link delay of ``scenario`` (module docstring). Returns the search
    result and the run settings (duration, window, leader velocity, per-delay judgements)."""
    A = scenario.comm_graph.dense()
    b = np.asarray(scenario.graph.pinning, dtype=float)
    h = np.asarray(scenario.offsets, dtype=float)
    q_init = np.asarray(scenario.initial_positions, dtype=float)
    g, dt = scenario.generator, scenario.timing.dt
    duration = default_duration(scenario, max_delay_s) if duration_s is None else duration_s
    T = max(4, int(round(duration / dt)))
    window = max(1, min(T // 2, max(int(round(1.0 / dt)), T // 10)))
    start = np.asarray(scenario.leader.start, dtype=float)
    heading = np.asarray(scenario.leader.goal, dtype=float) - start
    norm = float(np.linalg.norm(heading))
    v0 = heading / norm * speed if norm > 0 else np.array([speed, 0.0, 0.0])
    q0, v0s = constant_leader(start, v0, T, dt)
    c = steady_lag_factors(A, b)
    max_ticks = delivery_tick(0, max_delay_s, dt)
    judgements: dict[int, dict[str, Any]] = {}

    def run(d: int, ref: Judgement | None) -> Judgement:
        Q, V = simulate_generator(A, b, h, q_init, g.mu1, g.mu2, dt, d, q0, v0s)
        lag = -(d * dt) * c[:, None] * v0[None, :]
        if ref is None:
            return judge(Q, V, q0, v0s, h, lag, window)
        return judge(Q, V, q0, v0s, h, lag, window, ref.peak_q, ref.peak_v)

    free = run(0, None)  # the delay-free run: its peaks scale the threshold of every run

    def converges(d: int) -> bool:
        j = free if d == 0 else run(d, free)
        judgements[d] = asdict(j)
        if progress is not None:
            progress(d, j.converged)
        return j.converged

    res = find_margin(converges, max_ticks, tol_ticks, scan)
    info = {"duration_s": T * dt, "window_s": window * dt, "leader_velocity": [float(x) for x in v0], "judgements": judgements}
    return res, info


# ----------------------------------------------------------------------------- command line

_TICK_RE = re.compile(r"^\s*(\d+)\s*ticks?\s*$")


def _parse_tol(text: str, dt: float) -> int:
    """``--tol``: ``1tick``, ``3ticks`` or a duration (``10ms``), rounded up to whole ticks (>= 1)."""
    m = _TICK_RE.match(text)
    if m:
        n = int(m.group(1))
        if n < 1:
            raise ScenarioError("--tol", f"invalid tolerance {text!r}: at least 1 tick")
        return n
    try:
        s = parse_duration(text)
    except ValueError as e:
        raise ScenarioError("--tol", f"{e} (or a number of ticks such as '1tick')") from None
    if s <= 0:
        raise ScenarioError("--tol", f"invalid tolerance {text!r}: must be > 0")
    return max(1, delivery_tick(0, s, dt))


def _scenario_file(name: str) -> Path:
    p = Path(name)
    if p.suffix == ".toml" or p.exists() or "/" in name:
        if not p.is_file():
            raise ScenarioError("scenario", f"scenario file not found: {p}")
        return p
    q = Path(__file__).resolve().parent / "scenarios" / f"{name}.toml"
    if not q.is_file():
        raise ScenarioError("scenario", f"no built-in scenario {name!r} and no such file")
    return q


def build_parser(prog: str = "zenswarm sweep margin") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Empirical delay margin of the reference generator (eqs 16-17) beside the analytic one.\n\n"
            "Bisects a uniform link delay on every agent->agent and leader->agent link (the plant's\n"
            "links undelayed) for the largest delay at which the generator's formation still\n"
            "converges, and prints it beside the analytic margin of zenswarm's delay model (own\n"
            "state current: delay-independent when rho(Delta^-1 A) < 1 and mu dt max delta_i <= 1)\n"
            "and the classical fully delayed bound pi / (2 mu lambda_max(M)) (a different model).\n"
            "Simulates the generator alone (exact: it does not read the plant), with a leader at a\n"
            "constant velocity (Assumption 1) whose steady lag -tau M^-1 Delta 1 v0 is subtracted.\n"
            "Criterion and derivation: docs/delay_margin.md."
        ),
        epilog="Example: zenswarm sweep margin paper_example1 --max-delay 2s --tol 1tick\n"
        "Exit status 0 when the search ran, 2 on bad input.",
    )
    p.add_argument("scenario", help="scenario TOML file or built-in name (paper_example1, paper_example2)")
    p.add_argument("--max-delay", default="2s", help="largest delay to try, a duration (default: 2s)")
    p.add_argument("--tol", default="1tick", help="resolution of the bisection: a duration (10ms) or ticks (1tick; default)")
    p.add_argument("--seed", type=int, default=None, help="scenario seed (no effect: a uniform delay without loss draws nothing)")
    p.add_argument(
        "--duration",
        default=None,
        help="length of each run, a duration (default: 6 slowest delay-free time constants + 2 x max delay, 30-1200 s)",
    )
    p.add_argument("--speed", default=str(DEFAULT_SPEED), help=f"constant leader speed along start->goal, m/s (default: {DEFAULT_SPEED})")
    p.add_argument("--scan", type=int, default=8, help="delays scanned before bisecting, to check monotonicity (default: 8, >= 2)")
    p.add_argument("--json", type=Path, default=None, help="also write the result as JSON to this file")
    p.add_argument("--quiet", action="store_true", help="no per-delay lines")
    return p


def _duration_arg(flag: str, text: str) -> float:
    try:
        return parse_duration(text)
    except ValueError as e:
        raise ScenarioError(flag, str(e)) from None


def _fmt_s(x: float) -> str:
    return "inf (every delay)" if math.isinf(x) else f"{x:.3f} s"


def run(args: argparse.Namespace, out: Any = None) -> dict[str, Any]:
    """Validate every input (ScenarioError naming it), then search; returns the result dict.
    Prints to ``out`` (default: standard output)."""
    out = sys.stdout if out is None else out
    sc = load_scenario(_scenario_file(args.scenario))
    dt = sc.timing.dt
    max_delay = _duration_arg("--max-delay", args.max_delay)
    tol = _parse_tol(args.tol, dt)
    duration = None if args.duration is None else _duration_arg("--duration", args.duration)
    if duration is not None and duration < 20 * dt:
        raise ScenarioError("--duration", f"{args.duration!r} is too short: at least 20 control periods ({20 * dt:g} s)")
    try:
        speed = float(args.speed)
    except ValueError:
        raise ScenarioError("--speed", f"invalid speed {args.speed!r}: expected a number in m/s") from None
    if not (speed > 0 and math.isfinite(speed)):
        raise ScenarioError("--speed", f"invalid speed {args.speed!r}: must be > 0")
    if args.scan < 2:
        raise ScenarioError("--scan", f"must be >= 2, got {args.scan}")
    if args.seed is not None and args.seed < 0:
        raise ScenarioError("--seed", f"must be >= 0, got {args.seed}")
    if args.json is not None:  # a directory, or nowhere to write it: exit 2 now, not after the search
        check_output_file(args.json, "--json")

    max_ticks = delivery_tick(0, max_delay, dt)
    ana = analytic_summary(sc, max_ticks)

    def progress(d: int, ok: bool) -> None:
        if not args.quiet:
            print(f"  delay {d * dt:7.3f} s ({d:4d} ticks): {'converges' if ok else 'does NOT converge'}", file=out, flush=True)

    res, info = empirical_margin(sc, max_delay, tol, duration, speed, args.scan, progress)
    emp_s = res.margin_ticks * dt
    result = {
        "scenario": sc.name,
        "analytic": ana,
        "empirical": {
            "margin_ticks": res.margin_ticks,
            "margin_s": emp_s,
            "at_least": res.at_least,
            "max_delay_s": res.max_ticks * dt,
            "tol_ticks": tol,
            "monotone": res.monotone,
            "tried": [[d, ok] for d, ok in res.tried],
            **info,
        },
    }
    _print_summary(out, sc.name, dt, ana, res, info, tol)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe(result), indent=2, sort_keys=True) + "\n")
    return result


def _print_summary(out: Any, name: str, dt: float, ana: dict[str, Any], res: MarginResult, info: dict[str, Any], tol: int) -> None:
    """The lines of :func:`run` after the search: the analytic margin (``ana``), the empirical one
    (``res``, ``info``; delays in ticks of ``dt`` s, ``tol`` ticks) and the fully delayed bound."""
    emp_s = res.margin_ticks * dt
    emp_txt = (
        f">= {emp_s:.3f} s (converged at every delay tried up to --max-delay)"
        if res.at_least
        else (
            f"none: even without delay the formation does not converge within the {info['duration_s']:.0f} s run (a longer --duration?)"
            if res.margin_ticks < 0
            else f"{emp_s:.3f} s ({res.margin_ticks} ticks, +/- {tol} tick)"
        )
    )
    print(
        f"{name}: N={ana['n']} dt={dt:g} s mu1={ana['mu1']:g} mu2={ana['mu2']:g} "
        f"lambda(M) in [{ana['lambda_min_M']:.4g}, {ana['lambda_max_M']:.4g}]",
        file=out,
    )
    print(
        f"  analytic (zenswarm: own state current, Euler at dt): {_fmt_s(ana['margin_s'])}"
        f"  [rho(Delta^-1 A) = {ana['rho_Delta_inv_A']:.3f} < 1, mu dt max delta = {ana['a_delta_max']:.3f} <= 1: "
        f"{'delay-independent' if ana['delay_independent'] else 'NOT proved delay-independent'}]",
        file=out,
    )
    print(f"  empirical (generator, run {info['duration_s']:.0f} s):       {emp_txt}", file=out)
    if not res.monotone:
        print(
            "  note: convergence was NOT monotone in the delay over the scan; the margin is the largest delay below the first failure",
            file=out,
        )
    print(
        f"  for comparison, the fully delayed model x' = -mu M x(t - tau) (a different model): "
        f"pi / (2 mu2 lambda_max) = {ana['fully_delayed_bound_s']:.4f} s; Euler at dt: {ana['fully_delayed_discrete_margin_s']:.3f} s",
        file=out,
    )


def json_safe(x: Any) -> Any:
    """``x`` with every infinite float as the string ``"inf"`` (strict JSON has no Infinity)."""
    if isinstance(x, float) and math.isinf(x):
        return "inf" if x > 0 else "-inf"
    if isinstance(x, dict):
        return {str(k): json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    return x


def cli(argv: Sequence[str]) -> int:
    """``zenswarm sweep margin ARGV``: 0 when the search ran, 2 on bad input (the message names it)."""
    p = build_parser()
    try:
        args = p.parse_args(list(argv))
    except SystemExit as e:  # argparse: --help is 0, bad usage 2
        return int(e.code or 0)

    def body() -> int:
        run(args)
        return 0

    return run_command(body, "zenswarm sweep margin")


if __name__ == "__main__":  # pragma: no cover - `python -m zenswarm.compose.margin` (the same as `zenswarm sweep margin`)
    sys.exit(cli(sys.argv[1:]))

"""The delay-margin table of docs/delay_margin.md and the README: analytic vs empirical, side by side,
for the paper's examples and ring and complete graphs of 5 and 10 UAVs.

Per scenario (the paper's gains mu1 = 0.1, mu2 = 2, dt = 10 ms everywhere):

* analytic (:mod:`zenswarm.campaign.delaymargin`): the margin of zenswarm's delay model (the agent's own
  state current, the neighbours' and the leader's values tau old, Euler at dt), the certificate's
  two numbers rho(Delta^-1 A) and mu2 dt max delta_i, and for comparison the fully delayed
  model's pi / (2 mu2 lambda_max(M)) and its exact Euler form (Levin-May);
* empirical (:func:`zenswarm.compose.margin.empirical_margin`, what ``zenswarm sweep margin``
  runs): the search up to 2 s (the command's default), and up to 20 s, where the finite run
  (``default_duration``) rather than stability decides.

Generated scenarios: ``zenswarm scenario generate --n N --topology ring|complete --pinning
first|all`` (:func:`zenswarm.scenario.generate.generate_scenario`, circle formation, seed 0).

    python bench/delay_margin.py                      # writes bench/results/delay_margin.json
    python bench/delay_margin.py --quick              # 2 s search only

Deterministic (no random draw): the figures do not depend on the machine, only the wall time does.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from zenswarm.compose.margin import analytic_summary, empirical_margin, json_safe
from zenswarm.link import delivery_tick
from zenswarm.scenario.config import Scenario, load_scenario, scenario_from_dict
from zenswarm.scenario.generate import generate_scenario

REPO = Path(__file__).resolve().parent.parent
OUT = REPO / "bench" / "results" / "delay_margin.json"


def scenarios() -> list[tuple[str, Scenario]]:
    out = [(f"paper_example{i}", load_scenario(REPO / "compose" / "scenarios" / f"paper_example{i}.toml")) for i in (1, 2)]
    for topo in ("ring", "complete"):
        for n in (5, 10):
            for pin in ("first", "all"):
                d = generate_scenario(n, topology=topo, pinning=pin, seed=0)
                out.append((f"{topo} N={n} pinning {pin}", scenario_from_dict(d)))
    return out


def one(label: str, sc: Scenario, searches: list[float]) -> dict[str, Any]:
    dt = sc.timing.dt
    row: dict[str, Any] = {"label": label, "analytic": analytic_summary(sc, delivery_tick(0, max(searches), dt))}
    for max_delay in searches:
        t0 = time.perf_counter()
        res, info = empirical_margin(sc, max_delay)
        row[f"empirical_{max_delay:g}s"] = {
            "margin_s": res.margin_ticks * dt,
            "margin_ticks": res.margin_ticks,
            "at_least": res.at_least,
            "monotone": res.monotone,
            "duration_s": info["duration_s"],
            "runs": len(res.tried),
            "wall_s": time.perf_counter() - t0,
            "first_failure": _first_failure(res.tried, info["judgements"]),
        }
    return row


def _first_failure(tried: list[tuple[int, bool]], judgements: dict[int, Any]) -> dict[str, Any] | None:
    """The smallest delay (ticks) that did not converge, with the criterion's reason."""
    fails = [d for d, ok in tried if not ok]
    return None if not fails else {"ticks": min(fails), "reason": judgements[min(fails)]["reason"]}


def _emp(e: dict[str, Any]) -> str:
    if e["margin_ticks"] < 0:
        return "< 1 tick"
    return (">= " if e["at_least"] else "") + f"{e['margin_s']:.2f} s"


def table(rows: list[dict[str, Any]], searches: list[float]) -> str:
    head = (
        "| scenario | N | lambda(M) min / max | rho(Delta^-1 A) | mu2 dt max delta | analytic (zenswarm model) | "
        + " | ".join(f"empirical, search <= {s:g} s (run length)" for s in searches)
        + " | fully delayed: pi/(2 mu2 lambda_max) | fully delayed, Euler (Levin-May) |"
    )
    sep = "|" + "---|" * (head.count("|") - 1)
    lines = [head, sep]
    for r in rows:
        a = r["analytic"]
        ana = "inf (delay-independent)" if math.isinf(a["margin_s"]) else f"{a['margin_s']:.2f} s"
        emp = " | ".join(f"{_emp(r[f'empirical_{s:g}s'])} ({r[f'empirical_{s:g}s']['duration_s']:.0f} s)" for s in searches)
        lines.append(
            f"| {r['label']} | {a['n']} | {a['lambda_min_M']:.3f} / {a['lambda_max_M']:.2f} | {a['rho_Delta_inv_A']:.3f} | "
            f"{a['a_delta_max']:.2f} | {ana} | {emp} | {a['fully_delayed_bound_s']:.3f} s | {a['fully_delayed_discrete_margin_s']:.2f} s |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--quick", action="store_true", help="only the 2 s search")
    p.add_argument("--json", type=Path, default=OUT, help=f"output (default: {OUT.relative_to(REPO)})")
    args = p.parse_args(argv)
    searches = [2.0] if args.quick else [2.0, 20.0]
    rows = []
    for label, sc in scenarios():
        t0 = time.perf_counter()
        rows.append(one(label, sc, searches))
        print(f"{label}: done in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    md = table(rows, searches)
    print(md)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(json_safe({"command": "python bench/delay_margin.py", "rows": rows, "table_md": md}), indent=2) + "\n")
    print(f"wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

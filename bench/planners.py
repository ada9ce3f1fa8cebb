"""The leader planners side by side: the paper's AAPF (``aapf``, the default) and the escape planner
(``escape``, :mod:`zenswarm.leader.escape`), each flown by the full in-process simulator
(``zenswarm.compose.sim.simulate``: plant, agents, vehicle-based verdicts).

Layouts:

* paper examples 1 and 2 (``compose/scenarios``);
* ``--layouts`` generated "goal behind obstacles" layouts, seeded (``--seed0``, then +1, ...). Each
  starts from ``zenswarm scenario generate --n 3 --shape circle --topology ring --obstacles 0
  --seed S`` (3 UAVs, r_f = 0.173 m, a 3 m leg from the paper's start along its heading, 0.2 m
  up, the paper's gains, 70 s) and puts obstacles on the start-goal line (:func:`behind_layout`):
  even seeds one tall obstacle straight in front of the goal (radius 0.15-0.25 m, centre 35-65 %
  of the way, within 1 cm of the line); odd seeds two tall obstacles straddling the line whose
  surfaces are 0.10 m to 2 (r_f + d0) - 0.03 m apart, i.e. closer than the AAPF's repulsion
  bands let the formation through.

Per flight: the verdict (success, failure causes), time to goal, the smallest vehicle clearance to
an obstacle beyond the vehicle radius (``min_obstacle_margin_m``; > 0 = no contact), and the
leader velocity's total variation sum_k ||v0_{k+1} - v0_k|| (m/s; a chattering measure: the
AAPF's repulsion band makes v0 oscillate). A stalled run ends early (``leader_stalled``), so
its total variation covers a shorter flight.

    python bench/planners.py                                    # 20 generated layouts + the paper's
    python bench/planners.py --layouts 6 --json bench/results/planners.json

Deterministic (the simulator is): the figures do not depend on the machine, only the wall time does.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

PLANNERS = ("aapf", "escape")


def behind_layout(seed: int) -> dict[str, Any]:
    """A generated scenario dict with obstacles between start and goal, straight in front of the goal."""
    from zenswarm.scenario.generate import generate_scenario

    d = generate_scenario(3, "circle", "ring", n_obstacles=0, seed=seed, name=f"behind_s{seed}")
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xBE41,)))
    start = np.array(d["leader"]["start"], dtype=float)
    goal = np.array(d["leader"]["goal"], dtype=float)
    h = np.array(d["formation"]["offsets"], dtype=float)
    r_f = float(np.max(np.linalg.norm(h, axis=1)))
    d0 = float(d["leader"]["d0"])
    seg = goal[:2] - start[:2]
    along = seg / np.linalg.norm(seg)
    perp = np.array([-along[1], along[0]])
    t = rng.uniform(0.35, 0.65)
    off = rng.uniform(-0.01, 0.01)
    mid = start[:2] + t * seg + off * perp
    height = round(float(rng.uniform(0.8, 1.2)), 3)
    if seed % 2 == 0:
        r = round(float(rng.uniform(0.15, 0.25)), 3)
        obs = [(mid, r)]
        kind = "single"
    else:
        r = round(float(rng.uniform(0.10, 0.18)), 3)
        gap = float(rng.uniform(0.10, 2.0 * (r_f + d0) - 0.03))
        obs = [(mid + s * (gap / 2 + r) * perp, r) for s in (1.0, -1.0)]
        kind = f"pair gap {gap:.2f} m"
    d["obstacles"] = [{"center": [round(float(c[0]), 4), round(float(c[1]), 4), 0.0], "radius": r, "height": height} for c, r in obs]
    d["scenario"]["description"] = f"goal behind obstacles ({kind}), from generate seed {seed}"
    return d


def leader_tv(v0: np.ndarray) -> float:
    """sum_k ||v0_{k+1} - v0_k||, m/s, over a flight's (T, 3) leader velocities."""
    return float(np.sum(np.linalg.norm(np.diff(v0, axis=0), axis=1))) if len(v0) > 1 else 0.0


def fly(scenario: Any, planner: str) -> dict[str, Any]:
    from zenswarm.compose.sim import simulate
    from zenswarm.scenario.plugins import select

    t0 = time.perf_counter()
    res = simulate(select(scenario, planner=planner))
    wall = time.perf_counter() - t0
    r = res.results
    return {
        "planner": planner,
        "success": bool(r["success"]),
        "causes": sorted({f["cause"] for f in r["failures"]}),
        "time_to_goal_s": r.get("time_to_goal_s"),
        "min_obstacle_margin_m": r.get("min_obstacle_margin_m"),
        "leader_tv_m_s": leader_tv(res.series.v0),
        "sim_time_s": r.get("sim_time_s"),
        "wall_s": wall,
    }


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in rows if r["success"]]
    margins = [r["min_obstacle_margin_m"] for r in rows if r["min_obstacle_margin_m"] is not None]
    return {
        "n": len(rows),
        "success": len(ok),
        "success_rate": len(ok) / len(rows) if rows else None,
        "time_to_goal_s_median_of_successes": C.median(r["time_to_goal_s"] for r in ok),
        "min_obstacle_margin_m_min": min(margins) if margins else None,
        "leader_tv_m_s_median": C.median(r["leader_tv_m_s"] for r in rows),
        "leader_tv_m_s_median_of_successes": C.median(r["leader_tv_m_s"] for r in ok),
        "causes": sorted({c for r in rows for c in r["causes"]}),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--layouts", type=int, default=20, help="generated goal-behind-obstacle layouts (default 20)")
    ap.add_argument("--seed0", type=int, default=0, help="first layout seed (default 0)")
    ap.add_argument("--json", type=Path, default=None, help="write the raw figures here")
    args = ap.parse_args(argv)

    from zenswarm.scenario.config import load_scenario, scenario_from_dict

    flights: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for name, path in C.PAPER.items():
        sc = load_scenario(path)
        for pl in PLANNERS:
            flights.append({"layout": name, "family": "paper", **fly(sc, pl)})
    for seed in range(args.seed0, args.seed0 + args.layouts):
        d = behind_layout(seed)
        sc = scenario_from_dict(d)
        for pl in PLANNERS:
            f = {"layout": d["scenario"]["name"], "family": "behind", "description": d["scenario"]["description"], **fly(sc, pl)}
            flights.append(f)
            print(f"{f['layout']:>12} {pl:>6}: {'ok' if f['success'] else 'FAIL ' + ','.join(f['causes'])}", file=sys.stderr, flush=True)
    total = time.perf_counter() - t0

    rows = []
    for f in flights:
        if f["family"] == "paper":
            rows.append([f["layout"], f["planner"], "yes" if f["success"] else "no", C.fmt(f["time_to_goal_s"]),
                         C.fmt(f["min_obstacle_margin_m"], 3), C.fmt(f["leader_tv_m_s"], 3)])
    summ = {pl: summary([f for f in flights if f["family"] == "behind" and f["planner"] == pl]) for pl in PLANNERS}
    for pl, s in summ.items():
        rows.append([f"{args.layouts} goal-behind layouts", pl, f"{s['success']}/{s['n']}", C.fmt(s["time_to_goal_s_median_of_successes"]),
                     C.fmt(s["min_obstacle_margin_m_min"], 3), C.fmt(s["leader_tv_m_s_median"], 3)])
    print(C.table(["layout", "planner", "success", "time to goal s (median)", "min vehicle margin m", "leader v0 TV m/s (median)"], rows))
    print(f"total wall {total:.1f} s")
    C.write_json(args.json, {
        "command": C.command_line(),
        "machine": C.machine_info(),
        "total_wall_s": total,
        "summary_generated": summ,
        "flights": flights,
    })
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

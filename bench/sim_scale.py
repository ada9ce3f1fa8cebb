"""Peak memory and wall time of ``zenswarm sim`` on a large generated swarm (target: a 500-UAV
knn (k = 4) scenario completes and writes its results with a peak RSS under 2 GB).

Each run generates ``zenswarm scenario generate --n N --topology knn --k 4 --seed S`` (once per
N), then runs ``zenswarm sim SCEN --out DIR --quiet`` as a child process and reads its peak RSS
from ``os.wait4`` (ru_maxrss of that child alone). Reported per N: median wall time and peak RSS
over ``--runs``, the simulated time, whether results.json was written, and the verdict.

    python bench/sim_scale.py
    python bench/sim_scale.py --n 100 500 --runs 3 --json bench/results/sim_scale.json

Not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_RSS_MB = 2048.0


def run_once(scen: Path, out: Path, full_time: bool) -> dict:
    argv = [sys.executable, "-m", "zenswarm", "sim", str(scen), "--out", str(out), "--quiet"]
    if full_time:
        argv.append("--full-time")
    t0 = time.perf_counter()
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    assert p.stdout is not None
    text = p.stdout.read()
    code = os.waitstatus_to_exitcode(status)
    res_path = out / "results.json"
    res = json.loads(res_path.read_text()) if res_path.exists() else {}
    return {
        "exit": code,
        "wall_s": wall,
        "peak_rss_mb": usage.ru_maxrss / 1024.0,
        "results_written": res_path.exists(),
        "sim_time_s": res.get("sim_time_s"),
        "success": res.get("success"),
        "causes": sorted({f["cause"] for f in res.get("failures", [])}),
        "summary": [ln for ln in text.strip().splitlines() if not ln.startswith("wrote ")][-3:],  # no temp paths
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[500], help="swarm sizes (default 500)")
    ap.add_argument("--runs", type=int, default=3, help="runs per size (median reported)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--full-time", action="store_true", help="pass --full-time (fly the whole limit)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.n:
            scen = Path(tmp) / f"knn{n}.toml"
            subprocess.run(
                [sys.executable, "-m", "zenswarm", "scenario", "generate", "--n", str(n), "--topology", "knn", "--k", "4",
                 "--seed", str(a.seed), "--out", str(scen), "--force"],
                check=True, stdout=subprocess.DEVNULL,
            )
            runs = []
            for r in range(a.runs):
                x = run_once(scen, Path(tmp) / f"out{n}_{r}", a.full_time)
                runs.append(x)
                print(f"N={n} run {r + 1}: exit {x['exit']} wall {x['wall_s']:.1f} s peak RSS {x['peak_rss_mb']:.0f} MB "
                      f"sim {x['sim_time_s']} s causes {x['causes']}", flush=True)
            row = {
                "n": n,
                "runs": runs,
                "median_wall_s": statistics.median(x["wall_s"] for x in runs),
                "median_peak_rss_mb": statistics.median(x["peak_rss_mb"] for x in runs),
                "all_results_written": all(x["results_written"] for x in runs),
                "target_rss_mb": TARGET_RSS_MB,
            }
            row["met"] = row["all_results_written"] and row["median_peak_rss_mb"] < TARGET_RSS_MB
            rows.append(row)
            print(f"N={n}: median wall {row['median_wall_s']:.1f} s, median peak RSS {row['median_peak_rss_mb']:.0f} MB "
                  f"(target < {TARGET_RSS_MB:.0f} MB: {'met' if row['met'] else 'NOT met'})", flush=True)
    if a.json:
        machine = {"cpus": os.cpu_count(), "python": platform.python_version()}
        a.json.write_text(json.dumps({"machine": machine, "rows": rows}, indent=2) + "\n")
    return 0 if all(r["met"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())

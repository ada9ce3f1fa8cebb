"""``zenswarm sim`` on large generated swarms: start-up, x real time of the whole command, peak RSS.

Each run generates ``zenswarm scenario generate --n N --topology knn --k 4 --seed S --time-limit
D`` (once per N and interpreter), then runs ``zenswarm sim SCEN --out DIR`` (``--full-time``
unless ``--early-end``: a large swarm may end early on a failure, the whole D seconds are flown)
as a child process and reads its peak RSS from ``os.wait4`` (ru_maxrss of that child alone).
Per run:

* **start-up**: wall seconds from launch to the simulator's first progress line (printed after
  tick 0: the interpreter, the imports, the scenario's parse and checks, the swarm's build);
* **whole command**: wall seconds to exit (start-up, flight, judging, writing the outputs) and
  x real time = D / that; **flight**: ``wall_time_s`` of results.json (``simulate()``'s loop);
* **CPU** of the child (user + system) and **peak RSS**.

``--python A B ...`` runs the same with several interpreters (e.g. another checkout's venv, for a
before/after), interleaved run by run; each generates its own scenario file (an older checkout
writes the dense matrix). Medians over ``--runs``.

    python bench/sim_scale.py --n 500 1000 --runs 3 --json bench/results/sim_scale.json
    python bench/sim_scale.py --n 500 --runs 3 --python .venv/bin/python ../base/.venv/bin/python

Not a test: figures depend on the machine and its load (the background CPU of other jobs during
each run is printed).
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

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

TARGET_RSS_MB = 2048.0
TARGET_STARTUP_S = 5.0  # at 1000 UAVs (issue 42)


def run_once(python: str, scen: Path, out: Path, early_end: bool) -> dict:
    argv = [python, "-m", "zenswarm", "sim", str(scen), "--out", str(out)]
    if not early_end:
        argv.append("--full-time")
    load = C.CpuWindow()
    t0 = time.perf_counter()
    # cwd: not a checkout, whose zenswarm/ folder `python -m` would import instead of the interpreter's
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=out.parent)
    assert p.stderr is not None and p.stdout is not None
    first = p.stderr.readline()  # the first progress line: after tick 0
    startup = time.perf_counter() - t0 if first else None
    err = p.stderr.read()
    _, status, usage = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    text = p.stdout.read()
    code = os.waitstatus_to_exitcode(status)
    res_path = out / "results.json"
    res = json.loads(res_path.read_text()) if res_path.exists() else {}
    sim_s = res.get("sim_time_s")
    return {
        "exit": code,
        "startup_s": startup,
        "wall_s": wall,
        "x_real_time": (sim_s / wall) if sim_s else None,
        "flight_wall_s": res.get("wall_time_s"),
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_mb": usage.ru_maxrss / 1024.0,
        "results_written": res_path.exists(),
        "sim_time_s": sim_s,
        "causes": sorted({f["cause"] for f in res.get("failures", [])}),
        "background_cores": load.close()["background_cores"],
        "stderr_tail": [ln for ln in err.strip().splitlines() if not ln.startswith("[sim]")][-3:],
        "summary": [ln for ln in text.strip().splitlines() if not ln.startswith("wrote ")][-3:],  # no temp paths
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[500, 1000], help="swarm sizes (default 500 1000)")
    ap.add_argument("--runs", type=int, default=3, help="runs per size and interpreter (median reported)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=10.0, metavar="S", help="flight, s (--time-limit; default 10)")
    ap.add_argument("--early-end", action="store_true", help="no --full-time: a run may end on its first failure")
    ap.add_argument("--python", nargs="+", default=[sys.executable], metavar="PY",
                    help="interpreters to run zenswarm with, interleaved (default: this one)")
    ap.add_argument("--quiet-wait", type=float, default=0.0, metavar="CORES",
                    help="before each run wait (up to 60 s) until other jobs use at most CORES cores (0 = don't wait)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    a = ap.parse_args()
    a.python = [os.path.abspath(py) for py in a.python]  # absolute (the runs' cwd is elsewhere), symlinks kept (a venv's)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.n:
            scen = {}
            for x, py in enumerate(a.python):
                scen[py] = Path(tmp) / f"knn{n}_{x}.toml"
                subprocess.run(
                    [py, "-m", "zenswarm", "scenario", "generate", "--n", str(n), "--topology", "knn", "--k", "4",
                     "--seed", str(a.seed), "--time-limit", f"{a.duration:g}", "--out", str(scen[py]), "--force"],
                    check=True, stdout=subprocess.DEVNULL, cwd=tmp,
                )
            runs: dict[str, list[dict]] = {py: [] for py in a.python}
            for r in range(a.runs):
                for x, py in enumerate(a.python):
                    C.quiet_wait(a.quiet_wait, 60.0)
                    res = run_once(py, scen[py], Path(tmp) / f"out{n}_{x}_{r}", a.early_end)
                    runs[py].append(res)
                    print(f"N={n} [{x}] run {r + 1}: exit {res['exit']} start-up {C.fmt(res['startup_s'])} s, whole "
                          f"{res['wall_s']:.2f} s ({C.fmt(res['x_real_time'])}x), flight {C.fmt(res['flight_wall_s'])} s, "
                          f"cpu {res['cpu_s']:.2f} s, peak RSS {res['peak_rss_mb']:.0f} MB, background "
                          f"{res['background_cores']:.2f} cores, file {scen[py].stat().st_size} B", flush=True)
            for x, py in enumerate(a.python):
                rs = runs[py]
                row = {
                    "n": n,
                    "python": py,
                    "scenario_bytes": scen[py].stat().st_size,
                    "runs": rs,
                    "median_startup_s": C.median(x["startup_s"] for x in rs),
                    "median_wall_s": statistics.median(x["wall_s"] for x in rs),
                    "median_x_real_time": C.median(x["x_real_time"] for x in rs),
                    "median_flight_wall_s": C.median(x["flight_wall_s"] for x in rs),
                    "median_cpu_s": statistics.median(x["cpu_s"] for x in rs),
                    "median_peak_rss_mb": statistics.median(x["peak_rss_mb"] for x in rs),
                    "median_background_cores": statistics.median(x["background_cores"] for x in rs),
                    "all_results_written": all(x["results_written"] for x in rs),
                }
                rows.append(row)
                print(f"N={n} [{x}] {py}: median start-up {C.fmt(row['median_startup_s'])} s, whole command "
                      f"{row['median_wall_s']:.2f} s = {C.fmt(row['median_x_real_time'])}x real time, cpu "
                      f"{row['median_cpu_s']:.2f} s, peak RSS {row['median_peak_rss_mb']:.0f} MB "
                      f"(targets: RSS < {TARGET_RSS_MB:.0f} MB; at 1000 UAVs start-up <= {TARGET_STARTUP_S:g} s)", flush=True)
    if a.json:
        machine = {"cpus": os.cpu_count(), "python": platform.python_version(), "loadavg_at_end": list(os.getloadavg())}
        a.json.write_text(json.dumps({"benchmark": "sim_scale", "command": C.command_line(), "machine": machine,
                                      "rows": rows}, indent=2) + "\n")
    return 0 if all(r["all_results_written"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())

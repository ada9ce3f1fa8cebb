"""Throughput of ``zenswarm sweep`` (issue 17): runs per minute with 1 and 2 local workers and
through a loopback Dask cluster (a ``dask scheduler`` and two ``dask worker --nthreads 1``).

One campaign: paper example 1, ``--duration D`` (default 5 s of sim time), ``--seeds R`` (default
8 runs), the in-process simulator. Per repetition the three configurations run in turn
(interleaved: w1, w2, dask, w1, w2, dask, ...), each a fresh ``zenswarm sweep`` command (the
installed console script) into a new directory, so each pays its own start-up: the local pool
spawns its workers; the Dask cluster is started fresh before its run and waited for (2 workers
connected), not timed, as a user's existing cluster would be, and its workers import zenswarm on
their first task as the pool's do.

Per command: wall time of the whole command (start-up, runs, table, report) -> runs/min; the sum
of the runs' own ``wall_s`` (from runs.parquet); and the overhead per run,
(workers x command wall - sum wall_s) / runs: what a run slot spends outside flights (process
start, imports, scheduling, the table and the report). Medians over the repetitions.

    python bench/sweep_throughput.py                        # 3 repetitions
    python bench/sweep_throughput.py --reps 3 --json bench/results/sweep_throughput.json

Not a test: numbers depend on the machine and its load (the load average is printed per command).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

CONFIGS = ("workers1", "workers2", "dask2")


def _zenswarm() -> str:
    exe = Path(sysconfig.get_path("scripts")) / "zenswarm"
    return str(exe) if exe.is_file() else "zenswarm"


class Cluster:
    """A loopback Dask cluster: one scheduler, two single-threaded workers (no nanny), own session."""

    def __init__(self, logdir: Path) -> None:
        self.port = C.free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.procs: list[subprocess.Popen[bytes]] = []
        self.logs = [open(logdir / f"dask{i}.log", "wb") for i in range(3)]
        py = sys.executable
        self.procs.append(subprocess.Popen(
            [py, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(self.port), "--no-dashboard"],
            stdout=self.logs[0], stderr=subprocess.STDOUT, start_new_session=True))
        for i in (1, 2):
            self.procs.append(subprocess.Popen(
                [py, "-m", "distributed.cli.dask_worker", self.address, "--nthreads", "1", "--no-dashboard", "--no-nanny"],
                stdout=self.logs[i], stderr=subprocess.STDOUT, start_new_session=True, cwd=C.REPO))
        import distributed

        with distributed.Client(self.address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)

    def close(self) -> None:
        for p in self.procs:
            try:
                os.killpg(p.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        for p in self.procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(10)
        for f in self.logs:
            f.close()


def one(config: str, tmp: Path, rep: int, duration: float, runs: int) -> dict[str, Any]:
    import pyarrow.parquet as pq

    out = tmp / f"{config}-{rep}"
    cmd = [_zenswarm(), "sweep", "paper_example1", "--duration", str(duration), "--seeds", str(runs), "--quiet", "--out", str(out)]
    cluster = None
    if config == "dask2":
        cluster = Cluster(tmp)
        cmd += ["--scheduler", cluster.address]
        workers = 2
    else:
        workers = int(config[-1])
        cmd += ["--workers", str(workers)]
    shown = [f"TMP/{out.name}" if a == str(out) else a for a in cmd[1:]]  # no path of this machine in the JSON
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=C.bench_env(), timeout=1800)
    finally:
        wall = time.perf_counter() - t0
        if cluster is not None:
            cluster.close()
    if p.returncode != 0:
        raise SystemExit(f"{config}: exit {p.returncode}\n{p.stderr}")
    rows = pq.read_table(out / "runs.parquet").to_pylist()
    assert len(rows) == runs and all(r["error"] is None for r in rows)
    sum_run = sum(float(r["wall_s"]) for r in rows)
    return {
        "config": config, "rep": rep, "workers": workers, "wall_s": wall, "runs": runs,
        "runs_per_min": runs / wall * 60.0, "sum_run_wall_s": sum_run,
        "overhead_per_run_s": (workers * wall - sum_run) / runs,
        "loadavg_1min_before": load0, "loadavg_1min_after": os.getloadavg()[0], "command": " ".join(shown),
        "rows": [{k: r[k] for k in ("run", "seed", "success", "max_final_slot_error_m", "rms_tracking_error_m")} for r in rows],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=3, help="repetitions of the three configurations, interleaved (default 3)")
    ap.add_argument("--runs", type=int, default=8, help="runs per campaign (--seeds; default 8)")
    ap.add_argument("--duration", type=float, default=5.0, help="sim seconds per run (default 5)")
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON here")
    args = ap.parse_args()
    info = C.machine_info()
    print("\n".join(C.machine_lines(info)))
    results: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="zenswarm-sweep-bench-") as d:
        for rep in range(args.reps):
            for config in CONFIGS:
                r = one(config, Path(d), rep, args.duration, args.runs)
                results.append(r)
                print(f"rep {rep} {config:8s}: {r['wall_s']:6.2f} s, {r['runs_per_min']:6.1f} runs/min, "
                      f"overhead {r['overhead_per_run_s']:.2f} s/run, load {r['loadavg_1min_before']:.2f}", flush=True)
    # every configuration flies the same rows (a run's row is a pure function of its inputs)
    first = results[0]["rows"]
    same = all(r["rows"] == first for r in results)
    summary = []
    for config in CONFIGS:
        rs = [r for r in results if r["config"] == config]
        summary.append({
            "config": config,
            "wall_s": C.median(r["wall_s"] for r in rs),
            "runs_per_min": C.median(r["runs_per_min"] for r in rs),
            "overhead_per_run_s": C.median(r["overhead_per_run_s"] for r in rs),
            "sum_run_wall_s": C.median(r["sum_run_wall_s"] for r in rs),
        })
    by = {s["config"]: s for s in summary}
    speedup = by["workers2"]["runs_per_min"] / by["workers1"]["runs_per_min"]
    dask_vs_local = by["dask2"]["runs_per_min"] / by["workers2"]["runs_per_min"]
    print()
    print(C.table(["config", "wall s", "runs/min", "sum of run wall s", "overhead s/run"],
                  [[s["config"], s["wall_s"], s["runs_per_min"], s["sum_run_wall_s"], s["overhead_per_run_s"]] for s in summary]))
    print(f"\n2 workers / 1 worker: {speedup:.2f}x; Dask (2 workers) / local pool (2 workers): {dask_vs_local:.2f}x; "
          f"rows identical across all commands: {same}; load average at end: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    C.write_json(args.json, {"machine": info, "command": C.command_line(), "duration_s": args.duration, "runs": args.runs,
                             "results": results, "summary": summary, "speedup_2_over_1": speedup,
                             "dask_over_local2": dask_vs_local, "rows_identical": same,
                             "loadavg_at_end": list(os.getloadavg())})
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())

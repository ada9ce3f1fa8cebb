"""Speed of the in-process simulator (``zenswarm.compose.sim.simulate``): wall time and x real time.

Each run is a fresh interpreter that loads the scenario and times ``simulate(scenario)`` alone
(``time.perf_counter`` around the call: no imports, no scenario parsing, no output files); it
also reports the CPU time of the call (``time.process_time``), which is less sensitive to other
jobs on the machine. Runs of the different scenarios are interleaved (round-robin), and the
median of ``--runs`` is reported. x real time = simulated seconds / wall seconds.

Scenarios (default: all of them): paper example 1 (70 s, 3 UAVs, 100 Hz outer loop, 1 kHz
physics), paper example 2, and generated ``gen<N>`` scenarios, N = 3, 8, 16, 32, made by
``zenswarm scenario generate --n N --shape circle --topology knn --k 3 --obstacles 2 --seed 1``
(their own time limit, 75-90 s, unless ``--gen-time-limit`` shortens it). These are the baseline
of bench/swarm_lockstep.py, which runs the same simulator on the same files for its ratios.

    python bench/sim_speed.py                          # all scenarios, 5 runs each
    python bench/sim_speed.py --runs 3 --scenarios example1 gen16 --json bench/results/sim.json
    python bench/sim_speed.py --profile example1       # cProfile of one run, top functions

The README's OPENBLAS_CORETYPE/OPENBLAS_L2_SIZE are dropped from the measured command's
environment (``--keep-openblas-env`` keeps them). Not a test: numbers depend on the machine
and its load (the background CPU of other jobs during each run is printed).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

DEFAULT_SCENARIOS = ["example1", "example2", "gen3", "gen8", "gen16", "gen32"]


def profile(scenario: Path, top: int) -> None:
    import cProfile
    import pstats

    from zenswarm.compose.sim import simulate
    from zenswarm.scenario.config import load_scenario

    sc = load_scenario(scenario)
    pr = cProfile.Profile()
    pr.enable()
    simulate(sc)
    pr.disable()
    st = pstats.Stats(pr).strip_dirs().sort_stats("tottime")
    total = sum(v[2] for v in st.stats.values())
    print(f"cProfile of simulate({scenario.name}): {total:.2f} s of profiled time (profiling inflates it)")
    print(C.table(["function", "calls", "tottime s", "share"],
                  [[f"{k[0]}:{k[1]}({k[2]})", v[1], v[2], f"{100 * v[2] / total:.1f}%"]
                   for k, v in sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:top]]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5, help="runs per scenario (median reported; default 5)")
    ap.add_argument("--scenarios", nargs="+", default=DEFAULT_SCENARIOS, metavar="S",
                    help="example1, example2, gen<N> or TOML paths (default: %(default)s)")
    ap.add_argument("--gen-time-limit", type=float, default=None, metavar="S",
                    help="time limit of the generated scenarios, s (default: the generator's, 75-90 s)")
    ap.add_argument("--json", type=Path, metavar="FILE", help="write every run and the medians to FILE")
    ap.add_argument("--keep-openblas-env", action="store_true", help="keep OPENBLAS_CORETYPE/OPENBLAS_L2_SIZE")
    ap.add_argument("--quiet-wait", type=float, default=0.0, metavar="CORES",
                    help="before each run wait (up to 60 s) until other jobs use at most CORES cores (0 = don't wait)")
    ap.add_argument("--profile", metavar="S", help="instead: cProfile one run of scenario S and print the top functions")
    ap.add_argument("--top", type=int, default=15, help="rows of --profile output")
    a = ap.parse_args(argv)

    tmp = tempfile.TemporaryDirectory(prefix="zenswarm-sim-bench-")
    tmpdir = Path(tmp.name)
    if a.profile:
        _, path = C.scenario_file(a.profile, tmpdir, a.gen_time_limit)
        profile(path, a.top)
        return 0

    info = C.machine_info()
    for line in C.machine_lines(info):
        print(line)
    scen = [C.scenario_file(s, tmpdir, a.gen_time_limit) for s in a.scenarios]
    facts = {label: C.scenario_facts(p) for label, p in scen}
    runs: dict[str, list[dict]] = {label: [] for label, _ in scen}
    for r in range(a.runs):
        for label, path in scen:
            C.quiet_wait(a.quiet_wait, 60.0)
            res = C.run_sim_worker(path, a.keep_openblas_env)
            runs[label].append(res)
            print(f"  run {r + 1}/{a.runs} {label:9s} wall {res['wall_s']:7.3f} s  {res['x_real_time']:6.1f}x real time"
                  f"  cpu {res['cpu_s']:7.3f} s  background {res['background_cores']:.2f} cores", flush=True)

    rows, summary = [], {}
    for label, _ in scen:
        rs = runs[label]
        f = facts[label]
        m = {
            "n_uav": f["n_uav"],
            "sim_time_s": f["sim_time_s"],
            "wall_s_median": C.median(x["wall_s"] for x in rs),
            "wall_s_min": min(x["wall_s"] for x in rs),
            "cpu_s_median": C.median(x["cpu_s"] for x in rs),
            "background_cores_median": C.median(x["background_cores"] for x in rs),
            "success": all(x["success"] for x in rs),
            "runs": len(rs),
        }
        m["x_real_time_median"] = f["sim_time_s"] / m["wall_s_median"]
        m["x_real_time_cpu_median"] = f["sim_time_s"] / m["cpu_s_median"]
        m["ms_per_tick_median"] = 1e3 * m["wall_s_median"] / f["n_ticks"]
        summary[label] = m
        rows.append([label, m["n_uav"], f"{m['sim_time_s']:g}", m["wall_s_median"], m["wall_s_min"],
                     f"{m['x_real_time_median']:.1f}x", f"{m['x_real_time_cpu_median']:.1f}x", m["ms_per_tick_median"],
                     m["background_cores_median"], m["success"]])
    print()
    print(f"in-process simulator, median of {a.runs} runs")
    print(C.table(["scenario", "UAVs", "sim s", "wall s (median)", "wall s (min)", "x real time", "x real time (CPU)",
                   "ms/tick", "background cores", "mission ok"], rows))
    C.write_report(a.json, "sim_speed", info, scenarios=facts, summary=summary, runs=runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())

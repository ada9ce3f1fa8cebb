"""Memory of the swarm's processes during a flight: RSS per agent process (target <= 80 MB).

Each run starts ``zenswarm up SCEN --out DIR --quiet --quiet-children --swarm <unique> --listen
tcp/127.0.0.1:<free port>`` (lockstep by default, ``--realtime`` for wall-clock loops) and, while
it flies, reads every 0.25 s ``/proc/<pid>/status`` (VmRSS, VmHWM = peak RSS, RssAnon) and
``/proc/<pid>/smaps_rollup`` (Pss: shared pages such as numpy's and Zenoh's libraries divided
among the processes sharing them) of every process of the swarm. Per process the maximum over
the flight is kept; per run the agents' largest and median values are reported, with the
plant, the leader and the supervisor (router + result collector) for context, and the peak RSS
(``ru_maxrss``) of the in-process simulator flying the same scenario file, as the ratio
agent/sim. Median of ``--runs``.

Scenarios (default: example1 gen16): paper example 1 (3 agents, its full 70 s) and a generated
16-UAV scenario (``zenswarm scenario generate --n 16 --shape circle --topology knn --k 3
--obstacles 2 --seed 1``, shortened to ``--gen-time-limit``, default 10 s).

    python bench/memory.py
    python bench/memory.py --runs 5 --scenarios gen32 --realtime --json bench/results/memory.json

Every process a run starts is stopped at the end (or on Ctrl-C). Not a test.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

TARGET_MB = 80.0


def analyse(run: C.UpRun) -> dict:
    def mb(kb: int) -> float:
        return kb / 1024.0

    agents = [p for r, p in run.procs.items() if r.startswith("agent:")]
    m: dict = {"returncode": run.returncode, "agents_seen": len(agents), "up_wall_s": run.wall_s,
               "leftover_processes": len(run.leftovers), "port_free_after": run.port_free_after,
               "background_cores": run.cpu.get("background_cores")}
    if agents:
        rss = sorted(mb(p.rss_kb_max) for p in agents)
        m["agent_rss_mb_max"] = rss[-1]
        m["agent_rss_mb_median"] = C.median(rss)
        m["agent_hwm_mb_max"] = max(mb(p.hwm_kb) for p in agents)
        m["agent_pss_mb_max"] = max(mb(p.pss_kb_max) for p in agents)
        m["agent_pss_mb_median"] = C.median(mb(p.pss_kb_max) for p in agents)
        m["agent_anon_mb_max"] = max(mb(p.rss_anon_kb_max) for p in agents)
        m["agent_threads_max"] = max(p.threads for p in agents)
        m["agents_over_target"] = sum(mb(p.rss_kb_max) > TARGET_MB for p in agents)
        m["agents_rss_mb_sum"] = sum(rss)
        m["agents_pss_mb_sum"] = sum(mb(p.pss_kb_max) for p in agents)
    for role in ("plant", "leader", "supervisor"):
        p = run.procs.get(role)
        if p is not None:
            m[f"{role}_rss_mb"] = mb(p.rss_kb_max)
            m[f"{role}_pss_mb"] = mb(p.pss_kb_max)
    return m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3, help="runs per scenario (median reported; default 3)")
    ap.add_argument("--scenarios", nargs="+", default=["example1", "gen16"], metavar="S",
                    help="example1, example2, gen<N> or TOML paths (default: %(default)s)")
    ap.add_argument("--gen-time-limit", type=float, default=10.0, metavar="S",
                    help="flight length of generated scenarios, s (default 10; 0 = the generator's own)")
    ap.add_argument("--realtime", action="store_true", help="fly with --realtime (wall-clock loops)")
    ap.add_argument("--json", type=Path, metavar="FILE", help="write every run and the medians to FILE")
    ap.add_argument("--timeout", type=float, default=900.0, metavar="S", help="per-run limit of zenswarm up (default 900 s)")
    ap.add_argument("--no-sim", action="store_true", help="skip the simulator baseline (its peak RSS on the same scenario)")
    a = ap.parse_args(argv)
    tmp, info = C.start_bench("zenswarm-mem-bench-")
    tmpdir = Path(tmp.name)
    scen = [C.scenario_file(s, tmpdir, a.gen_time_limit or None) for s in a.scenarios]
    facts = {label: C.scenario_facts(p) for label, p in scen}
    runs: dict[str, list[dict]] = {label: [] for label, _ in scen}
    extra = ["--realtime"] if a.realtime else []
    try:
        for r in range(a.runs):
            for label, path in scen:
                out = tmpdir / f"{label}-run{r + 1}"
                run = C.run_up(path, out, tag=f"mem{r}", extra=extra, pss=True, timeout_s=a.timeout)
                m = analyse(run)
                if not a.no_sim:
                    m["sim_rss_mb"] = C.run_sim_worker(path)["maxrss_kb"] / 1024.0
                runs[label].append(m)
                shutil.rmtree(out, ignore_errors=True)
                print(f"  run {r + 1}/{a.runs} {label:9s} agents {m['agents_seen']}: RSS max {C.fmt(m.get('agent_rss_mb_max'), 1)} MB"
                      f" median {C.fmt(m.get('agent_rss_mb_median'), 1)} MB, PSS max {C.fmt(m.get('agent_pss_mb_max'), 1)} MB;"
                      f" plant {C.fmt(m.get('plant_rss_mb'), 1)} MB, supervisor {C.fmt(m.get('supervisor_rss_mb'), 1)} MB"
                      f"  (exit {run.returncode})", flush=True)
    finally:
        C.cleanup_all()

    keys = ["agent_rss_mb_max", "agent_rss_mb_median", "agent_hwm_mb_max", "agent_pss_mb_max", "agent_pss_mb_median",
            "agent_anon_mb_max", "agent_threads_max", "agents_over_target", "agents_rss_mb_sum", "agents_pss_mb_sum",
            "plant_rss_mb", "leader_rss_mb", "supervisor_rss_mb", "background_cores", "sim_rss_mb"]
    summary, rows = {}, []
    for label, _ in scen:
        rs = runs[label]
        s = {k: C.median(m.get(k) for m in rs) for k in keys}
        s["n_uav"] = facts[label]["n_uav"]
        s["leftover_processes"] = sum(m["leftover_processes"] for m in rs)
        summary[label] = s
        rows.append([label, s["n_uav"], "realtime" if a.realtime else "lockstep", s["agent_rss_mb_max"], s["agent_rss_mb_median"],
                     s["agent_hwm_mb_max"], s["agent_pss_mb_median"], s["agent_anon_mb_max"], s["agent_threads_max"],
                     f"{'yes' if (s['agent_rss_mb_max'] or 1e9) <= TARGET_MB else 'NO'}",
                     s["plant_rss_mb"], s["leader_rss_mb"], s["supervisor_rss_mb"], s["agents_pss_mb_sum"], s["sim_rss_mb"],
                     f"{s['agent_rss_mb_max'] / s['sim_rss_mb']:.2f}" if s["sim_rss_mb"] and s["agent_rss_mb_max"] else "-"])
    print()
    print(f"memory per process during the flight (MB = MiB), median of {a.runs} runs")
    print(C.table(["scenario", "UAVs", "mode", "agent RSS max", "agent RSS median", "agent peak (VmHWM)", "agent PSS median",
                   "agent anon RSS max", "agent threads", f"<= {TARGET_MB:g} MB", "plant RSS", "leader RSS", "supervisor RSS",
                   "all agents PSS", "simulator RSS", "agent/sim"], rows))
    C.write_report(a.json, "memory", info, scenarios=facts, summary=summary, runs=runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())

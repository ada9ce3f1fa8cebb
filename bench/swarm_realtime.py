"""The swarm in real time: 16 UAVs at 100 Hz (``zenswarm up --realtime``): missed deadlines, loop
jitter, neighbour message latency; beside the in-process simulator on the same scenario.

Scenario: ``zenswarm scenario generate --n 16 --shape circle --topology knn --k 3 --obstacles 2
--seed 1 --time-limit 25`` (``--n``, ``--flight``), flown by

    zenswarm up SCEN --realtime --out DIR --quiet --quiet-children --swarm <unique> --listen tcp/127.0.0.1:<free port>

Figures and how they are measured:

* missed deadlines and loop jitter: each process's own counters, from its last diagnostics
  message in ``results.json`` (``diagnostics.<process>``: ``loop_ticks``, ``missed_deadlines``
  = wake-ups more than one period late, ``jitter_mean_ms``/``jitter_max_ms`` = |wake-up - due
  time|). These cover the whole life of each loop, start-up included (agents start their loops
  while the other processes are still importing). "in flight" repeats the count between the
  first diagnostics message after the plant's first tick and the last one (see below).
* neighbour message latency: ``bench/stamps/sitecustomize.py`` is put on ``PYTHONPATH`` of the
  swarm's processes; it stamps (``time.monotonic_ns``; CLOCK_MONOTONIC is system-wide on Linux)
  every message right before ``publisher.put`` in the sender and on entry to the decoder in the
  receiver's Zenoh callback, keyed by (key, seq). Latency = receive - send, over every
  ``uav/<j>/ref`` received by a neighbouring agent (the path agent j -> router -> agent i).
  The same is reported for plant -> agent states, leader -> pinned agents and agent -> plant
  commands. The wrappers add two clock reads and a list append per message; nothing in the
  project's source is changed.
* publication period: intervals between the plant's successive clock messages and between an
  agent's successive commands (wall clock), |interval - 10 ms| as a second view of jitter.
* CPU: cores each role used in the middle 80 % of the flight (sampling /proc), and the same
  scenario in the in-process simulator: CPU seconds per simulated second (= cores it would need to
  run in real time), so "swarm/sim CPU" is how much more CPU the distributed system burns.

    python bench/swarm_realtime.py                        # 16 UAVs, 25 s of flight, 3 runs
    python bench/swarm_realtime.py --runs 5 --n 16 --flight 30 --json bench/results/realtime.json

Every process a run starts is stopped at the end (or on Ctrl-C). Not a test: numbers depend on
the machine and its load.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

# the per-run figures of the summary: loop counters by role group, message latency statistics
LOOP_STATS = ("missed_pct", "missed", "loop_ticks", "jitter_mean_ms", "jitter_max_ms")
LATENCY_STATS = ("n", "p50", "p90", "p99", "p99.9", "max", "over_1ms_pct")


# --------------------------------------------------------------------------- figures of one run
def key_kind(key: str) -> str:
    parts = key.split("/")
    if parts[-2:] == ["leader", "ref"]:
        return "leader_ref"
    return parts[-1]  # ref, state, cmd, clock


def latencies(stamps: list[dict]) -> tuple[dict[str, list[float]], int]:
    """Latency samples in ms by link class; and the number of receptions with no send stamp."""
    sent: dict[str, dict[int, int]] = {}
    for s in stamps:
        for key, lst in s["pub"].items():
            sent.setdefault(key, {}).update({seq: t for seq, _, t in lst})
    out: dict[str, list[float]] = {"neighbour ref (agent->agent)": [], "state (plant->agent)": [],
                                   "leader ref (leader->agent)": [], "cmd (agent->plant)": [], "clock (plant->leader)": []}
    unmatched = 0
    for s in stamps:
        role = s["role"]
        for key, lst in s["rx"].items():
            kind = key_kind(key)
            if kind == "ref" and role.startswith("agent"):
                cls = "neighbour ref (agent->agent)"
            elif kind == "state":
                cls = "state (plant->agent)"
            elif kind == "leader_ref":
                cls = "leader ref (leader->agent)"
            elif kind == "cmd":
                cls = "cmd (agent->plant)"
            elif kind == "clock":
                cls = "clock (plant->leader)"
            else:
                continue
            src = sent.get(key, {})
            for seq, _, t in lst:
                t0 = src.get(seq)
                if t0 is None:
                    unmatched += 1
                    continue
                out[cls].append((t - t0) / 1e6)
    return out, unmatched


def period_jitter(stamps: list[dict], dt_ms: float) -> dict[str, list[float]]:
    """|interval - dt| in ms between successive publications: plant clock, agents' cmd."""
    out: dict[str, list[float]] = {"plant": [], "agents": [], "leader": []}
    for s in stamps:
        role = s["role"]
        for key, lst in s["pub"].items():
            kind = key_kind(key)
            if (role == "plant" and kind == "clock") or (role.startswith("agent") and kind == "cmd") or (
                role == "leader" and kind == "leader_ref"):
                ts = [t for _, _, t in lst]
                grp = "plant" if role == "plant" else ("leader" if role == "leader" else "agents")
                out[grp] += [abs((b - a) / 1e6 - dt_ms) for a, b in zip(ts, ts[1:])]
    return out


def in_flight_missed(stamps: list[dict]) -> dict[str, tuple[int, int]]:
    """(missed, ticks) per role group between the first diag after the plant's first tick and the last."""
    start = None
    for s in stamps:
        if s["role"] == "plant":
            clk = [t for key, lst in s["pub"].items() if key_kind(key) == "clock" for _, _, t in lst]
            start = min(clk) if clk else None
    out: dict[str, list[int]] = {"plant": [0, 0], "leader": [0, 0], "agents": [0, 0]}
    if start is None:
        return {}
    for s in stamps:
        d = [x for x in s["diags"] if x[1] is not None and x[0] >= start]
        if len(d) < 2:
            continue
        grp = "agents" if s["role"].startswith("agent") else s["role"]
        out[grp][0] += d[-1][2] - d[0][2]
        out[grp][1] += d[-1][1] - d[0][1]
    return {k: (v[0], v[1]) for k, v in out.items()}


def analyse(run: C.UpRun, stamp_dir: Path, facts: dict) -> dict:
    res = run.results
    diag = res.get("diagnostics", {})
    m: dict = {"returncode": run.returncode, "up_wall_s": run.wall_s, "leftover_processes": len(run.leftovers),
               "port_free_after": run.port_free_after, "background_cores": run.cpu.get("background_cores"),
               "load1_start": run.cpu.get("load1_start"), "rms_tracking_error_m": res.get("rms_tracking_error_m"),
               "min_inter_uav_distance_m": res.get("min_inter_uav_distance_m"),
               "plant_finished": bool(diag.get("plant", {}).get("finished")), "timed_out": run.timed_out,
               "hung_after_plant_exit": run.hung_after_plant_exit,
               "still_running_after_plant": sorted(r for r, p in run.procs.items()
                                                   if r not in ("plant", "supervisor") and run.hung_after_plant_exit
                                                   and p.last_seen >= run.procs["plant"].last_seen + 5.0)
               if "plant" in run.procs else [],
               "hang_dumps": run.hang_dumps}
    groups: dict[str, dict] = {}
    for name, d in diag.items():
        if "loop_ticks" not in d:
            continue
        g = groups.setdefault("agents" if name.startswith("agent:") else name,
                              {"processes": 0, "loop_ticks": 0, "missed": 0, "jitter_mean_ms": [], "jitter_max_ms": 0.0})
        g["processes"] += 1
        g["loop_ticks"] += int(d["loop_ticks"])
        g["missed"] += int(d["missed_deadlines"])
        g["jitter_mean_ms"].append(float(d["jitter_mean_ms"]))
        g["jitter_max_ms"] = max(g["jitter_max_ms"], float(d["jitter_max_ms"]))
    for g in groups.values():
        g["jitter_mean_ms"] = sum(g["jitter_mean_ms"]) / len(g["jitter_mean_ms"])
        g["missed_pct"] = 100.0 * g["missed"] / g["loop_ticks"] if g["loop_ticks"] else None
    m["loops"] = groups
    tot_t = sum(g["loop_ticks"] for g in groups.values())
    tot_m = sum(g["missed"] for g in groups.values())
    m["missed_pct_all"] = 100.0 * tot_m / tot_t if tot_t else None
    m["processes_reporting_loops"] = sum(g["processes"] for g in groups.values())

    stamps = C.load_stamps(stamp_dir)
    m["stamp_files"] = len(stamps)
    lat, unmatched = latencies(stamps)
    m["latency_unmatched"] = unmatched
    m["latency_ms"] = {
        cls: {"n": len(v), "p50": C.pct(v, 50), "p90": C.pct(v, 90), "p99": C.pct(v, 99), "p99.9": C.pct(v, 99.9),
              "max": max(v) if v else None, "over_1ms_pct": 100.0 * sum(x > 1.0 for x in v) / len(v) if v else None}
        for cls, v in lat.items()
    }
    pj = period_jitter(stamps, 1e3 / facts["control_rate_hz"])
    m["period_jitter_ms"] = {g: {"n": len(v), "p50": C.pct(v, 50), "p99": C.pct(v, 99), "max": max(v) if v else None}
                             for g, v in pj.items()}
    fm = in_flight_missed(stamps)
    m["in_flight_missed"] = {g: {"missed": a, "ticks": b, "pct": 100.0 * a / b if b else None} for g, (a, b) in fm.items()}
    a_all = sum(a for a, _ in fm.values())
    b_all = sum(b for _, b in fm.values())
    m["in_flight_missed_pct_all"] = 100.0 * a_all / b_all if b_all else None

    cores = C.flight_cores(run.procs, facts["sim_time_s"])
    if cores is not None:
        m["flight_cores"] = cores
        m["flight_cores_total"] = sum(cores.values())
    return m


# --------------------------------------------------------------------------- the runs
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3, help="runs (median reported; default 3)")
    ap.add_argument("--n", type=int, default=16, help="UAVs (default 16)")
    ap.add_argument("--flight", type=float, default=25.0, metavar="S", help="seconds of flight (scenario time limit; default 25)")
    ap.add_argument("--scenario", type=Path, help="fly this TOML instead of a generated one (its own time limit)")
    ap.add_argument("--json", type=Path, metavar="FILE", help="write every run and the medians to FILE")
    ap.add_argument("--no-sim", action="store_true", help="skip the simulator baseline")
    ap.add_argument("--no-stamps", action="store_true",
                    help="fly without the latency instrumentation (bench/stamps); loop counters and CPU only")
    ap.add_argument("--end-grace", type=float, default=15.0, metavar="S",
                    help="if the swarm is still running S seconds after the plant exited, dump it (py-spy) and stop it;"
                    " counted as 'hung at the end' (default 15)")
    ap.add_argument("--keep", type=Path, metavar="DIR", help="keep each run's results.json (and stamps) under DIR")
    ap.add_argument("--timeout", type=float, default=None, metavar="S",
                    help="per-run limit of zenswarm up (default: flight + 120 s); a swarm still running then is dumped with"
                    " py-spy (if installed) and stopped")
    ap.add_argument("--quiet-wait", type=float, default=0.0, metavar="CORES",
                    help="before each run wait (up to 120 s) until other jobs use at most CORES cores (0 = don't wait)")
    return ap.parse_args(argv)


def scenario(a: argparse.Namespace, tmpdir: Path) -> tuple[Path, dict]:
    """The scenario flown (``--scenario``, or ``gen<--n>`` generated with ``--flight`` s), printed; its facts."""
    if a.scenario is not None:
        label, path = a.scenario.stem, a.scenario
    else:
        label, path = f"gen{a.n}", C.generated_scenario(a.n, tmpdir, a.flight)
    facts = C.scenario_facts(path)
    print(f"scenario {label}: {facts['n_uav']} UAVs, {facts['sim_time_s']:g} s at {facts['control_rate_hz']:g} Hz")
    return path, facts


def fly(a: argparse.Namespace, r: int, path: Path, facts: dict, tmpdir: Path) -> tuple[C.UpRun, dict]:
    """Run ``r``: ``zenswarm up --realtime`` (stamped unless ``--no-stamps``) and its figures; its
    results.json and stamps kept under ``--keep``/run<r+1> if asked."""
    sd = tmpdir / f"stamps{r}"
    sd.mkdir()
    out = tmpdir / f"run{r}"
    run = C.run_up(path, out, tag=f"rt{r}", extra=["--realtime"], env=C.bench_env() if a.no_stamps else C.stamps_env(sd),
                   timeout_s=a.timeout or facts["sim_time_s"] + 120.0, end_grace_s=a.end_grace)
    m = analyse(run, sd, facts)
    if a.keep is not None:
        dst = a.keep / f"run{r + 1}"
        dst.mkdir(parents=True, exist_ok=True)
        if (out / "results.json").exists():
            shutil.copy(out / "results.json", dst / "results.json")
        shutil.copytree(sd, dst / "stamps", dirs_exist_ok=True)
    shutil.rmtree(sd, ignore_errors=True)
    shutil.rmtree(out, ignore_errors=True)
    return run, m


def _pct_or_nan(x: float | None) -> float:
    return x if x is not None else float("nan")


def print_run(a: argparse.Namespace, r: int, run: C.UpRun, m: dict) -> None:
    """The line of one run, and what went wrong in it if anything did."""
    nb = m["latency_ms"]["neighbour ref (agent->agent)"]
    print(f"  run {r + 1}/{a.runs}: missed {_pct_or_nan(m['missed_pct_all']):.3f} %"
          f" (in flight {_pct_or_nan(m['in_flight_missed_pct_all']):.3f} %)"
          f"  neighbour latency p50 {C.fmt(nb['p50'], 3)} p99 {C.fmt(nb['p99'], 3)} max {C.fmt(nb['max'], 2)} ms"
          f" (n={nb['n']})  cores in flight {m.get('flight_cores_total', 0):.2f}  background {m['background_cores']:.2f}"
          f"  exit {run.returncode}", flush=True)
    if not a.no_stamps and nb["n"] == 0:
        print(f"    WARNING: no neighbour message was stamped ({m['stamp_files']} stamp files): the wrappers in"
              " bench/stamps/sitecustomize.py may no longer match zenswarm.process.runtime/zenswarm.bus.wire")
    still = m["still_running_after_plant"]
    if m["hung_after_plant_exit"]:
        print(f"    HUNG AT THE END: {len(still)} processes kept running after the plant exited"
              f" ({', '.join(still[:6])}{', ...' if len(still) > 6 else ''});"
              f" plant's final diagnostics received: {m['plant_finished']}")
    if not m["plant_finished"] and not m["hung_after_plant_exit"]:
        print(f"    the plant did not finish; output:\n{run.output_tail}")
        C.print_hang_dumps(run.hang_dumps)


# --------------------------------------------------------------------------- summary and report
def summarise(runs: list[dict], sims: list[dict], facts: dict) -> dict:
    """Medians over the runs (sums for the cleanup counts); the simulator's figures beside them."""
    med = C.median
    summary: dict = {"n_uav": facts["n_uav"], "flight_s": facts["sim_time_s"], "runs": len(runs)}
    summary["missed_pct_all"] = med(m["missed_pct_all"] for m in runs)
    summary["in_flight_missed_pct_all"] = med(m["in_flight_missed_pct_all"] for m in runs)
    groups = sorted({g for m in runs for g in m["loops"]})
    summary["loops"] = {g: {k: med(m["loops"].get(g, {}).get(k) for m in runs) for k in LOOP_STATS} for g in groups}
    summary["in_flight_missed"] = {g: med(m["in_flight_missed"].get(g, {}).get("pct") for m in runs) for g in groups}
    classes = list(runs[0]["latency_ms"]) if runs else []
    summary["latency_ms"] = {c: {k: med(m["latency_ms"][c][k] for m in runs) for k in LATENCY_STATS} for c in classes}
    summary["period_jitter_ms"] = {g: {k: med(m["period_jitter_ms"][g][k] for m in runs) for k in ("p50", "p99", "max")}
                                   for g in ("plant", "leader", "agents")}
    summary["flight_cores_total"] = med(m.get("flight_cores_total") for m in runs)
    summary["flight_cores"] = {k: med(m.get("flight_cores", {}).get(k) for m in runs)
                               for k in sorted({k for m in runs for k in m.get("flight_cores", {})})}
    summary["background_cores"] = med(m["background_cores"] for m in runs)
    summary["rms_tracking_error_m"] = med(m["rms_tracking_error_m"] for m in runs)
    summary["leftover_processes"] = sum(m["leftover_processes"] for m in runs)
    summary["runs_hung_at_end"] = sum(bool(m["hung_after_plant_exit"]) for m in runs)
    summary["ports_left_bound"] = sum(not m["port_free_after"] for m in runs)
    if sims:
        summary["sim_x_real_time"] = facts["sim_time_s"] / med(s["wall_s"] for s in sims)
        summary["sim_cores_for_real_time"] = med(s["cpu_s"] for s in sims) / facts["sim_time_s"]
        summary["sim_rms_tracking_error_m"] = med(s["rms_tracking_error_m"] for s in sims)
        if summary["flight_cores_total"]:
            summary["cpu_ratio_swarm_over_sim"] = summary["flight_cores_total"] / summary["sim_cores_for_real_time"]
    return summary


def print_loops(summary: dict) -> None:
    """Loop counters by role group, and all together."""
    rows: list[list[Any]] = []
    for g, s in summary["loops"].items():
        rows.append([g, s["loop_ticks"], s["missed"], f"{C.fmt(s['missed_pct'], 3)} %", f"{C.fmt(summary['in_flight_missed'].get(g), 3)} %",
                     s["jitter_mean_ms"], s["jitter_max_ms"], C.fmt(summary["period_jitter_ms"].get(g, {}).get("p99"), 2)])
    rows.append(["all", "", "", f"{C.fmt(summary['missed_pct_all'], 3)} %", f"{C.fmt(summary['in_flight_missed_pct_all'], 3)} %",
                 "", "", ""])
    print(C.table(["loops", "loop ticks", "missed", "missed %", "missed % in flight", "jitter mean ms", "jitter max ms",
                   "period |dT-10ms| p99 ms"], rows))


def print_latencies(summary: dict) -> None:
    print(C.table(["message latency (send->receive callback)", "n", "p50 ms", "p90 ms", "p99 ms", "p99.9 ms", "max ms", "> 1 ms"],
                  [[c, int(s["n"] or 0), C.fmt(s["p50"], 3), C.fmt(s["p90"], 3), C.fmt(s["p99"], 3), C.fmt(s["p99.9"], 3),
                    C.fmt(s["max"], 2), f"{C.fmt(s['over_1ms_pct'], 2)} %"] for c, s in summary["latency_ms"].items()]))


def print_summary(summary: dict, facts: dict, sims: list[dict]) -> None:
    """The tables (loops, message latency), CPU against the simulator, what was left behind."""
    runs = summary["runs"]
    print()
    print(f"realtime swarm, {facts['n_uav']} UAVs at {facts['control_rate_hz']:g} Hz, {facts['sim_time_s']:g} s of flight; "
          f"median of {runs} runs")
    print_loops(summary)
    print()
    print_latencies(summary)
    print()
    fc = summary["flight_cores"]
    print("CPU cores in flight: " + " ".join(f"{k}={v:.2f}" for k, v in fc.items() if v is not None)
          + f" total={C.fmt(summary['flight_cores_total'])}; background (other jobs) {C.fmt(summary['background_cores'])}")
    if sims:
        print(f"simulator on the same scenario: {summary['sim_x_real_time']:.1f}x real time, "
              f"{summary['sim_cores_for_real_time']:.3f} cores to keep up with real time -> swarm/sim CPU "
              f"{C.fmt(summary.get('cpu_ratio_swarm_over_sim'), 1)}; rms tracking error swarm {C.fmt(summary['rms_tracking_error_m'], 4)} m"
              f" vs simulator {C.fmt(summary['sim_rms_tracking_error_m'], 4)} m")
    print(f"runs where processes kept running after the plant exited (stopped by the bench): {summary['runs_hung_at_end']} of {runs}")
    print(f"cleanup: {summary['leftover_processes']} leftover processes, {summary['ports_left_bound']} ports left bound")


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    tmp, info = C.start_bench("zenswarm-rt-bench-")
    tmpdir = Path(tmp.name)
    path, facts = scenario(a, tmpdir)
    runs, sims = [], []
    try:
        for r in range(a.runs):
            if not a.no_sim:
                sims.append(C.run_sim_worker(path))
            C.quiet_wait(a.quiet_wait)
            run, m = fly(a, r, path, facts, tmpdir)
            runs.append(m)
            print_run(a, r, run, m)
    finally:
        C.cleanup_all()
    summary = summarise(runs, sims, facts)
    print_summary(summary, facts, sims)
    C.write_report(a.json, "swarm_realtime", info, scenario=facts, summary=summary, runs=runs, sim_runs=sims)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Speed of the distributed swarm in lockstep (``zenswarm up``), beside the in-process simulator.

Each run starts, as a child process,

    zenswarm up SCEN --out DIR --quiet --quiet-children --swarm <unique> --listen tcp/127.0.0.1:<free port>

(router inside the supervisor, plant, leader and one agent process per UAV, all on loopback)
and, interleaved with it, the in-process simulator (``zenswarm.compose.sim.simulate``, timed as in
bench/sim_speed.py) on the very same scenario file. Median of ``--runs``.

How the flight is timed: the plant is the lockstep clock, and its diagnostics in
``results.json`` (``diagnostics.plant``) give ``step_ms_mean`` (integrating a tick and publishing
the states) and ``wait_ms_mean`` (from the end of one tick to the start of the next: waiting for
the agents' commands). Flight wall time = n_ticks x (step_ms_mean + wait_ms_mean): from the
first tick to the last, without start-up (spawning ~N+3 Python processes, imports, Zenoh
sessions, liveliness handshakes) and shut-down. The whole command's wall time is reported too
(``up s``), and start-up + shut-down = up s - flight s. x real time = simulated s / flight s.
Ratio = swarm flight wall time / simulator wall time (how many times slower the swarm is).

While the swarm flies, the process tree is sampled every 0.25 s (/proc/<pid>/stat): the mean
CPU cores each role used in the middle 80 % of the flight tell where the CPU goes
(supervisor = router + result collector; plant; leader; all agents together).

Scenarios (default: example1 example2 gen3 gen8 gen16 gen32 gen64): the paper examples run their
full 70 s; generated ``gen<N>`` scenarios (``zenswarm scenario generate --n N --shape circle
--topology knn --k 3 --obstacles 2 --seed 1``) are shortened to ``--gen-time-limit`` (default
10 s of flight: per-tick cost is what is measured; the mission then "fails" for lack of time,
which is expected and not an error: a run counts when the plant finished every tick).

    python bench/swarm_lockstep.py                                  # defaults, 3 runs
    python bench/swarm_lockstep.py --runs 5 --scenarios example1 --json bench/results/lockstep.json
    python bench/swarm_lockstep.py --runs 3 --scenarios example1 gen16 --breakdown   # + where a tick goes

Every process a run starts is stopped at the end (or on Ctrl-C); leftovers and a port still
bound after a run are reported. Not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

DEFAULT_SCENARIOS = ["example1", "example2", "gen3", "gen8", "gen16", "gen32", "gen64"]
PARTS = ("plant publish spread", "hop plant->agent", "agent", "hop agent->plant", "plant integrate+publish")
# the per-run figures whose median over the finished runs the summary gives
MEDIANS = ("flight_wall_s", "up_wall_s", "startup_shutdown_s", "ms_per_tick", "plant_step_ms", "plant_wait_ms",
           "agent_step_ms_mean", "leader_step_ms", "flight_cores_total", "background_cores")
Scenarios = list[tuple[str, Path]]  # (label, TOML file)


# --------------------------------------------------------------------------- figures of one run
def _by_uav_tick(streams: dict[str, list], suffix: str, dt_ns: int, into: dict[tuple[int, int], int]) -> None:
    """Stamps of the messages on keys ``.../<uav>/<suffix>``, by (uav, tick); a message's tick is
    its sim time ``t`` in control periods of ``dt_ns``."""
    for key, lst in streams.items():
        if key.endswith("/" + suffix):
            i = int(key.split("/")[-2])
            for _, t, st in lst:
                into[(i, (t + dt_ns // 2) // dt_ns)] = st


def tick_breakdown(stamp_dir: Path, dt_ns: int) -> dict:
    """Follow each lockstep tick k along its critical path (bench/stamps): the plant publishes the
    states of tick k (first one at P0_k; the critical agent's at P_ik), agent i receives its state
    (R_ik), publishes cmd(k) (C_ik), the plant receives it (Q_ik; the critical agent is the one
    whose command arrives last), and the plant publishes the first state of tick k+1 (P0_k+1).
    tick = (P_ik - P0_k) + (R - P) + (C - R) + (Q - C) + (P0_k+1 - Q). Medians over ticks, ms."""
    stamps = C.load_stamps(stamp_dir)
    plant = next((x for x in stamps if x["role"] == "plant"), None)
    if plant is None:
        return {}
    Pi: dict = {}
    Q: dict = {}
    R: dict = {}
    Cm: dict = {}
    _by_uav_tick(plant["pub"], "state", dt_ns, Pi)
    _by_uav_tick(plant["rx"], "cmd", dt_ns, Q)
    for x in stamps:
        if x["role"].startswith("agent"):
            _by_uav_tick(x["rx"], "state", dt_ns, R)
            _by_uav_tick(x["pub"], "cmd", dt_ns, Cm)
    uavs = sorted({i for i, _ in Pi})
    ks = sorted({k for _, k in Pi})
    parts: dict[str, list[float]] = {p: [] for p in ("tick",) + PARTS}
    for k in ks[1:-1]:
        try:
            crit = max(uavs, key=lambda i: Q[(i, k)])
            p0 = min(Pi[(i, k)] for i in uavs)
            p1 = min(Pi[(i, k + 1)] for i in uavs)
            vals = (p1 - p0, Pi[(crit, k)] - p0, R[(crit, k)] - Pi[(crit, k)], Cm[(crit, k)] - R[(crit, k)],
                    Q[(crit, k)] - Cm[(crit, k)], p1 - Q[(crit, k)])
        except KeyError:
            continue
        for name, v in zip(("tick",) + PARTS, vals):
            parts[name].append(v / 1e6)
    out = {name: {"median": C.median(v), "mean": sum(v) / len(v) if v else None, "p90": C.pct(v, 90)} for name, v in parts.items()}
    out["ticks"] = len(parts["tick"])
    return out


def analyse(run: C.UpRun, facts: dict) -> dict:
    """Figures of one ``zenswarm up`` run."""
    res = run.results
    diag = res.get("diagnostics", {})
    plant = diag.get("plant", {})
    n_ticks = facts["n_ticks"]
    out: dict = {
        "returncode": run.returncode,
        "up_wall_s": run.wall_s,
        "finished": bool(plant.get("finished")),
        "mission_success": res.get("success"),
        "forced_ticks": sum(int(d.get("forced_ticks", 0) or 0) for d in diag.values()),
        "leftover_processes": len(run.leftovers),
        "port_free_after": run.port_free_after,
        "background_cores": run.cpu.get("background_cores"),
        "load1_start": run.cpu.get("load1_start"),
        "own_cpu_s": run.cpu.get("own_cpu_s"),
        "timed_out": run.timed_out,
        "hang_dumps": run.hang_dumps,
    }
    step, wait = plant.get("step_ms_mean"), plant.get("wait_ms_mean")
    if step is not None and wait is not None:
        fw = n_ticks * (step + wait) / 1e3
        out.update(plant_step_ms=step, plant_wait_ms=wait, ms_per_tick=step + wait, flight_wall_s=fw,
                   x_real_time=facts["sim_time_s"] / fw, startup_shutdown_s=run.wall_s - fw)
        agents = [d for name, d in diag.items() if name.startswith("agent:")]
        if agents:
            out["agent_step_ms_mean"] = sum(d.get("step_ms_mean", 0.0) for d in agents) / len(agents)
            out["agent_step_ms_max"] = max(d.get("step_ms_mean", 0.0) for d in agents)
        if "leader" in diag:
            out["leader_step_ms"] = diag["leader"].get("step_ms_mean")
        cores = C.flight_cores(run.procs, fw) if fw > 0.5 else None
        if cores is not None:
            out["flight_cores"] = cores
            out["flight_cores_total"] = sum(cores.values())
    return out


# --------------------------------------------------------------------------- the runs
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3, help="runs per scenario (median reported; default 3)")
    ap.add_argument("--scenarios", nargs="+", default=DEFAULT_SCENARIOS, metavar="S",
                    help="example1, example2, gen<N> or TOML paths (default: %(default)s)")
    ap.add_argument("--gen-time-limit", type=float, default=10.0, metavar="S",
                    help="flight length of the generated scenarios, s (default 10; 0 = the generator's own, 75-90 s)")
    ap.add_argument("--json", type=Path, metavar="FILE", help="write every run and the medians to FILE")
    ap.add_argument("--keep", type=Path, metavar="DIR", help="keep each run's results.json under DIR")
    ap.add_argument("--no-sim", action="store_true", help="skip the simulator baseline (no ratios)")
    ap.add_argument("--breakdown", action="store_true",
                    help="after the timed runs, one more run per scenario with bench/stamps instrumentation: where a "
                    "lockstep tick's time goes (messages hops vs computation); not part of the medians")
    ap.add_argument("--timeout", type=float, default=900.0, metavar="S", help="per-run limit of zenswarm up (default 900 s)")
    ap.add_argument("--quiet-wait", type=float, default=0.0, metavar="CORES",
                    help="before each run wait (up to 120 s) until other jobs use at most CORES cores (0 = don't wait)")
    return ap.parse_args(argv)


def fly(a: argparse.Namespace, path: Path, out: Path, tag: str, facts: dict,
        env: dict[str, str] | None = None) -> tuple[C.UpRun, dict]:
    """One ``zenswarm up`` of ``path`` into ``out`` and its figures; its results.json kept as
    ``--keep``/<out's name>.json if asked, ``out`` removed."""
    run = C.run_up(path, out, tag=tag, env=env, timeout_s=a.timeout)
    m = analyse(run, facts)
    if a.keep is not None and (out / "results.json").exists():
        a.keep.mkdir(parents=True, exist_ok=True)
        shutil.copy(out / "results.json", a.keep / f"{out.name}.json")
    shutil.rmtree(out, ignore_errors=True)
    return run, m


def print_run(a: argparse.Namespace, r: int, label: str, run: C.UpRun, m: dict, sim: dict[str, Any] | None) -> None:
    """The line of one timed run (or why it failed, with the py-spy dumps of a stuck swarm)."""
    if not m["finished"]:
        print(f"  run {r + 1}/{a.runs} {label}: the plant did not finish (exit {run.returncode});"
              f" output:\n{run.output_tail}", flush=True)
        C.print_hang_dumps(run.hang_dumps)
        return
    sim_txt = f"  sim {sim['wall_s']:.2f} s ({sim['x_real_time']:.1f}x)" if sim is not None else ""
    print(f"  run {r + 1}/{a.runs} {label:9s} flight {m['flight_wall_s']:7.2f} s = {m['x_real_time']:5.2f}x real time"
          f" ({m['ms_per_tick']:.2f} ms/tick: plant step {m['plant_step_ms']:.2f} + wait {m['plant_wait_ms']:.2f})"
          f"  up {m['up_wall_s']:.1f} s{sim_txt}  cpu cores in flight {m.get('flight_cores_total', 0):.2f}"
          f"  background {m['background_cores']:.2f}", flush=True)


def timed_runs(a: argparse.Namespace, scen: Scenarios, facts: dict, tmpdir: Path) -> tuple[dict, dict, int]:
    """``--runs`` rounds over the scenarios: the simulator (unless ``--no-sim``), then the swarm.
    Returns the swarm's figures and the simulator's by scenario, and how many runs did not finish."""
    swarm_runs: dict[str, list[dict]] = {label: [] for label, _ in scen}
    sim_runs: dict[str, list[dict]] = {label: [] for label, _ in scen}
    failures = 0
    for r in range(a.runs):
        for label, path in scen:
            sim = None
            if not a.no_sim:
                C.quiet_wait(a.quiet_wait)
                sim = C.run_sim_worker(path)
                sim_runs[label].append(sim)
            C.quiet_wait(a.quiet_wait)
            run, m = fly(a, path, tmpdir / f"{label}-run{r + 1}", f"ls{r}", facts[label])
            swarm_runs[label].append(m)
            if not m["finished"]:
                failures += 1
            print_run(a, r, label, run, m, sim)
    return swarm_runs, sim_runs, failures


def breakdown_runs(a: argparse.Namespace, scen: Scenarios, facts: dict, tmpdir: Path) -> dict[str, dict]:
    """``--breakdown``: one instrumented run per scenario, its figures and :func:`tick_breakdown`."""
    breakdowns: dict[str, dict] = {}
    for label, path in scen:
        C.quiet_wait(a.quiet_wait)
        sd = tmpdir / f"stamps-{label}"
        sd.mkdir()
        run = C.run_up(path, tmpdir / f"{label}-breakdown", tag="lsb", env=C.stamps_env(sd), timeout_s=a.timeout)
        dt_ns = round(1e9 / facts[label]["control_rate_hz"])
        breakdowns[label] = {"run": analyse(run, facts[label]), "parts": tick_breakdown(sd, dt_ns)}
        if not breakdowns[label]["parts"].get("ticks"):
            print(f"  WARNING {label}: no tick could be followed through the stamps; the wrappers in"
                  " bench/stamps/sitecustomize.py may no longer match zenswarm.process.runtime/zenswarm.bus.wire", flush=True)
        shutil.rmtree(sd, ignore_errors=True)
        shutil.rmtree(tmpdir / f"{label}-breakdown", ignore_errors=True)
    return breakdowns


# --------------------------------------------------------------------------- summary and report
def summarise(runs: list[dict], sims: list[dict], f: dict) -> dict:
    """Medians over the finished runs of one scenario (``{"runs_ok": 0}`` if none finished)."""
    ok = [m for m in runs if m["finished"]]
    if not ok:
        return {"runs_ok": 0}
    sm: dict = {"n_uav": f["n_uav"], "sim_time_s": f["sim_time_s"], "runs_ok": len(ok), "runs": len(runs)}
    for k in MEDIANS:
        sm[k] = C.median(m.get(k) for m in ok)
    roles = sorted({k for m in ok for k in m.get("flight_cores", {})})
    sm["flight_cores"] = {k: C.median(m.get("flight_cores", {}).get(k) for m in ok) for k in roles}
    sm["x_real_time"] = f["sim_time_s"] / sm["flight_wall_s"]
    sm["leftover_processes"] = sum(m["leftover_processes"] for m in runs)
    sm["port_left_bound"] = sum(not m["port_free_after"] for m in runs)
    sm["forced_ticks"] = sum(m["forced_ticks"] for m in ok)
    if sims:
        sw = C.median(s["wall_s"] for s in sims)
        sm["sim_wall_s"] = sw
        sm["sim_x_real_time"] = f["sim_time_s"] / sw
        sm["ratio_swarm_over_sim"] = sm["flight_wall_s"] / sw
    return sm


def summary_row(label: str, f: dict, sm: dict) -> list:
    """A scenario's row of the summary table."""
    if not sm["runs_ok"]:
        return [label, f["n_uav"], f"{f['sim_time_s']:g}"] + ["-"] * 11
    fc = sm["flight_cores"]
    return [
        label, f["n_uav"], f"{f['sim_time_s']:g}", sm["flight_wall_s"], f"{sm['x_real_time']:.2f}x",
        sm["ms_per_tick"], f"{sm['plant_step_ms']:.2f} / {sm['plant_wait_ms']:.2f}", sm["agent_step_ms_mean"],
        sm["startup_shutdown_s"],
        f"{sm['sim_x_real_time']:.1f}x" if "sim_x_real_time" in sm else "-",
        f"{sm['ratio_swarm_over_sim']:.1f}" if "ratio_swarm_over_sim" in sm else "-",
        " ".join(f"{k[:3]}={v:.2f}" for k, v in fc.items() if v is not None) or "-",
        sm["background_cores"], f"{sm['runs_ok']}/{sm['runs']}",
    ]


def print_summary(runs: int, facts: dict, summary: dict[str, dict]) -> None:
    print()
    print(f"lockstep swarm (zenswarm up) vs in-process simulator, median of {runs} runs")
    print(C.table(["scenario", "UAVs", "sim s", "flight wall s", "x real time", "ms/tick", "plant step/wait ms",
                   "agent step ms", "start+stop s", "simulator", "swarm/sim", "CPU cores in flight by role",
                   "background cores", "ok runs"], [summary_row(label, facts[label], sm) for label, sm in summary.items()]))


def print_breakdowns(facts: dict, breakdowns: dict[str, dict]) -> None:
    print()
    print("where a lockstep tick goes (one instrumented run per scenario; median over ticks, ms; see --help)")
    brows = []
    for label, b in breakdowns.items():
        p = b["parts"]
        if not p:
            continue
        brows.append([label, facts[label]["n_uav"], p["ticks"], p["tick"]["median"]] + [p[x]["median"] for x in PARTS]
                     + [b["run"].get("ms_per_tick")])
    print(C.table(["scenario", "UAVs", "ticks", "tick"] + list(PARTS) + ["ms/tick (diag, mean)"], brows))


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)
    tmp, info = C.start_bench("zenswarm-lockstep-bench-")
    tmpdir = Path(tmp.name)
    scen = [C.scenario_file(s, tmpdir, a.gen_time_limit or None) for s in a.scenarios]
    facts = {label: C.scenario_facts(p) for label, p in scen}
    breakdowns: dict[str, dict] = {}
    try:
        swarm_runs, sim_runs, failures = timed_runs(a, scen, facts, tmpdir)
        if a.breakdown:
            breakdowns = breakdown_runs(a, scen, facts, tmpdir)
    finally:
        C.cleanup_all()

    summary = {label: summarise(swarm_runs[label], sim_runs[label], facts[label]) for label, _ in scen}
    print_summary(a.runs, facts, summary)
    if breakdowns:
        print_breakdowns(facts, breakdowns)
    leftovers = sum(s.get("leftover_processes", 0) for s in summary.values())
    bound = sum(s.get("port_left_bound", 0) for s in summary.values())
    print(f"cleanup: {leftovers} leftover processes, {bound} ports left bound")
    C.write_report(a.json, "swarm_lockstep", info, scenarios=facts, summary=summary, swarm_runs=swarm_runs,
                   sim_runs=sim_runs, breakdown=breakdowns)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())

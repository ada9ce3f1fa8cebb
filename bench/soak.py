"""Realtime soak (issue 16): a long realtime flight of 8 UAVs at 100 Hz; worst loop jitter per
role, missed-deadline fraction, garbage-collector activity and every process's RSS over time.

    python bench/soak.py                       # the acceptance soak: 8 UAVs, 30 minutes (run on an idle machine)
    python bench/soak.py --minutes 2.5 --gc both --runs 2    # short, interleaved python/managed collector

Scenario: ``zenswarm scenario generate --n 8 --shape circle --topology knn --k 3 --obstacles 2
--seed 2 --time-limit <minutes * 60>``, flown by ``zenswarm up SCEN --realtime`` (the swarm
reaches its goal within a minute and hovers there: the loops run at full rate throughout; the
flight's verdict is printed: a soak that fails it is not a valid soak). ``--rt-priority P`` flies
with ``zenswarm up --rt-priority P`` (the flying processes under ``SCHED_FIFO``, after start-up;
:mod:`zenswarm.process.rtsched`; needs root or an RLIMIT_RTPRIO).

``--gc managed`` is the swarm as shipped (:class:`zenswarm.process.gcpolicy.GcPolicy`: frozen after
start-up, collected only at safe points); ``--gc python`` sets ``ZENSWARM_GC=python`` (CPython's
own automatic collector, as before issue 16); ``--gc both`` alternates them run by run, so both
see the same background load.

Figures:

* per role (plant, leader, agents, supervisor's children only; the agents pooled): loop ticks,
  missed deadlines (wake-ups more than one period late) as a fraction of the loop ticks, worst
  and mean |wake-up - due time| (each process's own ``jitter_*`` counters from its last
  diagnostics in ``results.json``; the loop's flight: from the plant's start, an agent's first
  state and the leader's first clock on, see :class:`zenswarm.process.clocks.LoopStats`), and the managed
  collector's collections, objects found unreachable and longest collection;
* memory: each process's RSS sampled every ``--sample`` s (``/proc/<pid>/status``); reported per
  role: RSS at 10 % of the flight and at its end, and the slope of a least-squares line through
  the samples of the last 80 % of the flight (MB per minute; flat memory is ~0). The agents are
  pooled: the largest slope of any agent.

Not a test: figures depend on the machine and its load (the background load is printed).
Every process a run starts is stopped at the end (or on Ctrl-C).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

SOAK_SEED = 2
"""Seed of the soak's generated layout: one whose mission the simulator flies to SUCCESS (seed 1's
layout makes the AAPF leader graze an obstacle, a failed verdict that says nothing of timing)."""


def rss_trend(hist: list, t0: float, t1: float) -> dict:
    """RSS (MB) at 10 % of [t0, t1] and at its end, and the slope (MB/min) over its last 80 %."""
    pts = [(t, r / 1024.0) for t, _, r in hist if t0 <= t <= t1 and r > 0]
    if len(pts) < 3:
        return {"rss_10pct_mb": None, "rss_end_mb": None, "slope_mb_per_min": None}
    span = t1 - t0
    early = [r for t, r in pts if t <= t0 + 0.1 * span] or [pts[0][1]]
    late = [(t, r) for t, r in pts if t >= t0 + 0.2 * span]
    slope = None
    if len(late) >= 3:
        mt = sum(t for t, _ in late) / len(late)
        mr = sum(r for _, r in late) / len(late)
        den = sum((t - mt) ** 2 for t, _ in late)
        slope = 60.0 * sum((t - mt) * (r - mr) for t, r in late) / den if den > 0 else None
    return {"rss_10pct_mb": early[-1], "rss_end_mb": pts[-1][1], "slope_mb_per_min": slope}


def analyse(run: C.UpRun) -> dict:
    diag = run.results.get("diagnostics", {})
    roles: dict[str, dict] = {}
    for name, d in diag.items():
        grp = "agents" if name.startswith("agent:") else name
        g = roles.setdefault(grp, {"processes": 0, "loop_ticks": 0, "missed": 0, "jitter_max_ms": 0.0, "jitter_mean_ms": [],
                                   "gc_collections": 0, "gc_collected": 0, "gc_max_ms": 0.0, "gc_managed": True})
        g["processes"] += 1
        if "loop_ticks" in d:
            g["loop_ticks"] += int(d["loop_ticks"])
            g["missed"] += int(d["missed_deadlines"])
            g["jitter_max_ms"] = max(g["jitter_max_ms"], float(d["jitter_max_ms"]))
            g["jitter_mean_ms"].append(float(d["jitter_mean_ms"]))
        g["skipped_ticks"] = g.get("skipped_ticks", 0) + int(d.get("skipped_ticks", 0))
        g["gc_collections"] += int(d.get("gc.collections", 0))
        g["gc_collected"] += int(d.get("gc.collected", 0))
        g["gc_max_ms"] = max(g["gc_max_ms"], float(d.get("gc.max_ms", 0.0)))
        g["gc_managed"] = g["gc_managed"] and d.get("gc.managed") == 1.0
    for g in roles.values():
        js = g.pop("jitter_mean_ms")
        g["jitter_mean_ms"] = sum(js) / len(js) if js else None
        g["missed_frac_pct"] = 100.0 * g["missed"] / g["loop_ticks"] if g["loop_ticks"] else None
    pl = run.procs.get("plant")
    mem: dict[str, dict] = {}
    if pl is not None and pl.hist:
        t0, t1 = pl.hist[0][0], pl.hist[-1][0]
        for role, ps in run.procs.items():
            grp = "agents" if role.startswith("agent:") else role
            tr = rss_trend(ps.hist, t0, t1)
            cur = mem.get(grp)
            if cur is None or (tr["slope_mb_per_min"] or 0.0) > (cur["slope_mb_per_min"] or 0.0):
                mem[grp] = tr
    tot_t = sum(g["loop_ticks"] for g in roles.values())
    tot_m = sum(g["missed"] for g in roles.values())
    return {"returncode": run.returncode, "wall_s": run.wall_s, "sim_time_s": run.results.get("sim_time_s"),
            "success": run.results.get("success"),
            "failures": [f"{f.get('cause')} at {f.get('t_s', 0.0):.2f} s" for f in run.results.get("failures", [])],
            "max_formation_error_m": run.results.get("max_formation_error_m"),
            "rt_priority": None, "background_cores": run.cpu.get("background_cores"),
            "loops": roles, "memory": mem, "missed_frac_pct_all": 100.0 * tot_m / tot_t if tot_t else None,
            "worst_jitter_ms": max((g["jitter_max_ms"] for g in roles.values() if g["loop_ticks"]), default=None),
            "leftovers": len(run.leftovers)}


def print_run(label: str, m: dict) -> None:
    print(f"\n{label}: exit {m['returncode']}, {C.fmt(m['sim_time_s'], 0)} s flown in {m['wall_s']:.0f} s wall,"
          f" background {C.fmt(m['background_cores'])} cores; missed {C.fmt(m['missed_frac_pct_all'], 4)} % of all loop ticks,"
          f" worst jitter {C.fmt(m['worst_jitter_ms'], 1)} ms")
    ag = m["loops"].get("agents", {})
    skipped = 100.0 * ag.get("skipped_ticks", 0) / ag["loop_ticks"] if ag.get("loop_ticks") else None
    print(f"verdict: {'SUCCESS' if m['success'] else 'FAILED: ' + '; '.join(m['failures'])}; max formation error"
          f" {C.fmt(m['max_formation_error_m'], 4)} m; agents skipped {C.fmt(skipped, 2)} % of the plant's states")
    rows = []
    for role in sorted(set(m["loops"]) | set(m["memory"])):
        g, r = m["loops"].get(role, {}), m["memory"].get(role, {})
        rows.append([role, g.get("processes", ""), g.get("loop_ticks", ""), f"{C.fmt(g.get('missed_frac_pct'), 4)} %",
                     C.fmt(g.get("jitter_max_ms"), 1), C.fmt(g.get("jitter_mean_ms"), 2),
                     f"{g.get('gc_collections', '')}/{g.get('gc_collected', '')}/{C.fmt(g.get('gc_max_ms'), 2)}",
                     C.fmt(r.get("rss_10pct_mb"), 1), C.fmt(r.get("rss_end_mb"), 1), C.fmt(r.get("slope_mb_per_min"), 3)])
    print(C.table(["role", "procs", "loop ticks", "missed", "jitter max ms", "jitter mean ms",
                   "gc collections/found/max ms", "RSS@10% MB", "RSS end MB", "RSS slope MB/min"], rows))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=8, help="UAVs (default 8)")
    ap.add_argument("--minutes", type=float, default=30.0, help="minutes of flight (default 30)")
    ap.add_argument("--gc", choices=("managed", "python", "both"), default="managed",
                    help="collector of the swarm processes (both: alternate run by run, python first)")
    ap.add_argument("--runs", type=int, default=1, help="runs (with --gc both: pairs; default 1)")
    ap.add_argument("--rt-priority", type=int, default=None, metavar="P",
                    help="fly with `zenswarm up --rt-priority P` (SCHED_FIFO for the flying processes; needs root)")
    ap.add_argument("--sample", type=float, default=1.0, metavar="S", help="RSS sampling period, s (default 1)")
    # (no end-of-flight hang detection: run_up's, which takes a plant unseen for 1 s for gone, misfires at
    # this sampling period; a hung swarm is stopped at the time limit + 180 s)
    ap.add_argument("--json", type=Path, metavar="FILE", help="write every run to FILE")
    a = ap.parse_args(argv)
    tmp, info = C.start_bench("zenswarm-soak-")
    tmpdir = Path(tmp.name)
    flight = 60.0 * a.minutes
    path = C.generated_scenario(a.n, tmpdir, flight, seed=SOAK_SEED)
    facts = C.scenario_facts(path)
    print(f"scenario gen{a.n}: {facts['n_uav']} UAVs, {facts['sim_time_s']:g} s at {facts['control_rate_hz']:g} Hz, realtime")
    modes = ["python", "managed"] if a.gc == "both" else [a.gc]
    rt = [] if a.rt_priority is None else ["--rt-priority", str(a.rt_priority)]
    runs = []
    try:
        for r in range(a.runs):
            for mode in modes:
                env = C.bench_env()
                env["ZENSWARM_GC"] = mode
                run = C.run_up(path, tmpdir / f"run{r}{mode}", tag=f"soak{r}{mode[0]}", extra=["--realtime", *rt], env=env,
                               timeout_s=flight + 180.0, sample_period_s=a.sample)
                m = analyse(run)
                m["gc"] = mode
                m["rt_priority"] = a.rt_priority
                runs.append(m)
                print_run(f"run {r + 1} gc={mode}", m)
    finally:
        C.cleanup_all()
    C.write_report(a.json, "soak", info, scenario=facts, runs=runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A flight's results as the simulator and the swarm's supervisor both assemble, write and say
them: the fields of ``results.json`` (:func:`flight_results`: the verdict's, the runner's facts, the
effective graph of a run with a radio model, what stopped the run), the files written
(:func:`write_outputs`: ``results.json`` and ``timeseries.npz``), and the lines said at the end
(:func:`closing_lines`: what the bus showed, the summary line, where the files are).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from zenswarm.errors import PluginFailure
from zenswarm.judge.metrics import TimeSeries, add_failure, add_plugin_failures, compute_results
from zenswarm.link import FaultPlan, effective_graph

__all__ = [
    "MAX_SUMMARY_FAILURES", "add_stop", "closing_lines", "failure_text", "flight_results", "radio_results", "summary_line",
    "write_outputs",
]  # fmt: skip

MAX_SUMMARY_FAILURES = 6
"""Failures named in the summary line; results.json lists them all."""


def radio_results(scenario: Any, faults: FaultPlan | None, series: TimeSeries) -> dict[str, Any]:
    """``effective_graph`` of a run with a radio model, a capacity queue or a link trace
    (:func:`zenswarm.link.swarm.effective_graph`; {} without any): the same figures for ``sim`` and
    ``up``, computed from the recorded series (its first row's tick from its time: a realtime
    series starts at the first tick every process had a value). ``scenario``: a
    :class:`zenswarm.scenario.config.Scenario`."""
    if faults is None or not (faults.radio_active or faults.queues is not None or faults.trace is not None):
        return {}
    nbrs = [scenario.neighbours(i) for i in range(scenario.n)]
    pinned = [float(b) > 0 for b in scenario.graph.pinning]
    dt = scenario.timing.dt
    first = int(round(float(series.t[0]) / dt)) if len(series.t) else 0
    graph = effective_graph(faults, nbrs, pinned, series.q, series.q0, dt, first)
    return {"effective_graph": graph}


def flight_results(
    ts: TimeSeries,
    scenario: Any,
    *,
    wall_time_s: float | None,
    full_time: bool,
    faults: FaultPlan | None,
    facts: dict[str, Any],
    t_s: float | None = None,
    died: tuple[str, str] | None = None,
    interrupted: str | None = None,
    plugin_failures: Sequence[PluginFailure] = (),
) -> dict[str, Any]:
    """The results of a flight judged on ``ts`` (its ticks to judge), the simulator's and the
    supervisor's: the verdict's fields (:func:`zenswarm.judge.metrics.compute_results`; judged up
    to its decided end unless ``full_time``), the runner's ``facts`` (the simulator's link counters,
    the supervisor's processes and the collector's :meth:`~zenswarm.process.collector.Collector.facts`),
    the effective graph (:func:`radio_results`), and what stopped the run (:func:`add_stop`; ``t_s``
    default: the judged end's sim time)."""
    res = compute_results(ts, scenario, wall_time_s=wall_time_s, early_end=not full_time)
    res.update(facts)
    res.update(radio_results(scenario, faults, ts))
    t_stop = res["sim_time_s"] if t_s is None else t_s
    add_stop(res, scenario.timing.dt, t_s=t_stop, died=died, interrupted=interrupted, plugin_failures=plugin_failures)
    return res


def add_stop(
    res: dict[str, Any],
    dt: float,
    *,
    t_s: float | None = None,
    died: tuple[str, str] | None = None,
    interrupted: str | None = None,
    plugin_failures: Sequence[PluginFailure] = (),
) -> None:
    """What stopped a run that the states cannot show, as its failures (in place of the
    ``incomplete`` or ``no_data`` it explains; the run is then not a success): a process that died,
    (name, how) (``process_died``), a signal (``interrupted``, why: ``Ctrl-C``, ``received SIGTERM``),
    both at sim time ``t_s``; the plug-ins that failed (``plugin_error`` each, at tick x ``dt`` s)."""
    if died is not None:
        add_failure(res, "process_died", f"process {died[0]} died ({died[1]})", t_s, process=died[0])
    if interrupted is not None:
        add_failure(res, "interrupted", f"interrupted ({interrupted}) at sim time {t_s:.2f} s", t_s)
    if plugin_failures:
        add_plugin_failures(res, plugin_failures, dt)


def write_outputs(out: Path, series: TimeSeries, results: dict[str, Any]) -> None:
    """Write ``results.json`` and ``timeseries.npz`` into ``out`` (created if needed); a value JSON
    has no type for is written as its text."""
    out.mkdir(parents=True, exist_ok=True)
    series.save(str(out / "timeseries.npz"))
    (out / "results.json").write_text(json.dumps(results, indent=2, sort_keys=True, default=str) + "\n")


def _fmt(x: object, unit: str = " m") -> str:
    """A figure to 4 significant digits (``0.2513 m``, ``1.43e-05 m``); ``n/a`` for None."""
    return "n/a" if x is None else f"{x:.4g}{unit}"


def failure_text(f: dict[str, Any]) -> str:
    """``collision_ground uav 2 at 3.41 s`` for one failure of a results dict."""
    uavs = f.get("uavs") or []
    who = f" uav {uavs[0]}" if len(uavs) == 1 else (f" uavs {','.join(map(str, uavs))}" if uavs else "")
    when = f" at {f['t_s']:.2f} s" if f.get("t_s") is not None else ""
    if f["cause"] == "plugin_error":  # which plug-in, which call, what was wrong
        who = who or f" {f.get('process', '?')}"
        return f"{f['cause']}{who}{when} ({f.get('kind')} {f.get('plugin')!r} {f.get('call')}(): {_tail(f)})"
    return f"{f['cause']}{who}{when}"


def _tail(f: dict[str, Any]) -> str:
    """The part of a plug-in failure's detail after its preamble (the exception or the bad field)."""
    detail = str(f.get("detail", ""))
    return detail.split("(): ", 1)[1] if "(): " in detail else detail


def summary_line(r: dict[str, Any]) -> str:
    """One line: the verdict with its named failures, the goal time and the headline figures."""
    fails = r.get("failures") or []
    if r["success"]:
        verdict = "SUCCESS"
    else:
        named = "; ".join(failure_text(f) for f in fails[:MAX_SUMMARY_FAILURES])
        more = f"; (+{len(fails) - MAX_SUMMARY_FAILURES} more in results.json)" if len(fails) > MAX_SUMMARY_FAILURES else ""
        verdict = f"FAILED: {named}{more}" if fails else "FAILED"
    ttg = r.get("time_to_goal_s")
    wall = r.get("wall_time_s")
    goal = f"reached at {ttg:.2f} s" if ttg is not None else "NOT reached"
    return (
        f"{r['scenario']}: {verdict}\n"
        f"  goal {goal}  "
        f"max formation error {_fmt(r.get('max_formation_error_m'))} "
        f"(vehicles; generator {_fmt(r.get('max_generator_formation_error_m'))})  "
        f"final slot error {_fmt(r.get('max_final_slot_error_m'))}  rms tracking {_fmt(r.get('rms_tracking_error_m'))}\n"
        f"  min margin to obstacles {_fmt(r.get('min_obstacle_margin_m'))}  between UAVs {_fmt(r.get('min_inter_uav_margin_m'))}  "
        f"(vehicle radius {_fmt(r.get('vehicle_radius_m'))})  sim {r.get('sim_time_s', 0.0):.2f} s"
        + (f"  wall {wall:.2f} s" if wall is not None else "")
    )


def _bus_lines(r: dict[str, Any]) -> list[str]:
    """What a swarm's results hold beside the verdict that the console says too: the samples
    ignored as foreign (``foreign_samples``) and every UAV held by a failsafe (``failsafe``); none
    for the simulator's."""
    lines = []
    foreign = r.get("foreign_samples") or {}
    if foreign:
        lines.append(f"ignored {sum(foreign.values())} messages from sessions that are not their key's process "
                     f"(on {len(foreign)} keys; results.json: foreign_samples)")
    for e in r.get("failsafe") or ():
        until = f"{e['to_s']:.2f} s" if e["to_s"] is not None else "the end"
        if {"link_lost", "lost"} & set(e["modes"]):  # the bridge lost the vehicle: its own failsafe flies it
            lines.append(f"failsafe: UAV {e['uav']} {' then '.join(e['modes'])} from sim time {e['from_s']:.2f} s to {until}: "
                         "the bridge lost its link; the vehicle's own failsafe flew it")  # fmt: skip
            continue
        lines.append(f"failsafe: UAV {e['uav']} flown by the plant ({' then '.join(e['modes'])}) from sim time "
                     f"{e['from_s']:.2f} s to {until}: agent:{e['uav']}'s commands were stale")
    return lines


def closing_lines(r: dict[str, Any], out: Path) -> list[str]:
    """The lines said once the results are written into ``out``: what the bus showed (swarm),
    the summary line (:func:`summary_line`), where the files are."""
    return [*_bus_lines(r), *summary_line(r).split("\n"), f"wrote {out / 'results.json'} and {out / 'timeseries.npz'}"]

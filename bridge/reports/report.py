"""``zenswarm report``: the flight report, from an MCAP recording alone (or a simulator time series).

This module is the report's driver and its command line: which figures a report has, and the
``results.json`` of a recorded flight. From a recording (``zenswarm report FILE.mcap --out DIR``)
the scenario comes from the file's ``zenswarm`` metadata record, the flight's
:class:`zenswarm.judge.metrics.TimeSeries` is rebuilt from the recorded samples by the supervisor's
:class:`zenswarm.process.collector.Collector` (the same code that builds it live, so a lockstep
recording gives the run's own series; :mod:`zenswarm.bridge.reports.flight`), and the results by
:func:`zenswarm.judge.metrics.compute_results` (so ``results.json`` matches the run's own on every field
of :data:`zenswarm.judge.metrics.FLIGHT_FIELDS`; ``wall_time_s`` is null, the recording does not know the
run's compute time). Figures (PNG, matplotlib Agg, no display needed; drawn by
:mod:`zenswarm.bridge.reports.figures`), after the paper's Figs 4-8:

``trajectories_3d.png``  3D trajectories of the virtual leader and the UAVs, obstacles as cylinders
                         with hemispherical caps, start/goal markers (Fig. 4); beside it a top view
                         with formation snapshots and the leader's enclosing circle r_f.
``formation_errors.png`` generator formation errors q*_i - q0 - h_i and v*_i - v0, per axis and UAV,
                         eqs (16)-(17) (Figs 5 and 7): the paper's analysis.
``formation_errors_vehicles.png`` the vehicles' formation errors q_i - q0 - h_i and v_i - v0: where
                         the UAVs really are (the verdict's ``max_formation_error_m``).
``tracking_errors.png``  tracking errors q*_i - q_i and v*_i - v_i, eq. (28) (Figs 6 and 8).
``clearance.png``        each UAV's distance to the nearest obstacle surface (capped cylinder) against
                         the vehicle radius (contact), and the leader sphere's clearance d_obs(q0)
                         against the threshold d0.
``commands.png``         per UAV, what the vehicle was asked and did: the commanded collective
                         thrust against the thrust its measured motion implies, m ||dv/dt + g e_z||
                         (drag and disturbances included), and the commanded roll, pitch, yaw
                         (``rpy_cmd``) against the measured attitude (``rpy``).
``plant.png``            flights whose plant model records internal signals only
                         (:attr:`zenswarm.plant.api.PlantModel.records`, ``plant.<name>`` in the
                         series, e.g. the built-in's rotor thrusts and torque): one row per signal,
                         its components over time for the first UAVs, with its unit.
``links.png``            messages per key in the recording (and how many the report's decoder
                         rejected), and the drop/reject/timeout counters each process reported in
                         its last ``diag`` message (recordings only).
``effective_graph.png``  runs with a radio model, a capacity queue or a link trace only: the
                         effective communication graph over time (connected components per tick,
                         where the leader-rooted spanning tree of Lemma 1 held, each ref/leader
                         link up/down per tick as a raster), each link's delivery ratio and the
                         histogram of the delivered messages' delays; recomputed from the fault
                         plan (scenario ``[faults]`` + the recorded fault flags) and the series,
                         as ``results.json``'s ``effective_graph``.

``zenswarm report --series RUN/timeseries.npz --scenario SCENARIO.toml --out DIR`` plots the
output of ``zenswarm sim`` (or of ``zenswarm up``) the same way, without ``links.png`` and without
rewriting the run's ``results.json``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from zenswarm.bridge.args import FIGURE_FORMATS, figure_formats
from zenswarm.bridge.reports.figures import (
    COMMAND_UAVS,
    GOAL_MS,
    PLANT_SIGNALS,
    PLANT_UAVS,
    VIEW_3D,
    hidden_behind_obstacles,
    leader_d_obs,
    plot_clearance,
    plot_commands,
    plot_effective_graph,
    plot_formation_errors,
    plot_links,
    plot_plant_records,
    plot_tracking_errors,
    plot_trajectories,
    plot_vehicle_formation_errors,
    uav_clearance,
)
from zenswarm.bridge.reports.flight import (
    METADATA_NAME,
    Flight,
    RecordedMessage,
    Recording,
    flight_from_recording,
    load_recording,
    recorded_fault_plan,
)
from zenswarm.errors import RecordingError, ScenarioError, ZenswarmError, run_command
from zenswarm.judge.metrics import TimeSeries, compute_results
from zenswarm.link import FaultPlan, plan_for
from zenswarm.process.paths import check_output_dir
from zenswarm.scenario.config import Scenario, load_scenario

__all__ = [
    "FIGURES",
    "report_recording",
    "report_from_series",
    "results_from_flight",
    "network_plan",
    "add_parsers",
    "main",
    # the flight loaded from a recording (zenswarm.bridge.reports.flight), importable from here as before
    "METADATA_NAME",
    "RecordedMessage",
    "Recording",
    "Flight",
    "load_recording",
    "flight_from_recording",
    "recorded_fault_plan",
    # the figures (zenswarm.bridge.reports.figures), importable from here as before
    "VIEW_3D",
    "GOAL_MS",
    "COMMAND_UAVS",
    "PLANT_UAVS",
    "PLANT_SIGNALS",
    "hidden_behind_obstacles",
    "leader_d_obs",
    "uav_clearance",
    "plot_trajectories",
    "plot_formation_errors",
    "plot_vehicle_formation_errors",
    "plot_tracking_errors",
    "plot_clearance",
    "plot_commands",
    "plot_plant_records",
    "plot_links",
    "plot_effective_graph",
]

FIGURES = (
    "trajectories_3d.png",
    "formation_errors.png",
    "formation_errors_vehicles.png",
    "tracking_errors.png",
    "clearance.png",
    "commands.png",
    "plant.png",
    "links.png",
)
"""Figures of a report from a recording (``links.png`` only from a recording, ``plant.png`` only
when the plant model records signals: the built-in ``quadrotor`` and ``rotorpy`` do)."""


# =========================================================================== reports


def network_plan(sc: Scenario, faults: FaultPlan | None) -> FaultPlan | None:
    """``faults`` if the run has a radio model, a capacity queue or a trace (the faults that make
    the effective graph worth a figure), else None."""
    if faults is None:
        return None
    return faults if (faults.radio_active or faults.queues is not None or faults.trace is not None) else None


def _written(first: Path, formats: Sequence[str]) -> list[Path]:
    """The files a figure was written as: ``first`` with each suffix of ``formats``."""
    return [first.with_suffix("." + f) for f in formats]


def report_from_series(
    ts: TimeSeries, scenario: Scenario, out_dir: str | Path, faults: FaultPlan | None = None, formats: Sequence[str] = ("png",)
) -> list[Path]:
    """Write the figures that need only the time series (trajectories, formation and tracking
    errors, clearance) into ``out_dir`` (created), each in every format of ``formats``
    (:data:`zenswarm.bridge.args.FIGURE_FORMATS`); returns their paths. With ``faults`` (the run's link-fault plan) that has a
    radio model, a capacity queue or a trace, also ``effective_graph.png``
    (:func:`~zenswarm.bridge.reports.figures.plot_effective_graph`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if len(ts.t) == 0:
        raise ZenswarmError("the time series is empty: nothing to plot")
    fm = tuple(formats) or ("png",)
    firsts = [
        plot_trajectories(ts, scenario, out / "trajectories_3d.png", fm),
        plot_formation_errors(ts, scenario, out / "formation_errors.png", fm),
        plot_vehicle_formation_errors(ts, scenario, out / "formation_errors_vehicles.png", fm),
        plot_tracking_errors(ts, scenario, out / "tracking_errors.png", fm),
        plot_clearance(ts, scenario, out / "clearance.png", fm),
        plot_commands(ts, scenario, out / "commands.png", fm),
    ]
    if ts.plant:
        firsts.append(plot_plant_records(ts, scenario, out / "plant.png", fm))
    net = network_plan(scenario, faults)
    if net is not None:
        firsts.append(plot_effective_graph(ts, scenario, net, out / "effective_graph.png", fm))
    return [f for first in firsts for f in _written(first, fm)]


def results_from_flight(fl: Flight, full_time: bool = False) -> dict[str, Any]:
    """results.json of a recorded flight: compute_results plus the bus statistics. The flight is
    judged up to the tick its outcome was decided (as the run ended there) unless ``full_time``."""
    res = compute_results(fl.series, fl.scenario, wall_time_s=None, early_end=not full_time)
    res["mode"] = fl.mode
    res["swarm"] = fl.swarm
    res["diagnostics"] = fl.diagnostics
    res["decoder_rejects"] = fl.decoder_counters
    res["message_counts"] = dict(sorted(fl.message_counts.items()))
    return res


def report_recording(
    path: str | Path,
    out_dir: str | Path,
    full_time: bool = False,
    warn: Callable[[str], None] | None = None,
    formats: Sequence[str] = ("png",),
) -> list[Path]:
    """The full report of a recording: every figure of :data:`FIGURES` and ``results.json``, and
    ``effective_graph.png`` when the run had a radio model, a capacity queue or a trace (the
    scenario's ``[faults]`` and the fault flags in the recording's metadata).

    full_time: judge every recorded tick, as ``--full-time`` runs do. formats: the figures'
    formats (:data:`zenswarm.bridge.args.FIGURE_FORMATS`), each figure once per format. warn: called with each
    thing the reader must know (:attr:`~zenswarm.bridge.reports.flight.Recording.notes`): a truncated or damaged recording (then
    also which sim time the report covers), payloads not recorded."""
    rec = load_recording(path)
    fl = flight_from_recording(rec)
    if warn is not None:
        for note in rec.notes:
            warn(note)
        if rec.truncated:
            sc = rec.scenario
            warn(f"the report covers sim time 0 to {len(fl.series.t) * sc.timing.dt:.2f} s of the {sc.timing.time_limit_s:g} s time limit")
    out = Path(out_dir)
    fm = tuple(formats) or ("png",)
    files = report_from_series(fl.series, fl.scenario, out, faults=recorded_fault_plan(rec), formats=fm)
    files += _written(plot_links(fl, out / "links.png", fm), fm)
    res = results_from_flight(fl, full_time=full_time)
    res["recording"] = str(rec.path)
    res["recording_truncated"] = rec.truncated
    rp = out / "results.json"
    rp.write_text(json.dumps(res, indent=2, sort_keys=True, default=str) + "\n")
    files.append(rp)
    return files


# =========================================================================== CLI


def _run_report(args: argparse.Namespace) -> int:
    if (args.recording is None) == (args.series is None):
        args._parser.error("give either a recording FILE or --series NPZ --scenario TOML")
    check_output_dir(args.out, "--out")
    if args.series is not None:
        if args.scenario is None:
            args._parser.error("--series needs --scenario (the scenario the series was flown with)")
        sc = load_scenario(args.scenario)
        try:
            ts = TimeSeries.load(str(args.series))
        except FileNotFoundError:
            raise RecordingError(f"{args.series}: no such time series file") from None
        except (OSError, ValueError, KeyError) as e:
            raise RecordingError(f"{args.series}: not a zenswarm timeseries.npz ({e})") from None
        if ts.q.ndim != 3 or ts.q.shape[1] != sc.n:
            got = ts.q.shape[1] if ts.q.ndim == 3 else "?"
            raise ScenarioError("--scenario", f"{args.scenario} has {sc.n} UAVs but {args.series} has {got}")
        files = report_from_series(ts, sc, args.out, faults=plan_for(sc), formats=args.format)
    else:
        import sys

        def warn(text: str) -> None:
            print(f"report: warning: {args.recording}: {text}", file=sys.stderr, flush=True)

        files = report_recording(args.recording, args.out, full_time=args.full_time, warn=warn, formats=args.format)
    for f in files:
        print(f)
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``zenswarm report`` on the CLI's subparsers."""
    p = sub.add_parser(
        "report",
        help="flight report (figures like the paper's Figs 4-8, results.json) from a recording",
        description=(
            "Write the flight report of a recording into OUT: trajectories_3d.png, "
            "formation_errors.png (generator), formation_errors_vehicles.png, tracking_errors.png, clearance.png, "
            "commands.png (commanded against achieved thrust and attitude), "
            "plant.png (what the plant model recorded, e.g. rotor thrusts), "
            "links.png, effective_graph.png (runs with a radio model, capacity queue or link trace) and results.json "
            "(the same fields as `zenswarm sim`). Works from the MCAP file alone; a "
            "truncated or damaged recording is reported from what can be read, with a warning on stderr (also for "
            "payloads the recorder did not record). With --series, plot a `zenswarm sim` time series instead (no "
            "links.png, no results.json)."
        ),
    )
    p.add_argument("recording", nargs="?", type=Path, metavar="FILE", help="MCAP recording (zenswarm up --record / zenswarm record)")
    p.add_argument("--out", type=Path, required=True, help="output directory (created)")
    p.add_argument("--series", type=Path, metavar="NPZ", help="a timeseries.npz written by zenswarm sim or zenswarm up")
    p.add_argument("--scenario", type=Path, metavar="TOML", help="with --series: the scenario file of that run")
    p.add_argument(
        "--format",
        type=figure_formats,
        default=("png",),
        metavar="FMT[,FMT...]",
        help=f"the figures' formats, comma-separated, of {', '.join(FIGURE_FORMATS)} (default png; e.g. png,svg,pdf: each "
        "figure in each; SVG and PDF are vector, for papers)",
    )
    p.add_argument(
        "--full-time",
        action="store_true",
        help="judge every recorded tick (for runs flown with --full-time); by default the flight is judged up to "
        "the tick its outcome was decided, as the run itself ended there",
    )
    p.set_defaults(func=_run_report, _parser=p)


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry (``python -m zenswarm.bridge.reports.report ...``): the ``report`` command only
    (``zenswarm`` wires ``report`` and ``export`` through :mod:`zenswarm.bridge.cli`; this module
    does not import :mod:`zenswarm.bridge.views.foxglove`, which reads flights with
    :mod:`zenswarm.bridge.reports.flight`)."""

    parser = argparse.ArgumentParser(prog="zenswarm")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parsers(sub)
    args = parser.parse_args(argv)
    return run_command(lambda: args.func(args))


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

"""The front door of ``zenswarm up``: its parser (``--help``), the flags as one typed
:class:`zenswarm.process.settings.FlightSettings`, checked against the scenario
(:mod:`zenswarm.compose.flight_checks`: bad input exits 2 before anything starts), handed to a
:class:`Supervisor` (the whole swarm) or to one role (``--only``). ``zenswarm.api.fly``'s supervisor enters at
:func:`run_settings_argv` with the settings already typed.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path
from typing import Any

import msgspec

from zenswarm.bridge.args import (
    add_flight_args,
    add_full_time_arg,
    add_rt_priority_arg,
    figure_formats,
    link_faults,
    positive_float,
    scenario_of,
)
from zenswarm.bridge.views.live import FOXGLOVE_DEFAULT, LIVE_HELP, LiveTarget, live_target
from zenswarm.compose.flight_checks import check_up_args
from zenswarm.compose.flight_checks import parse_kill as _parse_kill
from zenswarm.compose.placement import PLACEMENT_HELP
from zenswarm.compose.supervisor import Supervisor
from zenswarm.errors import ScenarioError
from zenswarm.process.runtime import gc_policy
from zenswarm.process.settings import DEFAULT_EXTERNAL_TIMEOUT_S, FlightSettings, LiveView, decode_flight, read_settings

__all__ = ["add_parsers", "UpOptions", "flight_settings", "up_options", "check_up_args", "fly", "run_settings_argv"]

UpOptions = FlightSettings
"""What ``zenswarm up`` was asked for, typed: :class:`zenswarm.process.settings.FlightSettings`
(its older name)."""


def flight_settings(args: argparse.Namespace) -> tuple[FlightSettings, dict[str, Any]]:
    """The flags of ``zenswarm up`` (:func:`add_parsers`) as :class:`FlightSettings`, its scenario
    parsed once (``--set``, ``--duration``, the plug-in flags applied and checked: a ScenarioError
    naming the flag or field, exit 2), and the overrides given (to write the effective scenario
    for the processes that take a file)."""
    sc, overrides = scenario_of(args)
    live: LiveTarget | None = args.live
    settings = FlightSettings(
        scenario=sc,
        scenario_file=args.scenario,
        swarm=args.swarm,
        out=args.out,
        realtime=args.realtime,
        plant=args.plant,
        mavlink_base_port=args.mavlink_base_port,
        crazyflie_base_port=args.crazyflie_base_port,
        external=tuple(args.external or ()),
        external_timeout=args.external_timeout,
        record=args.record,
        report=args.report,
        report_format=args.report_format,
        listen=tuple(args.listen or ()),
        connect=tuple(args.connect or ()),
        router_connect=tuple(args.router_connect or ()),
        secure=args.secure,
        tls=args.tls,
        keys=args.keys,
        insecure=args.insecure,
        only=args.only,
        lockstep_timeout=args.lockstep_timeout,
        kill=tuple(args.kill or ()),
        restart=args.restart,
        stop_at_goal=args.stop_at_goal,
        full_time=args.full_time,
        progress_every=args.progress_every,
        quiet=args.quiet,
        quiet_children=args.quiet_children,
        faults=link_faults(args),
        controller=args.controller,
        planner=args.planner,
        plant_model=args.plant_model,
        live=None if live is None else LiveView(live.viewer, live.port),
        rt_priority=args.rt_priority,
        router_lost_timeout=args.router_lost_timeout,
        scheduler=args.scheduler,
        placement=tuple(args.placement or ()),
    )
    return settings, overrides


def up_options(args: argparse.Namespace) -> FlightSettings:
    """The flags of ``zenswarm up`` as :class:`FlightSettings` (:func:`flight_settings`)."""
    return flight_settings(args)[0]


def _run_up(ns: argparse.Namespace) -> int:
    args, overrides = flight_settings(ns)  # --set, --duration, a bad plug-in name or parameter: exit 2 now
    args.faults.plan(args.scenario)  # bad flags: exit 2 now
    check_up_args(args, args.scenario)
    if overrides and not args.only:  # the scenario flown, as a file: OUT/scenario.toml (a recording names it)
        args = msgspec.structs.replace(args, scenario_file=_write_effective(args, overrides))
    return fly(args)


def fly(args: FlightSettings) -> int:
    """Fly these settings (checked: :func:`~zenswarm.compose.flight_checks.check_up_args`): the whole swarm under a
    :class:`Supervisor`, or one role with ``--only``. The exit status."""
    sc = args.scenario
    gc_policy()  # a bad ZENSWARM_GC: exit 2 now
    if args.only:
        if args.live is not None:
            raise ScenarioError("--live", "not with --only: the live view runs beside the supervisor of the whole swarm")
        return _run_only(args)
    sup = Supervisor(args, sc)
    view: Any = None
    if args.live is not None:  # bound now: a port in use is exit 2 before any process starts
        from zenswarm.bridge.views.live import open_view

        view = open_view(LiveTarget(args.live.viewer, args.live.port), sc, args.swarm)
        sup.taps.append(view)  # fed from the supervisor's bus loop
        sup.say(view.how_to_open())
    if args.record is not None and args.report:  # from the recording, once the results are written
        from zenswarm.compose.end_report import report_hook

        sup.on_end.append(report_hook(args.report_format, full_time=args.full_time))
    try:
        sup.t_start = time.monotonic()
        rc = sup.run()
        if view is not None and view.viewer == "rerun" and sys.stdin is not None and sys.stdin.isatty():
            # Rerun's server holds the whole flight: a browser opened now still gets all of it
            sup.say(f"flight over; Rerun keeps serving it on {view.url} until you press Enter (or Ctrl-C)")
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, signal.default_int_handler)  # raise KeyboardInterrupt here, not set the flight's stop flag
            try:
                input()
            except (EOFError, KeyboardInterrupt):
                pass
        return rc
    finally:
        if view is not None:
            view.close()


def run_settings_argv(argv: list[str]) -> int:
    """``zenswarm up --settings FILE --swarm NAME``: fly the :class:`FlightSettings` in FILE (``-``:
    standard input), as :func:`zenswarm.api.fly` starts its supervisor (:mod:`zenswarm.compose.launch`).
    Not for users (``zenswarm up --help`` does not list it): the settings are checked again here,
    and ``--swarm`` (the name the process table shows) must be theirs."""
    p = argparse.ArgumentParser(prog="zenswarm up", description="fly a flight's typed settings (zenswarm.api.fly's supervisor)")
    p.add_argument("--settings", required=True, metavar="FILE", help="msgpack of the FlightSettings; - for standard input")
    p.add_argument("--swarm", required=True)
    ns = p.parse_args(argv)
    args = decode_flight(read_settings(ns.settings))
    if args.swarm != ns.swarm:
        raise ScenarioError("--swarm", f"{ns.swarm!r}, but the settings fly swarm {args.swarm!r}")
    args.faults.plan(args.scenario)
    check_up_args(args, args.scenario)
    return fly(args)


def _write_effective(args: FlightSettings, overrides: dict[str, Any]) -> Path:
    """The scenario file with the overrides applied (``--set``, ``--duration``), written as
    OUT/scenario.toml: the scenario flown, kept with the run's outputs and named by a recording
    as its source (every process gets the scenario itself, :mod:`zenswarm.compose.commands`)."""
    from zenswarm.scenario.config import document_trace_beside, read_document
    from zenswarm.scenario.generate import to_toml
    from zenswarm.scenario.overrides import apply

    src = Path(args.scenario_file)
    doc = document_trace_beside(apply(read_document(src), overrides), src)  # a relative trace: beside the original file
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "scenario.toml"
    path.write_text(to_toml(doc))
    return path


def _run_only(args: FlightSettings) -> int:
    """``--only ROLE``: run one role of a swarm in this process, against a remote router, with
    its part of the settings (:meth:`FlightSettings.role`)."""
    from zenswarm.compose.roles import run_settings

    role = args.only or ""
    if not (role.startswith("agent:") or role in ("plant", "leader")):
        raise ScenarioError("--only", f"unknown role {role!r}: expected plant, leader or agent:<i>")
    return run_settings(args.role(role, args.connect or ("tcp/127.0.0.1:7447",), args.keys))


def _add_plant_args(p: argparse.ArgumentParser) -> None:
    """The plant (``--plant``, its ports) and the roles started elsewhere (``--external``)."""
    p.add_argument(
        "--plant",
        choices=("sim", "mavlink", "crazyflie"),
        default="sim",
        help="sim: the simulated plant process (default); mavlink: simulated MAVLink vehicles over UDP flown "
        "through the MAVLink bridge (zenswarm bridge mavlink), realtime; crazyflie: simulated Crazyflies (CRTP over "
        "UDP) flown through cflib by the Crazyflie bridge (zenswarm bridge crazyflie), realtime (docs/crazyflie.md)",
    )
    p.add_argument(
        "--crazyflie-base-port", type=int, metavar="P",
        help="with --plant crazyflie: simulated Crazyflie i on udp://127.0.0.1:P+i-1; checked free (default: free ports); "
        "with --external vehicles: where yours are (default: the scenario's [crazyflie] uris)",
    )
    p.add_argument(
        "--mavlink-base-port", type=int, metavar="P",
        help="with --plant mavlink: vehicle i on UDP P+i-1, sending from P+40+i-1; all checked free (default: free ports); "
        "with --external vehicles: where yours send to (default: the scenario's [mavlink] table)",
    )
    p.add_argument(
        "--external",
        action="append",
        metavar="ROLE",
        help="a role started elsewhere (e.g. another host or network namespace with --only); not spawned here: "
        "one of plant, leader, agent:1..N (vehicles, bridge with --plant mavlink). Watched through its liveliness "
        "token: if it goes away before the role finished, the swarm stops with exit 3, as for a process of ours "
        "that died (an external role cannot be restarted from here)",
    )
    p.add_argument(
        "--external-timeout",
        type=positive_float,
        default=DEFAULT_EXTERNAL_TIMEOUT_S,
        metavar="S",
        help=f"seconds an --external role may take to announce itself before the swarm gives up with exit 3 "
        f"(default {DEFAULT_EXTERNAL_TIMEOUT_S:g}); progress lines show it as waiting meanwhile",
    )


def _add_output_args(p: argparse.ArgumentParser) -> None:
    """The recording and the report (``--record``, ``--report``, ``--report-format``)."""
    p.add_argument(
        "--record",
        type=Path,
        metavar="FILE.mcap",
        help="record every message of the swarm to this MCAP file (a recorder process started first, stopped last; "
        "if it dies, the flight goes on and the loss is reported)",
    )
    p.add_argument(
        "--report",
        action="store_true",
        help="with --record: write the flight report (figures like the paper's, results.json) to OUT/report from the recording",
    )
    p.add_argument(
        "--report-format",
        type=figure_formats,
        default=("png",),
        metavar="FMT[,FMT...]",
        help="with --report: the figures' formats, comma-separated, of png, svg, pdf (default png)",
    )


def _add_network_args(p: argparse.ArgumentParser) -> None:
    """The router's endpoints, security, and one role joining a router elsewhere (``--only``)."""
    p.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help="router listen endpoint (repeatable); default tcp/127.0.0.1:<free port>. "
        "Use a non-loopback address so processes on other hosts can join",
    )
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="endpoint the swarm's processes connect to (default: the router's listen endpoints); "
        "with --only, the remote router to join",
    )
    p.add_argument("--router-connect", action="append", metavar="ENDPOINT", help="other routers this router connects to")
    p.add_argument(
        "--secure",
        action="store_true",
        help="router requires authentication (user/password) and enforces access control generated from the "
        "scenario's graph; the default whenever the router listens on a non-loopback address",
    )
    p.add_argument("--tls", action="store_true", help="secure mode with mutual TLS (tls/ endpoints) instead of user/password")
    p.add_argument(
        "--keys",
        type=Path,
        metavar="DIR",
        help="credentials from `zenswarm keys` (default with --secure: generate them into OUT/keys)",
    )
    p.add_argument("--insecure", action="store_true", help="allow an open router on a non-loopback address (not recommended)")
    p.add_argument(
        "--only",
        metavar="ROLE",
        help="run a single role here (plant, leader, agent:<i>) against a router elsewhere (--connect)",
    )
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="run the plant, the leader and every agent as processes on this Dask scheduler's workers (each still its own "
        "OS process); the router stays here: --listen on an address the workers reach (docs/cluster.md)",
    )
    p.add_argument("--placement", action="append", metavar="ROLES=TARGET", help=PLACEMENT_HELP)
    p.add_argument(
        "--router-lost-timeout",
        type=positive_float,
        default=None,
        metavar="S",
        help="with --only: seconds to wait for the remote router to come back once zenoh closed the link to it "
        "(its 10 s lease ran out) before the role gives up and exits 3 (default 30)",
    )


def _add_run_args(p: argparse.ArgumentParser) -> None:
    """How the flight runs and ends, faults injected, what is shown (``--lockstep-timeout`` .. ``--live``)."""
    p.add_argument(
        "--lockstep-timeout",
        type=positive_float,
        default=5.0,
        metavar="S",
        help="lockstep input wait (wall seconds, > 0) before a drop (default 5 s)",
    )
    p.add_argument(
        "--kill",
        action="append",
        type=_parse_kill,
        metavar="ROLE@T",
        help="inject a SIGKILL into ROLE when sim time reaches T, e.g. agent:2@10s; ROLE must be a process started "
        "here (plant, leader, agent:1..N, the recorder with --record; not --external ones) (repeatable; for tests "
        "and demos). The recorder is not a vehicle: its death is reported (results.json: recording_loss), the "
        "flight goes on. In lockstep the plant, leader and agents kill themselves just before the first tick at or "
        "after T (--kill-at-tick), so the fault falls on the same tick in every run",
    )
    p.add_argument(
        "--restart",
        action="store_true",
        help="restart crashed agents and the leader with the scenario's [restart] backoff (default policy if absent)",
    )
    p.add_argument(
        "--stop-at-goal",
        action="store_true",
        help="end the run as soon as its success is decided: the leader reached the goal and every UAV has been "
        "within mission.slot_tolerance_m of its slot for mission.settle_window_s (useful in realtime mode)",
    )
    add_full_time_arg(p)
    p.add_argument("--progress-every", type=float, default=1.0, metavar="S", help="seconds between progress lines while sim time moves "
                   "(at the same sim time, e.g. while the processes start: every 10 s)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--quiet-children", action="store_true", help="do not echo the processes' own output")
    p.add_argument(
        "--live",
        nargs="?",
        const=FOXGLOVE_DEFAULT,
        type=live_target,
        metavar="PORT|rerun[:PORT]",
        help=f"watch the flight live. {LIVE_HELP}. Run by this supervisor, not by the swarm's processes; "
        "a port in use: exit 2 before the flight",
    )


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "up",
        help="fly a scenario as a distributed swarm (router + plant + leader + one process per UAV)",
        description=(
            "Start a Zenoh router inside this process, then the plant, the leader and one agent "
            "process per UAV; show progress, merge their logs, stop everything on Ctrl-C, and write "
            "OUT/results.json and OUT/timeseries.npz. Exit status: 0 mission succeeded, 1 mission "
            "failed (goal not reached, collision), 2 bad input, 3 a process died, 4 a plug-in failed "
            "(plugin_error: it raised, or gave a non-finite or wrongly shaped output), 130 interrupted."
        ),
    )
    p.add_argument("scenario", type=Path, help="scenario TOML file")
    p.add_argument("--swarm", default="default", help="swarm name (key prefix swarm/<name>); default: default")
    p.add_argument("--out", type=Path, default=Path("runs/up"), help="output directory (default runs/up)")
    p.add_argument("--realtime", action="store_true", help="wall-clock mode: fixed-rate loops, latest value wins")
    _add_plant_args(p)
    _add_output_args(p)
    _add_network_args(p)
    _add_run_args(p)
    add_rt_priority_arg(p)
    add_flight_args(p)
    p.set_defaults(func=_run_up)

"""Command-line flags shared by the edges (``bridge/`` and ``compose/``), and the typed values
they parse into. Nothing below the edges sees argparse: the base and the roles take
:class:`zenswarm.link.swarm.LinkFaults`, :class:`zenswarm.process.security.ClientSecurity`, plain values.

A bad value is a usage error naming the flag (exit status 2), before any work starts.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from zenswarm.errors import ScenarioError
from zenswarm.link import LinkFaults
from zenswarm.process.security import ClientSecurity
from zenswarm.process.settings import RoleSettings
from zenswarm.scenario.config import Scenario, check_seed

__all__ = [
    "FIGURE_FORMATS",
    "figure_formats",
    "add_rt_priority_arg",
    "positive_float",
    "seed_arg",
    "add_fault_args",
    "recorded_link_faults",
    "recorded_fault_plan",
    "link_faults",
    "add_security_args",
    "client_security",
    "add_process_args",
    "process_settings",
    "add_full_time_arg",
    "add_flight_args",
]


FIGURE_FORMATS = ("png", "svg", "pdf")
"""The formats a report's figures can be written in (``zenswarm report --format``, ``up --report-format``)."""


def figure_formats(text: str) -> tuple[str, ...]:
    """argparse ``type`` of ``FMT[,FMT...]`` among :data:`FIGURE_FORMATS`: ``png,svg,pdf`` ->
    ("png", "svg", "pdf"), in order, each once; anything else names the bad value."""
    got: list[str] = []
    for word in (w.strip().lower() for w in text.split(",")):
        if word not in FIGURE_FORMATS:
            raise argparse.ArgumentTypeError(
                f"{word!r} is not a figure format: expected a comma-separated list of {', '.join(FIGURE_FORMATS)}"
            )
        if word not in got:
            got.append(word)
    return tuple(got)


def positive_float(text: str) -> float:
    """argparse ``type`` of a finite number > 0 (``--fixed-gain``, ``--lockstep-timeout``,
    ``--external-timeout``, ``scenario generate --spacing``): 0, negatives, nan and inf are refused."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0 (positive), got {text!r}")
    return v


def seed_arg(text: str) -> int:
    """argparse ``type`` of ``--seed`` flags: :func:`zenswarm.schema.check_seed` of an integer
    literal (a usage error, exit status 2, otherwise)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}") from None
    try:
        return check_seed(v, "--seed")
    except ScenarioError as e:
        raise argparse.ArgumentTypeError(e.message) from None


def add_fault_args(p: argparse.ArgumentParser) -> None:
    """The whole-swarm fault shortcuts (also valid in a scenario's [faults] table); read them
    back with :func:`link_faults`."""
    g = p.add_argument_group("link faults (applied where messages are received; see docs/faults.md)")
    g.add_argument("--link-delay", metavar="DUR", help="fixed delay on every link, e.g. 50ms")
    g.add_argument("--link-jitter", metavar="DUR", help="uniform jitter +-DUR on every link's delay, e.g. 10ms")
    g.add_argument("--link-loss", metavar="P", help="independent loss probability on every link, e.g. 0.2 or 20%%")
    g.add_argument(
        "--link-range",
        metavar="DIST",
        help="radio range of the links between vehicles and from the leader, e.g. 1.5m: beyond it nothing is delivered",
    )
    g.add_argument(
        "--link-fade",
        metavar="R50,WIDTH",
        help="radio delivery falling off with distance (logistic: 50%% at R50, width WIDTH), e.g. 1.2m,0.1m",
    )
    g.add_argument(
        "--partition",
        action="append",
        default=[],
        metavar="WHO@T1-T2",
        help="cut every link of a process (agent:2@10s-13s) or one directed link (agent:1->agent:2@1s-2s); repeatable",
    )
    g.add_argument("--link-capacity", metavar="RATE", help="capacity of every link's queue, e.g. 20kB/s (docs/faults.md)")
    g.add_argument("--link-queue", metavar="N|SIZE", help="queue bound behind the capacity: messages (8) or bytes (4kB); default 16")
    g.add_argument("--link-medium", choices=("sender", "link"), help="one queue per sender (shared medium, default) or per link")
    g.add_argument("--link-trace", metavar="CSV", help="replay per-link delay/delivery from a CSV trace (time,link,delay,delivered)")
    g.add_argument(
        "--seed",
        type=seed_arg,
        default=None,
        help="seed of disturbances and fault decisions, 0 to 2**63-1 (default: the scenario's)",
    )


def link_faults(args: argparse.Namespace) -> LinkFaults:
    """The flags of :func:`add_fault_args` as a typed value."""
    trace = getattr(args, "link_trace", None)
    return LinkFaults(
        args.link_delay, args.link_jitter, args.link_loss, tuple(args.partition or ()), args.seed,
        link_range=args.link_range, link_fade=args.link_fade,
        link_capacity=getattr(args, "link_capacity", None), link_queue=getattr(args, "link_queue", None),
        link_medium=getattr(args, "link_medium", None),
        link_trace=None if trace is None else str(Path(trace).absolute()),
    )  # fmt: skip


def recorded_link_faults(fault_args: str, source: str | Path) -> LinkFaults:
    """The fault flags a recorded run was flown with (its metadata ``fault_args``: a JSON list of
    the words of :func:`add_fault_args`), typed. Unusable words are a :class:`RecordingError`
    naming ``source`` (the recording), not an exit of argparse's."""
    import json

    from zenswarm.errors import RecordingError

    p = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    add_fault_args(p)
    try:
        return link_faults(p.parse_args([str(w) for w in json.loads(fault_args)]))
    except (ValueError, TypeError, SystemExit, argparse.ArgumentError) as e:
        raise RecordingError(f"{source}: metadata fault_args unusable ({e})") from None


def recorded_fault_plan(fault_args: str, scenario: Scenario, source: str | Path) -> Any:
    """The link-fault plan (:class:`zenswarm.link.FaultPlan`, None when no fault was active) of a
    recorded run: ``scenario``'s ``[faults]`` table plus its fault flags
    (:func:`recorded_link_faults`); a :class:`RecordingError` naming ``source`` when unusable."""
    from zenswarm.errors import RecordingError, ZenswarmError

    faults = recorded_link_faults(fault_args, source)
    try:
        return faults.plan(scenario)
    except ZenswarmError as e:
        raise RecordingError(f"{source}: metadata fault_args unusable ({e})") from None


def add_security_args(p: argparse.ArgumentParser) -> None:
    """``--keys DIR`` and ``--tls``: the flags a swarm process takes to join a secured router;
    read them back with :func:`client_security`."""
    p.add_argument(
        "--keys",
        type=Path,
        default=None,
        metavar="DIR",
        help="credentials written by `zenswarm keys` (the whole tree, or just this process's directory); "
        "joins the router with this process's user and password",
    )
    p.add_argument("--tls", action="store_true", help="with --keys: authenticate by mutual TLS instead (tls/ endpoints)")


def client_security(args: argparse.Namespace) -> ClientSecurity:
    """The flags of :func:`add_security_args` as a typed value."""
    return ClientSecurity(keys=args.keys, tls=bool(args.tls))


def add_plugin_args(p: argparse.ArgumentParser) -> None:
    """``--controller NAME``, ``--planner NAME`` and ``--plant-model NAME``: override the scenario's
    ``[agents] controller``, ``[leader] planner`` and ``[plant] model`` (:func:`zenswarm.scenario.plugins.select`)."""
    p.add_argument(
        "--controller", metavar="NAME", default=None,
        help="agent controller plug-in: a built-in name, module:attribute or an installed entry point "
        "(default: the scenario's [agents] controller; `zenswarm plugins` lists them)",
    )
    p.add_argument(
        "--planner", metavar="NAME", default=None,
        help="leader planner plug-in, named the same ways (default: the scenario's [leader] planner)",
    )
    p.add_argument(
        "--plant-model", metavar="NAME", default=None,
        help="plant model plug-in (the vehicles' dynamics: quadrotor, rotorpy, ...), named the same ways "
        "(default: the scenario's [plant] model, else quadrotor)",
    )


def add_process_args(p: argparse.ArgumentParser) -> None:
    """The flags every swarm process takes (read back with
    :meth:`zenswarm.process.options.ProcessOptions.of`): ``--scenario``, ``--swarm``, ``--connect``,
    ``--realtime``, the credentials (:func:`add_security_args`), the link faults
    (:func:`add_fault_args`), the plug-ins (:func:`add_plugin_args`), ``--lockstep-timeout``,
    ``--router-lost-timeout``, ``--kill-at-tick`` and ``--rt-priority`` (:func:`add_rt_priority_arg`)."""
    from zenswarm.process.runtime import DEFAULT_LOCKSTEP_TIMEOUT_S, DEFAULT_ROUTER_LOST_TIMEOUT_S

    p.add_argument("--scenario", type=Path, help="scenario TOML; if omitted, fetched from the leader's mission key")
    p.add_argument("--swarm", default="default", help="swarm name: the key prefix swarm/<name> (default: default)")
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh router endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--realtime", action="store_true", help="run on the wall clock (latest value wins) instead of lockstep")
    add_security_args(p)
    add_fault_args(p)
    add_plugin_args(p)
    p.add_argument(
        "--lockstep-timeout",
        type=positive_float,
        default=DEFAULT_LOCKSTEP_TIMEOUT_S,
        metavar="S",
        help=f"lockstep: wall seconds to wait for an input before it counts as a drop (default {DEFAULT_LOCKSTEP_TIMEOUT_S})",
    )
    p.add_argument(
        "--router-lost-timeout",
        type=positive_float,
        default=DEFAULT_ROUTER_LOST_TIMEOUT_S,
        metavar="S",
        help="wall seconds to wait for the router to come back once the link to it is closed (zenoh's 10 s lease ran "
        f"out) before giving up: the process stops and exits 3 (default {DEFAULT_ROUTER_LOST_TIMEOUT_S:g})",
    )
    p.add_argument(
        "--kill-at-tick",
        type=int,
        default=None,
        metavar="K",
        help="lockstep: SIGKILL this process itself just before it runs tick K, so the fault falls on the same tick "
        "in every run (what `zenswarm up --kill ROLE@T` passes its lockstep roles; default: never)",
    )
    add_rt_priority_arg(p)


def process_settings(args: argparse.Namespace, role: str, scenario: Scenario | None, realtime: bool = False) -> RoleSettings:
    """The flags of :func:`add_process_args` (and ``--expect``) as the settings of the swarm
    process ``role``, its scenario parsed (None: fetched from the leader's mission); ``realtime``:
    on the wall clock whatever ``--realtime`` says (the vehicle bridges)."""
    return RoleSettings(
        role=role, scenario=scenario, swarm=args.swarm, connect=tuple(args.connect or ()), realtime=realtime or bool(args.realtime),
        lockstep_timeout=args.lockstep_timeout, keys=args.keys, tls=bool(args.tls), faults=link_faults(args),
        controller=args.controller, planner=args.planner, plant_model=args.plant_model, rt_priority=args.rt_priority,
        router_lost_timeout=args.router_lost_timeout, kill_at_tick=args.kill_at_tick, expect=tuple(getattr(args, "expect", None) or ()),
    )  # fmt: skip


def add_rt_priority_arg(p: argparse.ArgumentParser) -> None:
    """``--rt-priority P`` (:mod:`zenswarm.process.rtsched`)."""
    p.add_argument(
        "--rt-priority",
        type=int,
        default=None,
        metavar="P",
        help="realtime only: once start-up is over, run this process's threads under SCHED_FIFO priority P (1-99), "
        "so its loop preempts normally scheduled work the moment it wakes; needs root or an RLIMIT_RTPRIO >= P "
        "(default: the normal scheduler)",
    )


def add_override_args(p: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` (repeatable) and ``--duration S``: scenario overrides by dotted path,
    the same keys as ``api.fly(overrides=)`` and ``zenswarm sweep --grid`` (:mod:`zenswarm.scenario.overrides`)."""
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a scenario field by its dotted path, e.g. --set controller.kp=[4,4,5] --set leader.goal=[10,0,2] "
        "--set obstacles[0].radius=0.4 (VALUE is read as TOML, else as a string; repeatable; validated as the file is)",
    )
    p.add_argument(
        "--duration", type=float, default=None, metavar="S",
        help="fly S sim seconds (sets timing.time_limit_s; default: the scenario's)",
    )


def add_full_time_arg(p: argparse.ArgumentParser) -> None:
    """``--full-time`` (``zenswarm sim``, ``zenswarm up``): fly the whole time limit."""
    p.add_argument(
        "--full-time",
        action="store_true",
        help="fly the whole time limit even after the outcome is decided (by default a stalled leader or a "
        "diverged UAV ends the run early; the verdict names the failure either way)",
    )


def add_flight_args(p: argparse.ArgumentParser) -> None:
    """What a flight of a scenario takes besides its own flags (``zenswarm sim``, ``zenswarm up``):
    the link faults (:func:`add_fault_args`, read back with :func:`link_faults`), the plug-ins
    (:func:`add_plugin_args`) and the scenario overrides (:func:`add_override_args`; the scenario
    with both: :func:`scenario_of`), in that order."""
    add_fault_args(p)
    add_plugin_args(p)
    add_override_args(p)


def overrides_of(args: argparse.Namespace) -> dict[str, Any]:
    """The ``--set`` and ``--duration`` overrides, in order (ScenarioError naming the flag on bad syntax)."""
    from zenswarm.errors import ScenarioError
    from zenswarm.scenario.overrides import parse_assignment

    out: dict[str, Any] = dict(parse_assignment(text) for text in getattr(args, "overrides", None) or [])
    duration = getattr(args, "duration", None)
    if duration is not None:
        if not (duration > 0 and duration == duration and duration != float("inf")):
            raise ScenarioError("--duration", f"must be a finite number of seconds > 0, got {duration!r}")
        out["timing.time_limit_s"] = float(duration)
    return out


def scenario_of(args: argparse.Namespace) -> tuple[Any, dict[str, Any]]:
    """``args.scenario`` with ``--set`` / ``--duration`` applied, then ``--controller`` /
    ``--planner`` / ``--plant-model`` (:func:`zenswarm.scenario.plugins.select`), the plug-ins resolved and their parameters
    decoded: bad input is a ScenarioError (an OverrideError for what an override caused) naming
    the field or flag, before any work. Returns (scenario, the overrides)."""
    from zenswarm.scenario.overrides import check_plugins, load_file
    from zenswarm.scenario.plugins import select

    ov = overrides_of(args)
    plant_model = getattr(args, "plant_model", None)
    sc = select(load_file(args.scenario, ov), args.controller, args.planner, plant_model)
    check_plugins(sc, ov, "--controller" if args.controller else None, "--planner" if args.planner else None,
                  plant_field="--plant-model" if plant_model else None)
    return sc, ov

"""A flight's settings checked before anything starts: every flag of ``zenswarm up`` (and every
argument of :func:`zenswarm.api.fly`) that names something (a role, an endpoint, a port, an output
path) is held against the scenario; bad input is a :class:`zenswarm.errors.ScenarioError` naming
the flag, exit status 2, with no process started and nothing written or lost. The command line's
``--kill ROLE@T`` text is read here too (:func:`parse_kill`)."""

from __future__ import annotations

import argparse
import math

from zenswarm import bus
from zenswarm.bus import wire
from zenswarm.compose.commands import role_names, swarm_roles
from zenswarm.compose.placement import parse_rule
from zenswarm.errors import ScenarioError, ZenswarmError
from zenswarm.process import rtsched
from zenswarm.process.paths import check_output_dir, check_output_file
from zenswarm.process.settings import FlightSettings
from zenswarm.scenario.config import Scenario
from zenswarm.scenario.plugins import DEFAULTS
from zenswarm.vehicle.autopilot import SITL_SEND_OFFSET

__all__ = ["check_up_args", "check_cluster_args", "check_rt_priority", "check_crazyflie", "check_mavlink_ports", "parse_kill"]


def check_up_args(args: FlightSettings, sc: Scenario) -> None:
    """Every flag of ``zenswarm up`` that names something (a role, an endpoint, an output path)
    is checked against ``sc`` before anything starts: :class:`ScenarioError` naming the flag,
    exit status 2, no process started and nothing lost."""
    if not (math.isfinite(args.lockstep_timeout) and args.lockstep_timeout > 0):  # settings built in code (the flag's type checks it)
        raise ScenarioError("--lockstep-timeout", f"must be a finite number > 0 (positive), got {args.lockstep_timeout!r}")
    bus.check_endpoint_syntax(list(args.listen), "--listen", listen=True)
    bus.check_endpoint_syntax(list(args.connect), "--connect")
    bus.check_endpoint_syntax(list(args.router_connect), "--router-connect")
    check_rt_priority(args)
    check_cluster_args(args, sc)
    if args.only:
        if args.only not in role_names(sc.n):
            raise ScenarioError("--only", f"unknown role {args.only!r}: this swarm's roles are {', '.join(role_names(sc.n))}")
        return  # one role here: nothing else is started, nothing written
    if args.report and args.record is None:  # the report is made from the recording: it would be silently skipped
        raise ScenarioError("--report", "makes the flight report from the recording: give --record FILE.mcap too")
    names = swarm_roles(sc.n, args.plant)
    for r in args.external:
        if r not in names:
            raise ScenarioError("--external", f"unknown role {r!r}: this swarm's roles are {', '.join(names)}")
    _check_kills(args, sc, names)
    if args.plant in ("mavlink", "crazyflie") and sc.plant.model != DEFAULTS["plant"]:
        where = "--plant-model" if args.plant_model is not None else "plant.model"
        raise ScenarioError(
            where, f"plant model {sc.plant.model!r} cannot fly with --plant {args.plant}: the simulated vehicles "
            f"fly zenswarm's own model ({DEFAULTS['plant']!r}); drop --plant {args.plant}, or the plant model"
        )
    if args.plant == "crazyflie":
        check_crazyflie(args, sc)
    if args.plant == "mavlink" and args.mavlink_base_port is not None:
        check_mavlink_ports(args.mavlink_base_port, sc.n, vehicles="vehicles" not in args.external, bridge="bridge" not in args.external)
    check_output_dir(args.out, "--out")
    if args.record is not None:
        check_output_file(args.record, "--record")


def check_cluster_args(args: FlightSettings, sc: Scenario) -> None:
    """``--scheduler`` and ``--placement``: the rules' syntax and roles (which workers exist is
    checked against the scheduler by :class:`zenswarm.compose.cluster.Cluster`, still before
    anything starts); ScenarioError naming the flag (exit 2)."""
    if args.scheduler is None:
        if args.placement:
            raise ScenarioError("--placement", "places roles on a Dask cluster: give --scheduler tcp://HOST:PORT too")
        return
    if not args.scheduler.strip() or any(c.isspace() for c in args.scheduler):
        raise ScenarioError("--scheduler", f"expected a Dask scheduler's address (tcp://HOST:PORT), got {args.scheduler!r}")
    if args.only:
        raise ScenarioError("--scheduler", "not with --only: one role runs here; --scheduler places a whole swarm on a cluster")
    for text in args.placement:
        rule = parse_rule(text)
        for role in rule.names(sc.n):
            if role in args.external:
                raise ScenarioError("--placement", f"{text!r}: {role} is --external, not started by this supervisor")


def check_rt_priority(args: FlightSettings) -> None:
    """``--rt-priority P``: 1-99, a realtime flight (``--realtime``, ``--plant mavlink`` or ``--plant
    crazyflie``), and permitted to this user (:func:`zenswarm.process.rtsched.probe`): else
    :class:`ScenarioError` naming the flag and the remedy, before anything starts."""
    how = "--realtime, --plant mavlink or --plant crazyflie"
    rtsched.validate(args.rt_priority, realtime=args.realtime or args.plant != "sim", how=how)


def check_crazyflie(args: FlightSettings, sc: Scenario) -> None:
    """``--plant crazyflie``: cflib installed, and ``--crazyflie-base-port P`` leaves P..P+N-1 free
    (the simulated Crazyflies' ports; not with ``--external vehicles``, which are there already),
    else :class:`ScenarioError` (exit 2, before anything starts)."""
    import importlib.util

    if importlib.util.find_spec("cflib") is None:
        raise ScenarioError("--plant", "--plant crazyflie needs cflib: pip install 'zenswarm[crazyflie]'")
    base = args.crazyflie_base_port
    if base is not None:
        if not 1 <= base <= 65535 - sc.n + 1:
            raise ScenarioError("--crazyflie-base-port", f"expected a port in 1..{65535 - sc.n + 1} ({sc.n} UAVs), got {base}")
        if "vehicles" in args.external:
            return  # the user's simulated Crazyflies hold P..P+N-1 already: the bridge dials them there
        busy = [p for p in range(base, base + sc.n) if bus.udp_ports_in_use([p], "127.0.0.1")]
        if busy:
            raise ScenarioError("--crazyflie-base-port", f"UDP port {busy[0]} on 127.0.0.1 is in use; the simulated Crazyflies "
                                f"need P..P+{sc.n - 1} free (P = {base})")  # fmt: skip


def check_mavlink_ports(base: int, n: int, host: str = "127.0.0.1", *, vehicles: bool = True, bridge: bool = True) -> None:
    """``--plant mavlink --mavlink-base-port P``: the simulated vehicle i (0-based) sends from UDP
    P+40+i to P+i, where the bridge listens (PX4 SITL's direction): the ports of the processes
    started here must be free on ``host`` (the bridge's P+i with ``bridge``, the vehicles' send
    ports P+40+i with ``vehicles``; ``--external vehicles`` hold theirs already), else
    :class:`ScenarioError` naming the flag and the first busy port (exit 2, before anything
    starts; a busy port would otherwise kill the vehicles' process mid-start)."""
    ports = [(base + i, f"where the bridge hears vehicle {i + 1}, P+{i}") for i in range(n)] if bridge else []
    if vehicles:
        ports += [(base + SITL_SEND_OFFSET + i, f"vehicle {i + 1}'s send port, P+{SITL_SEND_OFFSET}+{i}") for i in range(n)]
    need = " and ".join(
        ([f"P..P+{n - 1}"] if bridge else []) + ([f"P+{SITL_SEND_OFFSET}..P+{SITL_SEND_OFFSET + n - 1}"] if vehicles else [])
    )
    for port, what in ports:
        if bus.udp_ports_in_use([port], host):
            raise ScenarioError(
                "--mavlink-base-port",
                f"UDP port {port} on {host} ({what}) is in use or not a port; the simulated vehicles need {need} free (P = {base})",
            )


def _check_kills(args: FlightSettings, sc: Scenario, names: list[str]) -> None:
    """``--kill ROLE@T``: ROLE must be a process started here."""
    external = list(args.external)
    started = [r for r in names if r not in external] + (["recorder"] if args.record is not None else [])
    for role, t in args.kill:
        if role in started:
            continue
        if role in external:
            why = "is --external, not started here"
        elif role == "recorder":
            why = "runs only with --record"
        else:
            why = f"is not a process of this swarm ({sc.n} UAVs)"
        raise ScenarioError("--kill", f"{role}@{t:g}s: {role} {why}; processes started here: {', '.join(started)}")



def parse_kill(text: str) -> tuple[str, float]:
    """``agent:2@10s`` -> ("agent:2", 10.0); argparse turns ValueError into a usage error."""
    role, sep, when = text.partition("@")
    if not sep:
        raise argparse.ArgumentTypeError(f"{text!r}: expected ROLE@TIME, e.g. agent:2@10s")
    try:
        wire.validate_process(role)
    except ZenswarmError:
        raise argparse.ArgumentTypeError(f"{text!r}: unknown process {role!r} (plant, leader, agent:<i>, recorder)") from None
    w = when.strip()
    scale = 1.0
    for suffix, f in (("ms", 1e-3), ("s", 1.0)):
        if w.endswith(suffix):
            w, scale = w[: -len(suffix)], f
            break
    try:
        t = float(w) * scale
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: bad time {when!r} (e.g. 10s, 500ms)") from None
    if not t >= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: time must be >= 0")
    return role, t

"""CLI entry points of the swarm's processes (what the supervisor starts, one OS process each).

The edge of the roles: here the command line of ``zenswarm plant|leader|agent`` is parsed and
turned into the roles' typed options (:class:`zenswarm.process.options.ProcessOptions`,
:class:`zenswarm.agents.process.AgentOptions`, :class:`zenswarm.plant.process.PlantOptions`),
which their ``run`` functions take. A bad flag is a usage error (exit 2) before any work.

The supervisor of ``zenswarm up`` starts its roles as ``zenswarm ROLE [--id I] --swarm NAME
--settings - --supervisor PID``: the role reads its :class:`zenswarm.process.settings.RoleSettings`
on standard input (:func:`run_settings`), not from flags; the words on the command line only name
it in the process table. ``zenswarm up --only ROLE`` runs :func:`run_settings` in its own process.

The simulated vehicles (``mavlink-vehicle``, ``plant --mavlink``, ``crazyflie-vehicle``) take
typed settings too (:class:`MavlinkFleetSettings`, :class:`CrazyflieFleetSettings`): built from
their flags here, or read on standard input when ``zenswarm up`` starts them
(:mod:`zenswarm.compose.commands`).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec

from zenswarm.bridge.args import add_process_args, add_rt_priority_arg, add_security_args
from zenswarm.errors import ScenarioError
from zenswarm.process.runtime import ProcessOptions
from zenswarm.process.settings import RoleSettings
from zenswarm.scenario.config import Scenario

__all__ = ["add_parsers", "agent_options", "plant_options", "process_options", "run_role", "run_settings", "MavlinkFleetSettings",
           "mavlink_fleet_settings", "run_mavlink_fleet", "CrazyflieFleetSettings", "crazyflie_fleet_settings", "run_crazyflie_fleet"]


def process_options(args: argparse.Namespace) -> ProcessOptions:
    """The common options of a parsed process command line (:func:`add_process_args`)."""
    return ProcessOptions.of(args)


def agent_options(args: argparse.Namespace):
    from zenswarm.agents.process import AgentOptions

    return AgentOptions(id=int(args.id), process=process_options(args))


def plant_options(args: argparse.Namespace):
    from zenswarm.plant.process import PlantOptions

    return PlantOptions(process=process_options(args), expect=tuple(args.expect or ()))


def _main_agent(args: argparse.Namespace) -> int:
    from zenswarm.agents.process import run

    return run(agent_options(args))


def _main_leader(args: argparse.Namespace) -> int:
    from zenswarm.leader.process import run

    return run(process_options(args))


def _main_plant(args: argparse.Namespace) -> int:
    if getattr(args, "mavlink", False):
        return _main_mavlink_fleet(args)
    from zenswarm.plant.process import run

    return run(plant_options(args))


class MavlinkFleetSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What the simulated MAVLink vehicles are started with (``mavlink-vehicle``, ``plant
    --mavlink``; ``zenswarm up --plant mavlink`` hands them on standard input): the scenario
    (parsed), the swarm they fly in (a label: they open no Zenoh session), the flags of
    :func:`add_vehicle_args` (None: the scenario's), the seed of their disturbances (None: the
    scenario's), the plant model asked for (it must be zenswarm's own) and ``--rt-priority``."""

    scenario: Scenario
    swarm: str | None = None
    base_port: int | None = None
    autopilot: str | None = None
    telemetry_hz: float | None = None
    duration: float | None = None
    own_origin: bool = False
    sitl_ports: bool = False
    seed: int | None = None
    plant_model: str | None = None
    rt_priority: int | None = None


def mavlink_fleet_settings(args: argparse.Namespace) -> MavlinkFleetSettings:
    """The flags of ``mavlink-vehicle`` / ``plant --mavlink`` as :class:`MavlinkFleetSettings`
    (the scenario file parsed: a ScenarioError naming it, exit 2)."""
    from zenswarm.scenario.config import load_scenario

    if args.scenario is None:
        raise ScenarioError("--scenario", "plant --mavlink needs the scenario file (it has no bus to fetch it from)")
    return MavlinkFleetSettings(
        scenario=load_scenario(args.scenario), swarm=getattr(args, "swarm", None), base_port=args.base_port,
        autopilot=args.autopilot, telemetry_hz=args.telemetry_hz, duration=args.duration,
        own_origin=bool(getattr(args, "own_origin", False)), sitl_ports=bool(getattr(args, "sitl_ports", False)),
        seed=args.seed, plant_model=getattr(args, "plant_model", None), rt_priority=getattr(args, "rt_priority", None),
    )  # fmt: skip


def run_mavlink_fleet(s: MavlinkFleetSettings) -> int:
    """The scenario's quadrotors as simulated MAVLink vehicles over UDP
    (:mod:`zenswarm.plant.mavlink_vehicle`; no Zenoh session: the MAVLink bridge is their swarm side)."""
    from dataclasses import replace

    from zenswarm.plant.mavlink_vehicle import run_fleet
    from zenswarm.scenario.plugins import DEFAULTS
    from zenswarm.vehicle.autopilot import SITL_SEND_OFFSET

    sc = s.scenario
    model = s.plant_model or sc.plant.model
    if model != DEFAULTS["plant"]:
        raise ScenarioError(
            "--plant-model" if s.plant_model else "plant.model",
            f"plant model {model!r} cannot fly as MAVLink vehicles: they fly zenswarm's own model ({DEFAULTS['plant']!r})",
        )
    top = 65535 - sc.n + 1 - (SITL_SEND_OFFSET if s.sitl_ports else 0)  # vehicle i on P+i-1 (sending from P+40+i-1)
    if s.base_port is not None and not 1 <= s.base_port <= top:
        raise ScenarioError("--base-port", f"must leave room for {sc.n} UDP ports below 65536: expected 1..{top}, got {s.base_port}")
    if s.seed is not None:
        sc = replace(sc, seed=int(s.seed))
    return run_fleet(
        sc, base_port=s.base_port, autopilot=s.autopilot, telemetry_hz=s.telemetry_hz, duration=s.duration,
        own_origin=s.own_origin, sitl_ports=s.sitl_ports, rt_priority=s.rt_priority,
    )  # fmt: skip


def _main_mavlink_fleet(args: argparse.Namespace) -> int:
    """``plant --mavlink``, ``mavlink-vehicle``: :func:`run_mavlink_fleet` of their flags."""
    return run_mavlink_fleet(mavlink_fleet_settings(args))


def add_agent_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "agent",
        help="run one UAV's agent process (generator, ESO, controller)",
        description="Run agent I: reference generator (16-17), ESO (27) and controller (28) of UAV I, over Zenoh.",
    )
    p.add_argument("--id", type=int, required=True, metavar="I", help="UAV number, 1..N as in the paper")
    add_process_args(p)
    p.set_defaults(func=_main_agent)


def add_leader_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "leader",
        help="run the leader process (AAPF virtual leader)",
        description="Run the virtual leader: AAPF planner (eqs 8-15); publishes leader/ref and serves the mission.",
    )
    add_process_args(p)
    p.set_defaults(func=_main_leader)


def add_vehicle_args(p: argparse.ArgumentParser) -> None:
    """The simulated MAVLink vehicles' flags (``mavlink-vehicle`` and ``plant --mavlink``)."""
    g = p.add_argument_group("simulated MAVLink vehicles")
    g.add_argument(
        "--base-port", type=int, default=None, metavar="P", help="vehicle i listens on UDP P+i-1 (default mavlink.base_port, 14540)"
    )
    g.add_argument("--autopilot", choices=("px4", "ardupilot"), help="mode numbering and heartbeat flavour (default px4)")
    g.add_argument("--telemetry-hz", type=float, metavar="HZ", help="LOCAL_POSITION_NED + ATTITUDE rate (default 50)")
    g.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until SIGTERM/SIGINT)")
    g.add_argument("--own-origin", action="store_true", help="each vehicle's local NED origin is where it booted (as a real autopilot)")
    g.add_argument(
        "--sitl-ports", action="store_true", help="PX4 SITL's direction: vehicle i sends from P+40+i-1 to P+i-1 (a GCS listens, udpin)"
    )


def add_vehicles_parser(sub: argparse._SubParsersAction) -> None:
    """``mavlink-vehicle SCENARIO --base-port P`` (:mod:`zenswarm.plant.mavlink_vehicle`)."""
    from pathlib import Path

    from zenswarm.plant import mavlink_vehicle

    p = sub.add_parser(
        "mavlink-vehicle",
        help="run the scenario's quadrotors as simulated MAVLink (PX4-like) vehicles over UDP",
        description=(mavlink_vehicle.__doc__ or "").split("\n\n")[0],
    )
    p.add_argument("scenario", type=Path, help="scenario TOML (N vehicles, [vehicle], [timing], [mavlink])")
    add_vehicle_args(p)
    p.add_argument("--seed", type=int, default=None, help="seed of the disturbances (default: the scenario's)")
    add_rt_priority_arg(p)
    p.set_defaults(func=_main_mavlink_fleet)


class CrazyflieFleetSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What the simulated Crazyflies are started with (``crazyflie-vehicle``; ``zenswarm up
    --plant crazyflie`` hands them on standard input): the scenario (parsed), Crazyflie i at
    ``udp://HOST:base_port+i-1``, ``duration`` (s; None: until SIGTERM/SIGINT), and with
    ``mocap`` the motion-capture feed they publish at ``mocap_hz`` on ``swarm``'s bus through
    ``connect``, as the user :data:`zenswarm.process.security.MOCAP_FEEDER` of the credentials in
    ``keys`` (mutual TLS with ``tls``; None: an open router); ``rt_priority``: their loop under
    ``SCHED_FIFO`` once they are up (``--rt-priority``)."""

    scenario: Scenario
    base_port: int
    swarm: str | None = None
    host: str = "127.0.0.1"
    duration: float | None = None
    mocap: bool = False
    mocap_hz: float = 100.0
    connect: tuple[str, ...] = ()
    rt_priority: int | None = None
    keys: Path | None = None
    tls: bool = False


def crazyflie_fleet_settings(args: argparse.Namespace) -> CrazyflieFleetSettings:
    """The flags of ``crazyflie-vehicle`` as :class:`CrazyflieFleetSettings` (the scenario file
    parsed: a ScenarioError naming it, exit 2)."""
    from zenswarm.scenario.config import load_scenario

    return CrazyflieFleetSettings(
        scenario=load_scenario(args.scenario), base_port=args.base_port, swarm=args.swarm, host=args.host, duration=args.duration,
        mocap=bool(args.mocap), mocap_hz=args.mocap_hz, connect=tuple(args.connect or ()), rt_priority=args.rt_priority,
        keys=args.keys, tls=bool(args.tls),
    )  # fmt: skip


def run_crazyflie_fleet(s: CrazyflieFleetSettings) -> int:
    """The scenario's quadrotors as simulated Crazyflies speaking CRTP over UDP
    (:mod:`zenswarm.plant.crazyflie_vehicle`; no Zenoh session but the mocap feed's)."""
    from zenswarm.plant.crazyflie_vehicle import run_fleet
    from zenswarm.scenario.plugins import DEFAULTS

    sc = s.scenario
    if sc.plant.model != DEFAULTS["plant"]:
        raise ScenarioError(
            "plant.model", f"plant model {sc.plant.model!r} cannot fly as simulated Crazyflies: they fly zenswarm's own model"
        )
    if not 1 <= s.base_port <= 65535 - sc.n:
        raise ScenarioError("--base-port", f"must leave room for {sc.n} UDP ports below 65536, got {s.base_port}")
    mocap = None
    mocap_security: dict[str, Any] = {}
    if s.mocap:
        from zenswarm import bus
        from zenswarm.bus.wire import validate_swarm_name
        from zenswarm.process.security import MOCAP_FEEDER, ClientSecurity, client_fragments

        if not s.swarm or not s.connect:
            raise ScenarioError("--mocap", "needs --swarm NAME and --connect ENDPOINT (where the bridge listens for the feed)")
        mocap = (validate_swarm_name(s.swarm), bus.check_endpoint_syntax(list(s.connect), "--connect"))
        # its own user on a secured router (a CredentialsError naming what is missing: exit 2)
        mocap_security = client_fragments(MOCAP_FEEDER, ClientSecurity(s.keys, s.tls), connect=s.connect, swarm=s.swarm)
    elif s.keys is not None or s.tls:
        raise ScenarioError("--keys", "the credentials are the mocap feed's: give --mocap too")
    if not s.mocap_hz > 0:
        raise ScenarioError("--mocap-hz", f"must be > 0, got {s.mocap_hz}")
    return run_fleet(sc, base_port=s.base_port, host=s.host, duration=s.duration, mocap=mocap, mocap_hz=s.mocap_hz,
                     rt_priority=s.rt_priority, mocap_security=mocap_security)  # fmt: skip


def _main_crazyflie_fleet(args: argparse.Namespace) -> int:
    """``crazyflie-vehicle SCENARIO``: :func:`run_crazyflie_fleet` of its flags."""
    return run_crazyflie_fleet(crazyflie_fleet_settings(args))


def add_crazyflie_vehicles_parser(sub: argparse._SubParsersAction) -> None:
    """``crazyflie-vehicle SCENARIO --base-port P`` (:mod:`zenswarm.plant.crazyflie_vehicle`)."""
    from pathlib import Path

    from zenswarm.plant import crazyflie_vehicle

    p = sub.add_parser(
        "crazyflie-vehicle",
        help="run the scenario's quadrotors as simulated Crazyflies (CRTP over UDP, cflib's udp:// driver)",
        description=(crazyflie_vehicle.__doc__ or "").split("\n\n")[0],
    )
    p.add_argument("scenario", type=Path, help="scenario TOML (N vehicles, [vehicle], [timing])")
    p.add_argument(
        "--base-port",
        type=int,
        default=crazyflie_vehicle.DEFAULT_BASE_PORT,
        metavar="P",
        help="Crazyflie i at udp://HOST:P+i-1 (default 19850, where cflib scans)",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until SIGTERM/SIGINT)")
    p.add_argument(
        "--mocap",
        action="store_true",
        help="also be the motion-capture system: publish the true positions on swarm/NAME/mocap/<i> (positioning = extpos)",
    )
    p.add_argument("--mocap-hz", type=float, default=100.0, metavar="HZ", help="the feed's rate (default 100 Hz)")
    p.add_argument("--swarm", metavar="NAME", help="swarm name of the mocap feed")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="Zenoh router of the mocap feed (repeatable)")
    add_security_args(p)
    add_rt_priority_arg(p)
    p.set_defaults(func=_main_crazyflie_fleet)


def add_plant_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plant",
        help="run the plant process (simulated quadrotors; the lockstep clock)",
        description="Simulate every UAV of the scenario (eqs 1-5, onboard attitude PID) and publish their states.",
    )
    add_process_args(p)
    p.add_argument(
        "--expect",
        action="append",
        metavar="PROCESS",
        help="also wait for this process (e.g. recorder) to announce itself before the first tick",
    )
    p.add_argument(
        "--mavlink",
        action="store_true",
        help="run the quadrotors as simulated MAVLink vehicles over UDP instead (vehicle i on UDP --base-port + i - 1; "
        "fly them with `zenswarm bridge mavlink`); the bus flags are then ignored",
    )
    add_vehicle_args(p)
    p.set_defaults(func=_main_plant)


def add_parsers(sub: argparse._SubParsersAction) -> None:
    add_plant_parser(sub)
    add_vehicles_parser(sub)
    add_crazyflie_vehicles_parser(sub)
    add_leader_parser(sub)
    add_agent_parser(sub)


#: The swarm's own processes: their parsers (a role starts with only what it needs, so a restarted
#: agent rejoins sooner than it would after building the whole CLI's parser).
ROLE_PARSERS = {"agent": add_agent_parser, "leader": add_leader_parser, "plant": add_plant_parser}


def run_settings(settings: RoleSettings) -> int:
    """Run the role these settings name (``plant``, ``leader``, ``agent:<i>``) in this process."""
    role = settings.role
    if role.startswith("agent:"):
        from zenswarm.agents.process import AgentOptions
        from zenswarm.agents.process import run as run_agent

        return run_agent(AgentOptions(id=int(role.split(":", 1)[1]), process=settings.process_options()))
    if role == "leader":
        from zenswarm.leader.process import run as run_leader

        return run_leader(settings.process_options())
    if role == "plant":
        from zenswarm.plant.process import PlantOptions
        from zenswarm.plant.process import run as run_plant

        return run_plant(PlantOptions(process=settings.process_options(), expect=settings.expect))
    raise ScenarioError("--settings", f"unknown role {role!r}: expected plant, leader or agent:<i>")


def settings_words(prog: str, words: list[str], with_id: bool = False) -> argparse.Namespace:
    """``[--id I] --swarm NAME --settings FILE [--supervisor PID]``: the words after the command
    of a process ``zenswarm up`` hands its settings to (a role, or an edge:
    :func:`zenswarm.compose.commands.run_edge`); ``--id`` with ``with_id`` (an agent)."""
    p = argparse.ArgumentParser(prog=prog, description="run a process of zenswarm up with its typed settings")
    if with_id:
        p.add_argument("--id", type=int, required=True, metavar="I")
    p.add_argument("--swarm", required=True)
    p.add_argument("--settings", required=True, metavar="FILE", help="msgpack of its settings; - for standard input")
    p.add_argument("--supervisor", type=int, metavar="PID", help="the supervisor that started it (a label for the process table)")
    return p.parse_args(words)


def _settings_of(argv: list[str]) -> RoleSettings:
    """``ROLE [--id I] --swarm NAME --settings FILE [--supervisor PID]`` (what the supervisor
    starts): the :class:`RoleSettings` in FILE (``-``: standard input), which must be this role's
    and this swarm's."""
    from zenswarm.process.settings import decode_role, read_settings

    ns = settings_words(f"zenswarm {argv[0]}", argv[1:], with_id=argv[0] == "agent")
    settings = decode_role(read_settings(ns.settings))
    role = f"agent:{ns.id}" if argv[0] == "agent" else argv[0]
    if (settings.role, settings.swarm) != (role, ns.swarm):
        raise ScenarioError("--settings", f"the settings of {settings.role} in swarm {settings.swarm!r}, "
                                          f"not of {role} in swarm {ns.swarm!r}")  # fmt: skip
    return settings


def run_role(argv: Sequence[str]) -> int:
    """Run one role's command line (``agent --id 2 ...``, ``leader ...``, ``plant ...``) in this
    process, as ``zenswarm`` would: a :class:`zenswarm.errors.ZenswarmError` is printed as
    ``zenswarm: error: ...`` (exit 2), Ctrl-C is exit 130. With ``--settings FILE`` (the
    supervisor's children) the role's settings are read from FILE, not from flags."""
    from zenswarm.errors import run_command

    argv = list(argv)
    if not argv or argv[0] not in ROLE_PARSERS:
        raise ValueError(f"not a role's command line: {argv[:1]!r} (expected one of {', '.join(ROLE_PARSERS)})")

    def body() -> int:
        if "--settings" in argv:
            return run_settings(_settings_of(argv))
        parser = argparse.ArgumentParser(prog="zenswarm")
        ROLE_PARSERS[argv[0]](parser.add_subparsers(dest="command", metavar="COMMAND", required=True))
        args = parser.parse_args(argv)
        return int(args.func(args) or 0)

    return run_command(body)

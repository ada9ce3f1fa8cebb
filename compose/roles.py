"""CLI entry points of the swarm's processes (what the supervisor starts, one OS process each).

The edge of the roles: here the command line of ``zenswarm plant|leader|agent`` is parsed and
turned into the roles' typed options (:class:`zenswarm.runtime.ProcessOptions`,
:class:`zenswarm.agents.process.AgentOptions`, :class:`zenswarm.plant.process.PlantOptions`),
which their ``run`` functions take. A bad flag is a usage error (exit 2) before any work.
"""

from __future__ import annotations

import argparse

from zenswarm.argtypes import add_process_args
from zenswarm.runtime import ProcessOptions

__all__ = ["add_parsers", "agent_options", "plant_options", "process_options"]


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


def _main_mavlink_fleet(args: argparse.Namespace) -> int:
    """``plant --mavlink``: the scenario's quadrotors as simulated MAVLink vehicles over UDP
    (:mod:`plant.mavlink_vehicle`; no Zenoh session: the MAVLink bridge is their swarm side)."""
    from dataclasses import replace

    from zenswarm.plant.mavlink_vehicle import run_fleet

    from zenswarm.config import load_scenario
    from zenswarm.errors import ScenarioError

    if args.scenario is None:
        raise ScenarioError("--scenario", "plant --mavlink needs the scenario file (it has no bus to fetch it from)")
    sc = load_scenario(args.scenario)
    if args.seed is not None:
        sc = replace(sc, seed=int(args.seed))
    return run_fleet(sc, args)


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


def add_plant_parser(sub: argparse._SubParsersAction) -> None:
    from zenswarm.plant.mavlink_vehicle import add_vehicle_args

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
    from zenswarm.plant.mavlink_vehicle import add_parsers as add_vehicles

    add_plant_parser(sub)
    add_vehicles(sub)
    add_leader_parser(sub)
    add_agent_parser(sub)

"""CLI entry points of the swarm's processes (what the supervisor starts, one OS process each)."""

from __future__ import annotations

import argparse


def add_parsers(sub: argparse._SubParsersAction) -> None:
    from zenswarm.agents.process import add_parser as add_agent
    from zenswarm.leader.process import add_parser as add_leader
    from zenswarm.plant.mavlink_vehicle import add_parsers as add_vehicles
    from zenswarm.plant.process import add_parser as add_plant

    add_plant(sub)
    add_vehicles(sub)
    add_leader(sub)
    add_agent(sub)

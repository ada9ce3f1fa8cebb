"""The link model: what happens to a message between two processes of the swarm.

A run's links are described by a plan (:class:`FaultPlan`: delay, jitter, loss, bursts, timed
partitions, radio range and fading, capacity queues, a replayed trace), made once from the
scenario's ``[faults]`` table and the command line's shortcuts (:class:`LinkFaults`,
:func:`plan_for`). A receiver asks its :class:`Box` for each of its incoming links (``(src,
dst, kind)``) what becomes of a message: it offers what arrived and takes what is delivered at
a tick; lockstep decisions are pure functions of (seed, link, tick), so the simulator and the
swarm's processes decide alike. Realtime runs release kept messages late through a
:class:`DelayLine`.

This package's namespace is the one entry point: every module outside it imports
``zenswarm.link``, never one of its modules (an import-linter contract, ``bash .ci/lint``); its
modules are the model's parts: :mod:`~zenswarm.link.units` (durations, probabilities, ticks),
:mod:`~zenswarm.link.names` (processes and links), :mod:`~zenswarm.link.plan` (the plan),
:mod:`~zenswarm.link.decisions` (one message's fate), :mod:`~zenswarm.link.inbox` (the lockstep
receiver), :mod:`~zenswarm.link.config` (a plan from a scenario and the command line),
:mod:`~zenswarm.link.radio`, :mod:`~zenswarm.link.queue` (capacity and queueing),
:mod:`~zenswarm.link.trace` (trace replay) and :mod:`~zenswarm.link.swarm` (the plan of a
scenario's swarm, its boxes and graph series). :mod:`~zenswarm.link.faults` keeps the names of
the model's single module (before issue 44) for old code.
"""

from zenswarm.link.config import plan_from_scenario
from zenswarm.link.decisions import FaultState
from zenswarm.link.inbox import Held
from zenswarm.link.names import KINDS, agent_links, link_kind, parse_process, plant_links
from zenswarm.link.plan import FaultPlan, LinkFaultSpec
from zenswarm.link.queue import message_size, parse_capacity
from zenswarm.link.radio import parse_distance
from zenswarm.link.swarm import (
    Box,
    DelayLine,
    GraphSeries,
    LinkFaults,
    box_counters,
    distance,
    due_tick,
    effective_graph,
    graph_series,
    plan_for,
    scenario_links,
)
from zenswarm.link.units import delivery_tick, parse_duration

__all__ = [
    "FaultPlan", "FaultState", "Held", "LinkFaultSpec", "delivery_tick", "parse_duration", "plan_from_scenario",
    "KINDS", "agent_links", "link_kind", "parse_process",
    "plant_links", "message_size", "parse_capacity", "parse_distance", "Box", "DelayLine", "GraphSeries", "LinkFaults",
    "box_counters", "distance", "due_tick", "effective_graph", "graph_series", "plan_for", "scenario_links",
]  # fmt: skip

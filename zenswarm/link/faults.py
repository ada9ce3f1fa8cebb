"""The fault model's names as one module, as they were before it was split by concept (issue 44).

Code written for the single module (``zenswarm.link.faults``, or 0.1's ``zenswarm.faults``) keeps
working: every name it exported is here. They live in the model's modules now:
:mod:`~zenswarm.link.units` (durations, probabilities, ticks), :mod:`~zenswarm.link.names`
(processes and links), :mod:`~zenswarm.link.plan` (the plan), :mod:`~zenswarm.link.decisions`
(one message's fate), :mod:`~zenswarm.link.inbox` (the lockstep receiver) and
:mod:`~zenswarm.link.config` (a plan from a scenario and the command line). New code outside the
package imports :mod:`zenswarm.link`; tests import the module that holds a name.
"""

from __future__ import annotations

from zenswarm.link.config import plan_from_cli, plan_from_scenario, plan_with_radio
from zenswarm.link.decisions import BLOCK, BatchDelivery, Delivery, FaultState, decide
from zenswarm.link.inbox import Held, LinkInbox
from zenswarm.link.names import KINDS, agent_links, check_exists, link_kind, parse_process, plant_links
from zenswarm.link.plan import FaultPlan, GilbertElliott, LinkFaultSpec, Partition, parse_partition
from zenswarm.link.units import delivery_tick, parse_duration, parse_loss

__all__ = [
    "KINDS",
    "BLOCK",
    "GilbertElliott",
    "Partition",
    "LinkFaultSpec",
    "FaultPlan",
    "Delivery",
    "BatchDelivery",
    "FaultState",
    "Held",
    "LinkInbox",
    "decide",
    "delivery_tick",
    "link_kind",
    "parse_process",
    "parse_duration",
    "parse_partition",
    "parse_loss",
    "plan_from_cli",
    "plan_from_scenario",
    "plan_with_radio",
    "check_exists",
    "agent_links",
    "plant_links",
]

"""Supervisor policies from the scenario (pure): the ``[restart]`` backoff.

In the base layer because the scenario's loader validates the table (the supervisor in
``compose/`` applies it)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from zenswarm.schema import RestartTable, convert

__all__ = ["RestartPolicy", "restart_policy"]


@dataclass(frozen=True)
class RestartPolicy:
    """Backoff for restarting crashed processes: the n-th restart waits
    min(initial_delay_s * factor**n, max_delay_s); after max_restarts of one process the mission
    is aborted (every process stopped, the vehicles' failsafe lands them). The plant is never
    restarted (it is the world)."""

    enabled: bool = False
    initial_delay_s: float = 0.2
    factor: float = 2.0
    max_delay_s: float = 5.0
    max_restarts: int = 3

    def allows(self, role: str) -> bool:
        return self.enabled and role != "plant"

    def delay(self, n_done: int) -> float | None:
        if n_done >= self.max_restarts:
            return None
        return min(self.initial_delay_s * self.factor**n_done, self.max_delay_s)


def restart_policy(section: RestartTable | Mapping[str, Any] | None, force: bool = False) -> RestartPolicy:
    """The scenario's ``[restart]`` table (``Scenario.restart``, or a dict validated by the schema,
    :class:`zenswarm.schema.RestartTable`: enabled, initial_delay_s, factor, max_delay_s,
    max_restarts; a present table is enabled unless it says ``enabled = false``); ``force``
    (``--restart``) enables it. Errors name the field."""
    if section is None:
        return RestartPolicy(enabled=force)
    t = section if isinstance(section, RestartTable) else convert(section, RestartTable, "restart")
    return RestartPolicy(t.enabled or force, t.initial_delay_s, t.factor, t.max_delay_s, t.max_restarts)

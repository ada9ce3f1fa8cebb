"""Supervisor policies from the scenario (pure): the ``[restart]`` backoff.

In the base layer because the scenario's loader validates the table (the supervisor in
``compose/`` applies it)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from zenswarm.errors import ScenarioError

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


def restart_policy(section: dict[str, Any] | None, force: bool = False) -> RestartPolicy:
    """The scenario's ``[restart]`` table (enabled, initial_delay_s, factor, max_delay_s,
    max_restarts); ``force`` (``--restart``) enables it. Errors name the field."""
    if section is None:
        return RestartPolicy(enabled=force)
    allowed = {"enabled", "initial_delay_s", "factor", "max_delay_s", "max_restarts"}
    vals: dict[str, Any] = {}
    for k, v in section.items():
        if k not in allowed:
            raise ScenarioError(f"restart.{k}", f"unknown key (allowed: {', '.join(sorted(allowed))})")
        if k == "enabled":
            if not isinstance(v, bool):
                raise ScenarioError("restart.enabled", f"expected true or false, got {v!r}")
        elif k == "max_restarts":
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ScenarioError("restart.max_restarts", f"expected an integer >= 0, got {v!r}")
        elif isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0 or v == float("inf"):
            raise ScenarioError(f"restart.{k}", f"expected a finite number > 0, got {v!r}")
        elif k == "factor" and v < 1:
            raise ScenarioError("restart.factor", f"must be >= 1, got {v}")
        vals[k] = v
    pol = RestartPolicy(**{"enabled": True, **vals})
    return RestartPolicy(**{**pol.__dict__, "enabled": pol.enabled or force})

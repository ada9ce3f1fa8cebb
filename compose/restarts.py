"""The deaths and restarts of the processes ``zenswarm up``'s supervisor started, by its
:class:`~zenswarm.compose.policy.RestartPolicy`. Pure: wall times (monotonic s) are passed in; the
supervisor says what happens and starts the process again when :meth:`Restarts.due` says so.
"""

from __future__ import annotations

from typing import Any

from zenswarm.compose.policy import RestartPolicy

__all__ = ["Restarts"]


class Restarts:
    """The restarts ``policy`` allows: each death (:attr:`deaths`, as results.json's
    ``process_deaths``: process, how, sim_time_s), each restart waited for (:attr:`at`: role -> wall
    time it is due) and made (:attr:`done`: role -> restarts made, results.json's ``restarts``)."""

    def __init__(self, policy: RestartPolicy) -> None:
        self.policy = policy
        self.deaths: list[dict[str, Any]] = []
        self.at: dict[str, float] = {}
        self.done: dict[str, int] = {}

    def died(self, death: dict[str, Any], now: float) -> float | None:
        """A process died (``death``: process, how, sim_time_s) at wall time ``now``: the delay (s) after
        which it is restarted (:meth:`due`), or None when the policy does not restart it (disabled, the
        plant, or its restarts used up: :meth:`limit_reached`)."""
        self.deaths.append(death)
        role = death["process"]
        delay = self.policy.delay(self.done.get(role, 0)) if self.policy.allows(role) else None
        if delay is not None:
            self.at[role] = now + delay
        return delay

    def limit_reached(self, role: str) -> bool:
        """Would the policy have restarted ``role``, had its restarts not been used up?"""
        return self.policy.enabled and self.policy.allows(role)

    def waiting(self, role: str) -> bool:
        """Is ``role`` dead, waiting for its restart?"""
        return role in self.at

    def due(self, role: str, now: float) -> int | None:
        """At wall time ``now``: the number of the restart of ``role`` to make now (1 for its first),
        counted as made; None while it is not due (or none is waited for)."""
        if role not in self.at or now < self.at[role]:
            return None
        del self.at[role]
        self.done[role] = self.done.get(role, 0) + 1
        return self.done[role]

    def cancel(self) -> list[str]:
        """The flight is over: the restarts still waited for are not made; their roles."""
        roles = list(self.at)
        self.at.clear()
        return roles

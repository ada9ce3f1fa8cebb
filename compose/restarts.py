"""The deaths and restarts of the processes ``zenswarm up``'s supervisor started, by its
:class:`~zenswarm.compose.policy.RestartPolicy`, and none after the flight's end. Pure: wall times
(monotonic s) are passed in; the supervisor says what happens and starts the process again when
:meth:`Restarts.restart_now` says so.
"""

from __future__ import annotations

from typing import Any

from zenswarm.compose.policy import RestartPolicy

__all__ = ["FLIGHT_OVER_GRACE_S", "Restarts"]

FLIGHT_OVER_GRACE_S = 5.0
"""Once the plant ended the flight, the other roles leave by themselves within this long (plus
``--lockstep-timeout``); one still running then is stopped (:meth:`Restarts.flight_ended`)."""


class Restarts:
    """The restarts ``policy`` allows: each death (:attr:`deaths`, as results.json's
    ``process_deaths``: process, how, sim_time_s), each restart waited for (:attr:`at`: role -> wall
    time it is due) and made (:attr:`done`: role -> restarts made, results.json's ``restarts``)."""

    def __init__(self, policy: RestartPolicy) -> None:
        self.policy = policy
        self.deaths: list[dict[str, Any]] = []
        self.at: dict[str, float] = {}
        self.done: dict[str, int] = {}
        self.ended_at: float | None = None  # wall time the flight was first seen ended (flight_ended)

    def died(self, death: dict[str, Any], now: float) -> float | None:
        """A process died (``death``: process, how, sim_time_s) at wall time ``now``: the delay (s) after
        which it is restarted (:meth:`restart_now`), or None when the policy does not restart it (disabled, the
        plant, or its restarts used up: :meth:`limit_reached`)."""
        self.deaths.append(death)
        role = death["process"]
        delay = self.policy.delay(self.done.get(role, 0)) if self.policy.allows(role) else None
        if delay is not None:
            self.at[role] = now + delay
        return delay

    def how_died(self, role: str) -> str:
        """How ``role`` last died (``unknown`` if it did not)."""
        return next((d["how"] for d in reversed(self.deaths) if d["process"] == role), "unknown")

    def limit_reached(self, role: str) -> bool:
        """Would the policy have restarted ``role``, had its restarts not been used up?"""
        return self.policy.enabled and self.policy.allows(role)

    def waiting(self, role: str) -> bool:
        """Is ``role`` dead, waiting for its restart?"""
        return role in self.at

    def restart_now(self, role: str, now: float) -> int | None:
        """At wall time ``now``: the number of the restart of ``role`` to make now (1 for its first),
        counted as made; None while it is not due (or none is waited for)."""
        if role not in self.at or now < self.at[role]:
            return None
        del self.at[role]
        self.done[role] = self.done.get(role, 0) + 1
        return self.done[role]

    def cancel_pending(self) -> list[str]:
        """The flight is over: the restarts still waited for are not made; their roles."""
        roles = list(self.at)
        self.at.clear()
        return roles

    def flight_ended(self, now: float, grace_s: float) -> tuple[list[str], bool]:
        """The flight's clock ended the flight (seen at wall time ``now``): the restarts still waited
        for are not made (their roles, :meth:`cancel_pending`); and has ``grace_s`` gone by since it
        was first seen ended (then a process still running, one restarted just before the end waiting
        for a tick that never comes, no longer keeps the run going)?"""
        if self.ended_at is None:
            self.ended_at = now
        return self.cancel_pending(), now - self.ended_at >= grace_s

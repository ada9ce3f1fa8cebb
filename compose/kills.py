"""``zenswarm up --kill ROLE@T`` (tests and demos): who delivers each SIGKILL. In lockstep the
plant, the leader and the agents kill themselves just before the first tick at or after T
(``--kill-at-tick``, on their first start only), so the fault falls on the same tick in every
run; the rest (the recorder, every role of a realtime flight) are killed by the supervisor when
the collector's sim time gets to T (:class:`Kills`: both, for one flight). Pure.
"""

from __future__ import annotations

import signal
from collections.abc import Collection, Iterable, Sequence

from zenswarm.bus import wire
from zenswarm.process.lockstep import kill_self_line

__all__ = ["Kills", "kills_itself", "split_kills"]


def kills_itself(role: str) -> bool:
    """Does ``role`` kill itself at its tick in lockstep (the plant, the leader, an agent)?"""
    return role in ("plant", "leader") or role.startswith("agent:")


def split_kills(kills: Iterable[tuple[str, float]], *, realtime: bool, dt: float) -> tuple[dict[str, int], dict[str, int]]:
    """``--kill`` (role, T s) pairs as (the supervisor's: role -> sim time ns, the roles' own:
    role -> the first tick at or after T), ``dt`` the control tick (s)."""
    pending = {role: wire.t_ns(t) for role, t in kills}
    if realtime:
        return pending, {}
    dt_ns = wire.t_ns(dt)
    return pending, {r: -(-pending.pop(r) // dt_ns) for r in [r for r in pending if kills_itself(r)]}  # the first tick at or after T


class Kills:
    """The ``--kill`` (role, T s) pairs of one flight of control tick ``dt`` (s): those the
    supervisor delivers (:attr:`pending`: role -> sim time ns, :meth:`kills_due`), and the ticks
    the lockstep roles kill themselves at (:attr:`ticks`, handed to each on its first start,
    :meth:`take_tick`)."""

    def __init__(self, kills: Iterable[tuple[str, float]], *, realtime: bool, dt: float) -> None:
        self.dt = dt
        self.pending, self.ticks = split_kills(kills, realtime=realtime, dt=dt)
        self.started: dict[str, int] = {}  # role -> the tick it was started to kill itself at

    def take_tick(self, role: str) -> int | None:
        """The tick ``role`` is started to kill itself at: on its first start only (a restarted
        process is not killed again); None if none."""
        k = self.ticks.pop(role, None)
        if k is not None:
            self.started[role] = k
        return k

    def death_time(self, role: str, rc: int, lines: Sequence[str], t_s: float) -> float:
        """When ``role``, which exited with ``rc``, died (sim s): the tick it killed itself at,
        if it did (SIGKILL, and its last ``lines`` say so), else ``t_s`` (when the supervisor saw it)."""
        k = self.started.pop(role, None)
        if k is not None and rc == -signal.SIGKILL and any(ln.endswith(kill_self_line(k)) for ln in lines[-3:]):
            return k * self.dt
        return t_s

    def kills_due(self, sim_t_ns: int, running: Collection[str]) -> list[str]:
        """The roles the supervisor SIGKILLs now: their sim time has come (``sim_t_ns``, the
        collector's) and they are ``running`` (a role not running yet waits); taken (each is killed once)."""
        due = [r for r, at_ns in self.pending.items() if sim_t_ns >= at_ns and r in running]
        for r in due:
            del self.pending[r]
        return due

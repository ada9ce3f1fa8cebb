"""``zenswarm up --kill ROLE@T`` (tests and demos): who delivers each SIGKILL. In lockstep the
plant, the leader and the agents kill themselves just before the first tick at or after T
(``--kill-at-tick``, on their first start only), so the fault falls on the same tick in every
run; the rest (the recorder, every role of a realtime flight) are killed by the supervisor when
the collector's sim time gets to T. Pure.
"""

from __future__ import annotations

from collections.abc import Iterable

from zenswarm.bus import wire

__all__ = ["kills_itself", "split_kills"]


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

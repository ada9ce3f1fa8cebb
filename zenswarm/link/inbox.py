"""The receiver side of a link in lockstep: hold last value.

In lockstep the *sequence number of a message on a link is its tick*: the tick of its sim time
``t`` (``round(t / dt)``), and ``t_send_s = send_tick * dt`` (:mod:`zenswarm.link.decisions`). Every
process sends one message per link per tick, so a receiver can work out which message it needs
without waiting for the dropped ones: :meth:`LinkInbox.due`. A message of tick ``j`` with delay
``d`` is available from tick :func:`~zenswarm.link.units.delivery_tick` ``(j, d, dt)``.
:class:`LinkInbox` implements the receiver's *hold last value* policy: at tick ``k`` it holds the
newest (largest send tick) message that was not dropped and whose delivery tick is ``<= k``, never
goes back to an older one, and reports its age in ticks. The simulator and the agent/plant
processes both use it (through :class:`zenswarm.link.swarm.Box`), so they agree bit for bit.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from zenswarm.link.decisions import REASONS, Delivery, FaultState, check_seq
from zenswarm.link.names import KIND_ROLES, KINDS
from zenswarm.link.plan import FaultPlan
from zenswarm.link.units import EPS_TICK

__all__ = ["Held", "LinkInbox"]

_CHUNK = 256  # LinkInbox computes decisions in batches of this many ticks (a cache, not a definition)
_Chunk = tuple[list[bool], list[float], list[str], list[int]]
"""One batch of :class:`LinkInbox` decisions: dropped, delay_s, reason, delivery tick (one per send tick)."""


@dataclass(frozen=True)
class Held:
    """The value a receiver holds at tick k: the message's value, send tick and wire seq, and its
    age ``k - send_tick`` in ticks."""

    value: Any
    send_tick: int
    seq: int
    age_ticks: int


class LinkInbox:
    """Receiver side of one directed link in lockstep: the *hold last value* policy.

    Feed it every message that arrives on the link with :meth:`offer` (any order, duplicates
    ignored); ask :meth:`at` at each tick k, in non-decreasing order. The decision for a message
    is ``decide(plan, src, dst, kind, seq=send_tick, t_send_s=send_tick * dt)``: in lockstep a
    link's sequence number is the message's tick (one message per link per tick), which the
    receiver can predict, so :meth:`due` tells it which message it needs at tick k without
    waiting for dropped ones. The wire ``seq`` is kept only for information.

    Policy: ``at(k)`` holds the newest (largest send tick) offered message that was not dropped
    and whose :func:`delivery_tick` is ``<= k``; it never returns to an older message. A value
    expires only with a hold horizon (:attr:`FaultPlan.hold_s`, references only): beyond it ``at``
    returns None (counted in ``expired``); otherwise the age says how stale it is. ``None`` until
    the first message is delivered.

    Counters (:meth:`counters`), all deterministic when ``at`` is called every tick after the
    due message was offered: ``received`` offers (not counting duplicates), ``delivered`` (not
    dropped), ``dropped`` and ``dropped_<reason>``, ``late`` (delivered but never held because a
    newer message was available no later: overtaken through jitter), ``duplicates``,
    ``overflow`` (pending messages evicted beyond ``capacity``), ``timeouts`` (reported by the
    caller with :meth:`mark_timeout`), ``age_ticks`` (at the last ``at``) and ``max_age_ticks``.
    """

    def __init__(
        self,
        faults: FaultPlan | FaultState,
        src: str,
        dst: str,
        kind: str,
        dt: float,
        *,
        first_tick: int = 0,
        capacity: int = 4096,
    ) -> None:
        self.state = faults if isinstance(faults, FaultState) else FaultState(faults)
        if kind not in KIND_ROLES:
            raise ValueError(f"unknown message kind {kind!r} (allowed: {', '.join(KINDS)})")
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt!r}")
        self.src, self.dst, self.kind, self.dt = src, dst, kind, float(dt)
        self.first_tick = check_seq(first_tick)
        self.capacity = max(1, int(capacity))
        self.spec = self.state.plan.spec_for(src, dst, kind)
        self.horizon = self.state.plan.horizon_ticks(src, dst, kind, self.dt)
        self.hold_ticks = self.state.plan.hold_ticks(kind, self.dt)  # None: a held value never expires
        self._pending: dict[int, tuple[int, Any, int]] = {}  # send_tick -> (seq, value, delivery tick)
        self._seen: OrderedDict[int, None] = OrderedDict()
        self._held: tuple[int, int, Any] | None = None  # (send_tick, seq, value)
        self._last_k: int | None = None
        self._due_memo: tuple[int, int | None] | None = None  # (k, due(k))
        self._chunks: OrderedDict[int, _Chunk] = OrderedDict()
        self._n = {
            "received": 0,
            "delivered": 0,
            "dropped": 0,
            "dropped_loss": 0,
            "dropped_burst": 0,
            "dropped_partition": 0,
            "dropped_trace": 0,
            "dropped_queue": 0,
            "late": 0,
            "duplicates": 0,
            "overflow": 0,
            "timeouts": 0,
            "age_ticks": -1,
            "max_age_ticks": -1,
        }
        if self.hold_ticks is not None:
            self._n["expired"] = 0  # ticks the held reference was beyond the hold horizon

    @property
    def link(self) -> tuple[str, str, str]:
        return (self.src, self.dst, self.kind)

    def decision(self, send_tick: int) -> Delivery:
        """The fault decision of this link's message of ``send_tick``."""
        j = check_seq(send_tick)
        dropped, delay, reason, _ = self._chunk(j // _CHUNK)
        i = j % _CHUNK
        return Delivery(dropped[i], delay[i], reason[i])

    def _chunk(self, c: int) -> _Chunk:
        """Decisions of send ticks c*_CHUNK .. (c+1)*_CHUNK - 1, computed in one batch
        (element for element equal to :meth:`FaultState.decide`): dropped, delay_s, reason,
        delivery tick."""
        r = self._chunks.get(c)
        if r is None:
            j = np.arange(c * _CHUNK, (c + 1) * _CHUNK, dtype=np.int64)
            b = self.state.decide_batch(self.src, self.dst, self.kind, j, j * self.dt)
            dtick = j + np.maximum(0.0, np.ceil(b.delay_s / self.dt - EPS_TICK)).astype(np.int64)
            r = (
                b.dropped.tolist(),
                b.delay_s.tolist(),
                [REASONS[x] for x in b.reason.tolist()],
                dtick.tolist(),
            )
            self._chunks[c] = r
            if len(self._chunks) > 2 + (self.horizon + 1) // _CHUNK + 2:
                self._chunks.popitem(last=False)
        else:
            self._chunks.move_to_end(c)
        return r

    def _fate(self, j: int) -> tuple[bool, int]:
        """(dropped, delivery tick) of send tick j."""
        dropped, _, _, dtick = self._chunk(j // _CHUNK)
        i = j % _CHUNK
        return dropped[i], dtick[i]

    def offer(self, send_tick: int, seq: int, value: Any) -> Delivery:
        """A message of ``send_tick`` arrived (or, in the simulator, was sent). Returns its fate."""
        j = check_seq(send_tick)
        d = self.decision(j)
        dropped, dtick = self._fate(j)
        if j in self._seen or (self._held is not None and j == self._held[0]):
            self._n["duplicates"] += 1
            return d
        self._seen[j] = None
        if len(self._seen) > self.capacity:
            self._seen.popitem(last=False)
        self._n["received"] += 1
        if dropped:
            self._n["dropped"] += 1
            self._n["dropped_" + d.reason] += 1
            return d
        self._n["delivered"] += 1
        if self._held is not None and j < self._held[0]:
            self._n["late"] += 1
            return d
        self._pending[j] = (int(seq), value, dtick)
        if len(self._pending) > self.capacity:
            del self._pending[min(self._pending)]
            self._n["overflow"] += 1
        return d

    def due(self, k: int) -> int | None:
        """Send tick of the message :meth:`at` ``(k)`` holds if every message the sender sent by
        tick k arrives: the newest non-dropped ``j <= k`` with delivery tick ``<= k``; None if
        there is none (yet). The lockstep caller waits for exactly this message (if it has not
        been offered) and then calls ``at(k)``. Incremental: O(ticks since the last call +
        horizon) when k does not decrease."""
        k = int(k)
        lo = self.first_tick
        best: int | None = None
        memo = self._due_memo
        if memo is not None and k >= memo[0]:
            k0, best = memo
            if k == k0:
                return best
            # j <= k0 - horizon with delivery <= k0 were already considered at k0
            lo = max(lo, k0 - self.horizon + 1, (best + 1) if best is not None else lo)
        for j in range(k, lo - 1, -1):  # bounded: k - lo + 1 iterations
            dropped, dtick = self._fate(j)
            if not dropped and dtick <= k:
                best = j
                break
        self._due_memo = (k, best)
        return best

    def pending_ticks(self) -> list[int]:
        """Send ticks offered, delivered, not yet held (sorted)."""
        return sorted(self._pending)

    def has(self, send_tick: int) -> bool:
        """Was the message of ``send_tick`` offered (or overtaken/dropped after being offered)?"""
        return send_tick in self._seen or (self._held is not None and self._held[0] == send_tick)

    def at(self, k: int) -> Held | None:
        """Hold-last-value read at tick ``k`` (ticks must not decrease)."""
        k = int(k)
        if self._last_k is not None and k < self._last_k:
            raise ValueError(f"ticks must not go backwards: at({k}) after at({self._last_k})")
        self._last_k = k
        ready = [j for j, (_, _, dtick) in self._pending.items() if dtick <= k]
        if ready:
            newest = max(ready)
            seq, value, _ = self._pending[newest]
            for j in [j for j in self._pending if j < newest]:
                del self._pending[j]
                self._n["late"] += 1
            del self._pending[newest]
            self._held = (newest, seq, value)
        if self._held is None:
            return None
        age = k - self._held[0]
        self._n["age_ticks"] = age
        if age > self._n["max_age_ticks"]:
            self._n["max_age_ticks"] = age
        if self.hold_ticks is not None and age > self.hold_ticks:
            self._n["expired"] += 1  # beyond the hold horizon: not heard this tick
            return None
        return Held(self._held[2], self._held[0], self._held[1], age)

    def mark_timeout(self, send_tick: int) -> None:
        """The caller waited for the due message of ``send_tick`` and gave up (wall clock)."""
        self._n["timeouts"] += 1

    def counters(self) -> dict[str, int]:
        """A copy of the counters (for diagnostics)."""
        return dict(self._n)

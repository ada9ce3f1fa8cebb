"""Decisions: the fate of one message on one directed link, a pure function of the plan.

:func:`decide` (and :meth:`FaultState.decide`) returns a :class:`Delivery` that is a pure function
of ``(plan, src, dst, kind, seq, t_send_s)``: never of arrival order, call order, or which other
sequence numbers were asked for. Uniform draws come from a counter-based generator: the
sequence numbers of one link and one *stream* (``loss``, ``jitter``, ``ge_trans``, ``ge_loss``,
``ge_init``) are cut into blocks of :data:`BLOCK` and block ``b`` is
``numpy.random.Philox(key=blake2b(seed, src, dst, kind, stream, b)).random_raw(BLOCK)``, turned
into doubles in [0, 1) by ``(raw >> 11) * 2**-53``. Philox's raw output is a fixed, documented
stream, so decisions do not change across numpy versions or platforms.

Per decision, in order of precedence for the reported reason:

1. ``partition``: a :class:`~zenswarm.link.plan.Partition` covering the link is active at ``t_send_s``
   (``t_start_s <= t_send_s < t_end_s``);
2. ``burst``: Gilbert-Elliott chain of the link is in state bad (good) at ``seq`` and
   ``u_ge_loss[seq] < loss_bad`` (``loss_good``);
3. ``loss``: ``u_loss[seq] < loss``;
4. otherwise ``ok``.

On a link named by the plan's trace (:mod:`zenswarm.link.trace`) rules 2-3, the delay and the jitter
are replaced by the trace's row in force at ``t_send_s`` (a dropped row: reason ``trace``).
Then, on a link with a capacity (:mod:`zenswarm.link.queue`, ``seq`` is the tick), the queue's
wait and serialization time are added to the delay, and a message a full queue refused is
dropped with reason ``queue`` whatever the other rules said.

Every stream is drawn whether or not an earlier rule already dropped the message, so changing one
kind of fault never reshuffles another. The delay is
``max(0, delay_s + jitter_s * (2 u_jitter[seq] - 1))`` (uniform in ``[delay - jitter,
delay + jitter]``, floored at 0), reported for dropped messages too.

The Gilbert-Elliott chain of a link is one fixed Markov chain over sequence numbers:
state(0) is drawn from the stationary law (bad with probability
``pi_bad = p_gb / (p_gb + p_bg)``) and state(n) = T(state(n-1), u_ge_trans[n]) with
``T(good, u) = bad iff u < p_good_to_bad`` and ``T(bad, u) = good iff u < p_bad_to_good``.
:class:`FaultState` evaluates it block by block (vectorised) and memoises the state at each block
boundary, so asking for seq 10**6 first or last gives the same answer.

In lockstep a message's sequence number on a link is its tick (:mod:`zenswarm.link.inbox`). In
realtime the same :func:`decide` applies with ``seq`` the message's wire ``seq`` and ``t_send_s``
its sim/wall time since the start of the mission; the receiver releases a kept message
``delay_s`` after it arrived (:class:`zenswarm.link.swarm.DelayLine`).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from zenswarm.link.names import KIND_ROLES, KINDS
from zenswarm.link.plan import FaultPlan, GilbertElliott

__all__ = ["BLOCK", "REASONS", "Delivery", "BatchDelivery", "FaultState", "decide", "check_seq"]


#: Sequence numbers per block of the counter-based generator. Part of the definition of the
#: decisions (changing it changes every decision), so it is not a parameter.
BLOCK = 1024

#: The streams of uniforms of a link, one generator each (the module docstring).
_STREAMS = ("loss", "jitter", "ge_trans", "ge_loss", "ge_init")
#: Reasons of a decision, in the order of :attr:`BatchDelivery.reason`'s codes.
REASONS = ("ok", "loss", "burst", "partition", "trace", "queue")
_TWO_M53 = 2.0**-53


@dataclass(frozen=True)
class Delivery:
    """Fate of one message. dropped; delay_s >= 0 (s, also given when dropped); reason:
    ``ok``, ``loss``, ``burst``, ``partition``, ``trace`` (dropped by a replayed trace) or ``queue``
    (dropped by a full capacity queue at the sender)."""

    dropped: bool
    delay_s: float
    reason: str


@dataclass(frozen=True)
class BatchDelivery:
    """:meth:`FaultState.decide_batch` result: arrays of shape (m,). reason codes index
    :attr:`REASONS` (0 ok, 1 loss, 2 burst, 3 partition, 4 trace, 5 queue)."""

    dropped: np.ndarray
    delay_s: np.ndarray
    reason: np.ndarray
    REASONS = REASONS


def _key128(seed: int, link: tuple[str, str, str], stream: str, block: int) -> int:
    # the personalisation is part of the decisions' definition: the module's name before 0.2, kept
    h = hashlib.blake2b(digest_size=16, person=b"zenswarm.faults")
    h.update("\x1f".join((str(seed), link[0], link[1], link[2], stream, str(block))).encode())
    return int.from_bytes(h.digest(), "little")


def _ge_block_states(s0: bool, u: np.ndarray, p_gb: float, p_bg: float) -> np.ndarray:
    """States of one block given the state at its first index (``u[0]`` is unused there).

    Each step maps the previous state through T(., u): a constant (u forces the state), the
    identity, or a flip; the state at i is the last constant's value XOR the parity of the flips
    after it. Vectorised, exact.
    """
    n = u.shape[0]
    go = u < p_gb  # good -> bad
    stay = u >= p_bg  # bad -> bad
    const = go == stay
    flip = go & ~stay
    const[0] = True
    flip[0] = False
    val = go.copy()
    val[0] = s0
    last = np.maximum.accumulate(np.where(const, np.arange(n), 0))
    cf = np.cumsum(flip, dtype=np.int64)  # flip counts (what cumsum of bools gives, said explicitly)
    states: np.ndarray = val[last] ^ ((cf - cf[last]) & 1).astype(bool)
    return states


def _ge_step(s: bool, u: float, p_gb: float, p_bg: float) -> bool:
    return bool(u >= p_bg) if s else bool(u < p_gb)


class FaultState:
    """Caches for :func:`decide` under one plan: uniform blocks (LRU, at most ``cache_blocks``)
    and each link's Gilbert-Elliott chain (its state at every block boundary, computed in order on
    demand, plus recent blocks of states). The caches never change a result; they only make
    repeated queries fast. Memory: bounded by ``cache_blocks`` blocks plus one bool per
    :data:`BLOCK` sequence numbers per burst link.
    """

    def __init__(self, plan: FaultPlan, cache_blocks: int = 1024) -> None:
        if not isinstance(plan, FaultPlan):
            raise TypeError(f"plan must be a FaultPlan, got {type(plan).__name__}")
        self.plan = plan
        self.cache_blocks = max(1, int(cache_blocks))
        self._blocks: OrderedDict[tuple[object, ...], np.ndarray] = OrderedDict()
        self._ge_starts: dict[tuple[str, str, str], list[bool]] = {}

    # -- uniforms
    def _compute_ublock(self, link: tuple[str, str, str], stream: str, b: int) -> np.ndarray:
        raw = np.random.Philox(key=_key128(self.plan.seed, link, stream, b)).random_raw(BLOCK)
        return (raw >> np.uint64(11)).astype(np.float64) * _TWO_M53

    def _cached(self, key: tuple[object, ...], make: Callable[[], np.ndarray]) -> np.ndarray:
        arr = self._blocks.get(key)
        if arr is None:
            arr = make()
            self._blocks[key] = arr
            if len(self._blocks) > self.cache_blocks:
                self._blocks.popitem(last=False)
        else:
            self._blocks.move_to_end(key)
        return arr

    def uniform_block(self, link: tuple[str, str, str], stream: str, b: int) -> np.ndarray:
        """Uniforms of ``stream`` for seqs ``b*BLOCK .. (b+1)*BLOCK - 1`` of ``link``, shape (BLOCK,)."""
        return self._cached(("u", link, stream, b), lambda: self._compute_ublock(link, stream, b))

    def uniform(self, link: tuple[str, str, str], stream: str, seq: int) -> float:
        b, i = divmod(seq, BLOCK)
        return float(self.uniform_block(link, stream, b)[i])

    # -- Gilbert-Elliott
    def _ge_start(self, link: tuple[str, str, str], ge: GilbertElliott, b: int) -> bool:
        starts = self._ge_starts.get(link)
        if starts is None:
            u0 = float(self._compute_ublock(link, "ge_init", 0)[0])
            starts = self._ge_starts[link] = [bool(u0 < ge.pi_bad)]
        while len(starts) <= b:  # bounded: b + 1 - len(starts) iterations
            bb = len(starts) - 1
            states = self._ge_states_from(link, ge, bb, starts[bb])
            u_next = float(self._compute_ublock(link, "ge_trans", bb + 1)[0])
            starts.append(_ge_step(bool(states[-1]), u_next, ge.p_good_to_bad, ge.p_bad_to_good))
        return starts[b]

    def _ge_states_from(self, link: tuple[str, str, str], ge: GilbertElliott, b: int, s0: bool) -> np.ndarray:
        key = ("ge", link, b)
        arr = self._blocks.get(key)
        if arr is not None:
            return arr
        u = self._compute_ublock(link, "ge_trans", b)
        return _ge_block_states(s0, u, ge.p_good_to_bad, ge.p_bad_to_good)

    def ge_block(self, link: tuple[str, str, str], ge: GilbertElliott, b: int) -> np.ndarray:
        """Chain states (True = bad) of seqs ``b*BLOCK .. (b+1)*BLOCK - 1``, shape (BLOCK,)."""
        return self._cached(("ge", link, b), lambda: self._ge_states_from(link, ge, b, self._ge_start(link, ge, b)))

    def ge_bad(self, src: str, dst: str, kind: str, seq: int) -> bool:
        """Is the link's Gilbert-Elliott chain in the bad state at ``seq``? (False without burst.)"""
        ge = self.plan.spec_for(src, dst, kind).burst
        if ge is None:
            return False
        b, i = divmod(check_seq(seq), BLOCK)
        return bool(self.ge_block((src, dst, kind), ge, b)[i])

    # -- decisions
    def decide(self, src: str, dst: str, kind: str, seq: int, t_send_s: float) -> Delivery:
        """See :func:`decide`."""
        seq = check_seq(seq)
        if kind not in KIND_ROLES:
            raise ValueError(f"unknown message kind {kind!r} (allowed: {', '.join(KINDS)})")
        d = self._decide_model(src, dst, kind, seq, t_send_s)
        queues = self.plan.queues
        if queues is not None and (src, dst, kind) in queues:
            q_drop, q_wait = queues.one((src, dst, kind), seq)
            d = Delivery(True, q_wait + d.delay_s, "queue") if q_drop else Delivery(d.dropped, q_wait + d.delay_s, d.reason)
        return d

    def _decide_model(self, src: str, dst: str, kind: str, seq: int, t_send_s: float) -> Delivery:
        plan = self.plan
        spec = plan.spec_for(src, dst, kind)
        link = (src, dst, kind)
        delay = spec.delay_s
        traced = plan.trace is not None and link in plan.trace
        if traced:
            assert plan.trace is not None
            delay, delivered = plan.trace.lookup(link, t_send_s)
        elif spec.jitter_s > 0.0:
            delay = max(0.0, delay + spec.jitter_s * (2.0 * self.uniform(link, "jitter", seq) - 1.0))
        t = float(t_send_s)
        for p in plan.partitions:
            if p.covers(src, dst, t):
                return Delivery(True, delay, "partition")
        for p in spec.partitions:
            if p.covers(src, dst, t):
                return Delivery(True, delay, "partition")
        if traced:
            return Delivery(not delivered, delay, "ok" if delivered else "trace")
        ge = spec.burst
        if ge is not None:
            b, i = divmod(seq, BLOCK)
            bad = bool(self.ge_block(link, ge, b)[i])
            p_drop = ge.loss_bad if bad else ge.loss_good
            if p_drop > 0.0 and self.uniform(link, "ge_loss", seq) < p_drop:
                return Delivery(True, delay, "burst")
        if spec.loss > 0.0 and self.uniform(link, "loss", seq) < spec.loss:
            return Delivery(True, delay, "loss")
        return Delivery(False, delay, "ok")

    def decide_batch(self, src: str, dst: str, kind: str, seqs: Any, t_send_s: Any) -> BatchDelivery:
        """Vectorised :meth:`decide` over seqs (m,) and send times (m,) (or a scalar time);
        element for element equal to it."""
        if kind not in KIND_ROLES:
            raise ValueError(f"unknown message kind {kind!r} (allowed: {', '.join(KINDS)})")
        seqs = np.asarray(seqs)
        if seqs.ndim != 1 or (seqs.size and (seqs.dtype.kind not in "iu" or seqs.min() < 0)):
            raise ValueError("seqs must be a 1-d array of integers >= 0")
        seqs = seqs.astype(np.int64)
        t = np.broadcast_to(np.asarray(t_send_s, dtype=float), seqs.shape)
        spec = self.plan.spec_for(src, dst, kind)
        link = (src, dst, kind)
        m = seqs.size
        blk = seqs // BLOCK
        idx = seqs % BLOCK
        order = np.argsort(blk, kind="stable")
        blocks, starts = np.unique(blk[order], return_index=True)
        ends = np.append(starts[1:], m)

        def gather(get: Callable[[int], np.ndarray]) -> np.ndarray:
            out = np.empty(m)
            for b, s0, s1 in zip(blocks.tolist(), starts.tolist(), ends.tolist(), strict=True):
                sel = order[s0:s1]
                out[sel] = get(b)[idx[sel]]
            return out

        delay = np.full(m, spec.delay_s)
        reason = np.zeros(m, dtype=np.uint8)
        trace = self.plan.trace
        if trace is not None and link in trace:
            delay, delivered = trace.lookup_batch(link, t)
            reason[~delivered] = 4
            spec = replace(spec, jitter_s=0.0, loss=0.0, burst=None)
        if spec.jitter_s > 0.0:
            u = gather(lambda b: self.uniform_block(link, "jitter", b))
            delay = np.maximum(0.0, spec.delay_s + spec.jitter_s * (2.0 * u - 1.0))
        if spec.loss > 0.0:
            u = gather(lambda b: self.uniform_block(link, "loss", b))
            reason[u < spec.loss] = 1
        ge = spec.burst
        if ge is not None:
            bad = gather(lambda b: self.ge_block(link, ge, b).astype(float)) > 0.5
            p_drop = np.where(bad, ge.loss_bad, ge.loss_good)
            u = gather(lambda b: self.uniform_block(link, "ge_loss", b))
            reason[(p_drop > 0.0) & (u < p_drop)] = 2
        for p in tuple(self.plan.partitions) + spec.partitions:
            if p.applies_to(src, dst):
                reason[(p.t_start_s <= t) & (t < p.t_end_s)] = 3
        queues = self.plan.queues
        if queues is not None and link in queues:
            q_drop, q_wait = queues.batch(link, seqs)
            delay = q_wait + delay
            reason[q_drop] = 5
        return BatchDelivery(reason > 0, delay, reason)


def check_seq(seq: Any) -> int:
    """``seq`` as an int; ValueError unless it is an integer >= 0 (a sequence number or a tick)."""
    if isinstance(seq, bool) or not isinstance(seq, (int, np.integer)) or seq < 0:
        raise ValueError(f"seq must be an integer >= 0, got {seq!r}")
    return int(seq)


def decide(
    plan: FaultPlan, src: str, dst: str, kind: str, seq: int, t_send_s: float, state: FaultState | None = None
) -> Delivery:
    """Fate of the message ``seq`` sent at ``t_send_s`` (s) on ``src -> dst`` of ``kind``.

    A pure function of (plan.seed, link, kind, seq, t_send_s) and the plan's specs; see the module
    docstring for the rules. ``state`` is an optional cache (a :class:`FaultState` of this plan);
    without one a fresh cache is used, which is correct but recomputes burst chains from seq 0.
    """
    if state is None:
        state = FaultState(plan)
    elif state.plan is not plan:
        raise ValueError("state belongs to another plan")
    return state.decide(src, dst, kind, seq, t_send_s)

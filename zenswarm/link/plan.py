"""The plan of a run's link faults.

A :class:`LinkFaultSpec` is what happens on one directed link ``(src, dst, kind)``: delay, jitter,
independent loss, Gilbert-Elliott burst loss (:class:`GilbertElliott`), timed partitions
(:class:`Partition`), a radio model (:mod:`zenswarm.link.radio`) and a capacity queue
(:mod:`zenswarm.link.queue`). A :class:`FaultPlan` holds a run's specs (a default and per-link
globs, the last match winning), its seed, the partitions that cut whatever a link resolves to,
a replayed trace (:mod:`zenswarm.link.trace`), the capacity queues and the hold horizon of the
references. Plans are made from a scenario and the command line by :mod:`zenswarm.link.config`;
what a plan does to each message is decided by :mod:`zenswarm.link.decisions`.
"""

from __future__ import annotations

import fnmatch
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenswarm.link.names import KINDS, parse_process, parse_target
from zenswarm.link.queue import LinkQueues, QueueSpec
from zenswarm.link.radio import RADIO_KINDS, RadioModel
from zenswarm.link.trace import LinkTrace
from zenswarm.link.units import delivery_tick, parse_duration

__all__ = ["GilbertElliott", "Partition", "LinkFaultSpec", "FaultPlan", "parse_partition"]


@dataclass(frozen=True)
class GilbertElliott:
    """Two-state burst-loss channel, stepped once per sequence number of a link.

    p_good_to_bad, p_bad_to_good: transition probabilities per message, in [0, 1], not both 0;
    loss_good, loss_bad: drop probability in each state, in [0, 1].
    """

    p_good_to_bad: float
    p_bad_to_good: float
    loss_good: float = 0.0
    loss_bad: float = 1.0

    def __post_init__(self) -> None:
        for name in ("p_good_to_bad", "p_bad_to_good", "loss_good", "loss_bad"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 <= float(v) <= 1.0):
                raise ValueError(f"{name} must be a number in [0, 1], got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.p_good_to_bad + self.p_bad_to_good <= 0.0:
            raise ValueError("p_good_to_bad and p_bad_to_good cannot both be 0")

    @property
    def pi_bad(self) -> float:
        """Stationary probability of the bad state, p_gb / (p_gb + p_bg)."""
        return self.p_good_to_bad / (self.p_good_to_bad + self.p_bad_to_good)

    @property
    def mean_loss(self) -> float:
        """Long-run drop rate from bursts alone: pi_bad loss_bad + pi_good loss_good."""
        pb = self.pi_bad
        return pb * self.loss_bad + (1.0 - pb) * self.loss_good

    @property
    def mean_burst_length(self) -> float:
        """Mean sojourn in the bad state, messages: 1 / p_bad_to_good (inf if 0)."""
        return math.inf if self.p_bad_to_good == 0 else 1.0 / self.p_bad_to_good


@dataclass(frozen=True)
class Partition:
    """A timed cut. ``process_or_link``: ``agent:2`` cuts every link to and from agent 2;
    ``agent:1->agent:2`` cuts that one directed link. Down for ``t_start_s <= t_send < t_end_s``
    (s of sim time; ``t_end_s`` may be inf)."""

    process_or_link: str
    t_start_s: float
    t_end_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "process_or_link", parse_target(self.process_or_link))
        t0, t1 = float(self.t_start_s), float(self.t_end_s)
        if not (math.isfinite(t0) and t0 >= 0.0):
            raise ValueError(f"partition start must be finite and >= 0, got {self.t_start_s!r}")
        if math.isnan(t1) or not t1 > t0:
            raise ValueError(f"partition end must be after its start, got {self.t_start_s!r}..{self.t_end_s!r}")
        object.__setattr__(self, "t_start_s", t0)
        object.__setattr__(self, "t_end_s", t1)

    def applies_to(self, src: str, dst: str) -> bool:
        p = self.process_or_link
        if "->" in p:
            return p == f"{src}->{dst}"
        return p == src or p == dst

    def covers(self, src: str, dst: str, t_send_s: float) -> bool:
        """True if this partition drops a message sent on ``src -> dst`` at ``t_send_s``."""
        return self.t_start_s <= t_send_s < self.t_end_s and self.applies_to(src, dst)

    def __str__(self) -> str:
        end = "inf" if math.isinf(self.t_end_s) else f"{self.t_end_s:g}s"
        return f"{self.process_or_link}@{self.t_start_s:g}s-{end}"


def _parse_end(text: str) -> float:
    return math.inf if text.strip() in ("inf", "end") else parse_duration(text)


def parse_partition(text: str) -> Partition:
    """``"agent:2@10s-13s"`` or ``"agent:1->agent:2@10s-13.5s"`` -> :class:`Partition`.

    The end may be ``inf`` (or ``end``): down for the rest of the run. Raises ValueError naming
    the bad text.
    """
    if not isinstance(text, str) or "@" not in text:
        raise ValueError(f"invalid partition {text!r}: expected TARGET@START-END, e.g. 'agent:2@10s-13s'")
    target, _, rng = text.rpartition("@")
    tgt = parse_target(target)
    # split START-END at the '-' that leaves two valid parts (durations may contain 'e-3')
    for m in re.finditer("-", rng):
        a, b = rng[: m.start()], rng[m.end() :]
        try:
            t0, t1 = parse_duration(a), _parse_end(b)
        except ValueError:
            continue
        if not t1 > t0:
            raise ValueError(f"invalid partition {text!r}: end must be after start ({b.strip()} <= {a.strip()})")
        return Partition(tgt, t0, t1)
    raise ValueError(f"invalid partition {text!r}: expected START-END durations after '@', e.g. '10s-13s'")


@dataclass(frozen=True)
class LinkFaultSpec:
    """Faults on one directed link. delay_s, jitter_s >= 0 s; loss in [0, 1]; optional burst
    loss; partitions (each only applies where it matches the link, see :class:`Partition`);
    radio: a geometry-dependent model (:class:`zenswarm.link.radio.RadioModel`), applied by the
    receive boxes of the radio kinds only (``ref``, ``leader``; :data:`zenswarm.link.radio.RADIO_KINDS`);
    queue: optional capacity and bounded queue (:class:`zenswarm.link.queue.QueueSpec`)."""

    delay_s: float = 0.0
    jitter_s: float = 0.0
    loss: float = 0.0
    burst: GilbertElliott | None = None
    partitions: tuple[Partition, ...] = ()
    radio: RadioModel | None = None
    queue: QueueSpec | None = None

    def __post_init__(self) -> None:
        for name in ("delay_s", "jitter_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
            object.__setattr__(self, name, float(v))
        if isinstance(self.loss, bool) or not isinstance(self.loss, (int, float)) or not (0.0 <= self.loss <= 1.0):
            raise ValueError(f"loss must be a number in [0, 1], got {self.loss!r}")
        object.__setattr__(self, "loss", float(self.loss))
        if self.burst is not None and not isinstance(self.burst, GilbertElliott):
            raise ValueError(f"burst must be a GilbertElliott or None, got {self.burst!r}")
        parts = tuple(self.partitions)
        for p in parts:
            if not isinstance(p, Partition):
                raise ValueError(f"partitions must hold Partition objects, got {p!r}")
        object.__setattr__(self, "partitions", parts)
        if self.radio is not None and not isinstance(self.radio, RadioModel):
            raise ValueError(f"radio must be a RadioModel or None, got {self.radio!r}")

    @property
    def max_delay_s(self) -> float:
        return self.delay_s + self.jitter_s

    @property
    def active(self) -> bool:
        return bool(self.delay_s or self.jitter_s or self.loss or self.burst is not None or self.partitions
                    or self.radio_active or self.queue)

    @property
    def radio_active(self) -> bool:
        """A radio model that can drop a message is set."""
        return self.radio is not None and self.radio.active


def _norm_link_key(key: Any) -> tuple[str, str, str]:
    if isinstance(key, str):
        if "->" not in key:
            raise ValueError(f"invalid link pattern {key!r}: expected 'src->dst' or a (src, dst, kind) tuple")
        a, _, b = key.partition("->")
        key = (a.strip(), b.strip(), "*")
    if not (isinstance(key, tuple) and len(key) == 3 and all(isinstance(x, str) and x for x in key)):
        raise ValueError(f"invalid link pattern {key!r}: expected (src, dst, kind) strings")
    src, dst, kind = key
    if kind not in KINDS and not any(c in kind for c in "*?["):
        raise ValueError(f"invalid link pattern {key!r}: unknown kind {kind!r} (allowed: {', '.join(KINDS)}, or a glob)")
    for x in (src, dst):
        if not any(c in x for c in "*?["):
            parse_process(x)
    return (src, dst, kind)


@dataclass(frozen=True)
class FaultPlan:
    """Every link fault of a run.

    default: spec of every link no ``per_link`` entry matches.
    per_link: ``{(src, dst, kind): spec}`` where each part may be a glob (``agent:*``, ``*``), or
      ``{"src->dst": spec}`` (any kind). When several match, the *last* one (insertion order) wins;
      the spec replaces the default entirely.
    seed: keys every random draw (the run's ``--seed``).
    partitions: timed cuts that apply whatever spec a link resolves to (``--partition``).
    trace: per-link delay/delivery replayed in place of the model on the links it names
      (:class:`zenswarm.link.trace.LinkTrace`, ``--link-trace``).
    queues: the capacity queues of the run's links (:class:`zenswarm.link.queue.LinkQueues`, built
      from the specs' ``queue`` and the scenario's graph by :func:`zenswarm.link.swarm.plan_for`).
    hold_s: the hold horizon of the references, s (``[faults] hold``; None: forever). On the
      ``ref`` and ``leader`` links a receive box holds its newest message only while it is at
      most ``ceil(hold_s / dt)`` ticks old (counted from its send tick); older, :meth:`zenswarm.link.inbox.LinkInbox.at`
      returns None: the neighbour (or leader) is not heard and eqs (16)-(17) leave it out.
    """

    default: LinkFaultSpec = field(default_factory=LinkFaultSpec)
    per_link: Mapping[Any, LinkFaultSpec] = field(default_factory=dict)
    seed: int = 0
    partitions: tuple[Partition, ...] = ()
    trace: LinkTrace | None = None
    queues: LinkQueues | None = None
    hold_s: float | None = None
    _resolved: dict[tuple[str, str, str], LinkFaultSpec] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.default, LinkFaultSpec):
            raise ValueError(f"default must be a LinkFaultSpec, got {self.default!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)):
            raise ValueError(f"seed must be an integer, got {self.seed!r}")
        object.__setattr__(self, "seed", int(self.seed))
        items = self.per_link.items() if isinstance(self.per_link, Mapping) else self.per_link
        per: dict[tuple[str, str, str], LinkFaultSpec] = {}
        for key, spec in items:
            if not isinstance(spec, LinkFaultSpec):
                raise ValueError(f"per_link[{key!r}] must be a LinkFaultSpec, got {spec!r}")
            k = _norm_link_key(key)
            per.pop(k, None)  # re-inserting moves it to the end: it wins
            per[k] = spec
        object.__setattr__(self, "per_link", per)
        parts = tuple(self.partitions)
        for p in parts:
            if not isinstance(p, Partition):
                raise ValueError(f"partitions must hold Partition objects, got {p!r}")
        object.__setattr__(self, "partitions", parts)
        if self.hold_s is not None and not (isinstance(self.hold_s, (int, float)) and math.isfinite(self.hold_s) and self.hold_s > 0):
            raise ValueError(f"hold_s must be a finite number > 0 s or None, got {self.hold_s!r}")

    def hold_ticks(self, kind: str, dt: float) -> int | None:
        """The hold horizon of a link of ``kind`` in ticks of ``dt`` s (None: no horizon; only the
        references, ``ref`` and ``leader``, expire: the state and the command are always held)."""
        if self.hold_s is None or kind not in ("ref", "leader"):
            return None
        return max(1, math.ceil(self.hold_s / dt - 1e-9))

    def _key(self) -> tuple[object, ...]:
        return (self.default, tuple(self.per_link.items()), self.seed, self.partitions, id(self.trace), id(self.queues), self.hold_s)

    def __eq__(self, other: object) -> bool:  # per_link order matters (the last match wins)
        if not isinstance(other, FaultPlan):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    @classmethod
    def none(cls, seed: int = 0) -> FaultPlan:
        """No faults at all."""
        return cls(seed=seed)

    @property
    def active(self) -> bool:
        """False when no link of the run can be delayed or dropped."""
        return (
            bool(self.partitions)
            or self.trace is not None
            or self.default.active
            or any(s.active for s in self.per_link.values())
        )

    @property
    def radio_active(self) -> bool:
        """True when some link has a radio model (:mod:`zenswarm.link.radio`): senders then stamp
        their positions and receivers decide with the geometry."""
        return self.default.radio_active or any(s.radio_active for s in self.per_link.values())

    def radio_for(self, src: str, dst: str, kind: str) -> RadioModel | None:
        """The active radio model of a link, or None (always None for ``state`` and ``cmd``)."""
        if kind not in RADIO_KINDS:
            return None
        spec = self.spec_for(src, dst, kind)
        return spec.radio if spec.radio_active else None

    def spec_for(self, src: str, dst: str, kind: str) -> LinkFaultSpec:
        """The spec of the directed link ``src -> dst`` carrying ``kind``."""
        key = (src, dst, kind)
        spec = self._resolved.get(key)
        if spec is None:
            spec = self.default
            per_link = self.per_link
            assert isinstance(per_link, dict)  # __post_init__ made it one (ordered: the last match wins)
            for (ps, pd, pk), s in reversed(per_link.items()):
                if fnmatch.fnmatchcase(src, ps) and fnmatch.fnmatchcase(dst, pd) and fnmatch.fnmatchcase(kind, pk):
                    spec = s
                    break
            self._resolved[key] = spec
        return spec

    def max_delay_s(self, src: str, dst: str, kind: str) -> float:
        """Largest delay of the link, s: its trace's (or its spec's delay + jitter) plus the most
        its capacity queue can add."""
        link = (src, dst, kind)
        d = self.trace.max_delay_s(link) if self.trace is not None and link in self.trace else self.spec_for(*link).max_delay_s
        return d + (self.queues.max_wait_s(link) if self.queues is not None else 0.0)

    def worst_delay_s(self) -> float:
        """Largest delay of any link of the run, s (an upper bound): the specs' delay + jitter or
        the trace's largest delay, plus the most a capacity queue can add."""
        worst = max(spec.max_delay_s for spec in [self.default, *self.per_link.values()])
        if self.trace is not None and self.trace.links:
            worst = max(worst, max(self.trace.max_delay_s(lk) for lk in self.trace.links))
        if self.queues is not None and self.queues.links:
            worst += max(self.queues.max_wait_s(lk) for lk in self.queues.links)
        return worst

    def horizon_ticks(self, src: str, dst: str, kind: str, dt: float) -> int:
        """Largest delay of the link in ticks: no message is delivered later than send + this."""
        return delivery_tick(0, self.max_delay_s(src, dst, kind), dt)

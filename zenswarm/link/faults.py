"""Link faults: delay, jitter, independent loss, Gilbert-Elliott burst loss and timed partitions.

This is the one fault model shared by the in-process simulator and the distributed lockstep
swarm (design note, section Faults). It is pure: numpy and the standard library only, no zenoh,
no files, no clock. Faults are applied where a message is received, per *directed link*
``(src, dst, kind)``.

Processes and message kinds
---------------------------
Process names are ``plant``, ``leader`` and ``agent:<i>`` (UAVs numbered 1..N as in the paper).
A link carries one kind of message:

=========  =====================  ===========================================
kind       direction              wire key
=========  =====================  ===========================================
``ref``    ``agent:j -> agent:i``  ``uav/<j>/ref``   (q*_j, v*_j), eqs (16)-(17)
``leader`` ``leader -> agent:i``   ``leader/ref``    (q0, v0), eq. (15)
``state``  ``plant -> agent:i``    ``uav/<i>/state`` measured state
``cmd``    ``agent:i -> plant``    ``uav/<i>/cmd``   thrust and attitude
=========  =====================  ===========================================

(Both reference messages are ``k: "ref"`` on the wire; the fault model tells them apart so that the
leader's reference can be faulted separately, as the issue asks.)

Decisions
---------
:func:`decide` (and :meth:`FaultState.decide`) returns a :class:`Delivery` that is a pure function
of ``(plan, src, dst, kind, seq, t_send_s)``: never of arrival order, call order, or which other
sequence numbers were asked for. Uniform draws come from a counter-based generator: the
sequence numbers of one link and one *stream* (``loss``, ``jitter``, ``ge_trans``, ``ge_loss``,
``ge_init``) are cut into blocks of :data:`BLOCK` and block ``b`` is
``numpy.random.Philox(key=blake2b(seed, src, dst, kind, stream, b)).random_raw(BLOCK)``, turned
into doubles in [0, 1) by ``(raw >> 11) * 2**-53``. Philox's raw output is a fixed, documented
stream, so decisions do not change across numpy versions or platforms.

Per decision, in order of precedence for the reported reason:

1. ``partition``: a :class:`Partition` covering the link is active at ``t_send_s``
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

Lockstep
--------
In lockstep the *sequence number of a message on a link is its tick*: the tick of its sim time
``t`` (``round(t / dt)``), and ``t_send_s = send_tick * dt``. Every process sends one message per
link per tick, so a receiver can work out which message it needs without waiting for the dropped
ones: :meth:`LinkInbox.due`. A message of tick ``j`` with delay ``d`` is available from tick
:func:`delivery_tick` ``(j, d, dt)``. :class:`LinkInbox` implements the receiver's *hold last
value* policy: at tick ``k`` it holds the newest (largest send tick) message that was not dropped
and whose delivery tick is ``<= k``, never goes back to an older one, and reports its age in ticks.
The simulator and the agent/plant processes both use it, so they agree bit for bit.

Realtime
--------
The same :func:`decide` applies with ``seq`` the message's wire ``seq`` and ``t_send_s`` its
sim/wall time since the start of the mission; the receiver releases a kept message
``delay_s`` after it arrived.

Configuration
-------------
:func:`plan_from_scenario` reads the ``[faults]`` table of a scenario, :func:`plan_from_cli` the
``--link-delay``, ``--link-jitter``, ``--link-loss`` and ``--partition`` shortcuts. Example::

    [faults]
    delay = "50ms"            # every directed link, unless a [[faults.links]] entry matches
    jitter = "10ms"
    loss = 0.2                # independent drop probability, [0, 1]
    burst = { p_good_to_bad = 0.01, p_bad_to_good = 0.25 }   # optional Gilbert-Elliott
    partitions = ["agent:2@10s-13s", "agent:1->agent:3@20s-21.5s"]

    [[faults.links]]          # later entries win; omitted fields inherit [faults]
    src = "agent:*"           # glob over process names; default "*"
    dst = "agent:3"
    kind = "ref"              # ref | leader | state | cmd | "*"; default "*"
    delay = "100ms"
    loss = 0.0
    burst = false             # no burst loss on this link (overrides an inherited burst)

Capacity and queue (``capacity``, ``queue``, ``medium`` in ``[faults]`` and ``[[faults.links]]``,
``--link-capacity``, ``--link-queue``, ``--link-medium``): :mod:`zenswarm.link.queue`; traces
(``[faults] trace``, ``--link-trace``): :mod:`zenswarm.link.trace`, loaded with the scenario's graph
by :func:`zenswarm.link.swarm.plan_for`.
"""

from __future__ import annotations

import fnmatch
import hashlib
import math
import re
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.link.names import KIND_ROLES, KINDS, PROCESS_RE, agent_links, link_kind, parse_process, plant_links, role_of
from zenswarm.link.queue import LinkQueues, QueueSpec, queue_spec
from zenswarm.link.radio import RADIO_KINDS, RadioModel, parse_distance, parse_fade
from zenswarm.link.trace import LinkTrace
from zenswarm.schema import BurstTable, FadeTable, FaultsTable, LinkFaultsTable, PartitionTable, convert

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


#: Sequence numbers per block of the counter-based generator. Part of the definition of the
#: decisions (changing it changes every decision), so it is not a parameter.
BLOCK = 1024

_STREAMS = ("loss", "jitter", "ge_trans", "ge_loss", "ge_init")
_REASONS = ("ok", "loss", "burst", "partition", "trace", "queue")
_TWO_M53 = 2.0**-53
_EPS_TICK = 1e-9
_CHUNK = 256  # LinkInbox computes decisions in batches of this many ticks (a cache, not a definition)
_Chunk = tuple[list[bool], list[float], list[str], list[int]]
"""One batch of :class:`LinkInbox` decisions: dropped, delay_s, reason, delivery tick (one per send tick)."""


# ----------------------------------------------------------------------------------------------
# names and parsing


_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_DUR_RE = re.compile(rf"^\s*(?P<num>{_NUM})\s*(?P<unit>ns|us|µs|ms|s|min)?\s*$")
_UNIT_S = {"ns": 1e-9, "us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0, "min": 60.0}


def parse_duration(text: str) -> float:
    """``"50ms"``, ``"1.5s"``, ``"200us"``, ``"0"`` -> seconds (float >= 0).

    Units: ns, us (or µs), ms, s, min. A bare number is accepted only for zero. Raises ValueError
    naming the bad text.
    """
    if not isinstance(text, str):
        raise ValueError(f"invalid duration {text!r}: expected a string such as '50ms'")
    m = _DUR_RE.match(text)
    if not m:
        if text.strip().startswith("-"):
            raise ValueError(f"invalid duration {text!r}: must be >= 0")
        raise ValueError(f"invalid duration {text!r}: expected a number with a unit (ns, us, ms, s, min), e.g. '50ms'")
    value = float(m.group("num"))
    unit = m.group("unit")
    if unit is None:
        if value != 0.0:
            raise ValueError(f"invalid duration {text!r}: missing unit (ns, us, ms, s, min), e.g. '{m.group('num')}ms'")
        return 0.0
    s = value * _UNIT_S[unit]
    if not math.isfinite(s):
        raise ValueError(f"invalid duration {text!r}: not finite")
    return s


def parse_loss(text: str | float | int) -> float:
    """A probability in [0, 1]: ``0.2``, ``"0.2"`` or ``"20%"``. Raises ValueError naming the bad text."""
    if isinstance(text, bool):
        raise ValueError(f"invalid loss {text!r}: expected a probability in [0, 1]")
    if isinstance(text, (int, float)):
        p = float(text)
    elif isinstance(text, str):
        t = text.strip()
        try:
            p = float(t[:-1]) / 100.0 if t.endswith("%") else float(t)
        except ValueError:
            raise ValueError(f"invalid loss {text!r}: expected a probability in [0, 1] such as 0.2 or 20%") from None
    else:
        raise ValueError(f"invalid loss {text!r}: expected a probability in [0, 1]")
    if not (0.0 <= p <= 1.0):  # also rejects NaN
        raise ValueError(f"invalid loss {text!r}: must be in [0, 1]")
    return p


def _parse_target(text: str) -> str:
    """``agent:2`` (a process: every link to and from it) or ``agent:1->agent:2`` (one directed link)."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"invalid partition target {text!r}: expected a process or src->dst")
    if "->" in text:
        a, _, b = text.partition("->")
        try:
            sa, sb = parse_process(a), parse_process(b)
        except ValueError as e:
            raise ValueError(f"invalid partition target {text!r}: {e}") from None
        if sa == sb:
            raise ValueError(f"invalid partition target {text!r}: a link needs two different processes")
        return f"{sa}->{sb}"
    try:
        return parse_process(text)
    except ValueError as e:
        raise ValueError(f"invalid partition target {text!r}: {e}") from None


def check_exists(path: str, target: str, n: int | None) -> None:
    """Raise :class:`ScenarioError` naming ``path`` when ``target`` (a process, a link
    ``src->dst`` or a glob) names an agent beyond the scenario's ``n`` UAVs; ``n=None``: no check."""
    if n is None:
        return
    for part in target.split("->"):
        m = PROCESS_RE.match(part.strip())
        if m and m.group(2) is not None and not 1 <= int(m.group(2)) <= n:
            raise ScenarioError(path, f"{part.strip()} does not exist: the scenario has {n} UAVs (agent:1 to agent:{n})")


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
    tgt = _parse_target(target)
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


# ----------------------------------------------------------------------------------------------
# configuration


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
        object.__setattr__(self, "process_or_link", _parse_target(self.process_or_link))
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
      most ``ceil(hold_s / dt)`` ticks old (counted from its send tick); older, :meth:`LinkInbox.at`
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


# ----------------------------------------------------------------------------------------------
# decisions


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
    REASONS = _REASONS


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
        b, i = divmod(_check_seq(seq), BLOCK)
        return bool(self.ge_block((src, dst, kind), ge, b)[i])

    # -- decisions
    def decide(self, src: str, dst: str, kind: str, seq: int, t_send_s: float) -> Delivery:
        """See :func:`decide`."""
        seq = _check_seq(seq)
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


def _check_seq(seq: Any) -> int:
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


def delivery_tick(send_tick: int, delay_s: float, dt: float) -> int:
    """First tick at which a message of ``send_tick`` with ``delay_s`` is available:
    ``send_tick + ceil(delay_s / dt - 1e-9)`` (0 delay: the same tick; 50 ms at dt 10 ms: +5)."""
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt!r}")
    return int(send_tick) + max(0, math.ceil(delay_s / dt - _EPS_TICK))


# ----------------------------------------------------------------------------------------------
# receiver side, lockstep


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
        self.first_tick = _check_seq(first_tick)
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
        j = _check_seq(send_tick)
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
            dtick = j + np.maximum(0.0, np.ceil(b.delay_s / self.dt - _EPS_TICK)).astype(np.int64)
            r = (
                b.dropped.tolist(),
                b.delay_s.tolist(),
                [_REASONS[x] for x in b.reason.tolist()],
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
        j = _check_seq(send_tick)
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


# ----------------------------------------------------------------------------------------------
# building plans from the CLI and from a scenario


def plan_from_cli(
    link_delay: str | None = None,
    link_jitter: str | None = None,
    link_loss: str | float | None = None,
    partitions: Iterable[str] = (),
    seed: int = 0,
    base: FaultPlan | None = None,
    n: int | None = None,
    link_capacity: str | None = None,
    link_queue: str | None = None,
    link_medium: str | None = None,
) -> FaultPlan:
    """The whole-swarm shortcuts ``--link-delay 50ms --link-jitter 10ms --link-loss 0.2
    --partition agent:2@10s-13s --link-capacity 20kB/s --link-queue 8 --link-medium sender`` as a plan.

    Given values replace the fields of ``base.default`` (a plan from the scenario; its per-link
    entries and partitions are kept); partitions are added. ``seed`` replaces ``base.seed``.
    ``n``, if given, is the number of UAVs: a partition of ``agent:<i>`` with i > n is refused.
    Raises :class:`ScenarioError` whose field is the flag (``--link-loss``).
    """
    base = base if base is not None else FaultPlan(seed=seed)
    d = base.default
    delay, jitter, loss = d.delay_s, d.jitter_s, d.loss
    try:
        if link_delay is not None:
            delay = parse_duration(link_delay)
    except ValueError as e:
        raise ScenarioError("--link-delay", str(e)) from None
    try:
        if link_jitter is not None:
            jitter = parse_duration(link_jitter)
    except ValueError as e:
        raise ScenarioError("--link-jitter", str(e)) from None
    try:
        if link_loss is not None:
            loss = parse_loss(link_loss)
    except ValueError as e:
        raise ScenarioError("--link-loss", str(e)) from None
    parts = list(base.partitions)
    for text in partitions or ():
        try:
            parts.append(parse_partition(text))
        except ValueError as e:
            raise ScenarioError("--partition", str(e)) from None
        check_exists("--partition", parts[-1].process_or_link, n)
    queue = queue_spec(("--link-capacity", "--link-queue", "--link-medium"), link_capacity, link_queue, link_medium, d.queue)
    default = LinkFaultSpec(delay, jitter, loss, d.burst, d.partitions, radio=d.radio, queue=queue)
    return FaultPlan(default, dict(base.per_link), seed, tuple(parts), base.trace, base.queues, base.hold_s)


def _duration_field(path: str, x: Any) -> float:
    if isinstance(x, (int, float)) and not isinstance(x, bool) and x == 0:
        return 0.0
    if not isinstance(x, str):
        raise ScenarioError(path, f"expected a duration string with a unit such as \"50ms\", got {x!r}")
    try:
        return parse_duration(x)
    except ValueError as e:
        raise ScenarioError(path, str(e)) from None


def _burst_field(path: str, x: BurstTable | bool) -> GilbertElliott | None:
    if x is False:
        return None
    if not isinstance(x, BurstTable):
        raise ScenarioError(path, f"expected a table or false, got {x!r}")
    return GilbertElliott(x.p_good_to_bad, x.p_bad_to_good, x.loss_good, x.loss_bad)


def _partition_field(path: str, x: str | PartitionTable) -> Partition:
    if isinstance(x, str):
        try:
            return parse_partition(x)
        except ValueError as e:
            raise ScenarioError(path, str(e)) from None
    try:
        target = _parse_target(x.target)
    except ValueError as e:
        raise ScenarioError(f"{path}.target", str(e)) from None
    t0 = _duration_field(f"{path}.start", x.start)
    if isinstance(x.end, str) and x.end.strip() in ("inf", "end"):
        t1 = math.inf
    else:
        t1 = _duration_field(f"{path}.end", x.end)
    if not t1 > t0:
        raise ScenarioError(f"{path}.end", f"must be after start ({x.end!r} <= {x.start!r})")
    return Partition(target, t0, t1)


def _endpoint_field(path: str, x: str) -> str:
    x = x.strip()
    if not x:
        raise ScenarioError(path, f"expected a process name or glob (plant, leader, agent:<i>, agent:*, *), got {x!r}")
    if any(c in x for c in "*?["):
        return x
    try:
        return parse_process(x)
    except ValueError as e:
        raise ScenarioError(path, str(e)) from None


def _link_key(p: str, e: LinkFaultsTable, n_uavs: int | None) -> tuple[str, str, str]:
    """(src, dst, kind) of a ``[[faults.links]]`` entry at path ``p``, checked."""
    src = _endpoint_field(f"{p}.src", e.src)
    dst = _endpoint_field(f"{p}.dst", e.dst)
    check_exists(f"{p}.src", src, n_uavs)
    check_exists(f"{p}.dst", dst, n_uavs)
    kind = e.kind
    if kind not in KINDS and kind != "*":
        raise ScenarioError(f"{p}.kind", f"unknown kind {kind!r} (allowed: {', '.join(KINDS)}, *)")
    if kind != "*":
        want = KIND_ROLES[kind]
        for name, ep, role in (("src", src, want[0]), ("dst", dst, want[1])):
            if not any(c in ep for c in "*?[") and role_of(ep) != role:
                raise ScenarioError(f"{p}.{name}", f"a {kind!r} link goes {want[0]} -> {want[1]}; {ep!r} is not a {role}")
    if src == dst and not any(c in src for c in "*?["):
        raise ScenarioError(f"{p}.dst", f"a link needs two different processes, got {src!r} twice")
    return src, dst, kind


def _distance_field(path: str, x: Any, allow_inf: bool = True) -> float:
    if isinstance(x, bool) or not isinstance(x, (str, int, float)):
        raise ScenarioError(path, f"expected a distance such as \"1.5m\" (or metres), got {x!r}")
    try:
        return parse_distance(x, allow_inf=allow_inf)
    except ValueError as e:
        raise ScenarioError(path, str(e)) from None


def _radio_field(p: str, e: FaultsTable | LinkFaultsTable, inherit: RadioModel | None) -> RadioModel | None:
    """The radio model of table ``e`` at ``p`` (keys ``range``, ``fade``), inheriting the rest."""
    if e.range is None and e.fade is None:
        return inherit
    base = inherit if inherit is not None else RadioModel()
    rng = base.range_m if e.range is None else _distance_field(f"{p}.range", e.range)
    r50, width = base.fade_50_m, base.fade_width_m
    if e.fade is False:
        r50, width = math.inf, 1.0
    elif isinstance(e.fade, FadeTable):
        r50 = _distance_field(f"{p}.fade.r50", e.fade.r50, allow_inf=False)
        width = _distance_field(f"{p}.fade.width", e.fade.width, allow_inf=False)
    elif e.fade is not None:
        raise ScenarioError(f"{p}.fade", f"expected a table {{ r50, width }} or false, got {e.fade!r}")
    return RadioModel(rng, r50, width)


def _spec(p: str, e: FaultsTable | LinkFaultsTable, inherit: LinkFaultSpec) -> LinkFaultSpec:
    """The link spec of table ``e`` at path ``p``; keys it does not set come from ``inherit``."""
    return LinkFaultSpec(
        inherit.delay_s if e.delay is None else _duration_field(f"{p}.delay", e.delay),
        inherit.jitter_s if e.jitter is None else _duration_field(f"{p}.jitter", e.jitter),
        inherit.loss if e.loss is None else float(e.loss),
        inherit.burst if e.burst is None else _burst_field(f"{p}.burst", e.burst),
        radio=_radio_field(p, e, inherit.radio),
        queue=queue_spec((f"{p}.capacity", f"{p}.queue", f"{p}.medium"), e.capacity, e.queue, e.medium, inherit.queue),
    )


def plan_from_scenario(section: FaultsTable | Mapping[str, Any] | None, seed: int, n_uavs: int | None = None) -> FaultPlan:
    """Build a plan from a scenario's ``[faults]`` table (``Scenario.faults``, or a dict validated
    by the schema, :class:`zenswarm.schema.FaultsTable`; ``None`` or ``{}``: no faults).

    Keys (all optional): ``delay``, ``jitter`` (duration strings), ``loss`` (probability),
    ``burst`` (table: ``p_good_to_bad``, ``p_bad_to_good`` required, ``loss_good`` = 0,
    ``loss_bad`` = 1), ``partitions`` (strings ``TARGET@START-END`` or tables ``{target, start,
    end}``), and ``[[faults.links]]`` entries with ``src``, ``dst`` (process names or globs,
    default ``*``), ``kind`` (``ref``, ``leader``, ``state``, ``cmd`` or ``*``) and any of
    ``delay``, ``jitter``, ``loss``, ``burst`` (``false`` to turn an inherited burst off); omitted
    fields inherit the ``[faults]`` values; later entries win. ``n_uavs``, if given, is the number
    of UAVs: naming ``agent:<i>`` with i > n is refused. Raises :class:`ScenarioError` naming the
    field, e.g. ``faults.links[0].loss``.
    """
    if section is None:
        return FaultPlan(seed=seed)
    t = section if isinstance(section, FaultsTable) else convert(section, FaultsTable, "faults")
    parts = [_partition_field(f"faults.partitions[{i}]", p) for i, p in enumerate(t.partitions)]
    for i, part in enumerate(parts):
        check_exists(f"faults.partitions[{i}]", part.process_or_link, n_uavs)
    default = _spec("faults", t, LinkFaultSpec(0.0, 0.0, 0.0, None))
    per: dict[tuple[str, str, str], LinkFaultSpec] = {}
    for n, entry in enumerate(t.links):
        p = f"faults.links[{n}]"
        key = _link_key(p, entry, n_uavs)
        if (entry.range is not None or entry.fade is not None) and key[2] in ("state", "cmd"):
            field_ = "range" if entry.range is not None else "fade"
            raise ScenarioError(f"{p}.{field_}", f"a {key[2]!r} link is on board (agent <-> its own autopilot), not radio")
        per.pop(key, None)
        per[key] = _spec(p, entry, default)
    hold = None
    if t.hold is not None:
        hold = _duration_field("faults.hold", t.hold)
        if not (math.isfinite(hold) and hold > 0):
            raise ScenarioError("faults.hold", f"the hold horizon must be a duration > 0 such as \"0.5s\", got {t.hold!r}")
    return FaultPlan(default, per, seed, tuple(parts), hold_s=hold)


def plan_with_radio(plan: FaultPlan, link_range: str | None = None, link_fade: str | None = None) -> FaultPlan:
    """The whole-swarm radio shortcuts ``--link-range 1.5m`` and ``--link-fade 1.2m,0.1m``
    (:mod:`zenswarm.link.radio`) applied to ``plan``: they replace the range / fall-off of its
    default spec, keeping the ``[[faults.links]]`` entries, as the other shortcuts do
    (:func:`plan_from_cli`). Raises :class:`ScenarioError` whose field is the flag."""
    if link_range is None and link_fade is None:
        return plan
    rng: float | None = None
    fade: tuple[float, float] | None = None
    try:
        if link_range is not None:
            rng = parse_distance(link_range)
    except ValueError as e:
        raise ScenarioError("--link-range", str(e)) from None
    try:
        if link_fade is not None:
            fade = parse_fade(link_fade)
    except ValueError as e:
        raise ScenarioError("--link-fade", str(e)) from None

    def with_radio(spec: LinkFaultSpec) -> LinkFaultSpec:
        r = spec.radio if spec.radio is not None else RadioModel()
        model = RadioModel(
            r.range_m if rng is None else rng,
            r.fade_50_m if fade is None else fade[0],
            r.fade_width_m if fade is None else fade[1],
        )
        return replace(spec, radio=model)

    return replace(plan, default=with_radio(plan.default), per_link=dict(plan.per_link))

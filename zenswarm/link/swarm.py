"""Link faults wired into the simulator and the processes (the model: :mod:`zenswarm.link.plan`, :mod:`zenswarm.link.decisions`).

Faults are applied where a message is received, per directed link ``(src, dst, kind)``:

* ``plant -> agent:i`` (``state``), ``agent:j -> agent:i`` (``ref``), ``leader -> agent:i``
  (``leader``), ``agent:i -> plant`` (``cmd``).

Lockstep: the decision for a link's message of tick k is a pure function of (seed, link, k)
(:class:`zenswarm.link.decisions.FaultState`); the receiver holds the newest delivered value
(:class:`Box`). The in-process simulator makes the same decisions with the same boxes, so a faulty
lockstep swarm still equals the simulator bit for bit. The messages of tick 0 (the start-up
exchange that initialises every generator) are never faulted.

Realtime: the same decision per (link, tick of the message) on receipt; a kept message is released
``delay`` seconds of wall time after it arrived (:class:`DelayLine`).
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.link.config import plan_from_cli, plan_from_scenario, plan_with_radio
from zenswarm.link.decisions import Delivery, FaultState
from zenswarm.link.inbox import LinkInbox
from zenswarm.link.names import agent_links, plant_links
from zenswarm.link.plan import FaultPlan
from zenswarm.link.queue import LinkQueues
from zenswarm.link.radio import GEOMETRY_TICK_OFFSET, components, leader_reaches_all, radio_reason
from zenswarm.link.trace import LinkTrace, load_trace
from zenswarm.schema import ScenarioTables

__all__ = [
    "Box", "LinkFaults", "plan_for", "scenario_links", "DelayLine", "box_counters", "distance", "due_tick",
    "effective_graph", "graph_series", "GraphSeries", "LinkSeries",
]  # fmt: skip


def distance(a: Any, b: Any) -> float:
    """Euclidean distance (m) between two positions (3,): ``sqrt((dx*dx + dy*dy) + dz*dz)``,
    the one formula every side of a radio link uses (so they agree to the last bit)."""
    dx, dy, dz = float(a[0]) - float(b[0]), float(a[1]) - float(b[1]), float(a[2]) - float(b[2])
    return math.sqrt((dx * dx + dy * dy) + dz * dz)


class Box(LinkInbox):
    """:class:`LinkInbox` whose tick-0 message is always delivered at once (start-up exchange).

    On a link with a radio model (:meth:`zenswarm.link.plan.FaultPlan.radio_for`) a message's fate
    also depends on the distance between the sender's position (given to :meth:`offer` as
    ``pos``) and the receiver's own position at the message's geometry tick (given to
    :meth:`own_position`; :data:`zenswarm.link.radio.GEOMETRY_TICK_OFFSET`). An offered message
    whose geometry is not known yet waits (parked) until it is; :meth:`due` names a message
    whose radio fate is unknown as the one to wait for. Extra counters ``dropped_range`` and
    ``dropped_fade``.
    """

    def __init__(self, faults: FaultPlan | FaultState, src: str, dst: str, kind: str, dt: float, **kw: Any) -> None:
        super().__init__(faults, src, dst, kind, dt, **kw)
        self.radio = self.state.plan.radio_for(src, dst, kind)
        self.geo_offset = GEOMETRY_TICK_OFFSET.get(kind, 0)
        self._radio_drop: dict[int, str | None] = {}  # send tick -> radio reason (None: delivered)
        self._own: dict[int, tuple[float, float, float]] = {}  # geometry tick -> own position
        self._parked: dict[int, tuple[int, Any, tuple[float, float, float]]] = {}  # send tick -> (seq, value, pos)
        self._rmemo: tuple[int, int | None] | None = None
        if self.radio is not None:
            self._n["dropped_range"] = 0
            self._n["dropped_fade"] = 0

    def _fate(self, j: int) -> tuple[bool, int]:
        if j == 0:
            return False, 0
        dropped, dtick = super()._fate(j)
        if not dropped and self.radio is not None and self._radio_drop.get(j) is not None:
            return True, dtick
        return dropped, dtick

    def decision(self, send_tick: int) -> Delivery:
        d = super().decision(send_tick)
        if send_tick == 0 and d.dropped:
            return type(d)(False, 0.0, "ok")
        if send_tick > 0 and not d.dropped and self.radio is not None:
            why = self._radio_drop.get(send_tick)
            if why is not None:
                return type(d)(True, d.delay_s, why)
        return d

    # -- geometry
    def own_position(self, tick: int, q: Any) -> None:
        """The receiver's own true position (m) at ``tick``; decides the parked messages whose
        geometry tick it is. No-op on a link without a radio model."""
        if self.radio is None:
            return
        pos = (float(q[0]), float(q[1]), float(q[2]))
        self._own[int(tick)] = pos
        for j in [j for j in self._parked if j + self.geo_offset == tick]:
            seq, value, spos = self._parked.pop(j)
            self._resolve(j, spos)
            super().offer(j, seq, value)
        if len(self._own) > 4 * (self.horizon + 8):
            for g in sorted(self._own)[: len(self._own) // 2]:
                del self._own[g]

    def _resolve(self, j: int, spos: tuple[float, float, float]) -> None:
        assert self.radio is not None
        own = self._own[j + self.geo_offset]
        u = self.state.uniform(self.link, "radio", j) if self.radio.uses_uniform else 0.0
        self._radio_drop[j] = radio_reason(self.radio, distance(spos, own), u)
        if len(self._radio_drop) > 4 * (self.horizon + 8) + 64:
            for x in sorted(self._radio_drop)[: len(self._radio_drop) // 2]:
                del self._radio_drop[x]

    def known(self, send_tick: int) -> bool:
        """Is the fate of the message of ``send_tick`` known (always, without a radio model)?"""
        # a message offered and not parked was decided when it was offered (its entry in
        # _radio_drop may since have been pruned: the held one, long ago)
        return self.radio is None or send_tick == 0 or send_tick in self._radio_drop or LinkInbox.has(self, send_tick)

    def offer(self, send_tick: int, seq: int, value: Any, pos: Any = None) -> Delivery:
        """:meth:`LinkInbox.offer`; on a radio link ``pos`` is the sender's position stamp (m, (3,)):
        without one (an unstamped message) the message counts as beyond range."""
        j = int(send_tick)
        if self.radio is None or j == 0 or j in self._radio_drop:
            return super().offer(j, seq, value)
        if j in self._parked:
            self._n["duplicates"] += 1
            return Delivery(False, 0.0, "ok")
        spos = (math.inf, math.inf, math.inf) if pos is None or len(pos) != 3 else (float(pos[0]), float(pos[1]), float(pos[2]))
        if j + self.geo_offset not in self._own:
            self._parked[j] = (int(seq), value, spos)
            return Delivery(False, 0.0, "ok")  # not decided yet
        self._resolve(j, spos)
        return super().offer(j, seq, value)

    def has(self, send_tick: int) -> bool:
        return super().has(send_tick) or send_tick in self._parked

    def due(self, k: int) -> int | None:
        """:meth:`LinkInbox.due`; on a radio link a message whose fate is not known yet counts as
        deliverable (it is the one to wait for), and the scan goes on below it once it is known."""
        if self.radio is None:
            return super().due(k)
        k = int(k)
        lo = self.first_tick
        best: int | None = None
        memo = self._rmemo
        if memo is not None and k >= memo[0]:
            k0, best = memo
            lo = max(lo, k0 - self.horizon + 1, (best + 1) if best is not None else lo)
        for j in range(k, lo - 1, -1):
            dropped, dtick = self._fate(j)
            if dropped or dtick > k:
                continue
            if not self.known(j):
                return j  # wait for it (memo not updated: its fate is still open)
            best = j
            break
        self._rmemo = (k, best)
        return best

    def ready(self, k: int) -> bool:
        """True when the message this link must deliver by tick k (if any) has been offered and
        its fate is known."""
        j = self.due(k)
        return j is None or (self.has(j) and self.known(j))

    def timed_out(self, k: int) -> None:
        """Not :meth:`ready` at tick k (its due message was not offered) and the lockstep wait gave
        up: the due message's timeout is counted (:meth:`LinkInbox.mark_timeout`)."""
        due = self.due(k)
        assert due is not None, "a box that is not ready has a due message"
        self.mark_timeout(due)


def due_tick(box: Box | None, k: int) -> int:
    """The send tick of the message a lockstep receiver waits for at tick k: k without link
    faults; with them the tick its receive box is due to deliver (:meth:`Box.due`), unless that
    message was already offered (a radio link may still be deciding its fate: wait for it)."""
    if box is None:
        return k
    j = box.due(k)
    return k if j is None or box.has(j) else j


def scenario_links(scenario: ScenarioTables) -> list[tuple[str, str, str]]:
    """Every directed link ``(src, dst, kind)`` of the scenario: each agent's state, its
    neighbours' refs and (if pinned) the leader's ref, then every agent's command to the plant."""
    g = scenario.graph
    links = [lk for i in range(scenario.n) for lk in agent_links(i + 1, [j + 1 for j in scenario.neighbours(i)], g.pinning[i] > 0)]
    return links + plant_links(scenario.n)


def _trace(scenario: ScenarioTables, link_trace: str | None) -> LinkTrace | None:
    """The run's trace: ``--link-trace`` (relative to the working directory) or the scenario's
    ``[faults] trace`` (resolved against the scenario file by :func:`zenswarm.scenario.config.load_scenario`)."""
    if link_trace is not None:
        field, path = "--link-trace", link_trace
    elif scenario.faults is not None and scenario.faults.trace is not None:
        field, path = "faults.trace", scenario.faults.trace
    else:
        return None
    try:
        trace = load_trace(path)
    except ScenarioError as e:
        if e.field == str(path):  # unreadable file: name the setting
            raise ScenarioError(field, e.message) from None
        raise
    trace.check_links(scenario_links(scenario))
    return trace


def plan_for(
    scenario: ScenarioTables,
    link_delay: str | None = None,
    link_jitter: str | None = None,
    link_loss: str | None = None,
    partitions: list[str] | tuple[str, ...] = (),
    seed: int | None = None,
    link_range: str | None = None,
    link_fade: str | None = None,
    link_capacity: str | None = None,
    link_queue: str | None = None,
    link_medium: str | None = None,
    link_trace: str | None = None,
) -> FaultPlan | None:
    """The fault plan of a run: the scenario's ``[faults]`` table, then the CLI shortcuts
    (``link_range``, ``link_fade``: :func:`zenswarm.link.config.plan_with_radio`); the capacity queues
    of the scenario's links (:class:`zenswarm.link.queue.LinkQueues`) and the trace
    (:mod:`zenswarm.link.trace`; ``link_trace`` replaces the scenario's).

    ``seed`` defaults to the scenario's. Returns None when no fault is active (the fast path).
    Raises :class:`zenswarm.errors.ScenarioError` naming the field, flag or trace line.
    """
    seed = scenario.seed if seed is None else int(seed)
    base = plan_from_scenario(scenario.faults, seed, scenario.n)
    plan = plan_from_cli(
        link_delay, link_jitter, link_loss, list(partitions or ()), seed=seed, base=base, n=scenario.n,
        link_capacity=link_capacity, link_queue=link_queue, link_medium=link_medium,
    )  # fmt: skip
    plan = plan_with_radio(plan, link_range, link_fade)
    trace = _trace(scenario, link_trace)
    specs = {lk: q for lk in scenario_links(scenario) if (q := plan.spec_for(*lk).queue) is not None}
    try:
        queues = LinkQueues(specs, scenario.timing.dt) if specs else None
    except ValueError as e:
        raise ScenarioError("--link-capacity" if link_capacity is not None else "faults.capacity", str(e)) from None
    if trace is not None or queues is not None:
        plan = replace(plan, trace=trace, queues=queues)
    return plan if plan.active else None


@dataclass(frozen=True)
class LinkFaults:
    """The whole-swarm fault shortcuts of a run, as given on the command line (``--link-delay``,
    ``--link-jitter``, ``--link-loss``, ``--partition``, ``--seed``, ``--link-range``,
    ``--link-fade``, ``--link-capacity``, ``--link-queue``, ``--link-medium``, ``--link-trace``;
    the edges parse them, see
    :mod:`zenswarm.bridge.args`). Texts are checked by :meth:`plan` (``ScenarioError`` naming
    the flag); ``seed`` None means the scenario's."""

    link_delay: str | None = None
    link_jitter: str | None = None
    link_loss: str | None = None
    partitions: tuple[str, ...] = ()
    seed: int | None = None
    link_range: str | None = None
    link_fade: str | None = None
    link_capacity: str | None = None
    link_queue: str | None = None
    link_medium: str | None = None
    link_trace: str | None = None

    def plan(self, scenario: ScenarioTables) -> FaultPlan | None:
        """The fault plan of a run of ``scenario`` with these shortcuts (:func:`plan_for`)."""
        return plan_for(
            scenario, self.link_delay, self.link_jitter, self.link_loss, self.partitions, self.seed,
            link_range=self.link_range, link_fade=self.link_fade, link_capacity=self.link_capacity,
            link_queue=self.link_queue, link_medium=self.link_medium, link_trace=self.link_trace,
        )  # fmt: skip

    def argv(self) -> list[str]:
        """These shortcuts as command-line words (the supervisor passes them on to its processes;
        the recorder stores them for ``replay --verify``)."""
        out: list[str] = []
        for flag, v in (("--link-delay", self.link_delay), ("--link-jitter", self.link_jitter), ("--link-loss", self.link_loss),
                        ("--link-range", self.link_range), ("--link-fade", self.link_fade)):
            if v is not None:
                out += [flag, str(v)]
        for flag, v in (
            ("--link-capacity", self.link_capacity),
            ("--link-queue", self.link_queue),
            ("--link-medium", self.link_medium),
            ("--link-trace", self.link_trace),
        ):
            if v is not None:
                out += [flag, str(v)]
        for part in self.partitions:
            out += ["--partition", part]
        if self.seed is not None:
            out += ["--seed", str(self.seed)]
        return out


def box_counters(boxes: dict[str, Box]) -> dict[str, int]:
    """Per-link counters for diagnostics: ``link:<src>-><dst>:<kind>.<counter>``."""
    out: dict[str, int] = {}
    for box in boxes.values():
        name = f"link:{box.src}->{box.dst}:{box.kind}"
        for k, v in box.counters().items():
            out[f"{name}.{k}"] = v
    return out


class DelayLine:
    """Realtime link faults: drop or delay each received message by its link's decision.

    ``offer`` (from a Zenoh callback) decides and queues; ``release(now, deliver)`` (from the
    process loop) hands over every message whose release time has come. Thread-safe enough for
    one producer per key and one consumer, under the caller's lock.
    """

    def __init__(self, state: FaultState, dt: float) -> None:
        self.state = state
        self.dt = dt
        self._heap: list[tuple[float, int, str, int, Any]] = []
        self._count = itertools.count()
        self.dropped: dict[str, int] = {}
        self._own_q: Any = None  # the receiver's newest own position (its raw state), for radio links

    def offer(self, now: float, link: tuple[str, str, str], key: str, tick: int, msg: Any) -> None:
        if link[2] == "state":
            self._own_q = msg.q
        if tick == 0:
            heapq.heappush(self._heap, (now, next(self._count), key, tick, msg))
            return
        d = self.state.decide(link[0], link[1], link[2], tick, tick * self.dt)
        model = self.state.plan.radio_for(*link)
        if not d.dropped and model is not None and self._own_q is not None:
            # realtime: the sender's stamp (the leader's q0) against the newest own state
            pos = msg.q if link[2] == "leader" else getattr(msg, "pos", ())
            dist = distance(pos, self._own_q) if len(pos) == 3 else math.inf
            u = self.state.uniform(link, "radio", tick) if model.uses_uniform else 0.0
            why = radio_reason(model, dist, u)
            if why is not None:
                d = Delivery(True, d.delay_s, why)
        if d.dropped:
            name = f"link:{link[0]}->{link[1]}:{link[2]}.dropped"
            self.dropped[name] = self.dropped.get(name, 0) + 1
            return
        heapq.heappush(self._heap, (now + d.delay_s, next(self._count), key, tick, msg))

    def release(self, now: float, deliver: Callable[[str, int, Any], None]) -> None:
        while self._heap and self._heap[0][0] <= now:
            _, _, key, tick, msg = heapq.heappop(self._heap)
            deliver(key, tick, msg)


@dataclass(frozen=True)
class LinkSeries:
    """Per-tick fate of one link of the effective graph (:func:`graph_series`).

    name: ``"src->dst"``; kind: ``ref`` or ``leader``; up: (T,) bool, its message of tick k was
    delivered; delay_s: (T,) float, s, the delay of that message (queue wait + serialization +
    the link's delay and jitter, or its trace's; meaningful where ``up``; 0 at tick 0)."""

    name: str
    kind: str
    up: np.ndarray
    delay_s: np.ndarray


@dataclass(frozen=True)
class GraphSeries:
    """The effective communication graph of a flight, per tick (:func:`graph_series`).

    links: the ref and leader links; components: (T,) int, connected components of the
    undirected graph of the leader and the agents over the links up; tree: (T,) bool, a directed
    spanning tree rooted at the leader exists over the links up (Lemma 1's assumption)."""

    links: tuple[LinkSeries, ...]
    components: np.ndarray
    tree: np.ndarray


def graph_series(
    plan: FaultPlan, neighbours: list[list[int]], pinned: list[bool], q: Any, q0: Any, dt: float, first_tick: int = 0
) -> GraphSeries:
    """The effective communication graph of a flight, tick by tick, from its fault plan and its
    time series.

    Link ``src -> dst`` (a ``ref`` link ``agent:j -> agent:i`` for every neighbour j of agent i,
    a ``leader`` link for every pinned agent) is *up* at tick k when its message of tick k is
    delivered: not dropped by any fault (:meth:`zenswarm.link.decisions.FaultState.decide_batch`: loss,
    burst, partition, trace, full queue) nor by its radio model at the geometry of that tick (the
    plant's positions ``q`` (T, n, 3) and the leader's ``q0`` (T, 3), as recorded;
    :mod:`zenswarm.link.radio`), the same decision the receive boxes make (:class:`Box`). Tick 0 is
    always up (start-up exchange, delay 0).

    neighbours: per agent (0-based), its neighbours' 0-based indices; pinned: per agent; dt: s;
    first_tick: the tick of the series' first row (a realtime series starts at the first tick
    every process had a value: row r is tick ``first_tick + r``, and its faults are that tick's).
    The per-tick arrays have a row per row of ``q``; a link judged at the positions of the tick
    before (:data:`GEOMETRY_TICK_OFFSET`) has none in the first row of a series that starts
    late: there only its other faults decide.
    """
    fs = FaultState(plan)
    q = np.asarray(q, dtype=float)
    q0 = np.asarray(q0, dtype=float)
    T = int(q.shape[0])
    n = len(neighbours)
    first_tick = int(first_tick)
    if first_tick < 0:
        raise ValueError(f"first_tick must be >= 0, got {first_tick}")
    ticks = np.arange(first_tick, first_tick + T, dtype=np.int64)
    links: list[tuple[int, int, LinkSeries]] = []  # (src node, dst node, series); node 0 the leader
    for i in range(n):
        rows = [(j + 1, f"agent:{j + 1}", "ref") for j in neighbours[i]]
        if pinned[i]:
            rows.append((0, "leader", "leader"))
        for node, src, kind in rows:
            dst = f"agent:{i + 1}"
            if T:
                d = fs.decide_batch(src, dst, kind, ticks, ticks * dt)
                up, delay = ~d.dropped, np.array(d.delay_s, dtype=float)
            else:
                up, delay = np.zeros(0, dtype=bool), np.zeros(0)
            model = plan.radio_for(src, dst, kind)
            if model is not None and T:
                off = GEOMETRY_TICK_OFFSET[kind]
                for k in range(1 if first_tick == 0 else 0, T):  # k: the row; tick first_tick + k
                    g = k + off
                    if not up[k] or g < 0:
                        continue
                    a = q0[k] if kind == "leader" else q[g, node - 1]
                    u = fs.uniform((src, dst, kind), "radio", first_tick + k) if model.uses_uniform else 0.0
                    dd = distance(a, q[g, i])
                    if radio_reason(model, dd if math.isfinite(dd) else math.inf, u) is not None:
                        up[k] = False
            if T and first_tick == 0:
                up[0] = True
                delay[0] = 0.0
            links.append((node, i + 1, LinkSeries(f"{src}->{dst}", kind, up, delay)))
    comps = np.zeros(T, dtype=np.int64)
    tree = np.zeros(T, dtype=bool)
    for k in range(T):
        edges = [(a, b) for a, b, ls in links if ls.up[k]]
        comps[k] = components(n + 1, edges)
        tree[k] = leader_reaches_all(n, edges)
    return GraphSeries(tuple(ls for _, _, ls in links), comps, tree)


def effective_graph(
    plan: FaultPlan, neighbours: list[list[int]], pinned: list[bool], q: Any, q0: Any, dt: float, first_tick: int = 0
) -> dict[str, Any]:
    """The effective communication graph of a flight, summarised (:func:`graph_series` per tick).

    Returns ``link_up_fraction`` (``"src->dst"`` -> fraction of ticks up), ``components``
    (number of connected components of the undirected graph of the leader and the agents over
    the links up, per tick, as a run-length list ``[[first_tick, count], ...]``),
    ``max_components``, ``spanning_tree_fraction`` (fraction of ticks with a directed spanning
    tree rooted at the leader over the links up: Lemma 1's assumption), ``ticks`` (how many) and
    ``first_tick`` (the first one: ``first_tick`` of :func:`graph_series`, the tick of the series'
    first row).
    """
    gs = graph_series(plan, neighbours, pinned, q, q0, dt, first_tick)
    T = int(gs.components.shape[0])
    comps: list[list[int]] = []
    for k in range(T):
        c = int(gs.components[k])
        if not comps or comps[-1][1] != c:
            comps.append([int(first_tick) + k, c])
    return {
        "ticks": T,
        "first_tick": int(first_tick),
        "link_up_fraction": {ls.name: float(np.mean(ls.up)) if T else 0.0 for ls in gs.links},
        "components": comps,
        "max_components": int(gs.components.max()) if T else 0,
        "spanning_tree_fraction": int(np.count_nonzero(gs.tree)) / T if T else 0.0,
    }

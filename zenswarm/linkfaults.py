"""Link faults wired into the simulator and the processes (the model is :mod:`zenswarm.faults`).

Faults are applied where a message is received, per directed link ``(src, dst, kind)``:

* ``plant -> agent:i`` (``state``), ``agent:j -> agent:i`` (``ref``), ``leader -> agent:i``
  (``leader``), ``agent:i -> plant`` (``cmd``).

Lockstep: the decision for a link's message of tick k is a pure function of (seed, link, k)
(:class:`zenswarm.faults.FaultState`); the receiver holds the newest delivered value
(:class:`Box`). The in-process simulator makes the same decisions with the same boxes, so a faulty
lockstep swarm still equals the simulator bit for bit. The messages of tick 0 (the start-up
exchange that initialises every generator) are never faulted.

Realtime: the same decision per (link, tick of the message) on receipt; a kept message is released
``delay`` seconds of wall time after it arrived (:class:`DelayLine`).
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from .config import Scenario
from .errors import ScenarioError
from .faults import Delivery, FaultPlan, FaultState, LinkInbox, agent_links, plan_from_cli, plan_from_scenario, plant_links
from .linkqueue import LinkQueues
from .linktrace import LinkTrace, load_trace

__all__ = ["Box", "LinkFaults", "plan_for", "scenario_links", "DelayLine", "box_counters"]


class Box(LinkInbox):
    """:class:`LinkInbox` whose tick-0 message is always delivered at once (start-up exchange)."""

    def _fate(self, j: int) -> tuple[bool, int]:
        if j == 0:
            return False, 0
        return super()._fate(j)

    def decision(self, send_tick: int) -> Delivery:
        d = super().decision(send_tick)
        if send_tick == 0 and d.dropped:
            return type(d)(False, 0.0, "ok")
        return d

    def ready(self, k: int) -> bool:
        """True when the message this link must deliver by tick k (if any) has been offered."""
        j = self.due(k)
        return j is None or self.has(j)


def scenario_links(scenario: Scenario) -> list[tuple[str, str, str]]:
    """Every directed link ``(src, dst, kind)`` of the scenario: each agent's state, its
    neighbours' refs and (if pinned) the leader's ref, then every agent's command to the plant."""
    g = scenario.graph
    links = [lk for i in range(scenario.n) for lk in agent_links(i + 1, [j + 1 for j in g.neighbours(i)], g.pinning[i] > 0)]
    return links + plant_links(scenario.n)


def _trace(scenario: Scenario, link_trace: str | None) -> LinkTrace | None:
    """The run's trace: ``--link-trace`` (relative to the working directory) or the scenario's
    ``[faults] trace`` (resolved against the scenario file by :func:`zenswarm.config.load_scenario`)."""
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
    scenario: Scenario,
    link_delay: str | None = None,
    link_jitter: str | None = None,
    link_loss: str | None = None,
    partitions: list[str] | tuple[str, ...] = (),
    seed: int | None = None,
    link_capacity: str | None = None,
    link_queue: str | None = None,
    link_medium: str | None = None,
    link_trace: str | None = None,
) -> FaultPlan | None:
    """The fault plan of a run: the scenario's ``[faults]`` table, then the CLI shortcuts; the
    capacity queues of the scenario's links (:class:`zenswarm.linkqueue.LinkQueues`) and the trace
    (:mod:`zenswarm.linktrace`; ``link_trace`` replaces the scenario's).

    ``seed`` defaults to the scenario's. Returns None when no fault is active (the fast path).
    Raises :class:`zenswarm.errors.ScenarioError` naming the field, flag or trace line.
    """
    seed = scenario.seed if seed is None else int(seed)
    base = plan_from_scenario(scenario.faults, seed, scenario.n)
    plan = plan_from_cli(
        link_delay, link_jitter, link_loss, list(partitions or ()), seed=seed, base=base, n=scenario.n,
        link_capacity=link_capacity, link_queue=link_queue, link_medium=link_medium,
    )  # fmt: skip
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
    ``--link-jitter``, ``--link-loss``, ``--partition``, ``--seed``, ``--link-capacity``,
    ``--link-queue``, ``--link-medium``, ``--link-trace``; the edges parse them, see
    :mod:`zenswarm.bridge.args`). Texts are checked by :meth:`plan` (``ScenarioError`` naming
    the flag); ``seed`` None means the scenario's."""

    link_delay: str | None = None
    link_jitter: str | None = None
    link_loss: str | None = None
    partitions: tuple[str, ...] = ()
    seed: int | None = None
    link_capacity: str | None = None
    link_queue: str | None = None
    link_medium: str | None = None
    link_trace: str | None = None

    def plan(self, scenario: Scenario) -> FaultPlan | None:
        """The fault plan of a run of ``scenario`` with these shortcuts (:func:`plan_for`)."""
        return plan_for(
            scenario, self.link_delay, self.link_jitter, self.link_loss, self.partitions, self.seed,
            self.link_capacity, self.link_queue, self.link_medium, self.link_trace,
        )  # fmt: skip

    def argv(self) -> list[str]:
        """These shortcuts as command-line words (the supervisor passes them on to its processes;
        the recorder stores them for ``replay --verify``)."""
        out: list[str] = []
        for flag, v in (("--link-delay", self.link_delay), ("--link-jitter", self.link_jitter), ("--link-loss", self.link_loss)):
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

    def offer(self, now: float, link: tuple[str, str, str], key: str, tick: int, msg: Any) -> None:
        if tick == 0:
            heapq.heappush(self._heap, (now, next(self._count), key, tick, msg))
            return
        d = self.state.decide(link[0], link[1], link[2], tick, tick * self.dt)
        if d.dropped:
            name = f"link:{link[0]}->{link[1]}:{link[2]}.dropped"
            self.dropped[name] = self.dropped.get(name, 0) + 1
            return
        heapq.heappush(self._heap, (now + d.delay_s, next(self._count), key, tick, msg))

    def release(self, now: float, deliver: Callable[[str, int, Any], None]) -> None:
        while self._heap and self._heap[0][0] <= now:
            _, _, key, tick, msg = heapq.heappop(self._heap)
            deliver(key, tick, msg)

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

import argparse
import heapq
import itertools
from typing import Any, Callable

from .config import Scenario, seed_arg
from .faults import FaultPlan, FaultState, LinkInbox, plan_from_cli, plan_from_scenario

__all__ = ["Box", "plan_for", "plan_from_args", "add_fault_args", "fault_argv", "DelayLine", "box_counters"]


class Box(LinkInbox):
    """:class:`LinkInbox` whose tick-0 message is always delivered at once (start-up exchange)."""

    def _fate(self, j: int) -> tuple[bool, int]:
        if j == 0:
            return False, 0
        return super()._fate(j)

    def decision(self, send_tick: int):  # noqa: ANN201 - same type as the base class
        d = super().decision(send_tick)
        if send_tick == 0 and d.dropped:
            return type(d)(False, 0.0, "ok")
        return d

    def ready(self, k: int) -> bool:
        """True when the message this link must deliver by tick k (if any) has been offered."""
        j = self.due(k)
        return j is None or self.has(j)


def plan_for(
    scenario: Scenario,
    link_delay: str | None = None,
    link_jitter: str | None = None,
    link_loss: str | None = None,
    partitions: list[str] | tuple[str, ...] = (),
    seed: int | None = None,
) -> FaultPlan | None:
    """The fault plan of a run: the scenario's ``[faults]`` table, then the CLI shortcuts.

    ``seed`` defaults to the scenario's. Returns None when no fault is active (the fast path).
    Raises :class:`zenswarm.errors.ScenarioError` naming the field or flag.
    """
    seed = scenario.seed if seed is None else int(seed)
    base = plan_from_scenario(scenario.faults, seed, scenario.n)
    plan = plan_from_cli(link_delay, link_jitter, link_loss, list(partitions or ()), seed=seed, base=base, n=scenario.n)
    return plan if plan.active else None


def add_fault_args(p: argparse.ArgumentParser) -> None:
    """The whole-swarm fault shortcuts (also valid in a scenario's [faults] table)."""
    g = p.add_argument_group("link faults (applied where messages are received; see docs/faults.md)")
    g.add_argument("--link-delay", metavar="DUR", help="fixed delay on every link, e.g. 50ms")
    g.add_argument("--link-jitter", metavar="DUR", help="uniform jitter +-DUR on every link's delay, e.g. 10ms")
    g.add_argument("--link-loss", metavar="P", help="independent loss probability on every link, e.g. 0.2 or 20%%")
    g.add_argument(
        "--partition",
        action="append",
        default=[],
        metavar="WHO@T1-T2",
        help="cut every link of a process (agent:2@10s-13s) or one directed link (agent:1->agent:2@1s-2s); repeatable",
    )
    g.add_argument(
        "--seed",
        type=seed_arg,
        default=None,
        help="seed of disturbances and fault decisions, 0 to 2**63-1 (default: the scenario's)",
    )


def plan_from_args(scenario: Scenario, args: argparse.Namespace) -> FaultPlan | None:
    return plan_for(
        scenario,
        getattr(args, "link_delay", None),
        getattr(args, "link_jitter", None),
        getattr(args, "link_loss", None),
        getattr(args, "partition", None) or (),
        getattr(args, "seed", None),
    )


def fault_argv(args: argparse.Namespace) -> list[str]:
    """The fault flags of ``args`` as command-line words (the supervisor passes them on)."""
    out: list[str] = []
    for flag, name in (("--link-delay", "link_delay"), ("--link-jitter", "link_jitter"), ("--link-loss", "link_loss")):
        v = getattr(args, name, None)
        if v is not None:
            out += [flag, str(v)]
    for part in getattr(args, "partition", None) or ():
        out += ["--partition", part]
    if getattr(args, "seed", None) is not None:
        out += ["--seed", str(args.seed)]
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

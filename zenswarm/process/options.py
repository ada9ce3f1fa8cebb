"""What every swarm process is started with: :class:`ProcessOptions` (the common flags, typed)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from zenswarm.scenario.config import Scenario

if TYPE_CHECKING:
    from zenswarm.link import FaultPlan

__all__ = ["ProcessOptions", "DEFAULT_LOCKSTEP_TIMEOUT_S", "DEFAULT_ROUTER_LOST_TIMEOUT_S"]

# Lockstep: a missing input is waited for this long (wall clock) before it counts as a drop.
DEFAULT_LOCKSTEP_TIMEOUT_S = 5.0

DEFAULT_ROUTER_LOST_TIMEOUT_S = 30.0
"""``--router-lost-timeout``: wall seconds a process waits for its router to come back once zenoh
has closed the link to it (the session lease, 10 s, ran out) before it gives up, stops and exits
with :data:`zenswarm.process.runtime.EXIT_ROUTER_LOST`: the router, or the host it runs on, is gone for good."""


@dataclass(frozen=True)
class ProcessOptions:
    """What every swarm process is started with (the common flags, typed; the command line is
    turned into these at the edge, :mod:`zenswarm.compose.roles`).

    scenario: the scenario itself (parsed once by the front door: how ``zenswarm up`` starts its
    roles, :class:`zenswarm.process.settings.RoleSettings`), or its TOML file (a role started by
    hand), or None: fetched from the leader's mission key. swarm: key prefix
    ``swarm/<swarm>``. connect: Zenoh router endpoints (empty: ``tcp/127.0.0.1:7447``).
    realtime: wall clock, latest value wins (else lockstep). lockstep_timeout: wall seconds an
    input is waited for before it counts as a drop. keys, tls: credentials of a secured router
    (:mod:`zenswarm.process.security`). link_delay, link_jitter, link_loss, partition, link_range,
    link_fade, link_capacity, link_queue, link_medium, link_trace: the whole-swarm link faults
    (:mod:`zenswarm.link.swarm`); seed: disturbances and fault decisions (None: the
    scenario's). controller, planner, plant_model: plug-in names overriding the scenario's
    (:func:`zenswarm.scenario.plugins.select`; None: the scenario's). rt_priority: realtime only, run
    the process's threads under ``SCHED_FIFO`` at this priority once start-up is over
    (:mod:`zenswarm.process.rtsched`; None: the fair scheduler). router_lost_timeout: wall seconds to wait
    for a lost router to come back before giving up (:data:`DEFAULT_ROUTER_LOST_TIMEOUT_S`).
    kill_at_tick: lockstep only, the process SIGKILLs itself just before it runs this tick
    (:class:`zenswarm.process.lockstep.Lockstep`; ``zenswarm up --kill``), so the fault falls on the same tick in every run.
    """

    scenario: Scenario | Path | None = None
    swarm: str = "default"
    connect: tuple[str, ...] = ()
    realtime: bool = False
    lockstep_timeout: float = DEFAULT_LOCKSTEP_TIMEOUT_S
    keys: Path | None = None
    tls: bool = False
    link_delay: str | None = None
    link_jitter: str | None = None
    link_loss: str | None = None
    partition: tuple[str, ...] = ()
    seed: int | None = None
    link_range: str | None = None
    link_fade: str | None = None
    controller: str | None = None
    link_capacity: str | None = None
    link_queue: str | None = None
    link_medium: str | None = None
    link_trace: str | None = None
    planner: str | None = None
    rt_priority: int | None = None
    plant_model: str | None = None
    router_lost_timeout: float = DEFAULT_ROUTER_LOST_TIMEOUT_S
    kill_at_tick: int | None = None

    @classmethod
    def of(cls, obj: Any) -> ProcessOptions:
        """The options read off any object with these attribute names (e.g. a parsed command
        line); a missing or None attribute takes the default. An object with a
        ``process_options()`` method (a role's or an edge's typed settings) gives its own."""
        if isinstance(obj, ProcessOptions):
            return obj
        own = getattr(obj, "process_options", None)
        if callable(own):
            return own()  # type: ignore[no-any-return]

        def get(name: str, default: Any) -> Any:
            value = getattr(obj, name, None)
            return default if value is None else value

        return cls(
            scenario=get("scenario", None),
            swarm=str(get("swarm", "default")),
            connect=tuple(get("connect", ())),
            realtime=bool(get("realtime", False)),
            lockstep_timeout=float(get("lockstep_timeout", DEFAULT_LOCKSTEP_TIMEOUT_S)),
            keys=get("keys", None),
            tls=bool(get("tls", False)),
            link_delay=get("link_delay", None),
            link_jitter=get("link_jitter", None),
            link_loss=get("link_loss", None),
            partition=tuple(get("partition", ())),
            seed=get("seed", None),
            link_range=get("link_range", None),
            link_fade=get("link_fade", None),
            controller=get("controller", None),
            planner=get("planner", None),
            link_capacity=get("link_capacity", None),
            link_queue=get("link_queue", None),
            link_medium=get("link_medium", None),
            link_trace=get("link_trace", None),
            rt_priority=get("rt_priority", None),
            plant_model=get("plant_model", None),
            router_lost_timeout=float(get("router_lost_timeout", DEFAULT_ROUTER_LOST_TIMEOUT_S)),
            kill_at_tick=get("kill_at_tick", None),
        )

    def fault_plan(self, scenario: Scenario) -> FaultPlan | None:
        """The link-fault plan of this run (scenario's ``[faults]`` plus the flags); None when no
        fault is active. Raises :class:`zenswarm.errors.ScenarioError` naming the bad field."""
        from zenswarm.link import plan_for

        return plan_for(
            scenario, self.link_delay, self.link_jitter, self.link_loss, self.partition, self.seed,
            link_range=self.link_range, link_fade=self.link_fade, link_capacity=self.link_capacity,
            link_queue=self.link_queue, link_medium=self.link_medium, link_trace=self.link_trace,
        )  # fmt: skip

"""A flight's settings as one typed value, and what each of its processes is started with.

The front door builds a :class:`FlightSettings` once: ``zenswarm up``'s command line
(:func:`zenswarm.compose.up.flight_settings`) or :func:`zenswarm.api.fly`'s arguments. It
carries the scenario parsed and checked (overrides and plug-in names applied), so no process
reads the scenario file again. The supervisor takes it, and hands each role it starts (plant,
leader, agent i) that role's part, a :class:`RoleSettings`, in one serialized form: msgpack on the
child's standard input (:func:`encode`, :func:`decode_role`); the edges it starts (the recorder,
a vehicle bridge, the simulated vehicles) get theirs the same way (:func:`decode_as`; what each
process is started with: :mod:`zenswarm.compose.commands`). ``api.fly`` hands the whole
:class:`FlightSettings` to its ``zenswarm up`` child the same way (:func:`decode_flight`).

A role started by hand on another host (``zenswarm up --only agent:2 --connect ...``, or
``zenswarm agent --id 2 --scenario F``) builds its settings from its own command line: only the
supervisor's children receive them serialized.

The scenario travels typed (msgpack of :class:`zenswarm.scenario.config.Scenario`, its floats as
IEEE doubles): it decodes equal to what was encoded, field for field, without another TOML
parse or validation (``tests/test_settings.py``). Paths travel as text. Nothing here imports
argparse: the command line is parsed at the edges.
"""

from __future__ import annotations

import sys
from pathlib import Path, PurePath
from typing import Any, TypeVar

import msgspec

from zenswarm.errors import ScenarioError
from zenswarm.link import LinkFaults
from zenswarm.process.options import DEFAULT_LOCKSTEP_TIMEOUT_S, DEFAULT_ROUTER_LOST_TIMEOUT_S, ProcessOptions
from zenswarm.scenario.config import Scenario

__all__ = ["FlightSettings", "RoleSettings", "LiveView", "encode", "decode_as", "decode_flight", "decode_role", "read_settings",
           "DEFAULT_EXTERNAL_TIMEOUT_S"]

DEFAULT_EXTERNAL_TIMEOUT_S = 60.0
"""``--external-timeout``: how long an external role may take to announce itself (the plant
waits as long for the processes it needs before its first tick)."""


class LiveView(msgspec.Struct, frozen=True):
    """What ``--live`` asks for: ``viewer`` (``foxglove`` or ``rerun``) served on ``port``
    (:mod:`zenswarm.bridge.views.live` opens it)."""

    viewer: str
    port: int


class RoleSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What one role of a flight (``plant``, ``leader``, ``agent:<i>``) is started with: the
    scenario, the bus it joins, its credentials, the link faults, the plug-ins, and the options
    of this start (``kill_at_tick``: lockstep, the first start of a role named by ``--kill``;
    ``expect``: the plant waits for these processes too before its first tick).

    connect: the router's endpoints (empty: ``tcp/127.0.0.1:7447``). keys, tls: credentials of
    a secured router (the tree of ``zenswarm keys``; the process joins with its own user only,
    :mod:`zenswarm.process.security`). Durations in wall seconds."""

    role: str
    scenario: Scenario | None = None  # None: fetched from the leader's mission key (an edge started by hand without a file)
    swarm: str = "default"
    connect: tuple[str, ...] = ()
    realtime: bool = False
    lockstep_timeout: float = DEFAULT_LOCKSTEP_TIMEOUT_S
    keys: Path | None = None
    tls: bool = False
    faults: LinkFaults = msgspec.field(default_factory=LinkFaults)
    controller: str | None = None
    planner: str | None = None
    plant_model: str | None = None
    rt_priority: int | None = None
    router_lost_timeout: float = DEFAULT_ROUTER_LOST_TIMEOUT_S
    kill_at_tick: int | None = None
    expect: tuple[str, ...] = ()

    def process_options(self) -> ProcessOptions:
        """The options of the role's :class:`zenswarm.process.runtime.SwarmProcess`."""
        f = self.faults
        return ProcessOptions(
            scenario=self.scenario, swarm=self.swarm, connect=self.connect, realtime=self.realtime,
            lockstep_timeout=self.lockstep_timeout, keys=self.keys, tls=self.tls,
            link_delay=f.link_delay, link_jitter=f.link_jitter, link_loss=f.link_loss, partition=f.partitions, seed=f.seed,
            link_range=f.link_range, link_fade=f.link_fade, link_capacity=f.link_capacity, link_queue=f.link_queue,
            link_medium=f.link_medium, link_trace=f.link_trace,
            controller=self.controller, planner=self.planner, plant_model=self.plant_model, rt_priority=self.rt_priority,
            router_lost_timeout=self.router_lost_timeout, kill_at_tick=self.kill_at_tick,
        )  # fmt: skip


class FlightSettings(msgspec.Struct, frozen=True, kw_only=True):
    """One flight of ``zenswarm up``, typed: everything its flags and :func:`zenswarm.api.fly`'s
    arguments say (the flags' help tells what each means). Durations in wall seconds.

    scenario: parsed and checked once by the front door (overrides and ``--controller`` /
    ``--planner`` / ``--plant-model`` applied; ``--seed`` is in ``faults``). scenario_file: the
    file it came from (with overrides, the effective one the supervisor wrote): what a recording
    names as its scenario's source (no process reads it). Built by :func:`zenswarm.compose.up.flight_settings` (the
    command line) or by :func:`zenswarm.api.fly`."""

    scenario: Scenario
    scenario_file: Path
    swarm: str = "default"
    out: Path = Path("runs/up")
    realtime: bool = False
    plant: str = "sim"
    mavlink_base_port: int | None = None
    crazyflie_base_port: int | None = None
    external: tuple[str, ...] = ()
    external_timeout: float = DEFAULT_EXTERNAL_TIMEOUT_S
    record: Path | None = None
    report: bool = False
    report_format: tuple[str, ...] = ("png",)
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    router_connect: tuple[str, ...] = ()
    secure: bool = False
    tls: bool = False
    keys: Path | None = None
    insecure: bool = False
    only: str | None = None
    lockstep_timeout: float = DEFAULT_LOCKSTEP_TIMEOUT_S
    kill: tuple[tuple[str, float], ...] = ()  # (process, sim time s)
    restart: bool = False
    stop_at_goal: bool = False
    full_time: bool = False
    progress_every: float = 1.0
    quiet: bool = False
    quiet_children: bool = False
    faults: LinkFaults = msgspec.field(default_factory=LinkFaults)
    controller: str | None = None  # plug-in names overriding the scenario's (zenswarm.scenario.plugins.select)
    planner: str | None = None
    plant_model: str | None = None
    live: LiveView | None = None  # --live: serve the flight to a viewer (zenswarm.bridge.views.live)
    rt_priority: int | None = None  # --rt-priority P: the flying processes under SCHED_FIFO P (zenswarm.process.rtsched)
    router_lost_timeout: float | None = None  # --only: give up on a lost router after S s (zenswarm.process.runtime)
    scheduler: str | None = None  # --scheduler: the Dask scheduler whose workers run the roles (zenswarm.compose.cluster)
    placement: tuple[str, ...] = ()  # --placement ROLES=TARGET rules (zenswarm.compose.placement)

    @property
    def mode(self) -> str:
        """``realtime`` or ``lockstep``."""
        return "realtime" if self.realtime else "lockstep"

    def role(
        self, role: str, connect: tuple[str, ...], keys: Path | None = None, *,
        kill_at_tick: int | None = None, expect: tuple[str, ...] = (),
    ) -> RoleSettings:  # fmt: skip
        """The settings of one role of this flight, joining the router at ``connect`` with the
        credentials in ``keys`` (None: an open router)."""
        rlt = self.router_lost_timeout
        return RoleSettings(
            role=role, scenario=self.scenario, swarm=self.swarm, connect=connect, realtime=self.realtime,
            lockstep_timeout=self.lockstep_timeout, keys=keys, tls=self.tls and keys is not None, faults=self.faults,
            controller=self.controller, planner=self.planner, plant_model=self.plant_model, rt_priority=self.rt_priority,
            router_lost_timeout=DEFAULT_ROUTER_LOST_TIMEOUT_S if rlt is None else rlt, kill_at_tick=kill_at_tick, expect=expect,
        )  # fmt: skip

    def plugin_argv(self) -> list[str]:
        """``--controller NAME`` / ``--planner NAME`` / ``--plant-model NAME``: the plug-in flags
        of these settings (those given), for a command line of a process started by hand."""
        words: list[str] = []
        for flag, name in (("--controller", self.controller), ("--planner", self.planner), ("--plant-model", self.plant_model)):
            if name is not None:
                words += [flag, name]
        return words


def _enc_hook(obj: Any) -> Any:
    if isinstance(obj, PurePath):
        return str(obj)
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


def _dec_hook(tp: Any, obj: Any) -> Any:
    if tp is Path and isinstance(obj, str):
        return Path(obj)
    raise NotImplementedError(f"cannot decode {tp!r}")


_ENCODER = msgspec.msgpack.Encoder(enc_hook=_enc_hook)
_T = TypeVar("_T", bound=msgspec.Struct)


def encode(settings: msgspec.Struct) -> bytes:
    """The settings as msgpack (what a child reads on its standard input). A scenario built in
    code with values msgpack cannot carry (a numpy array, say) is a ScenarioError naming it."""
    try:
        return _ENCODER.encode(settings)
    except (TypeError, NotImplementedError, msgspec.EncodeError) as e:
        raise ScenarioError("scenario", f"cannot be handed to the swarm's processes: {e}") from None


def decode_as(data: bytes, tp: type[_T]) -> _T:
    """The settings of type ``tp`` (a frozen msgspec struct: a role's, an edge's) from
    :func:`encode`'s bytes (ScenarioError naming ``--settings`` otherwise)."""
    try:
        return msgspec.msgpack.decode(data, type=tp, dec_hook=_dec_hook)
    except msgspec.MsgspecError as e:
        raise ScenarioError("--settings", f"not the {tp.__name__} of a flight: {e}") from None


def decode_flight(data: bytes) -> FlightSettings:
    """:class:`FlightSettings` from :func:`encode`'s bytes (ScenarioError naming ``--settings`` otherwise)."""
    return decode_as(data, FlightSettings)


def decode_role(data: bytes) -> RoleSettings:
    """:class:`RoleSettings` from :func:`encode`'s bytes (ScenarioError naming ``--settings`` otherwise)."""
    return decode_as(data, RoleSettings)


def read_settings(where: str) -> bytes:
    """The bytes of ``--settings FILE`` (``-``: standard input, read to its end)."""
    if where == "-":
        return sys.stdin.buffer.read()
    try:
        return Path(where).read_bytes()
    except OSError as e:
        raise ScenarioError("--settings", f"cannot read {where}: {e}") from None

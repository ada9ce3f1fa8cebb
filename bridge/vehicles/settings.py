"""What the vehicle bridges are started with: :class:`MavlinkBridgeSettings` (``zenswarm bridge
mavlink``) and :class:`CrazyflieBridgeSettings` (``zenswarm bridge crazyflie``), typed.

Each is built once: from the bridge command's flags, or by ``zenswarm up`` from its flight
(:mod:`zenswarm.compose.commands`, msgpack on the bridge's standard input). ``process`` is what
the bridge's swarm process joins the bus with (:class:`zenswarm.process.settings.RoleSettings`,
role ``bridge``, realtime); the other fields override the scenario's ``[mavlink]`` /
``[crazyflie]`` table (None or empty: the table's value; :func:`zenswarm.vehicle.autopilot.mavlink_settings`,
:func:`zenswarm.vehicle.crazyflie_settings.crazyflie_settings`). This module loads no vehicle
library: the supervisor builds these without pymavlink or cflib.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any, TypeVar

import msgspec

from zenswarm.errors import EXIT_BAD_INPUT, ZenswarmError
from zenswarm.process.options import ProcessOptions
from zenswarm.process.settings import RoleSettings
from zenswarm.scenario.config import Scenario

__all__ = ["MavlinkBridgeSettings", "CrazyflieBridgeSettings", "run_bridge", "bridge_main"]


class _BridgeSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What both bridges take: the swarm process's settings, and whether to wait for the leader's
    and agents' liveliness before starting the mission clock (``--no-wait-alive``: not)."""

    process: RoleSettings
    no_wait_alive: bool = False

    @property
    def swarm(self) -> str:
        return self.process.swarm

    @property
    def expect(self) -> tuple[str, ...]:
        """Processes also waited for before the mission clock starts (``--expect``)."""
        return self.process.expect

    def process_options(self) -> ProcessOptions:
        """The options of the bridge's :class:`zenswarm.process.runtime.SwarmProcess`."""
        return self.process.process_options()

    def overrides(self) -> dict[str, Any]:
        """The overrides of the scenario's vehicle table (each bridge's own)."""
        raise NotImplementedError


class MavlinkBridgeSettings(_BridgeSettings, frozen=True, kw_only=True):
    """``zenswarm bridge mavlink``: overrides of the scenario's ``[mavlink]`` table, by flag
    (``--conn I=URL`` -> ``conn[I]``, ``--origin I=X,Y,Z`` (m, ENU) -> ``origin[I]``, ``--rate``
    -> ``rate_hz``, ``--no-takeoff`` -> ``takeoff`` False, ``--link-timeout S`` -> ``link_timeout_s``, ...)."""

    conn: dict[int, str] = msgspec.field(default_factory=dict)
    sysid: dict[int, int] = msgspec.field(default_factory=dict)
    origin: dict[int, tuple[float, ...]] = msgspec.field(default_factory=dict)
    base_port: int | None = None
    host: str | None = None
    setpoint: str | None = None
    rate_hz: float | None = None
    autopilot: str | None = None
    hover_throttle: float | None = None
    takeoff: bool | None = None
    link_timeout_s: float | None = None
    land_timeout_s: float | None = None
    stream_s: float | None = None
    start_timeout_s: float | None = None

    def overrides(self) -> dict[str, Any]:
        """What :func:`zenswarm.vehicle.autopilot.mavlink_settings` takes."""
        return {k: getattr(self, k) for k in _MAVLINK_KEYS}


_MAVLINK_KEYS = ("conn", "sysid", "origin", "base_port", "host", "setpoint", "rate_hz", "autopilot", "hover_throttle", "takeoff",
                 "link_timeout_s", "land_timeout_s", "stream_s", "start_timeout_s")  # fmt: skip


class CrazyflieBridgeSettings(_BridgeSettings, frozen=True, kw_only=True):
    """``zenswarm bridge crazyflie``: overrides of the scenario's ``[crazyflie]`` table, by flag
    (``--uri I=URI`` -> ``uri[I]``, ``--cf-host`` -> ``host``, ``--rate`` -> ``rate_hz``,
    ``--no-takeoff`` -> ``takeoff`` False, ``--connect-timeout S`` -> ``connect_timeout_s``, ...)."""

    uri: dict[int, str] = msgspec.field(default_factory=dict)
    base_port: int | None = None
    host: str | None = None
    rate_hz: float | None = None
    takeoff: bool | None = None
    link_timeout_s: float | None = None
    land_timeout_s: float | None = None
    connect_timeout_s: float | None = None
    start_timeout_s: float | None = None
    positioning: str | None = None

    def overrides(self) -> dict[str, Any]:
        """What :func:`zenswarm.vehicle.crazyflie_settings.crazyflie_settings` takes."""
        return {k: getattr(self, k) for k in _CRAZYFLIE_KEYS}


_CRAZYFLIE_KEYS = ("uri", "base_port", "host", "rate_hz", "takeoff", "link_timeout_s", "land_timeout_s", "connect_timeout_s",
                   "start_timeout_s", "positioning")  # fmt: skip


_S = TypeVar("_S", bound=_BridgeSettings)


def _bad_input(e: ZenswarmError) -> int:
    """``bridge: error: ...`` on stderr; exit status 2."""
    print(f"bridge: error: {e}", file=sys.stderr, flush=True)
    return EXIT_BAD_INPUT


def run_bridge(s: _S, check: Callable[[Scenario, dict[str, Any]], object], body: Callable[[Any], int]) -> int:
    """Run a vehicle bridge with settings ``s`` as the swarm process ``bridge`` (``body`` takes
    its :class:`zenswarm.process.runtime.SwarmProcess`). With the scenario at hand, ``check`` of
    it and the overrides first (``mavlink_settings``, ``crazyflie_settings``): a bad table or
    override is exit 2 naming the field, before any work (no Zenoh session, no vehicle link)."""
    from zenswarm.process.runtime import run_process

    if s.process.scenario is not None:
        try:
            check(s.process.scenario, s.overrides())
        except ZenswarmError as e:
            return _bad_input(e)
    return run_process(body, "bridge", s)


def bridge_main(build: Callable[[argparse.Namespace], _S], run: Callable[[_S], int]) -> Callable[[argparse.Namespace], int]:
    """The ``func`` of a ``zenswarm bridge KIND`` command: its settings ``build`` from the flags
    (a :class:`ZenswarmError`: exit 2 naming the flag or file), then ``run`` with them."""

    def main(args: argparse.Namespace) -> int:
        try:
            s = build(args)
        except ZenswarmError as e:
            return _bad_input(e)
        return run(s)

    return main

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

from typing import Any

import msgspec

from zenswarm.process.options import ProcessOptions
from zenswarm.process.settings import RoleSettings

__all__ = ["MavlinkBridgeSettings", "CrazyflieBridgeSettings"]


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

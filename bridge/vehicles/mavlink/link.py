"""A MAVLink bridge's link to one UAV: pymavlink (MAVLink 2), the phases a link goes through, the
vehicle's latest telemetry (:class:`Telemetry`), the connection it shares with other UAVs
(:class:`Endpoint`), the bridge's state of the UAV (:class:`UavLink`), and the frames between a
vehicle's own local NED and the swarm's ENU (:func:`vehicle_to_swarm`, :func:`swarm_to_vehicle`).

Importing this module sets ``MAVLINK20=1`` in the environment before importing pymavlink
(:func:`zenswarm.vehicle.autopilot.load_mavutil`), so all connections of the process speak MAVLink 2.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import VehicleParams, load_mavutil, mode_name

__all__ = ["mavutil", "mavlink", "Telemetry", "Endpoint", "UavLink", "vehicle_to_swarm", "swarm_to_vehicle",
           "CONNECTING", "PARAMS", "STREAM", "MODE", "ARM", "TAKEOFF", "READY", "REFUSED", "RELEASED", "GROUNDED", "LANDING", "DONE"]

mavutil = load_mavutil()
mavlink = mavutil.mavlink

# phases of a link (diag: uav.<i>.phase)
CONNECTING, PARAMS, STREAM, MODE, ARM, TAKEOFF, READY, REFUSED, RELEASED, GROUNDED, LANDING, DONE = (
    "connecting", "params", "stream", "mode", "arm", "takeoff", "ready", "refused", "released", "grounded", "landing", "done",
)
_TIMESYNC_WINDOW = 8  # the clock offset comes from the fastest of the last answers (NTP's rule)


@dataclass
class Telemetry:
    """The latest report of one vehicle, MAVLink frames; times are time.monotonic() s."""

    last_rx: float = -math.inf
    hb_rx: float = -math.inf
    hb_count: int = 0
    armed: bool = False
    custom_mode: int | None = None
    autopilot: str | None = None
    pos_ned: np.ndarray | None = None
    vel_ned: np.ndarray | None = None
    pos_rx: float = -math.inf
    rpy_ned: np.ndarray | None = None
    rates_frd: np.ndarray | None = None
    att_rx: float = -math.inf
    att_euler_rx: float = -math.inf  # last ATTITUDE (Euler): ATTITUDE_QUATERNION is then redundant
    pos_boot_s: float | None = None  # the vehicle's time_boot_ms of the position sample, s
    sensors: tuple[int, int, int] | None = None  # SYS_STATUS (present, enabled, health) bitmasks
    ss_rx: float = -math.inf
    landed_state: int | None = None  # EXTENDED_SYS_STATE.landed_state (MAV_LANDED_STATE), None: never sent
    params: dict[str, float] = field(default_factory=dict)  # PARAM_VALUE by name (decoded)
    param_rx: dict[str, float] = field(default_factory=dict)  # when each parameter was last received
    rtt_s: float | None = None  # TIMESYNC round trip, s (latest)
    clock_offset_s: float | None = None  # vehicle clock - bridge monotonic clock, s (TIMESYNC, else time_boot_ms)
    clock_from_timesync: bool = False
    timesync_samples: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=_TIMESYNC_WINDOW))  # (rtt, offset)


class Endpoint:
    """One MAVLink connection (possibly shared by several UAVs with different system ids)."""

    def __init__(self, url: str, source_system: int) -> None:
        self.url = url
        self.source_system = source_system
        self.conn: Any = None
        self.links: dict[int, UavLink] = {}
        self.next_open = 0.0
        self.open_error: str | None = None
        self.next_heartbeat = 0.0

    def ensure_open(self, now: float) -> bool:
        if self.conn is not None:
            return True
        if now < self.next_open:
            return False
        self.next_open = now + 2.0
        try:
            self.conn = mavutil.mavlink_connection(
                self.url,
                source_system=self.source_system,
                source_component=mavlink.MAV_COMP_ID_ONBOARD_COMPUTER,
                retries=0,
                autoreconnect=True,
                udp_timeout=5,
            )
            self.open_error = None
        except Exception as e:  # noqa: BLE001 - serial/tcp may fail now and work later
            self.open_error = f"{type(e).__name__}: {e}"
            self.conn = None
            return False
        return True

    def close(self) -> None:
        c, self.conn = self.conn, None
        if c is not None:
            try:
                c.close()
            except Exception:  # noqa: BLE001
                pass


@dataclass
class UavLink:
    """Bridge state of UAV ``uav`` (1-based) on its vehicle ``sysid``."""

    uav: int
    sysid: int
    endpoint: Endpoint
    origin: np.ndarray  # (3,) m ENU: the vehicle's local NED origin in the swarm frame
    takeoff_enu: np.ndarray  # (3,) m ENU
    tel: Telemetry = field(default_factory=Telemetry)
    phase: str = CONNECTING
    reason: str = ""
    autopilot: str = "px4"
    wanted_mode: int | None = None
    healthy: bool = False
    was_lost: bool = False  # a link loss happened since the UAV was last engaged
    engaged_once: bool = False
    armed_by_us: bool = False
    phase_t: float = 0.0
    hold_ned: np.ndarray | None = None
    hold_yaw_ned: float = 0.0
    mode_req_t: float = -math.inf
    mode_attempts: int = 0
    mode_accepted_t: float = -math.inf
    mismatch: int = 0
    last_hb_seen: int = 0
    arm_req_t: float = -math.inf
    arm_attempts: int = 0
    land_req_t: float = -math.inf
    still_since: float = math.inf
    recovered_t: float = -math.inf
    takeoff_sent: bool = False
    takeoff_req_t: float = -math.inf
    takeoff_attempts: int = 0
    climbed: bool = False  # ArduPilot: the takeoff altitude was reached (position targets allowed)
    airborne_known: bool = False  # took off under the bridge, or adopted in flight
    tmap: frames.ThrustMap | None = None  # per vehicle: from its hover throttle parameter
    vparams: VehicleParams | None = None
    param_req_t: float = -math.inf
    guid_set_t: float = -math.inf
    timesync_t: float = -math.inf
    state_age_s: float | None = None  # age of the last published state's sample (vehicle time), s
    acks: list[tuple[float, int, int]] = field(default_factory=list)

    def info(self, now: float) -> dict[str, Any]:
        t = self.tel
        return {
            "sysid": self.sysid,
            "phase": self.phase,
            "healthy": self.healthy,
            "armed": bool(t.armed),
            "mode": mode_name(self.autopilot, t.custom_mode),
            "wanted_mode": mode_name(self.autopilot, self.wanted_mode) if self.wanted_mode is not None else "",
            "silent_s": round(now - t.last_rx, 3) if math.isfinite(t.last_rx) else -1.0,
            "reason": self.reason,
            "url": self.endpoint.url,
            "params": {k: round(v, 6) for k, v in sorted(t.params.items())},
            "hover_throttle": self.vparams.hover_throttle if self.vparams is not None else None,
            "latency_ms": round(t.rtt_s * 500.0, 2) if t.rtt_s is not None else None,
            "state_age_ms": round(self.state_age_s * 1000.0, 2) if self.state_age_s is not None else None,
            "landed_state": t.landed_state,
        }


def vehicle_to_swarm(p_ned: Any, origin_enu: Any) -> np.ndarray:
    """A point of a vehicle's own local NED frame (m; origin = that vehicle's estimator origin,
    which differs from vehicle to vehicle on real autopilots) in the swarm's common ENU frame (m):
    ``ned_to_enu(p_ned) + origin_enu``; origin_enu (3,) = where the vehicle's local origin is in
    the swarm frame (``mavlink.origins``)."""
    return np.asarray(frames.ned_to_enu(np.asarray(p_ned, dtype=float)), dtype=float) + np.asarray(origin_enu, dtype=float)


def swarm_to_vehicle(q_enu: Any, origin_enu: Any) -> np.ndarray:
    """Inverse of :func:`vehicle_to_swarm`: a swarm-frame ENU point (m) in the vehicle's local NED (m)."""
    return np.asarray(frames.enu_to_ned(np.asarray(q_enu, dtype=float) - np.asarray(origin_enu, dtype=float)), dtype=float)

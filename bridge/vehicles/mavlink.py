"""MAVLink bridge: fly the swarm's agents on PX4 or ArduPilot vehicles (or the simulated ones of
:mod:`zenswarm.plant.mavlink_vehicle`) without changing a line of the agents.

``zenswarm bridge mavlink SCENARIO --swarm S --connect EP [--conn I=URL ...]`` takes the plant's place on the swarm bus in realtime
mode. For each UAV i it opens (or shares) a MAVLink connection (pymavlink connection string:
``udpout:host:port``, ``udpin:host:port``, ``tcp:host:port``, ``/dev/ttyUSB0,921600``) to the
vehicle with system id ``sysid_i`` and then:

1. sends its own HEARTBEAT at 1 Hz (MAV_TYPE_ONBOARD_CONTROLLER) and waits for the vehicle's;
   then reads the autopilot's parameters (PX4 ``MPC_THR_HOVER``, ``COM_OF_LOSS_T``; ArduCopter
   ``GUID_OPTIONS``, ``GUID_TIMEOUT``, ``MOT_THST_HOVER``): the hover throttle of the thrust map,
   the check that ``link_timeout_s`` is below the vehicle's loss timeout, and on ArduCopter with
   attitude setpoints ``GUID_OPTIONS`` bit 3 set (thrust as thrust, not a climb rate); a missing
   or bad parameter refuses the UAV (:func:`zenswarm.vehicle.autopilot.vehicle_params`);
2. streams setpoints (a position hold at the current position) for ``stream_s`` seconds before
   asking for the offboard mode, as PX4 requires (it refuses OFFBOARD unless setpoints arrive at
   more than 2 Hz, and leaves it after ``COM_OF_LOSS_T`` without them);
3. asks for the mode with MAV_CMD_DO_SET_MODE (PX4: OFFBOARD = main mode 6; ArduPilot copter:
   GUIDED = 4 for position setpoints or a takeoff, GUIDED_NOGPS = 20 for attitude only) and waits
   until the vehicle's heartbeat reports it. It never arms a vehicle whose heartbeat reports a
   mode it did not ask for: if the vehicle acknowledges the request but keeps reporting another
   mode, the UAV is *refused* (reason in the diag message) and left alone. Nor one whose
   SYS_STATUS reports a present, enabled subsystem unhealthy or failing pre-arm checks
   (:func:`health_problem`);
4. arms (MAV_CMD_COMPONENT_ARM_DISARM) and, with ``takeoff = true``, flies to the UAV's initial
   position of the scenario with position setpoints (ArduCopter: MAV_CMD_NAV_TAKEOFF first, and
   no position target until its altitude is reached, see ``_ardupilot_climb``);
5. once every UAV is ready (or ``start_timeout_s`` passed) and, unless ``--no-wait-alive``, the
   leader and the agents hold liveliness tokens, starts the mission clock: every control tick it
   publishes ``clock`` and each ready UAV's ``uav/<i>/state`` (from LOCAL_POSITION_NED and
   ATTITUDE/ATTITUDE_QUATERNION, converted to ENU/FLU by :mod:`zenswarm.vehicle.frames`; stamped ``ts``
   with the vehicle's ``time_boot_ms`` on the mission clock once TIMESYNC gave its clock offset,
   :meth:`Bridge.sample_time`), as the realtime
   plant does (mission time is wall time since the start: a tick the loop missed on an overloaded
   host is skipped and counted in ``ticks_skipped``, never caught up in a burst), and forwards
   each agent's ``uav/<i>/cmd`` as SET_ATTITUDE_TARGET
   (quaternion + normalised thrust through :class:`zenswarm.vehicle.frames.ThrustMap`) at
   ``max(rate_hz, 20)`` Hz, re-sending the latest command if the agent is slower; with
   ``setpoint = "position"`` it forwards ``uav/<i>/ref`` as SET_POSITION_TARGET_LOCAL_NED
   (position + velocity) instead and lets the vehicle run its own position loop. A command older
   than ``cmd_timeout_s`` is replaced by a position hold;
6. a vehicle silent for more than ``link_timeout_s`` is marked unhealthy in ``diag/bridge``
   (its state is no longer published; the other UAVs keep flying); when it talks again it is
   marked healthy and, if it left the offboard mode during the silence (offboard-loss failsafe)
   but is still armed, the bridge asks for the mode again. If the mode changes while the link
   is healthy (a pilot took over), the UAV is *released* and no longer commanded;
7. at the end of the mission (``timing.time_limit_s``) or on SIGTERM/SIGINT it switches every
   vehicle it armed to the land mode (PX4 AUTO.LAND, ArduPilot LAND), waits (at most
   ``land_timeout_s``) until the vehicles report disarmed (auto-disarm after landing) and sends a
   (non-forced) disarm to any that did not.

Unknown and malformed MAVLink traffic (bad CRC/garbage, unknown message ids, non-finite fields,
other system ids) is ignored and counted (``mav_bad``, ``mav_unknown``, ``mav_malformed``,
``mav_other_system``, ``mav_unhandled`` in the bridge's diag counters).

Configuration: the scenario's ``[mavlink]`` table (see :func:`mavlink_settings` for every key),
overridden by command-line flags. All frames conversions are in :mod:`zenswarm.vehicle.frames`.

Importing this module sets ``MAVLINK20=1`` in the environment before importing pymavlink, so all
connections of the process speak MAVLink 2 (PX4 and ArduPilot both do).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from zenswarm.bridge.vehicles.settings import MavlinkBridgeSettings
from zenswarm.errors import ScenarioError
from zenswarm.scenario.config import Scenario
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import (  # re-exported: the mode tables and settings are the bridge's vocabulary
    AP_COPTER_MODES,
    AUTOPILOT_PARAMS,
    GUID_OPTIONS_THRUST_AS_THRUST,
    PX4_AUTO_SUB,
    PX4_HOLD,
    PX4_LAND,
    PX4_MAIN,
    PX4_OFFBOARD,
    PX4_POSCTL,
    MavlinkSettings,
    VehicleParams,
    _same_mode,
    autopilot_name,
    load_mavutil,
    mavlink_settings,
    mode_name,
    mode_request_params,
    param_value,
    px4_custom_mode,
    px4_decode,
    vehicle_params,
)

mavutil = load_mavutil()
mavlink = mavutil.mavlink

__all__ = [
    "Bridge",
    "vehicle_to_swarm",
    "swarm_to_vehicle",
    "health_problem",
    "add_parsers",
    "add_mavlink_parser",
    # re-exported from zenswarm.vehicle.autopilot: the bridge's vocabulary (modes, settings)
    "AP_COPTER_MODES",
    "PX4_AUTO_SUB",
    "PX4_HOLD",
    "PX4_LAND",
    "PX4_MAIN",
    "PX4_OFFBOARD",
    "PX4_POSCTL",
    "MavlinkSettings",
    "autopilot_name",
    "mavlink_settings",
    "mode_name",
    "mode_request_params",
    "px4_custom_mode",
    "px4_decode",
]

# --------------------------------------------------------------------------- per-UAV link

# SET_ATTITUDE_TARGET type_mask: ignore the body rates (bits 0-2), use attitude and thrust.
ATT_MASK = (
    mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_ROLL_RATE_IGNORE
    | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_PITCH_RATE_IGNORE
    | mavlink.ATTITUDE_TARGET_TYPEMASK_BODY_YAW_RATE_IGNORE
)
# SET_POSITION_TARGET_LOCAL_NED type_mask: use position, velocity and yaw; ignore acceleration
# and yaw rate.
POS_MASK = (
    mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)

# phases of a link (diag: uav.<i>.phase)
CONNECTING, PARAMS, STREAM, MODE, ARM, TAKEOFF, READY, REFUSED, RELEASED, GROUNDED, LANDING, DONE = (
    "connecting", "params", "stream", "mode", "arm", "takeoff", "ready", "refused", "released", "grounded", "landing", "done",
)
_PENDING = (CONNECTING, PARAMS, STREAM, MODE, ARM, TAKEOFF)
_PARAM_RETRY_S = 0.5  # PARAM_REQUEST_READ / PARAM_SET repeated this often until answered
_SYS_STATUS_WAIT_S = 3.0  # ARM: no SYS_STATUS this long -> refused (health unknown)
_TAKEOFF_RETRY_S = 1.0
_TIMESYNC_S = 1.0  # TIMESYNC request period per vehicle (link latency)
_TIMESYNC_WINDOW = 8  # the clock offset comes from the fastest of the last answers (NTP's rule)
# MAV_LANDED_STATE (MAVLink common.xml, sent in EXTENDED_SYS_STATE): IN_AIR, TAKEOFF, LANDING
_AIRBORNE_STATES = (2, 3, 4)
_MODE_RETRY_S = 1.0
_MODE_ATTEMPTS = 8
_ARM_RETRY_S = 1.0
_ARM_ATTEMPTS = 5
_MISMATCH_HEARTBEATS = 2  # heartbeats reporting another mode after an accepted request -> refuse
_STALL_S = 0.25  # a bridge loop gap this long may have tripped an offboard-loss failsafe


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


def _finite(*xs: float) -> bool:
    return all(math.isfinite(x) for x in xs)


def vehicle_to_swarm(p_ned: Any, origin_enu: Any) -> np.ndarray:
    """A point of a vehicle's own local NED frame (m; origin = that vehicle's estimator origin,
    which differs from vehicle to vehicle on real autopilots) in the swarm's common ENU frame (m):
    ``ned_to_enu(p_ned) + origin_enu``; origin_enu (3,) = where the vehicle's local origin is in
    the swarm frame (``mavlink.origins``)."""
    return np.asarray(frames.ned_to_enu(np.asarray(p_ned, dtype=float)), dtype=float) + np.asarray(origin_enu, dtype=float)


def swarm_to_vehicle(q_enu: Any, origin_enu: Any) -> np.ndarray:
    """Inverse of :func:`vehicle_to_swarm`: a swarm-frame ENU point (m) in the vehicle's local NED (m)."""
    return np.asarray(frames.enu_to_ned(np.asarray(q_enu, dtype=float) - np.asarray(origin_enu, dtype=float)), dtype=float)


_SENSOR_NAMES = {
    int(getattr(mavlink, name)): name.removeprefix("MAV_SYS_STATUS_").removeprefix("SENSOR_").lower()
    for name in dir(mavlink)
    if name.startswith("MAV_SYS_STATUS_") and not name.endswith("ENUM_END") and isinstance(getattr(mavlink, name), int)
}


def health_problem(present: int, enabled: int, health: int) -> str:
    """Why a vehicle reporting these SYS_STATUS bitmasks (``onboard_control_sensors_present``,
    ``_enabled``, ``_health``) must not be armed, or "" if it may. A subsystem that is present and
    enabled but not healthy blocks arming; ``MAV_SYS_STATUS_PREARM_CHECK`` (PX4 and ArduPilot set
    it present and enabled, healthy once their pre-arm checks pass; MAVLink common.xml) is
    reported as the pre-arm checks failing."""
    bad = int(present) & int(enabled) & ~int(health) & 0xFFFFFFFF
    if not bad:
        return ""
    prearm = int(mavlink.MAV_SYS_STATUS_PREARM_CHECK)
    names = [_SENSOR_NAMES.get(1 << k, f"bit {k}") for k in range(32) if bad & (1 << k) and (1 << k) != prearm]
    parts = (["pre-arm checks failing"] if bad & prearm else []) + ([f"unhealthy: {', '.join(names)}"] if names else [])
    return "; ".join(parts)


class Bridge:
    """The bridge's core: MAVLink side, phase machines, setpoints. The bus side is injected.

    Parameters
    ----------
    settings : MavlinkSettings
    scenario : Scenario
    counters : dict[str, float]
        Incremented in place (the process's diag counters).
    get_cmd, get_ref : callable(uav) -> (message or None, age s)
        The latest ``uav/<i>/cmd`` / ``uav/<i>/ref`` of the swarm and its age.
    log : callable(str)
    clock : callable() -> float
        Monotonic clock, s (time.monotonic).
    """

    def __init__(
        self,
        settings: MavlinkSettings,
        scenario: Scenario,
        counters: dict[str, float],
        get_cmd: Callable[[int], tuple[Any, float]],
        get_ref: Callable[[int], tuple[Any, float]],
        log: Callable[[str], None] = print,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        from zenswarm.vehicle.params import QuadParams

        self.s = settings
        self.sc = scenario
        self.counters = counters
        self.get_cmd = get_cmd
        self.get_ref = get_ref
        self.log = log
        self.clock = clock
        params = QuadParams.from_vehicle(scenario.vehicle)
        self.hover_thrust = params.hover_thrust
        self.max_thrust = params.max_thrust
        # until a vehicle's parameters are read: the hover_throttle setting, else thrust / max_thrust
        self.tmap = frames.ThrustMap(params.max_thrust, params.hover_thrust, settings.hover_throttle)
        self.yaw_ned = float(frames.euler_enu_to_ned([0.0, 0.0, scenario.controller.yaw])[2])
        self.endpoints: dict[str, Endpoint] = {}
        self.links: list[UavLink] = []
        self.boot = clock()
        self.changed = False  # a phase or health transition since the last diag (publish it now)
        self.warned_grounded = False  # the ArduCopter takeoff = false + position warning was given
        for i in range(settings.n):
            url = settings.connections[i]
            ep = self.endpoints.get(url)
            if ep is None:
                ep = self.endpoints[url] = Endpoint(url, settings.source_system)
            link = UavLink(
                uav=i + 1,
                sysid=settings.sysids[i],
                endpoint=ep,
                origin=np.array(settings.origins[i], dtype=float),
                takeoff_enu=np.array(scenario.initial_positions[i], dtype=float),
                phase_t=self.boot,
            )
            if settings.autopilot != "auto":
                link.autopilot = settings.autopilot
            ep.links[link.sysid] = link
            self.links.append(link)

    # ------------------------------------------------------------------ helpers
    def _count(self, name: str, k: float = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + k

    def _ms(self, now: float) -> int:
        return int((now - self.boot) * 1000.0) & 0xFFFFFFFF

    def _set_phase(self, link: UavLink, phase: str, now: float, reason: str | None = None) -> None:
        if link.phase != phase:
            self.changed = True
            if phase in (TAKEOFF, READY):
                link.hold_ned = None  # the pre-arm hold (on the ground) must not outlive its phase
            self.log(f"bridge: uav {link.uav}: {link.phase} -> {phase}" + (f" ({reason})" if reason else ""))
            link.phase = phase
            link.phase_t = now
        if reason is not None:
            link.reason = reason

    def _mav(self, link: UavLink) -> Any:
        c = link.endpoint.conn
        return None if c is None else c.mav

    # ------------------------------------------------------------------ receive
    def poll(self, now: float, max_per_endpoint: int = 2000) -> None:
        """Open what is not open yet, drain every connection (bounded), update health."""
        for ep in self.endpoints.values():
            if not ep.ensure_open(now):
                continue
            for _ in range(max_per_endpoint):
                try:
                    m = ep.conn.recv_msg()
                except Exception as e:  # noqa: BLE001 - a broken link must not stop the loop
                    self._count("mav_recv_errors")
                    if self.counters.get("mav_recv_errors", 0) <= 3:
                        self.log(f"bridge: {ep.url}: receive error {type(e).__name__}: {e}")
                    break
                if m is None:
                    break
                self._handle(ep, m, now)
        for link in self.links:
            self._update_health(link, now)

    def _handle(self, ep: Endpoint, m: Any, now: float) -> None:
        mtype = m.get_type()
        if mtype == "BAD_DATA":
            self._count("mav_bad")
            return
        if mtype.startswith("UNKNOWN_"):
            self._count("mav_unknown")
            return
        link = ep.links.get(m.get_srcSystem())
        if link is None:
            self._count("mav_other_system")
            return
        rx = self._RX.get(mtype)
        if rx is None:
            self._count("mav_unhandled")  # a valid message the bridge has no use for: still a sign of life
        elif not rx(self, link, m, now):
            return  # ignored (counted by the handler): not a sign of life
        link.tel.last_rx = now
        self._count("mav_rx")

    # Each receive handler stores one message in the link's telemetry and returns True, or counts
    # why it ignored it and returns False.
    def _rx_heartbeat(self, link: UavLink, m: Any, now: float) -> bool:
        if m.get_srcComponent() != mavlink.MAV_COMP_ID_AUTOPILOT1 or m.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
            self._count("mav_unhandled")  # another component of that system (camera, GCS...)
            return False
        t = link.tel
        t.hb_rx = now
        t.hb_count += 1
        t.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        t.custom_mode = int(m.custom_mode)
        t.autopilot = autopilot_name(m.autopilot)
        if self.s.autopilot == "auto":
            link.autopilot = t.autopilot
        return True

    def _rx_local_position(self, link: UavLink, m: Any, now: float) -> bool:
        if not _finite(m.x, m.y, m.z, m.vx, m.vy, m.vz):
            self._count("mav_malformed")
            return False
        t = link.tel
        t.pos_ned = np.array([m.x, m.y, m.z])
        t.vel_ned = np.array([m.vx, m.vy, m.vz])
        t.pos_rx = now
        t.pos_boot_s = m.time_boot_ms / 1000.0
        if not t.clock_from_timesync:
            # no TIMESYNC answer (yet): the offset that makes the fastest delivery seen so far
            # take no time; ages measured with it are upper bounds minus that fastest latency
            off = t.pos_boot_s - now
            if t.clock_offset_s is None or off > t.clock_offset_s or off < t.clock_offset_s - 5.0:  # reboot: restart
                t.clock_offset_s = off
        return True

    def _rx_attitude(self, link: UavLink, m: Any, now: float) -> bool:
        if not _finite(m.roll, m.pitch, m.yaw, m.rollspeed, m.pitchspeed, m.yawspeed):
            self._count("mav_malformed")
            return False
        t = link.tel
        t.rpy_ned = np.array([m.roll, m.pitch, m.yaw])
        t.rates_frd = np.array([m.rollspeed, m.pitchspeed, m.yawspeed])
        t.att_rx = t.att_euler_rx = now
        return True

    def _rx_attitude_quaternion(self, link: UavLink, m: Any, now: float) -> bool:
        if now - link.tel.att_euler_rx < 0.1:
            return True  # ATTITUDE streams too (same estimate): skip the conversion, a sign of life
        try:
            rpy = frames.quat_to_euler([m.q1, m.q2, m.q3, m.q4])
        except ValueError:
            self._count("mav_malformed")
            return False
        if not _finite(m.rollspeed, m.pitchspeed, m.yawspeed):
            self._count("mav_malformed")
            return False
        t = link.tel
        t.rpy_ned = rpy
        t.rates_frd = np.array([m.rollspeed, m.pitchspeed, m.yawspeed])
        t.att_rx = now
        return True

    def _rx_command_ack(self, link: UavLink, m: Any, now: float) -> bool:
        # an ACK answers whoever sent the command: addressed to another system, or to another
        # component of ours (a ground station may share the system id), it is not ours
        if m.target_system not in (0, self.s.source_system) or m.target_component not in (0, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER):
            self._count("mav_ack_not_ours")
            return False
        link.acks.append((now, int(m.command), int(m.result)))
        del link.acks[:-16]
        return True

    def _rx_sys_status(self, link: UavLink, m: Any, now: float) -> bool:
        t = link.tel
        t.sensors = (int(m.onboard_control_sensors_present), int(m.onboard_control_sensors_enabled), int(m.onboard_control_sensors_health))
        t.ss_rx = now
        return True

    def _rx_extended_sys_state(self, link: UavLink, m: Any, now: float) -> bool:
        link.tel.landed_state = int(m.landed_state)
        return True

    def _rx_param_value(self, link: UavLink, m: Any, now: float) -> bool:
        name = m.param_id.decode(errors="replace") if isinstance(m.param_id, bytes) else str(m.param_id)
        name = name.rstrip("\x00")
        if not math.isfinite(m.param_value):
            self._count("mav_malformed")
            return False
        ap = link.tel.autopilot or link.autopilot
        link.tel.params[name] = param_value(ap, m.param_type, m.param_value)
        link.tel.param_rx[name] = now
        return True

    def _rx_timesync(self, link: UavLink, m: Any, now: float) -> bool:
        """TIMESYNC answer (tc1 = the vehicle's time, ns; ts1 = ours, echoed): round trip and
        clock offset (MAVLink timesync protocol; PX4 and ArduPilot both answer), the offset from
        the fastest of the last ``_TIMESYNC_WINDOW`` answers. A request from the vehicle
        (tc1 = 0) is answered."""
        t = link.tel
        if m.tc1 == 0:
            mav = self._mav(link)
            if mav is not None:
                mav.timesync_send(int(self.clock() * 1e9), m.ts1)
            return True
        sent = m.ts1 / 1e9
        rtt = now - sent
        if not 0.0 <= rtt < 10.0:
            self._count("timesync_stale")
            return True
        t.rtt_s = rtt
        offset = m.tc1 / 1e9 - (sent + now) / 2.0
        if t.timesync_samples and abs(offset - t.timesync_samples[-1][1]) > 5.0:  # the vehicle rebooted
            t.timesync_samples.clear()
        t.timesync_samples.append((rtt, offset))
        # Half the round trip is assumed each way, so an answer's offset is off by up to rtt/2:
        # the fastest recent answer is the best estimate (a slow, lopsided one under load would
        # otherwise date states into the future). The window follows clock drift.
        t.clock_offset_s = min(t.timesync_samples)[1]
        t.clock_from_timesync = True
        return True

    _RX: ClassVar[dict[str, Callable[[Bridge, UavLink, Any, float], bool]]] = {
        "SYS_STATUS": _rx_sys_status,
        "EXTENDED_SYS_STATE": _rx_extended_sys_state,
        "PARAM_VALUE": _rx_param_value,
        "TIMESYNC": _rx_timesync,
        "HEARTBEAT": _rx_heartbeat,
        "LOCAL_POSITION_NED": _rx_local_position,
        "ATTITUDE": _rx_attitude,
        "ATTITUDE_QUATERNION": _rx_attitude_quaternion,
        "COMMAND_ACK": _rx_command_ack,
    }

    def _update_health(self, link: UavLink, now: float) -> None:
        ok = (now - link.tel.last_rx) <= self.s.link_timeout_s
        if ok == link.healthy:
            return
        link.healthy = ok
        self.changed = True
        if ok:
            link.recovered_t = now
            if link.tel.hb_count and link.phase != CONNECTING:
                self._count("link_recovered")
                self.log(f"bridge: uav {link.uav}: link recovered")
                self._request_telemetry(link)  # the vehicle may have rebooted (rates reset)
        else:
            if math.isfinite(link.tel.last_rx):
                self._count("link_lost")
                link.was_lost = True
                self.log(f"bridge: uav {link.uav}: link lost (silent > {self.s.link_timeout_s:g} s), marked unhealthy")

    def _ack(self, link: UavLink, command: int, since: float) -> int | None:
        for t, c, r in reversed(link.acks):
            if c == command and t >= since:
                return r
        return None

    # ------------------------------------------------------------------ commands
    def _command(self, link: UavLink, command: int, *params: float) -> None:
        mav = self._mav(link)
        if mav is None:
            return
        p = list(params) + [0.0] * (7 - len(params))
        mav.command_long_send(link.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, command, 0, *p)

    def _request_telemetry(self, link: UavLink) -> None:
        """Ask the vehicle for LOCAL_POSITION_NED and ATTITUDE at ``telemetry_hz``
        (MAV_CMD_SET_MESSAGE_INTERVAL, param1 = message id, param2 = interval in us). PX4's onboard
        link streams both by default (30 and 100 Hz); ArduPilot sends on a port only what its
        SRn_* parameters or such a request ask for. The answer is not waited for."""
        if not self.s.request_telemetry:
            return
        interval_us = 1e6 / self.s.telemetry_hz
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            self._command(link, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)
        self._count("telemetry_requests")

    def _request_mode(self, link: UavLink, mode: int, now: float) -> None:
        self._command(link, mavlink.MAV_CMD_DO_SET_MODE, *mode_request_params(link.autopilot, mode))
        link.mode_req_t = now
        self._count("mode_requests")

    def _offboard_mode(self, link: UavLink) -> int:
        if link.autopilot == "ardupilot":
            need_pos = self.s.setpoint == "position" or (self.s.takeoff and not link.engaged_once)
            return AP_COPTER_MODES["GUIDED" if need_pos else "GUIDED_NOGPS"]
        return PX4_OFFBOARD

    def _land_mode(self, link: UavLink) -> int:
        return AP_COPTER_MODES["LAND"] if link.autopilot == "ardupilot" else PX4_LAND

    # ------------------------------------------------------------------ phases
    def advance(self, now: float) -> None:
        """Run every UAV's phase machine one step."""
        for link in self.links:
            self._advance(link, now)

    def _advance(self, link: UavLink, now: float) -> None:
        if not link.healthy:
            return  # keep the phase; setpoints keep streaming (the uplink may still work)
        step = self._PHASE_STEPS.get(link.phase)  # none for REFUSED, RELEASED, GROUNDED, LANDING, DONE
        if step is not None:
            step(self, link, now)

    def _step_connecting(self, link: UavLink, now: float) -> None:
        """CONNECTING -> STREAM at the vehicle's first heartbeat."""
        t = link.tel
        if not t.hb_count:
            return
        link.wanted_mode = self._offboard_mode(link)
        self._request_telemetry(link)
        link.param_req_t = -math.inf
        self._set_phase(link, PARAMS, now, "")
        self.log(
            f"bridge: uav {link.uav}: vehicle sysid {link.sysid} ({link.autopilot}) on {link.endpoint.url}, "
            f"mode {mode_name(link.autopilot, t.custom_mode)}, {'armed' if t.armed else 'disarmed'}"
        )

    def _step_params(self, link: UavLink, now: float) -> None:
        """PARAMS -> STREAM once the autopilot's parameters (:data:`AUTOPILOT_PARAMS`) are read
        and acceptable (:func:`zenswarm.vehicle.autopilot.vehicle_params`), and ArduCopter's GUID_OPTIONS
        is written if the thrust mapping needs it (PARAM_SET, confirmed by the PARAM_VALUE echo).
        REFUSED (the reason names the parameter) after ``params_timeout_s`` or on a bad value."""
        t = link.tel
        names = AUTOPILOT_PARAMS[link.autopilot]
        missing = [n for n in names if n not in t.params]
        if now - link.phase_t > self.s.params_timeout_s:
            what = (
                f"parameter(s) {', '.join(missing)} not received" if missing else "GUID_OPTIONS not confirmed after PARAM_SET"
            )
            self._count("params_timeouts")
            self._refuse(link, now, f"{what} within {self.s.params_timeout_s:g} s (PARAM_REQUEST_READ); not arming")
            return
        if missing:
            if now - link.param_req_t >= _PARAM_RETRY_S:
                link.param_req_t = now
                mav = self._mav(link)
                for n in missing:
                    if mav is not None:
                        mav.param_request_read_send(link.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, n.encode(), -1)
                    self._count("param_requests")
            return
        vp = vehicle_params(link.autopilot, {n: t.params[n] for n in names}, self.s.link_timeout_s, self.s.setpoint, self.s.hover_throttle)
        if vp.error:
            self._refuse(link, now, vp.error + "; not arming")
            return
        if vp.set_guid_options is not None:
            if int(t.params["GUID_OPTIONS"]) & GUID_OPTIONS_THRUST_AS_THRUST:  # the echo came
                vp = VehicleParams(vp.hover_throttle, vp.loss_timeout_s, None, "", vp.notes + " (set)")
            else:
                if now - link.guid_set_t >= _PARAM_RETRY_S:
                    link.guid_set_t = now
                    mav = self._mav(link)
                    if mav is not None:
                        mav.param_set_send(
                            link.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, b"GUID_OPTIONS", float(vp.set_guid_options or 0),
                            mavlink.MAV_PARAM_TYPE_INT32,
                        )
                    self._count("param_sets")
                return
        if math.isfinite(link.guid_set_t):
            vp = VehicleParams(vp.hover_throttle, vp.loss_timeout_s, None, "", vp.notes + " (bit 3 set by the bridge: thrust as thrust)")
        link.vparams = vp
        h = vp.hover_throttle
        link.tmap = frames.ThrustMap(self.max_thrust, self.hover_thrust, h) if h is not None else self.tmap
        hover_u = float(link.tmap.to_normalized(self.hover_thrust))
        self.log(f"bridge: uav {link.uav}: parameters {vp.notes}; hover throttle {hover_u:.3f}")
        self._set_phase(link, STREAM, now, "")

    def _step_stream(self, link: UavLink, now: float) -> None:
        """STREAM -> MODE after ``stream_s`` of setpoints (a position hold needs a position)."""
        if link.tel.pos_ned is None and self._needs_position(link):
            return  # a position hold needs the vehicle's position first
        if now - link.phase_t >= self.s.stream_s:
            self._to_mode(link, now)

    def _to_mode(self, link: UavLink, now: float, reason: str | None = None) -> None:
        link.mode_attempts = 0
        link.mismatch = 0
        link.mode_req_t = -math.inf
        self._set_phase(link, MODE, now, reason)

    def _step_mode(self, link: UavLink, now: float) -> None:
        """MODE -> ARM once a heartbeat after the request reports the mode; REFUSED if the vehicle
        accepts but keeps reporting another mode, or after ``_MODE_ATTEMPTS`` requests."""
        t = link.tel
        if _same_mode(link.autopilot, t.custom_mode, link.wanted_mode) and t.hb_rx > link.mode_req_t:
            link.arm_attempts = 0
            link.arm_req_t = -math.inf
            self._set_phase(link, ARM, now)
            return
        acc = self._ack(link, mavlink.MAV_CMD_DO_SET_MODE, link.mode_req_t)
        if acc == mavlink.MAV_RESULT_ACCEPTED and link.last_hb_seen != t.hb_count and t.hb_rx > self._ack_time(link):
            link.last_hb_seen = t.hb_count
            link.mismatch += 1  # accepted, but a later heartbeat reports another mode
            if link.mismatch >= _MISMATCH_HEARTBEATS:
                self._refuse(
                    link,
                    now,
                    f"vehicle reports mode {mode_name(link.autopilot, t.custom_mode)} after accepting "
                    f"{mode_name(link.autopilot, link.wanted_mode)}; not arming",
                )
                return
        if now - link.mode_req_t < _MODE_RETRY_S:
            return
        if acc is not None and acc != mavlink.MAV_RESULT_ACCEPTED:
            self._count("mode_rejected")
        if link.mode_attempts >= _MODE_ATTEMPTS:
            self._refuse(link, now, f"mode {mode_name(link.autopilot, link.wanted_mode)} not reached after {link.mode_attempts} requests")
            return
        link.mode_attempts += 1
        self._request_mode(link, link.wanted_mode, now)  # type: ignore[arg-type]
        link.last_hb_seen = t.hb_count

    def _step_arm(self, link: UavLink, now: float) -> None:
        """ARM -> TAKEOFF or READY once a heartbeat reports armed; never arms a vehicle in a mode
        the bridge did not ask for (back to MODE); REFUSED after ``_ARM_ATTEMPTS`` requests."""
        t = link.tel
        if not _same_mode(link.autopilot, t.custom_mode, link.wanted_mode):
            # never arm a vehicle that reports a mode we did not ask for
            self._count("arm_withheld")
            link.mode_req_t = -math.inf
            self._set_phase(link, MODE, now, f"vehicle reports {mode_name(link.autopilot, t.custom_mode)} before arming")
            return
        if t.armed and t.hb_rx > link.phase_t:
            self._armed(link, now)
            return
        if link.engaged_once and not t.armed and t.hb_rx > link.phase_t:
            self._set_phase(link, GROUNDED, now, "vehicle disarmed while re-engaging; not re-arming")
            return
        if now - link.arm_req_t >= _ARM_RETRY_S and not (link.engaged_once or t.armed):
            if not self._healthy_to_arm(link, now):
                return
            if link.arm_attempts >= _ARM_ATTEMPTS:
                self._refuse(link, now, f"vehicle did not arm after {link.arm_attempts} requests")
                return
            link.arm_attempts += 1
            self._command(link, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
            link.arm_req_t = now
            link.armed_by_us = True
            self._count("arm_requests")

    def _healthy_to_arm(self, link: UavLink, now: float) -> bool:
        """The vehicle's latest SYS_STATUS allows arming (:func:`health_problem`); otherwise
        REFUSED, saying why (no SYS_STATUS within ``_SYS_STATUS_WAIT_S``, unhealthy subsystems,
        pre-arm checks failing). The bridge never arms a vehicle that says it is not ready."""
        t = link.tel
        if t.sensors is None:
            if now - link.phase_t >= _SYS_STATUS_WAIT_S:
                self._count("arm_unhealthy")
                self._refuse(link, now, f"no SYS_STATUS within {_SYS_STATUS_WAIT_S:g} s: health unknown; not arming")
            return False
        why = health_problem(*t.sensors)
        if why:
            self._count("arm_unhealthy")
            self._refuse(link, now, f"vehicle not healthy: {why}; not arming")
            return False
        return True

    def _armed(self, link: UavLink, now: float) -> None:
        """The vehicle reports armed in the wanted mode: where the ARM phase goes next."""
        link.was_lost = False
        if link.engaged_once:
            self._set_phase(link, READY, now, "re-engaged")
        elif not link.armed_by_us:
            # already armed (and in our mode) when we met it, e.g. the bridge restarted in
            # flight: adopt it where it is, no takeoff; it is ours to land at the end
            link.engaged_once = True
            link.armed_by_us = True
            link.airborne_known = True
            self._set_phase(link, READY, now, "vehicle already armed; adopted in place")
        elif self.s.takeoff:
            link.takeoff_sent = False
            link.takeoff_attempts = 0
            link.takeoff_req_t = -math.inf
            link.climbed = False
            self._set_phase(link, TAKEOFF, now, "")
        else:
            link.engaged_once = True
            self._set_phase(link, READY, now, "")
            self._warn_grounded_position(link)

    def _warn_grounded_position(self, link: UavLink) -> None:
        """ArduCopter armed on the ground by the bridge with ``takeoff = false`` and position
        setpoints: GUIDED's position controller never lifts a landed vehicle off (ArduCopter
        ``mode_guided.cpp``: ``pos_control_run`` only does ground handling while
        ``is_disarmed_or_landed()``), so it stays on the ground and auto-disarms (``DISARM_DELAY``).
        Said once per bridge (counted per vehicle: ``grounded_position``), not refused: a vehicle
        lifted off by other means (a pilot, a script) flies the targets."""
        if link.autopilot != "ardupilot" or self.s.setpoint != "position" or self._airborne(link):
            return
        self._count("grounded_position")
        if self.warned_grounded:
            return
        self.warned_grounded = True
        self.log(
            f"bridge: WARNING: uav {link.uav} (and any other ArduCopter on the ground) will not take off: "
            "takeoff = false with setpoint = \"position\" sends GUIDED position targets to a landed vehicle, "
            "which ArduCopter's GUIDED position controller never lifts off (ground handling only while landed, "
            "mode_guided.cpp); it will auto-disarm after DISARM_DELAY. Set takeoff = true (the bridge then "
            "sends MAV_CMD_NAV_TAKEOFF first), or have the vehicles airborne before the bridge starts (it "
            "adopts an armed vehicle in place). See docs/mavlink.md, ArduCopter modes."
        )

    def _still_engaged(self, link: UavLink, now: float) -> bool:
        """READY/TAKEOFF: False (and the phase moved to MODE, GROUNDED or RELEASED) if the vehicle
        left the wanted mode or disarmed, or if no heartbeat came since the link recovered."""
        t = link.tel
        if t.hb_rx <= link.recovered_t:
            return False  # judge the mode only from a heartbeat sent after the link came back
        if not _same_mode(link.autopilot, t.custom_mode, link.wanted_mode):
            now_mode = mode_name(link.autopilot, t.custom_mode)
            if link.was_lost and t.armed and self.s.reengage:
                self._count("reengage")
                link.hold_ned = None
                self._to_mode(link, now, f"vehicle in {now_mode} after a link loss; re-engaging")
            elif link.was_lost and not t.armed:
                self._set_phase(link, GROUNDED, now, f"vehicle in {now_mode} and disarmed after a link loss; not re-arming")
            else:
                self._count("released")
                self._set_phase(link, RELEASED, now, f"vehicle switched to {now_mode} (pilot or failsafe); no longer commanded")
            return False
        link.was_lost = False
        if not t.armed:
            self._set_phase(link, GROUNDED, now, "vehicle disarmed")
            return False
        return True

    def _step_ready(self, link: UavLink, now: float) -> None:
        self._still_engaged(link, now)

    def _step_takeoff(self, link: UavLink, now: float) -> None:
        """TAKEOFF -> READY within ``takeoff_tolerance_m`` of the initial position and slower than
        0.2 m/s, or after ``takeoff_timeout_s`` (ArduPilot: after MAV_CMD_NAV_TAKEOFF)."""
        if not self._still_engaged(link, now):
            return
        t = link.tel
        if link.autopilot == "ardupilot" and not link.climbed:
            self._ardupilot_climb(link, now)
        elif t.pos_ned is not None:
            err = float(np.linalg.norm(t.pos_ned - self._takeoff_ned(link)))
            speed = float(np.linalg.norm(t.vel_ned)) if t.vel_ned is not None else 0.0
            if err <= self.s.takeoff_tolerance_m and speed <= 0.2:
                link.engaged_once = True
                link.airborne_known = True
                self._set_phase(link, READY, now, "")
                link.hold_ned = self._takeoff_ned(link)  # hold there until the agent commands
                link.hold_yaw_ned = self.yaw_ned
                return
        if now - link.phase_t > self.s.takeoff_timeout_s:
            link.engaged_once = True
            link.airborne_known = True
            link.climbed = True
            self._set_phase(
                link, READY, now,
                f"takeoff not within {self.s.takeoff_tolerance_m:g} m after {self.s.takeoff_timeout_s:g} s; flying anyway",
            )

    def _takeoff_alt(self, link: UavLink) -> float:
        """Takeoff altitude, m above the vehicle's local origin (ArduCopter: above home)."""
        return float(-self._takeoff_ned(link)[2])

    def _ardupilot_climb(self, link: UavLink, now: float) -> None:
        """ArduCopter's takeoff: MAV_CMD_NAV_TAKEOFF (param7 = altitude, m), repeated each
        second until acknowledged, and NO position target until the altitude is reached. A
        position target switches GUIDED's sub-mode from TakeOff to a position controller whose
        run function, while the vehicle is landed, only does ground handling (ArduCopter
        ``mode_guided.cpp``: ``ModeGuided::set_destination`` -> ``pos_control_start``;
        ``pos_control_run`` returns early while ``is_disarmed_or_landed()``): the vehicle
        would never lift off and would auto-disarm."""
        t = link.tel
        alt = self._takeoff_alt(link)
        if t.pos_ned is not None and -float(t.pos_ned[2]) >= alt - max(self.s.takeoff_tolerance_m, 0.1):
            link.climbed = True
            link.airborne_known = True
            self.log(f"bridge: uav {link.uav}: takeoff altitude {alt:.2f} m reached; flying to the initial position")
            return
        acked = self._ack(link, mavlink.MAV_CMD_NAV_TAKEOFF, link.takeoff_req_t) == mavlink.MAV_RESULT_ACCEPTED
        if not acked and now - link.takeoff_req_t >= _TAKEOFF_RETRY_S and link.takeoff_attempts < _ARM_ATTEMPTS:
            self._command(link, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, alt)
            link.takeoff_req_t = now
            link.takeoff_attempts += 1
            link.takeoff_sent = True
            self._count("takeoff_requests")

    # one step of each pending phase (and READY); the other phases do not move by themselves
    _PHASE_STEPS: ClassVar[dict[str, Callable[[Bridge, UavLink, float], None]]] = {
        CONNECTING: _step_connecting,
        PARAMS: _step_params,
        STREAM: _step_stream,
        MODE: _step_mode,
        ARM: _step_arm,
        TAKEOFF: _step_takeoff,
        READY: _step_ready,
    }

    def note_stall(self, gap_s: float) -> None:
        """The bridge's own loop stopped for ``gap_s`` seconds (overloaded host, suspended
        process). Its setpoint streams were interrupted, so a vehicle that left the offboard mode
        meanwhile did so because of us: treat it like a link loss (re-engage), not like a pilot
        taking over."""
        if gap_s < _STALL_S:
            return
        self._count("loop_stalls")
        self.log(f"bridge: loop stalled for {gap_s:.2f} s (setpoints interrupted)")
        for link in self.links:
            if link.phase in (READY, TAKEOFF):
                link.was_lost = True
                link.recovered_t = max(link.recovered_t, self.clock())

    def _ack_time(self, link: UavLink) -> float:
        for t, c, _result in reversed(link.acks):
            if c == mavlink.MAV_CMD_DO_SET_MODE and t >= link.mode_req_t:
                return t
        return math.inf

    def _refuse(self, link: UavLink, now: float, reason: str) -> None:
        self._count("refused")
        self._set_phase(link, REFUSED, now, reason)

    def _needs_position(self, link: UavLink) -> bool:
        return not (link.autopilot == "ardupilot" and link.wanted_mode == AP_COPTER_MODES["GUIDED_NOGPS"])

    def _takeoff_ned(self, link: UavLink) -> np.ndarray:
        return swarm_to_vehicle(link.takeoff_enu, link.origin)

    def _airborne(self, link: UavLink) -> bool:
        """The vehicle is flying: EXTENDED_SYS_STATE's landed state if the vehicle sends it
        (IN_AIR, TAKEOFF, LANDING), else whether it took off under the bridge or was adopted in
        flight. Hover throttle is only ever sent to an airborne vehicle."""
        ls = link.tel.landed_state
        if ls is not None and ls != 0:  # 0: MAV_LANDED_STATE_UNDEFINED
            return ls in _AIRBORNE_STATES
        return link.airborne_known

    @property
    def settled(self) -> bool:
        """Every UAV ready or given up on (the mission clock may start)."""
        return all(link.phase not in _PENDING for link in self.links)

    @property
    def ready(self) -> list[UavLink]:
        return [link for link in self.links if link.phase == READY]

    # ------------------------------------------------------------------ send
    def send(self, now: float) -> None:
        """Heartbeats (1 Hz per connection) and one setpoint per engaged UAV."""
        for ep in self.endpoints.values():
            if ep.conn is not None and now >= ep.next_heartbeat:
                ep.next_heartbeat = now + 1.0
                try:
                    ep.conn.mav.heartbeat_send(
                        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
                    )
                except Exception:  # noqa: BLE001
                    self._count("mav_send_errors")
        for link in self.links:
            try:
                self._timesync(link, now)
                self._send_setpoint(link, now)
            except Exception as e:  # noqa: BLE001
                self._count("mav_send_errors")
                if self.counters.get("mav_send_errors", 0) <= 3:
                    self.log(f"bridge: uav {link.uav}: send error {type(e).__name__}: {e}")

    def _timesync(self, link: UavLink, now: float) -> None:
        """A TIMESYNC request (tc1 = 0, ts1 = our clock, ns) once a second to each vehicle that
        talks: its answer gives the link's round trip (diag ``latency_ms`` = half of it) and the
        vehicle's clock offset (state ages from ``time_boot_ms``)."""
        mav = self._mav(link)
        if mav is None or not link.tel.hb_count or now - link.timesync_t < _TIMESYNC_S:
            return
        link.timesync_t = now
        mav.timesync_send(0, int(now * 1e9))

    def _hold(self, link: UavLink) -> None:
        t = link.tel
        if link.hold_ned is None and t.pos_ned is not None:
            link.hold_ned = t.pos_ned.copy()
            link.hold_yaw_ned = float(t.rpy_ned[2]) if t.rpy_ned is not None else self.yaw_ned

    def _send_setpoint(self, link: UavLink, now: float) -> None:
        mav = self._mav(link)
        if mav is None or link.phase in (CONNECTING, REFUSED, RELEASED, GROUNDED, LANDING, DONE):
            return
        if link.phase in (PARAMS,):
            return  # nothing to hold yet: the vehicle's parameters decide how
        ms = self._ms(now)
        if link.autopilot == "ardupilot" and self.s.takeoff and not link.engaged_once and not link.climbed:
            # ArduCopter needs no setpoint stream to enter GUIDED, and a position target before
            # the takeoff altitude is reached would cancel the takeoff (see _ardupilot_climb)
            return
        if link.phase == TAKEOFF:
            p = self._takeoff_ned(link)
            self._pos_target(mav, link, ms, p, np.zeros(3), self.yaw_ned)
            return
        if link.phase == READY:
            if self.s.setpoint == "attitude":
                cmd, age = self.get_cmd(link.uav)
                if cmd is not None and age <= self.s.cmd_timeout_s:
                    link.hold_ned = None
                    q = frames.attitude_to_quat_ned(cmd.rpy)
                    thr = (link.tmap or self.tmap).to_normalized(cmd.thrust)
                    mav.set_attitude_target_send(ms, link.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, ATT_MASK, q.tolist(), 0.0, 0.0, 0.0, thr)
                    self._count("setpoints_attitude")
                    return
            else:
                ref, age = self.get_ref(link.uav)
                if ref is not None and age <= self.s.cmd_timeout_s:
                    link.hold_ned = None
                    p = frames.enu_to_ned(np.asarray(ref.q) - link.origin)
                    v = frames.enu_to_ned(ref.v)
                    self._pos_target(mav, link, ms, p, v, self.yaw_ned)
                    self._count("setpoints_position")
                    return
            self._count("cmd_stale_ticks")
        # before the mission, or without a fresh command: hold where the vehicle is
        if not self._needs_position(link):
            # attitude-only vehicle: level at the current yaw; hover throttle only to a vehicle
            # that is flying (never to one on the ground, e.g. with takeoff = false), else 0
            q = frames.euler_to_quat([0.0, 0.0, link.tel.rpy_ned[2] if link.tel.rpy_ned is not None else self.yaw_ned])
            flying = link.phase == READY and self._airborne(link)
            thr = (link.tmap or self.tmap).to_normalized(self.hover_thrust) if flying else 0.0
            mav.set_attitude_target_send(ms, link.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, ATT_MASK, q.tolist(), 0.0, 0.0, 0.0, thr)
            return
        self._hold(link)
        if link.hold_ned is not None:
            self._pos_target(mav, link, ms, link.hold_ned, np.zeros(3), link.hold_yaw_ned)

    def _pos_target(self, mav: Any, link: UavLink, ms: int, p: np.ndarray, v: np.ndarray, yaw: float) -> None:
        mav.set_position_target_local_ned_send(
            ms, link.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, mavlink.MAV_FRAME_LOCAL_NED, POS_MASK,
            float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2]), 0.0, 0.0, 0.0, float(yaw), 0.0,
        )

    # ------------------------------------------------------------------ state out
    def state_enu(self, link: UavLink, now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """(q, v, rpy, w) of the UAV in the swarm frame (ENU/FLU), or None if the telemetry is
        missing or older than the link timeout."""
        t = link.tel
        if t.pos_ned is None or t.rpy_ned is None:
            return None
        lim = self.s.link_timeout_s
        if now - t.pos_rx > lim or now - t.att_rx > lim:
            return None
        q = vehicle_to_swarm(t.pos_ned, link.origin)
        v = frames.ned_to_enu(t.vel_ned)
        if t.pos_boot_s is not None and t.clock_offset_s is not None:
            link.state_age_s = now - (t.pos_boot_s - t.clock_offset_s)  # the sample's age, from the vehicle's own stamp
        rpy = frames.euler_ned_to_enu(t.rpy_ned)
        w = frames.frd_to_flu(t.rates_frd)
        return q, v, rpy, w

    def sample_time(self, link: UavLink) -> float | None:
        """When the vehicle measured its latest position and velocity, on the bridge's clock, s:
        ``LOCAL_POSITION_NED.time_boot_ms`` (the vehicle's own clock) minus the clock offset that
        TIMESYNC measured (half the round trip assumed each way). None until the vehicle has
        answered a TIMESYNC request: the fallback offset (the fastest delivery taken as
        instantaneous) serves the ``max_state_age_ms`` diagnostic but is not put on the wire."""
        t = link.tel
        if t.pos_boot_s is None or t.clock_offset_s is None or not t.clock_from_timesync:
            return None
        return t.pos_boot_s - t.clock_offset_s

    def info(self, now: float) -> dict[str, Any]:
        """The diag ``info`` map: ``uav`` (per-UAV details), plus flat scalars that survive into
        the supervisor's results.json (``phases`` = ``"1:ready,2:ready,..."``, ``armed_uavs`` =
        how many vehicles report armed, ``unhealthy_uavs``)."""
        return {
            "phases": ",".join(f"{link.uav}:{link.phase}" for link in self.links),
            "armed_uavs": sum(1 for link in self.links if link.tel.armed),
            "unhealthy_uavs": sum(1 for link in self.links if not link.healthy),
            "airborne_uavs": sum(1 for link in self.links if self._airborne(link)),
            "max_latency_ms": max((round(lk.tel.rtt_s * 500.0, 2) for lk in self.links if lk.tel.rtt_s is not None), default=-1.0),
            "max_state_age_ms": max(
                (round(lk.state_age_s * 1000.0, 2) for lk in self.links if lk.state_age_s is not None), default=-1.0
            ),
            "uav": {str(link.uav): link.info(now) for link in self.links},
            "unhealthy": [link.uav for link in self.links if not link.healthy],
            "ready": [link.uav for link in self.links if link.phase == READY],
        }

    # ------------------------------------------------------------------ landing
    def begin_landing(self, now: float, why: str) -> None:
        for link in self.links:
            if link.phase in (REFUSED, RELEASED, DONE, CONNECTING) or not link.armed_by_us:
                if link.phase != DONE and link.phase not in (REFUSED, RELEASED):
                    self._set_phase(link, DONE, now, f"{why}; never armed by the bridge")
                continue
            self._set_phase(link, LANDING, now, why)
            link.land_req_t = -math.inf

    def land_step(self, now: float) -> bool:
        """One step of landing; True when every landing UAV is disarmed (or given up).

        Asks for the land mode once a second until the vehicle reports it, then waits for the
        vehicle's own auto-disarm after touchdown. A normal (non-forced) disarm is sent only
        once the vehicle has been in the land mode and still (|v| < 0.1 m/s) for 2 s, so a
        vehicle that is still flying is never asked to stop its motors.
        """
        busy = False
        for link in self.links:
            if link.phase != LANDING:
                continue
            t = link.tel
            if not t.armed and t.hb_rx > link.phase_t:
                self._set_phase(link, DONE, now, "landed and disarmed")
                self._count("landed")
                continue
            busy = True
            in_land = _same_mode(link.autopilot, t.custom_mode, self._land_mode(link))
            still = in_land and t.vel_ned is not None and float(np.linalg.norm(t.vel_ned)) < 0.1
            if not still:
                link.still_since = math.inf
            elif not math.isfinite(link.still_since):
                link.still_since = now
            if now - link.land_req_t >= 1.0:
                link.land_req_t = now
                if not in_land:
                    self._request_mode(link, self._land_mode(link), now)
                elif now - link.still_since >= 2.0:
                    self._command(link, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
                    self._count("disarm_requests")
        return not busy

    def give_up_landing(self, now: float) -> None:
        """Landing timed out: report it. The vehicles are left in their land mode (they land and
        disarm by themselves); the bridge never force-disarms a vehicle that may be flying."""
        for link in self.links:
            if link.phase == LANDING:
                self._set_phase(
                    link, DONE, now,
                    f"still armed after {self.s.land_timeout_s:g} s of landing; left in "
                    f"{mode_name(link.autopilot, link.tel.custom_mode)}",
                )
                self._count("land_timeouts")

    def close(self) -> None:
        for ep in self.endpoints.values():
            ep.close()


# --------------------------------------------------------------------------- process


def _make_bridge(proc: Any, settings: MavlinkSettings) -> Bridge:
    """Subscribe to the agents' commands (or references) through the link-fault delay line and
    build the :class:`Bridge` that reads them."""
    sc = proc.scenario
    n = sc.n
    keys = proc.keys
    cmd_keys = [keys.cmd(i + 1) for i in range(n)]
    ref_keys = [keys.ref(i + 1) for i in range(n)]
    inbox = proc.inbox

    def latest(key: str) -> tuple[Any, float]:
        m = inbox.latest.get(key)
        if m is None:
            return None, math.inf
        return m, time.monotonic() - inbox.latest_rx.get(key, -math.inf)

    # Link faults (--link-delay/--link-jitter/--link-loss/--partition, or the scenario's [faults]):
    # the bridge takes the plant's place, so agent i's link to it is the plant's `agent:i -> plant`
    # cmd link (also when it forwards uav/<i>/ref as position setpoints), decided on receipt and
    # released after its delay, exactly as in the realtime plant.
    from zenswarm.link import FaultState

    in_keys = cmd_keys if settings.setpoint == "attitude" else ref_keys
    plan = proc.options.fault_plan(sc)
    if plan is not None:
        proc.use_delay_line(FaultState(plan), {key: (f"agent:{i + 1}", "plant", "cmd") for i, key in enumerate(in_keys)})
    for key in in_keys:
        proc.subscribe(key, "cmd" if settings.setpoint == "attitude" else "ref")
    return Bridge(
        settings,
        sc,
        proc.counters,
        get_cmd=lambda i: latest(cmd_keys[i - 1]),
        get_ref=lambda i: latest(ref_keys[i - 1]),
        log=proc.log,
    )


class _BridgeLoop:
    """The bridge process's loop: pre-mission phases, the mission clock, setpoint pacing, diag,
    then landing. ``code`` is the process's exit code (3: no UAV ready, or a process missing)."""

    def __init__(self, proc: Any, bridge: Bridge, settings: MavlinkSettings) -> None:
        from zenswarm.bus import wire
        from zenswarm.process.runtime import WallClock

        sc = proc.scenario
        self.proc = proc
        self.bridge = bridge
        self.settings = settings
        self.n = sc.n
        self.dt = sc.timing.dt
        self.dt_ns = wire.t_ns(self.dt)
        self.n_ticks = sc.timing.n_ticks
        sub = max(1, math.ceil(settings.rate_hz / sc.timing.control_rate_hz - 1e-9))
        self.period = self.dt / sub  # s between loop iterations (setpoints)
        # the loop's pacing: more than a period behind, start again from now (no burst of
        # back-to-back setpoints); the deadline is moved to "now + period" where the loop restarts
        self.clock = WallClock(self.period, first_wait=True, resync_after_s=self.period)
        self.stats = self.clock.stats
        self.code = 0
        self.k_tick = 0  # control tick of the mission clock last published
        self.t0 = math.inf  # time.monotonic() of mission time 0
        self.seq = 0
        self.started = False
        self.finished = False
        self.start_deadline = time.monotonic() + settings.start_timeout_s
        self.next_diag = 0.0
        self.waited_alive = getattr(proc.args, "no_wait_alive", False)
        self.last = time.monotonic()  # when the last iteration ran (stall detection)

    def fly(self) -> None:
        """Until the mission ends, the process is asked to stop, or the start fails."""
        proc, bridge = self.proc, self.bridge
        self.last = time.monotonic()
        self.clock.next = self.last + self.period
        while not proc.stop.is_set():
            now = time.monotonic()
            bridge.note_stall(now - self.last)
            self.last = now
            proc.release_delayed()
            bridge.poll(now)
            bridge.advance(now)
            if not self.started and (bridge.settled or now >= self.start_deadline):
                started_at = self._start(now)
                if started_at is None:
                    break
                now = started_at
            if self._publish_tick(now):
                break
            bridge.send(now)
            self._diag(now, {"started": self.started}, with_stats=True)
            self._pace()

    def _start(self, now: float) -> float | None:
        """Start the mission clock (after waiting for the other processes' liveliness); the start
        time, or None (``code`` = 3) if no UAV is ready or a process never announced itself."""
        proc, bridge = self.proc, self.bridge
        if not bridge.ready:
            proc.log("bridge: no UAV is ready: " + "; ".join(f"uav {lk.uav}: {lk.phase} {lk.reason}" for lk in bridge.links))
            self.code = 3
            return None
        if not self.waited_alive:
            others = ["leader"] + [f"agent:{i + 1}" for i in range(self.n)] + list(getattr(proc.args, "expect", None) or [])
            missing = proc.wait_for_alive(others, timeout_s=60.0)
            self.waited_alive = True
            if missing and not proc.stop.is_set():
                proc.log(f"bridge: these processes never announced themselves: {', '.join(missing)}")
                self.code = 3
                return None
            now = self.last = time.monotonic()
            self.clock.next = now + self.period
        self.started = True
        self.t0 = now
        self.k_tick = -1
        proc.log(f"bridge: mission clock started with UAV(s) {[lk.uav for lk in bridge.ready]}")
        return now

    def _publish_tick(self, now: float) -> bool:
        """Publish the clock and the ready UAVs' states if a control tick is due; True at the
        mission's last tick (``finished``)."""
        from zenswarm.bus import wire

        if not self.started:
            return False
        proc = self.proc
        # Mission time is wall time since the start: the tick due now is published (once), and
        # ticks the loop missed (an overloaded host) are skipped, never caught up in a burst.
        # Every stream derived from the clock (the leader's and agents' refs, the commands)
        # then advances with the wall clock, as the receivers' input guards expect.
        # The tick is taken from the clock right before publishing: a message sent late for its
        # tick would look, to the receivers, like the stream slowing down and then jumping.
        k_due = min(self.n_ticks, int((time.monotonic() - self.t0) / self.dt + 1e-9))
        if k_due <= self.k_tick:
            return False
        if k_due > self.k_tick + 1:
            proc.counters["ticks_skipped"] += k_due - self.k_tick - 1
        self.k_tick = k_due
        t = self.k_tick * self.dt_ns
        self.seq += 1
        seq = self.seq
        proc.publish(proc.keys.clock, wire.Clock(t=t, seq=seq))
        for link in self.bridge.ready:
            st = self.bridge.state_enu(link, now)
            if st is not None:
                q, v, rpy, w = st
                proc.publish(
                    proc.keys.state(link.uav), wire.State(t=t, seq=seq, q=q, v=v, rpy=rpy, w=w, stamp=self.stamp_ns(link))
                )
                proc.counters["states_published"] += 1
        proc.inbox.forget_before(self.k_tick - 2)
        if self.k_tick >= self.n_ticks:
            self.finished = True
        return self.finished

    def stamp_ns(self, link: UavLink) -> int | None:
        """The state's ``stamp`` (wire ``ts``): :meth:`Bridge.sample_time` on the mission clock
        (ns since mission time 0, negative for a sample measured before the start; clipped to
        +-``wire.MAX_T_NS``), or None (left out) without a TIMESYNC clock offset."""
        from zenswarm.bus import wire

        ts = self.bridge.sample_time(link)
        if ts is None or not math.isfinite(self.t0):
            return None
        return max(-wire.MAX_T_NS, min(wire.MAX_T_NS, round((ts - self.t0) * 1e9)))

    def _diag(self, now: float, extra: dict[str, Any], with_stats: bool = False) -> None:
        """``diag/bridge`` once a second, and at once after a phase or health change."""
        bridge = self.bridge
        if now >= self.next_diag or bridge.changed:
            self.next_diag = now + 1.0
            bridge.changed = False
            stats = self.stats.as_dict() if with_stats else {}
            self.proc.publish_diag(max(self.k_tick, 0) * self.dt_ns, {**bridge.info(now), **stats, **extra})

    def _pace(self) -> None:
        """Sleep until the next iteration is due (:class:`zenswarm.process.runtime.WallClock`); more than
        a period behind: start again from now, counted in ``loop_resync``."""
        resyncs = self.clock.resyncs
        self.clock.wait()
        self.proc.counters["loop_resync"] += self.clock.resyncs - resyncs

    def land(self) -> None:
        """Land and disarm whatever the bridge armed: end of mission, SIGTERM/SIGINT, or an error."""
        proc, bridge = self.proc, self.bridge
        why = "mission finished" if self.finished else ("stop requested" if proc.stop.is_set() else "bridge stopping")
        bridge.begin_landing(time.monotonic(), why)
        deadline = time.monotonic() + self.settings.land_timeout_s
        while time.monotonic() < deadline:
            now = time.monotonic()
            # a stall here (the host loaded by the other processes ending with the mission) is
            # the bridge's own, as in fly(): not judged as the vehicles' silence
            bridge.note_stall(now - self.last)
            self.last = now
            bridge.poll(now)
            bridge.send(now)
            if bridge.land_step(now):
                break
            self._diag(now, {"landing": True})
            time.sleep(0.02)
        else:
            bridge.give_up_landing(time.monotonic())
        now = time.monotonic()
        proc.publish_diag(max(self.k_tick, 0) * self.dt_ns, {**bridge.info(now), **self.stats.as_dict(), "finished": self.finished})
        proc.log("bridge: done: " + "; ".join(f"uav {lk.uav}: {lk.phase} {lk.reason}" for lk in bridge.links))


def _run(proc: Any) -> int:
    settings = mavlink_settings(proc.scenario, proc.args.overrides())
    bridge = _make_bridge(proc, settings)
    proc.announce()
    n = proc.scenario.n
    loop = _BridgeLoop(proc, bridge, settings)
    proc.log(
        f"bridge: {n} UAV(s), setpoint={settings.setpoint}, {1 / loop.period:g} Hz setpoints, "
        + ", ".join(f"uav {i + 1}: sysid {settings.sysids[i]} @ {settings.connections[i]}" for i in range(n))
    )
    try:
        loop.fly()
        loop.land()
    finally:
        bridge.close()
    return loop.code


def _cli_overrides(args: argparse.Namespace) -> dict[str, Any]:
    def pairs(items: list[str] | None, flag: str, conv: Callable[[str], Any]) -> dict[int, Any]:
        out: dict[int, Any] = {}
        for s in items or []:
            i, sep, val = s.partition("=")
            if not sep or not i.strip().isdigit() or not val:
                raise ScenarioError(flag, f"expected I=VALUE (I = UAV number), got {s!r}")
            try:
                out[int(i)] = conv(val)
            except ValueError:
                raise ScenarioError(flag, f"bad value in {s!r}") from None
        return out

    return {
        "conn": pairs(getattr(args, "conn", None), "--conn", str),
        "sysid": pairs(getattr(args, "sysid", None), "--sysid", int),
        "origin": pairs(getattr(args, "origin", None), "--origin", lambda v: tuple(float(c) for c in v.split(","))),
        "base_port": getattr(args, "base_port", None),
        "host": getattr(args, "mav_host", None),
        "setpoint": getattr(args, "setpoint", None),
        "rate_hz": getattr(args, "rate", None),
        "autopilot": getattr(args, "autopilot", None),
        "hover_throttle": getattr(args, "hover_throttle", None),
        "takeoff": False if getattr(args, "no_takeoff", False) else None,
        "link_timeout_s": getattr(args, "link_timeout", None),
        "land_timeout_s": getattr(args, "land_timeout", None),
        "stream_s": getattr(args, "stream_s", None),
        "start_timeout_s": getattr(args, "start_timeout", None),
    }


def bridge_settings(args: argparse.Namespace) -> MavlinkBridgeSettings:
    """``zenswarm bridge mavlink``'s flags as :class:`MavlinkBridgeSettings`: the scenario file
    parsed (none given: fetched from the leader's mission), realtime; a bad file or flag is a
    ScenarioError naming it."""
    from zenswarm.bridge.args import process_settings
    from zenswarm.scenario.config import load_scenario

    path = args.scenario_path if getattr(args, "scenario_path", None) is not None else args.scenario
    sc = None if path is None else load_scenario(path)
    return MavlinkBridgeSettings(process=process_settings(args, "bridge", sc, realtime=True), no_wait_alive=bool(args.no_wait_alive),
                                 **_cli_overrides(args))  # fmt: skip


def run(s: MavlinkBridgeSettings) -> int:
    """Run the bridge with these settings (its command's flags, or ``zenswarm up``'s on its
    standard input). Bad ``[mavlink]`` settings or overrides (ids, timeouts): exit 2 naming the
    field before any work (no Zenoh session, no MAVLink link opened); the process checks again
    with the scenario it runs (fetched from the leader if none is given)."""
    from zenswarm.errors import ZenswarmError
    from zenswarm.process.runtime import run_process

    if s.process.scenario is not None:
        try:
            mavlink_settings(s.process.scenario, s.overrides())
        except ZenswarmError as e:
            print(f"bridge: error: {e}", file=sys.stderr, flush=True)
            return 2
    return run_process(_run, "bridge", s)


def _main_args(args: argparse.Namespace) -> int:
    from zenswarm.errors import ZenswarmError

    try:
        s = bridge_settings(args)
    except ZenswarmError as e:
        print(f"bridge: error: {e}", file=sys.stderr, flush=True)
        return 2
    return run(s)


def _configure(p: argparse.ArgumentParser) -> None:
    from zenswarm.bridge.args import add_process_args

    p.add_argument(
        "scenario_path", nargs="?", type=Path, metavar="SCENARIO", help="scenario TOML (its [mavlink] table configures the links)"
    )
    add_process_args(p)
    g = p.add_argument_group("MAVLink")
    g.add_argument(
        "--conn", action="append", metavar="I=URL",
        help="pymavlink connection string of UAV I, e.g. 1=udpout:127.0.0.1:14540, 2=udpin:0.0.0.0:14541, "
        "3=tcp:127.0.0.1:5762, 4=/dev/ttyUSB0,921600 (repeatable; overrides mavlink.connections)",
    )
    g.add_argument("--sysid", action="append", metavar="I=ID", help="MAVLink system id of UAV I's vehicle (repeatable)")
    g.add_argument(
        "--origin", action="append", metavar="I=X,Y,Z",
        help="where UAV I's local NED origin is in the swarm's ENU frame, m (repeatable; overrides mavlink.origins)",
    )
    g.add_argument("--base-port", type=int, help="default connections udpout:HOST:P+i-1 (overrides mavlink.base_port)")
    g.add_argument("--mav-host", help="host of the default connections (overrides mavlink.host)")
    g.add_argument(
        "--setpoint",
        choices=("attitude", "position"),
        help="SET_ATTITUDE_TARGET from uav/<i>/cmd, or SET_POSITION_TARGET_LOCAL_NED from uav/<i>/ref",
    )
    g.add_argument("--rate", type=float, metavar="HZ", help="minimum setpoint rate, >= 20 Hz")
    g.add_argument("--autopilot", choices=("auto", "px4", "ardupilot"), help="mode numbering (default: from the vehicle's heartbeat)")
    g.add_argument("--hover-throttle", type=float, metavar="U", help="normalised throttle at hover (PX4 MPC_THR_HOVER)")
    g.add_argument("--no-takeoff", action="store_true", help="do not fly to the initial positions before the mission")
    g.add_argument("--link-timeout", type=float, metavar="S", help="silence after which a vehicle is unhealthy (default 1 s)")
    g.add_argument("--land-timeout", type=float, metavar="S", help="wait at most S for the vehicles to land and disarm")
    g.add_argument("--stream-s", type=float, metavar="S", help="setpoints streamed before asking for the offboard mode")
    g.add_argument("--start-timeout", type=float, metavar="S", help="start the mission after S even if some UAV is not ready")
    g.add_argument("--no-wait-alive", action="store_true", help="start the mission clock without waiting for the leader and agents")
    g.add_argument(
        "--expect", action="append", metavar="PROCESS",
        help="also wait for this process (e.g. recorder) to announce itself before starting the mission clock",
    )
    p.set_defaults(func=_main_args)


def add_mavlink_parser(bridge_sub: argparse._SubParsersAction) -> None:
    """Add the ``mavlink`` subcommand to an existing ``bridge`` subcommand's subparsers (for a
    ``bridge`` command that also has other subcommands, e.g. record/replay)."""
    m = bridge_sub.add_parser(
        "mavlink",
        help="fly the swarm's agents on MAVLink vehicles (PX4, ArduPilot, or `mavlink-vehicle`)",
        description=(__doc__ or "").split("\n\n")[0],
    )
    _configure(m)


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``bridge`` with its ``mavlink`` subcommand (``zenswarm bridge mavlink ...``)."""
    p = sub.add_parser(
        "bridge",
        help="connect the swarm bus to the outside (MAVLink vehicles)",
        description="Bridges between the swarm bus and the outside world.",
    )
    bsub = p.add_subparsers(dest="bridge_cmd", metavar="{mavlink}", required=True)
    add_mavlink_parser(bsub)


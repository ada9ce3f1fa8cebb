"""One simulated MAVLink vehicle's link (:class:`MavlinkLink`): its UDP endpoint and what crosses
it, encoded and decoded, for the autopilot (:mod:`zenswarm.plant.mavlink.autopilot`) that owns
it. No flight logic: the autopilot hands over its state (armed, mode, home, ...) and gets typed
setpoints back.

* the endpoint: ``udpin:HOST:PORT`` (it answers whoever talks to it), or with ``sitl_ports`` PX4
  SITL's direction, bound to ``PORT + SITL_SEND_OFFSET`` and sending to ``PORT``; a port that
  cannot be bound is a :class:`zenswarm.errors.ScenarioError` naming it (exit 2);
* routing (https://mavlink.io/en/guide/routing.html): bad and unknown messages, and those for
  another system or another component than the autopilot, are counted and dropped; the vehicle
  streams only once a peer has spoken (always with ``sitl_ports``); :attr:`MavlinkLink.muted_until`
  drops all traffic both ways (a test hook: a lost link);
* in: SET_ATTITUDE_TARGET and SET_POSITION_TARGET_LOCAL_NED decoded and checked
  (:func:`decode_attitude_target`, :func:`decode_position_target`), the parameter protocol
  (:class:`zenswarm.plant.mavlink.params.ParamStore`), TIMESYNC;
* out: COMMAND_ACK, STATUSTEXT, LOCAL_POSITION_NED, ATTITUDE (PX4: and ATTITUDE_QUATERNION),
  GLOBAL_POSITION_INT at a fifth of their rate, HEARTBEAT, SYS_STATUS, EXTENDED_SYS_STATE,
  HOME_POSITION, AUTOPILOT_VERSION, each as the flavour (PX4 or ArduCopter) sends it.

Frames: the wire is MAVLink's, local NED (m, m/s) about the vehicle's origin, body FRD; the
autopilot's state is in the swarm's ENU frame (m), attitude ZYX rad. Global positions are a
flat-earth GPS about :data:`REF_LLA` (:func:`lla`), the swarm's ENU origin at its altitude.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.plant.mavlink.params import ParamStore
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import SITL_SEND_OFFSET, load_mavutil

if TYPE_CHECKING:
    from zenswarm.plant.mavlink.options import VehicleOptions

mavutil = load_mavutil()
mavlink = mavutil.mavlink

__all__ = ["MavlinkLink", "AttitudeTarget", "PositionTarget", "decode_attitude_target", "decode_position_target", "lla", "REF_LLA"]

# PX4 SITL's global position of the default world (Zurich), used as every vehicle's GPS
# reference: lat, lon in degrees, AMSL altitude in m.
REF_LLA = (47.397742, 8.545594, 488.0)
_EARTH_R = 6371000.0


def lla(q_enu: np.ndarray) -> tuple[int, int, float]:
    """(lat 1e-7 deg, lon 1e-7 deg, alt AMSL m) of swarm ENU ``q_enu`` (m) about REF_LLA."""
    lat = REF_LLA[0] + math.degrees(float(q_enu[1]) / _EARTH_R)
    lon = REF_LLA[1] + math.degrees(float(q_enu[0]) / (_EARTH_R * math.cos(math.radians(REF_LLA[0]))))
    return int(round(lat * 1e7)), int(round(lon * 1e7)), REF_LLA[2] + float(q_enu[2])


@dataclass(frozen=True)
class AttitudeTarget:
    """A SET_ATTITUDE_TARGET, decoded: ``q_ned`` the normalised attitude quaternion (NED, FRD),
    None when the attitude is ignored; ``rates_frd`` the body rates (rad/s, FRD; an ignored axis
    0) when the attitude is ignored and rates are given, else None; ``thrust`` in [0, 1], None
    when ignored."""

    q_ned: np.ndarray | None
    rates_frd: np.ndarray | None
    thrust: float | None


@dataclass(frozen=True)
class PositionTarget:
    """A SET_POSITION_TARGET_LOCAL_NED, decoded: position (m) and velocity (m/s), local NED about
    the vehicle's origin, and yaw (rad, NED); each None when its type-mask bits say ignored."""

    pos_ned: np.ndarray | None
    vel_ned: np.ndarray | None
    yaw_ned: float | None


def decode_attitude_target(m: Any) -> AttitudeTarget | None:
    """SET_ATTITUDE_TARGET ``m`` as an :class:`AttitudeTarget`; None if malformed (a non-finite
    quaternion, thrust or used rate, or a quaternion that cannot be normalised)."""
    mask = int(m.type_mask)
    vals = list(m.q) + [m.thrust]
    if not all(math.isfinite(x) for x in vals):
        return None
    attitude_ignored = bool(mask & mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE)
    q_ned = None
    if not attitude_ignored:
        try:
            q_ned = frames.quat_normalize(list(m.q))
        except ValueError:
            return None
    rates_frd = None
    if attitude_ignored and (mask & 0b111) != 0b111:
        # attitude ignored, body rates given: a rate setpoint (PX4 mavlink_receiver.cpp
        # handle_message_set_attitude_target -> vehicle_rates_setpoint; ArduCopter
        # GCS_Mavlink.cpp -> ModeGuided::set_angle with ang_vel); an ignored axis is 0 rad/s
        rates = [0.0 if mask & (1 << i) else float(x) for i, x in enumerate((m.body_roll_rate, m.body_pitch_rate, m.body_yaw_rate))]
        if not all(math.isfinite(x) for x in rates):
            return None
        rates_frd = np.array(rates)
    thrust = None if mask & mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE else min(max(float(m.thrust), 0.0), 1.0)
    return AttitudeTarget(q_ned, rates_frd, thrust)


def decode_position_target(m: Any) -> PositionTarget | str:
    """SET_POSITION_TARGET_LOCAL_NED ``m`` as a :class:`PositionTarget`, or why not (the counter
    to count): ``unsupported_frame`` (not MAV_FRAME_LOCAL_NED), ``malformed`` (a used field not
    finite)."""
    if m.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
        return "unsupported_frame"
    vals = [m.x, m.y, m.z, m.vx, m.vy, m.vz, m.yaw]
    mask = int(m.type_mask)
    pos_use = (mask & 0b111) != 0b111
    vel_use = (mask & 0b111000) != 0b111000
    yaw_use = not mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
    used = (vals[0:3] if pos_use else []) + (vals[3:6] if vel_use else []) + ([vals[6]] if yaw_use else [])
    if not all(math.isfinite(x) for x in used):
        return "malformed"
    return PositionTarget(
        np.array(vals[0:3]) if pos_use else None, np.array(vals[3:6]) if vel_use else None, float(vals[6]) if yaw_use else None
    )


class MavlinkLink:
    """The UDP MAVLink endpoint of vehicle ``index`` (0-based), system id ``sysid``, port ``port``
    (``opts``: host, ``sitl_ports``, the autopilot flavour), booted at ``boot`` (s, monotonic:
    the messages' time since boot). What it drops and serves is counted in ``counters`` (the
    vehicle's)."""

    def __init__(self, index: int, sysid: int, port: int, opts: VehicleOptions, boot: float, counters: dict[str, int]) -> None:
        self.sysid = sysid
        self.autopilot = opts.autopilot
        self.boot = boot
        self.counters = counters
        if opts.sitl_ports:
            # PX4 SITL (ROMFS px4-rc.mavlink: mavlink start -u 14580+i -o 14540+i): the vehicle
            # binds its own port and streams to the ground station's from boot on
            self.conn = mavutil.mavlink_connection(
                f"udpout:{opts.host}:{port}", source_system=sysid, source_component=mavlink.MAV_COMP_ID_AUTOPILOT1
            )
            try:
                self.conn.port.bind((opts.host, port + SITL_SEND_OFFSET))
            except (OSError, OverflowError) as e:  # OverflowError: not a port number
                self.conn.close()
                why = getattr(e, "strerror", None) or e
                raise ScenarioError(
                    "--base-port",
                    f"UDP port {opts.host}:{port + SITL_SEND_OFFSET} (vehicle {index + 1}'s send port, base port + "
                    f"{SITL_SEND_OFFSET} + {index}, PX4 SITL's direction) cannot be bound: {why}",
                ) from None
        else:
            try:
                self.conn = mavutil.mavlink_connection(
                    f"udpin:{opts.host}:{port}", source_system=sysid, source_component=mavlink.MAV_COMP_ID_AUTOPILOT1, udp_timeout=5
                )
            except (OSError, OverflowError) as e:  # OverflowError: not a port number
                why = getattr(e, "strerror", None) or e
                raise ScenarioError(
                    "--base-port",
                    f"UDP port {opts.host}:{port} (vehicle {index + 1}'s port, base port + {index}) cannot be bound: {why}",
                ) from None
        self.muted_until = -math.inf
        self.peer_seen = bool(opts.sitl_ports)
        self.acks: list[tuple[int, int]] = []  # (command, result) sent, latest last (bounded)
        self.telemetry_sent = 0

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def muted(self, now: float) -> bool:
        return now < self.muted_until

    def _ms(self, now: float) -> int:
        return int((now - self.boot) * 1000.0) & 0xFFFFFFFF

    def _streaming(self, now: float) -> bool:
        return not self.muted(now) and self.peer_seen

    # ------------------------------------------------------------------ in
    def receive(self, now: float, cap: int = 1000) -> Iterator[Any]:
        """Drain the socket (at most ``cap`` datagrams' messages): every message addressed to this
        vehicle's autopilot, one at a time (the caller acts on each before the next is read)."""
        for _ in range(cap):
            try:
                m = self.conn.recv_msg()
            except Exception:  # noqa: BLE001 - e.g. a malformed datagram; never stop the vehicle
                self._count("recv_errors")
                continue
            if m is None:
                return
            if self.muted(now):
                self._count("dropped_muted")
                continue
            if self._addressed(m):
                yield m

    def _addressed(self, m: Any) -> bool:
        mtype = m.get_type()
        if mtype == "BAD_DATA":
            self._count("bad")
            return False
        if mtype.startswith("UNKNOWN_"):
            self._count("unknown")
            return False
        self.peer_seen = True
        target = getattr(m, "target_system", 0)
        if target not in (0, self.sysid):
            self._count("other_target")
            return False
        # addressed to another component of this system (a camera, a gimbal, ...): not the
        # autopilot's (MAVLink routing, https://mavlink.io/en/guide/routing.html)
        if getattr(m, "target_component", 0) not in (0, mavlink.MAV_COMP_ID_AUTOPILOT1):
            self._count("other_component")
            return False
        return True

    def timesync(self, m: Any, now: float) -> None:
        """MAVLink timesync protocol (https://mavlink.io/en/services/timesync.html): a request
        (tc1 = 0) is answered with tc1 = this vehicle's time since boot, ns, and the request's ts1
        echoed; both autopilots do (PX4 src/modules/mavlink/mavlink_timesync.cpp via
        lib/timesync/Timesync.cpp, ArduPilot GCS_MAVLINK::handle_timesync). An answer is ignored."""
        self._count("timesync_requests")
        if m.tc1 != 0 or self.muted(now):
            return
        self.conn.mav.timesync_send(int((now - self.boot) * 1e9), int(m.ts1))

    def serve_params(self, m: Any, store: ParamStore) -> None:
        """The parameter protocol (see :mod:`zenswarm.plant.mavlink.params`) on ``store``."""
        mtype = m.get_type()
        i: int | None
        if mtype == "PARAM_REQUEST_LIST":
            self._count("param_lists")
            for i in range(len(store)):
                self._send_param(store, i)
            return
        if mtype == "PARAM_REQUEST_READ":
            self._count("param_reads")
            i = store.lookup(m.param_id, int(m.param_index))
        else:
            self._count("param_sets")
            i = store.handle_set(m.param_id, float(m.param_value))
        if i is None:
            self._count("param_unknown")  # both autopilots stay silent
            return
        self._send_param(store, i)

    def _send_param(self, store: ParamStore, i: int) -> None:
        if not self.muted(time.monotonic()):
            self.conn.mav.param_value_send(*store.value_msg(i))

    # ------------------------------------------------------------------ out
    def ack(self, m: Any, result: int) -> None:
        """COMMAND_ACK of COMMAND_LONG ``m`` with MAV_RESULT ``result`` (remembered in ``acks``)."""
        self.acks.append((int(m.command), int(result)))
        del self.acks[:-32]
        if not self.muted(time.monotonic()):
            self.conn.mav.command_ack_send(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent())

    def statustext(self, text: str) -> None:
        """STATUSTEXT at severity CRITICAL (at most 50 bytes)."""
        self.conn.mav.statustext_send(mavlink.MAV_SEVERITY_CRITICAL, text.encode()[:50])

    def telemetry(self, now: float, p_ned: np.ndarray, v_ned: np.ndarray, rpy_ned: np.ndarray, w_frd: np.ndarray,
                  origin: np.ndarray, home_enu: np.ndarray) -> None:  # fmt: skip
        """LOCAL_POSITION_NED (``p_ned`` m, ``v_ned`` m/s about the vehicle's ``origin``, m ENU),
        ATTITUDE (``rpy_ned`` rad, ``w_frd`` rad/s; PX4: and ATTITUDE_QUATERNION), and every fifth
        time GLOBAL_POSITION_INT (altitude relative to ``home_enu``, m ENU)."""
        if not self._streaming(now):
            return
        ms = self._ms(now)
        mav = self.conn.mav
        mav.local_position_ned_send(ms, *map(float, p_ned), *map(float, v_ned))
        mav.attitude_send(ms, *map(float, rpy_ned), *map(float, w_frd))
        if self.autopilot == "px4":
            # PX4 streams ATTITUDE_QUATERNION beside ATTITUDE (mavlink_main.cpp stream lists);
            # ArduPilot only on request
            qn = frames.attitude_to_quat_ned(frames.euler_ned_to_enu(rpy_ned))
            mav.attitude_quaternion_send(ms, *map(float, qn), *map(float, w_frd))
        self.telemetry_sent += 1
        if self.telemetry_sent % 5 == 1:
            # GLOBAL_POSITION_INT at a fifth of the rate: simulated GPS about REF_LLA (flat earth)
            q = frames.ned_to_enu(p_ned) + origin
            v = frames.ned_to_enu(v_ned)
            lat, lon, alt = lla(q)
            rel = q[2] - home_enu[2]
            hdg = int(round(math.degrees(float(rpy_ned[2])) % 360.0 * 100.0)) % 36000
            mav.global_position_int_send(
                ms, lat, lon, int(alt * 1000), int(rel * 1000), int(v[1] * 100), int(v[0] * 100), int(-v[2] * 100), hdg
            )

    def status_extra(self, now: float, landed_state: int, home_enu: np.ndarray, origin: np.ndarray) -> None:
        """EXTENDED_SYS_STATE (``landed_state``, a MAV_LANDED_STATE) and HOME_POSITION (both
        autopilots stream them at low rate)."""
        if not self._streaming(now):
            return
        self.conn.mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, landed_state)
        self.home(home_enu, origin)

    def requested(self, now: float, pending: list[str], home_enu: np.ndarray, origin: np.ndarray) -> None:
        """The messages requested with MAV_CMD_REQUEST_MESSAGE: ``home`` (HOME_POSITION),
        ``version`` (AUTOPILOT_VERSION with the flavour's capabilities)."""
        if self.muted(now):
            return
        for what in pending:
            if what == "home":
                self.home(home_enu, origin)
            elif what == "version":
                caps = (
                    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                )
                if self.autopilot == "px4":
                    caps |= mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                else:
                    caps |= mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
                self.conn.mav.autopilot_version_send(caps, 0, 0, 0, 0, bytes(8), bytes(8), bytes(8), 0, 0, self.sysid, bytes(18))

    def home(self, home_enu: np.ndarray, origin: np.ndarray) -> None:
        """HOME_POSITION of ``home_enu`` (m ENU): GPS, and local NED about ``origin``."""
        lat, lon, alt = lla(home_enu)
        x, y, z = (float(c) for c in frames.enu_to_ned(home_enu - origin))
        self.conn.mav.home_position_send(lat, lon, int(alt * 1000), x, y, z, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)

    def heartbeat(self, now: float, armed: bool, offboard: bool, custom_mode: int) -> None:
        """HEARTBEAT: a quadrotor of this flavour, CUSTOM_MODE_ENABLED (| SAFETY_ARMED; offboard:
        | GUIDED_ENABLED | STABILIZE_ENABLED), ``custom_mode``, ACTIVE when armed else STANDBY."""
        if not self._streaming(now):
            return
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if offboard:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        ap = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA if self.autopilot == "ardupilot" else mavlink.MAV_AUTOPILOT_PX4
        status = mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, ap, base, custom_mode, status)

    def sys_status(self, now: float, prearm_failing: bool) -> None:
        """SYS_STATUS: every sensor present, enabled and healthy, but with ``prearm_failing`` the
        PREARM_CHECK and 3D_MAG bits unhealthy."""
        if not self._streaming(now):
            return
        sensors = (
            mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
            | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
            | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
            | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
        )
        sensors |= mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_PREARM_CHECK
        # health: all sensors healthy; the PREARM_CHECK bit is healthy when the vehicle would arm
        # (PX4 mavlink_messages SYS_STATUS from health_report; ArduCopter GCS_MAVLink
        # update_sensor_status_flags: MAV_SYS_STATUS_PREARM_CHECK set when pre_arm_checks pass)
        health = sensors
        if prearm_failing:
            health &= ~(mavlink.MAV_SYS_STATUS_PREARM_CHECK | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG)
        # load 0.1 %, battery 4.2 V (1S), current and remaining unknown (-1)
        self.conn.mav.sys_status_send(sensors, sensors, health, 100, 4200, -1, -1, 0, 0, 0, 0, 0, 0)

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:  # noqa: BLE001
            pass

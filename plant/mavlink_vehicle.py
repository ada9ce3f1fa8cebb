"""Simulated quadrotors exposed as MAVLink vehicles over UDP: the subset of a PX4 multicopter
that the MAVLink bridge (:mod:`zenswarm.bridge.mavlink`) uses, so the whole chain agents -> bridge ->
MAVLink/UDP -> vehicles runs on one machine and in CI.

Each UAV i of the scenario is a vehicle with its own system id (default i) listening on its own
UDP port (``udpin:HOST:BASE_PORT + i - 1``; it answers whoever talks to it), or with
``sitl_ports`` sending as PX4 SITL does from ``BASE_PORT + 40 + i - 1`` to ``BASE_PORT + i - 1``
(a ground station listens with ``udpin``). Physics is :func:`zenswarm.plant.quadrotor.step` (eqs 1-5 with
the onboard attitude PID) for all UAVs at once, ``timing.physics_rate_hz`` sub-steps (1 kHz) in
chunks of ``timing.substeps`` (10) at ``timing.control_rate_hz`` (100 Hz) on the wall clock, plus
the scenario's disturbances and a flat ground at ``ground_z`` (vehicles spawn on it below their
scenario initial position).

Spoken (PX4 flavour by default; ``autopilot = "ardupilot"`` switches to ArduCopter's mode numbers,
heartbeat and behaviours; each behaviour cites its autopilot source next to its code):

* HEARTBEAT 1 Hz: MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4 / ARDUPILOTMEGA, base_mode =
  CUSTOM_MODE_ENABLED (| SAFETY_ARMED), custom_mode = PX4 ``main << 16 | sub << 24`` or the
  ArduCopter mode number; SYS_STATUS 1 Hz with the sensor, GPS and MAV_SYS_STATUS_PREARM_CHECK
  health bits; EXTENDED_SYS_STATE (landed state) and HOME_POSITION 1 Hz;
* LOCAL_POSITION_NED and ATTITUDE (PX4: and ATTITUDE_QUATERNION) at ``telemetry_hz`` (50 Hz),
  GLOBAL_POSITION_INT at a fifth of it (a simulated GPS about PX4 SITL's default home);
  local NED about the swarm origin, or with ``own_origin`` about where each vehicle booted;
* the parameter protocol with each autopilot's parameters (:mod:`zenswarm.plant.mavlink_params`),
  which the vehicle follows (COM_OF_LOSS_T, MIS_TAKEOFF_ALT, MPC_TKO_SPEED, MPC_LAND_SPEED,
  COM_DISARM_LAND, RTL_RETURN_ALT; GUID_OPTIONS, GUID_TIMEOUT, WPNAV_SPEED_UP/DN, LAND_SPEED,
  DISARM_DELAY, RTL_ALT);
* COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE (and SET_MODE),
  MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_LAND, MAV_CMD_NAV_RETURN_TO_LAUNCH, MAV_CMD_REQUEST_MESSAGE
  (HOME_POSITION, AUTOPILOT_VERSION), each answered with COMMAND_ACK; other commands get
  MAV_RESULT_UNSUPPORTED; messages for another system or another component are ignored;
* SET_ATTITUDE_TARGET (quaternion, or body rates when the attitude is ignored; PX4: normalised
  thrust through :class:`zenswarm.vehicle.frames.ThrustMap`; ArduCopter: a climb rate unless GUID_OPTIONS
  bit 3) and SET_POSITION_TARGET_LOCAL_NED (position/velocity/yaw in MAV_FRAME_LOCAL_NED; the
  vehicle then runs its own PD position loop producing thrust and attitude).

PX4 modes: OFFBOARD (main 6) follows the setpoints; it is refused (MAV_RESULT_TEMPORARILY_REJECTED)
unless a setpoint arrived in the last COM_OF_LOSS_T; HOLD (AUTO.LOITER, POSCTL, ALTCTL) holds the
position where it was entered; AUTO.TAKEOFF climbs to MIS_TAKEOFF_ALT (or param7 AMSL) then
holds; AUTO.RTL climbs to RTL_RETURN_ALT, returns over home and lands; AUTO.LAND descends at
MPC_LAND_SPEED and disarms COM_DISARM_LAND after touchdown. Offboard-loss failsafe: no setpoint
for COM_OF_LOSS_T -> HOLD; still none ``failsafe_land_s`` later -> LAND. Arming in OFFBOARD needs
fresh setpoints; disarming needs the vehicle on the ground unless forced (param2 = 21196).

ArduCopter modes: GUIDED / GUIDED_NOGPS stay in the mode without setpoints; their sub-modes
(TakeOff, Pos, PosVelAccel, VelAccel, Angle) follow ArduCopter ``mode_guided.cpp``: landed,
only MAV_CMD_NAV_TAKEOFF or a positive climb rate lifts off (position targets do not), and
velocity/angle targets older than GUID_TIMEOUT are dropped (stop, or level and hold altitude);
LOITER, BRAKE, POSHOLD, ALT_HOLD, STABILIZE hold; LAND descends at LAND_SPEED and disarms on
touchdown; RTL climbs to RTL_ALT, returns and lands; landed for DISARM_DELAY -> disarm.

Test hooks (also what a faulty vehicle looks like): :meth:`MavlinkFleet.silence` drops all
traffic of one vehicle both ways for a while (physics goes on); ``mode_override`` makes a vehicle
accept mode requests but keep reporting (and flying) another mode;
:meth:`MavlinkFleet.set_prearm_failure` makes it fail its pre-arm checks.

Not simulated: PX4's RTL_DESCEND_ALT loiter and COM_DISARM_PRFLT, ArduCopter's RTL_LOIT_TIME,
the auto_armed / throttle-zero subtleties of ArduCopter's auto-disarm,
MAV_CMD_SET_MESSAGE_INTERVAL (answered UNSUPPORTED), missions, geofence, RC.

``zenswarm mavlink-vehicle SCENARIO --base-port P`` (or ``zenswarm plant --mavlink --scenario
SCENARIO --base-port P``) runs the fleet until
SIGTERM/SIGINT. Importing this module sets ``MAVLINK20=1`` (see bridge.mavlink).
"""

from __future__ import annotations

import math
import signal
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.fleet import FleetThread
from zenswarm.plant.mavlink_params import ParamStore, ardupilot_params, px4_params
from zenswarm.plant.quadrotor import PlantState, initial_state, step
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import (
    AP_COPTER_MODES,
    PX4_AUTO_SUB,
    PX4_HOLD,
    PX4_LAND,
    PX4_MAIN,
    PX4_OFFBOARD,
    SITL_SEND_OFFSET,
    load_mavutil,
    mavlink_settings,
    mode_name,
    px4_custom_mode,
    px4_decode,
)
from zenswarm.vehicle.params import QuadParams

mavutil = load_mavutil()
mavlink = mavutil.mavlink

__all__ = ["VehicleOptions", "SimVehicle", "MavlinkFleet", "run_fleet"]

_FORCE_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that forces (dis)arming

# mode kinds
OFFBOARD, HOLD, LAND, TAKEOFF, RTL = "offboard", "hold", "land", "takeoff", "rtl"

# ArduCopter GUIDED sub-modes (ArduCopter/mode.h ModeGuided::SubMode)
SUB_TAKEOFF, SUB_POS, SUB_POSVEL, SUB_VEL, SUB_ANGLE = "TakeOff", "Pos", "PosVelAccel", "VelAccel", "Angle"

_GUID_THRUST_AS_THRUST = 8  # GUID_OPTIONS bit 3 (ArduCopter mode.h ModeGuided::Option::SetAttitudeTarget_ThrustAsThrust)

# PX4 SITL's global position of the default world (Zurich), used as every vehicle's GPS
# reference: lat, lon in degrees, AMSL altitude in m.
REF_LLA = (47.397742, 8.545594, 488.0)
_EARTH_R = 6371000.0


@dataclass(frozen=True)
class VehicleOptions:
    """Behaviour of the simulated vehicles (units inline).

    autopilot: "px4" or "ardupilot" (mode numbering, heartbeat autopilot field).
    telemetry_hz: LOCAL_POSITION_NED + ATTITUDE rate, Hz (sent on loop ticks: at most the loop
        rate, a whole divisor of it).
    heartbeat_hz, sys_status_hz: Hz.
    offboard_loss_s: a setpoint must be this recent to enter OFFBOARD or arm in it; no setpoint
        for this long in OFFBOARD -> HOLD (PX4 COM_OF_LOSS_T), s.
    failsafe_land_s: after that HOLD, still no setpoint for this long -> LAND, s.
    land_speed: descent rate in LAND, m/s, the initial MPC_LAND_SPEED / LAND_SPEED (None: the
        autopilot's default, 0.7 / 0.5 m/s). disarm_after_land_s: on the ground in LAND this long
        -> disarm, s (None: PX4 COM_DISARM_LAND 2 s; ArduCopter 1 s, its land detector's time).
    ground_z: ground height, m ENU. pos_kp (1/s^2), pos_kd (1/s): the vehicle's own position PD.
    max_pos_err: position error clipped to this norm in the PD, m (limits the approach speed).
    hover_throttle: the vehicle's throttle at hover, or None (thrust = throttle * max_thrust).
    host: address the UDP sockets bind to.
    own_origin: each vehicle's local NED origin is where it booted (its estimator origin, as on a
        real autopilot); False: every vehicle reports NED about the swarm's ENU origin (legacy).
    sitl_ports: PX4 SITL's UDP direction: vehicle i (0-based) sends from ``base_port + 40 + i``
        to ``base_port + i`` (PX4 SITL: from 14580+i to 14540+i) from boot on, and a ground
        station listens with ``udpin``; False: the vehicle listens on ``base_port + i``.
    """

    autopilot: str = "px4"
    telemetry_hz: float = 50.0
    heartbeat_hz: float = 1.0
    sys_status_hz: float = 1.0
    offboard_loss_s: float = 1.0  # PX4 COM_OF_LOSS_T default
    failsafe_land_s: float = 5.0
    land_speed: float | None = None
    disarm_after_land_s: float | None = None
    ground_z: float = 0.0
    pos_kp: tuple[float, float, float] = (4.0, 4.0, 6.0)
    pos_kd: tuple[float, float, float] = (3.5, 3.5, 4.5)
    max_pos_err: float = 1.0
    hover_throttle: float | None = None
    host: str = "127.0.0.1"
    own_origin: bool = False
    sitl_ports: bool = False

    def __post_init__(self) -> None:
        if self.autopilot not in ("px4", "ardupilot"):
            raise ValueError(f"VehicleOptions.autopilot must be 'px4' or 'ardupilot', got {self.autopilot!r}")
        for name in ("telemetry_hz", "heartbeat_hz", "sys_status_hz", "offboard_loss_s", "land_speed", "disarm_after_land_s"):
            x = getattr(self, name)
            if x is None and name in ("land_speed", "disarm_after_land_s"):
                continue
            if not (math.isfinite(x) and x > 0):
                raise ValueError(f"VehicleOptions.{name} must be > 0, got {x!r}")

    @property
    def modes(self) -> dict[str, int]:
        """The custom_mode values of this flavour: offboard, hold, land, boot."""
        if self.autopilot == "ardupilot":
            return {
                "offboard": AP_COPTER_MODES["GUIDED"],
                "hold": AP_COPTER_MODES["LOITER"],
                "land": AP_COPTER_MODES["LAND"],
                "boot": AP_COPTER_MODES["STABILIZE"],
            }
        return {"offboard": PX4_OFFBOARD, "hold": PX4_HOLD, "land": PX4_LAND, "boot": PX4_HOLD}

    def mode_kind(self, custom_mode: int) -> str | None:
        """OFFBOARD, HOLD, LAND, or None if this simulation does not fly that mode."""
        if self.autopilot == "ardupilot":
            return {
                AP_COPTER_MODES["GUIDED"]: OFFBOARD,
                AP_COPTER_MODES["GUIDED_NOGPS"]: OFFBOARD,
                AP_COPTER_MODES["LOITER"]: HOLD,
                AP_COPTER_MODES["BRAKE"]: HOLD,
                AP_COPTER_MODES["POSHOLD"]: HOLD,
                AP_COPTER_MODES["ALT_HOLD"]: HOLD,
                AP_COPTER_MODES["STABILIZE"]: HOLD,
                AP_COPTER_MODES["LAND"]: LAND,
                AP_COPTER_MODES["RTL"]: RTL,
            }.get(int(custom_mode))
        main, sub = px4_decode(custom_mode)
        if main == PX4_MAIN["OFFBOARD"] and sub == 0:
            return OFFBOARD
        if main in (PX4_MAIN["POSCTL"], PX4_MAIN["ALTCTL"]) and sub == 0:
            return HOLD
        if main == PX4_MAIN["AUTO"]:
            return {
                PX4_AUTO_SUB["LOITER"]: HOLD,
                PX4_AUTO_SUB["LAND"]: LAND,
                PX4_AUTO_SUB["TAKEOFF"]: TAKEOFF,
                PX4_AUTO_SUB["RTL"]: RTL,
            }.get(sub)
        return None




class SimVehicle:
    """One simulated vehicle: its MAVLink endpoint and its autopilot's logic (not its physics,
    which :class:`MavlinkFleet` integrates for all vehicles at once). Row ``index`` of the fleet."""

    def __init__(self, index: int, sysid: int, port: int, opts: VehicleOptions, params: QuadParams, boot: float, spawn: Any = None) -> None:
        self.index = index
        self.sysid = sysid
        self.port = port
        self.opts = opts
        self.params = params
        self.boot = boot
        self.tmap = frames.ThrustMap(params.max_thrust, params.hover_thrust, opts.hover_throttle)
        hover_u = float(self.tmap.to_normalized(params.hover_thrust))
        if opts.autopilot == "ardupilot":
            specs = ardupilot_params(sysid, hover_u, opts.land_speed)
        else:
            specs = px4_params(sysid, hover_u, opts.offboard_loss_s, opts.land_speed)
        self.ap_params = ParamStore(specs, bytewise=opts.autopilot == "px4")
        # the estimator origin (swarm ENU, m): where the vehicle booted, or the swarm's origin
        self.spawn = np.zeros(3) if spawn is None else np.array(spawn, dtype=float)
        self.origin = self.spawn.copy() if opts.own_origin else np.zeros(3)
        self.home_enu = self.spawn.copy()  # home: set again on arming (both autopilots)
        if opts.sitl_ports:
            # PX4 SITL (ROMFS px4-rc.mavlink: mavlink start -u 14580+i -o 14540+i): the vehicle
            # binds its own port and streams to the ground station's from boot on
            self.conn = mavutil.mavlink_connection(
                f"udpout:{opts.host}:{port}", source_system=sysid, source_component=mavlink.MAV_COMP_ID_AUTOPILOT1
            )
            try:
                self.conn.port.bind((opts.host, port + SITL_SEND_OFFSET))
            except OSError as e:
                self.conn.close()
                raise ScenarioError(
                    "--base-port",
                    f"UDP port {opts.host}:{port + SITL_SEND_OFFSET} (vehicle {index + 1}'s send port, base port + "
                    f"{SITL_SEND_OFFSET} + {index}, PX4 SITL's direction) cannot be bound: {e.strerror or e}",
                ) from None
        else:
            try:
                self.conn = mavutil.mavlink_connection(
                    f"udpin:{opts.host}:{port}", source_system=sysid, source_component=mavlink.MAV_COMP_ID_AUTOPILOT1, udp_timeout=5
                )
            except OSError as e:
                raise ScenarioError(
                    "--base-port",
                    f"UDP port {opts.host}:{port} (vehicle {index + 1}'s port, base port + {index}) cannot be bound: {e.strerror or e}",
                ) from None
        self.armed = False
        self.guided_sub: str | None = None  # ArduCopter GUIDED sub-mode
        self.land_complete = True  # ArduCopter ap.land_complete (the land detector's verdict)
        self.landed_since = boot
        self.takeoff_z = math.nan  # takeoff target, m ENU
        self.takeoff_t0 = -math.inf  # when the last ArduCopter takeoff was accepted, s
        self._pending: list[str] = []  # messages requested (MAV_CMD_REQUEST_MESSAGE), sent next tick
        self.rtl_phase = ""
        self.climb_rate = 0.0  # ArduCopter angle control: climb rate from SET_ATTITUDE_TARGET.thrust, m/s
        self.rates_frd: np.ndarray | None = None  # body-rate setpoint (attitude ignored), rad/s FRD
        self.att_int: np.ndarray | None = None  # attitude integrated from the body rates, rpy ENU
        self.prearm_failure: str | None = None
        self.period = 0.01  # the fleet's loop period, s (set by the fleet)
        self.custom_mode = opts.modes["boot"]
        self.mode_override: int | None = None
        self.muted_until = -math.inf
        self.last_sp = -math.inf
        self.sp_kind: str | None = None
        self.att_q = np.array([1.0, 0.0, 0.0, 0.0])
        self.att_thrust = 0.0
        self.pos_ned: np.ndarray | None = None
        self.vel_ned = np.zeros(3)
        self.pos_use = False
        self.vel_use = False
        self.yaw_ned: float | None = None
        self.hold_enu: np.ndarray | None = None
        self.hold_yaw = 0.0
        self.failsafe = False
        self.on_ground = True
        self.ground_since = -math.inf
        self.peer_seen = bool(opts.sitl_ports)
        self.counters: dict[str, int] = {}
        self.acks: list[tuple[int, int]] = []  # (command, result) sent, latest last (bounded)
        self.telemetry_sent = 0

    # ------------------------------------------------------------------ helpers
    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def kind(self) -> str | None:
        return self.opts.mode_kind(self.custom_mode)

    @property
    def mode(self) -> str:
        """Readable current mode, e.g. ``OFFBOARD``."""
        return mode_name(self.opts.autopilot, self.custom_mode)

    def muted(self, now: float) -> bool:
        return now < self.muted_until

    def _ms(self, now: float) -> int:
        return int((now - self.boot) * 1000.0) & 0xFFFFFFFF

    def _setpoint_fresh(self, now: float) -> bool:
        return now - self.last_sp <= self.loss_s

    # ------------------------------------------------------------------ parameters the vehicle follows
    @property
    def loss_s(self) -> float:
        """Offboard-loss time, s: PX4 COM_OF_LOSS_T (ArduCopter: the option, see GUID_TIMEOUT)."""
        if self.opts.autopilot == "px4":
            return self.ap_params["COM_OF_LOSS_T"]
        return self.opts.offboard_loss_s

    @property
    def land_speed(self) -> float:
        """Descent rate in LAND, m/s (PX4 MPC_LAND_SPEED, ArduCopter LAND_SPEED in cm/s)."""
        if self.opts.autopilot == "px4":
            return self.ap_params["MPC_LAND_SPEED"]
        return self.ap_params["LAND_SPEED"] / 100.0

    @property
    def disarm_after_land_s(self) -> float:
        """Time on the ground in LAND before the auto-disarm, s."""
        if self.opts.disarm_after_land_s is not None:
            return self.opts.disarm_after_land_s
        if self.opts.autopilot == "px4":
            return max(self.ap_params["COM_DISARM_LAND"], 0.0)  # PX4 commander: auto-disarm on land
        return 1.0  # ArduCopter mode_land.cpp: disarms once the land detector (about 1 s) says landed

    def _enter(self, custom_mode: int, q: np.ndarray, yaw: float) -> None:
        """Switch mode; HOLD and LAND remember where they were entered."""
        self.custom_mode = int(custom_mode)
        k = self.kind()
        if k in (HOLD, LAND):
            self.hold_enu = q.copy()
            self.hold_yaw = float(yaw)
        self.failsafe = False  # the failsafe path sets it again after entering HOLD

    # ------------------------------------------------------------------ receive
    def poll(self, now: float, q: np.ndarray, yaw: float, cap: int = 1000) -> None:
        """Drain the socket (bounded) and act on every message. q: (3,) m ENU; yaw: rad ENU."""
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
            self._handle(m, now, q, yaw)

    def _ack(self, m: Any, result: int) -> None:
        self.acks.append((int(m.command), int(result)))
        del self.acks[:-32]
        if not self.muted(time.monotonic()):
            self.conn.mav.command_ack_send(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent())

    def _handle(self, m: Any, now: float, q: np.ndarray, yaw: float) -> None:
        mtype = m.get_type()
        if mtype == "BAD_DATA":
            self._count("bad")
            return
        if mtype.startswith("UNKNOWN_"):
            self._count("unknown")
            return
        self.peer_seen = True
        target = getattr(m, "target_system", 0)
        if target not in (0, self.sysid):
            self._count("other_target")
            return
        # addressed to another component of this system (a camera, a gimbal, ...): not the
        # autopilot's (MAVLink routing, https://mavlink.io/en/guide/routing.html)
        if getattr(m, "target_component", 0) not in (0, mavlink.MAV_COMP_ID_AUTOPILOT1):
            self._count("other_component")
            return
        if mtype == "COMMAND_LONG":
            self._command(m, now, q, yaw)
        elif mtype == "SET_ATTITUDE_TARGET":
            self._attitude_target(m, now)
        elif mtype == "SET_POSITION_TARGET_LOCAL_NED":
            self._position_target(m, now)
        elif mtype == "SET_MODE":
            if m.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                self._set_mode(int(m.custom_mode), now, q, yaw)
        elif mtype == "HEARTBEAT":
            self._count("peer_heartbeats")
        elif mtype in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET"):
            self._param(m)
        elif mtype == "TIMESYNC":
            self._timesync(m, now)
        else:
            self._count("ignored")

    def _timesync(self, m: Any, now: float) -> None:
        """MAVLink timesync protocol (https://mavlink.io/en/services/timesync.html): a request
        (tc1 = 0) is answered with tc1 = this vehicle's time since boot, ns, and the request's ts1
        echoed; both autopilots do (PX4 src/modules/mavlink/mavlink_timesync.cpp via
        lib/timesync/Timesync.cpp, ArduPilot GCS_MAVLINK::handle_timesync). An answer is ignored."""
        self._count("timesync_requests")
        if m.tc1 != 0 or self.muted(now):
            return
        self.conn.mav.timesync_send(int((now - self.boot) * 1e9), int(m.ts1))

    def _param(self, m: Any) -> None:
        """The parameter protocol (see :mod:`zenswarm.plant.mavlink_params`)."""
        store = self.ap_params
        mtype = m.get_type()
        i: int | None
        if mtype == "PARAM_REQUEST_LIST":
            self._count("param_lists")
            for i in range(len(store)):
                self._send_param(i)
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
        self._send_param(i)

    def _send_param(self, i: int) -> None:
        if not self.muted(time.monotonic()):
            self.conn.mav.param_value_send(*self.ap_params.value_msg(i))

    def _command(self, m: Any, now: float, q: np.ndarray, yaw: float) -> None:
        p = (m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7)
        if m.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            self._count("arm_requests" if p[0] == 1 else "disarm_requests")
            self._ack(m, self._arm(p[0] == 1, int(p[1]) == _FORCE_MAGIC if math.isfinite(p[1]) else False, now, q, yaw))
        elif m.command == mavlink.MAV_CMD_DO_SET_MODE:
            self._count("mode_requests")
            self._ack(m, self._cmd_set_mode(p, now, q, yaw))
        elif m.command == mavlink.MAV_CMD_NAV_TAKEOFF:
            self._count("takeoff_requests")
            if self.opts.autopilot == "ardupilot":
                self._ack(m, self._ap_takeoff(p[6], now, q))
            else:
                self._ack(m, self._px4_takeoff(p[6], now, q, yaw))
        elif m.command == mavlink.MAV_CMD_NAV_LAND:
            # PX4 commander: NAV_LAND -> AUTO.LAND; ArduCopter GCS_Mavlink.cpp: set_mode(LAND)
            # (MAV_RESULT_FAILED if refused)
            self._ack(m, self._set_mode(self.opts.modes["land"], now, q, yaw))
        elif m.command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            # PX4: -> AUTO.RTL; ArduCopter: set_mode(RTL)
            rtl = AP_COPTER_MODES["RTL"] if self.opts.autopilot == "ardupilot" else px4_custom_mode(4, PX4_AUTO_SUB["RTL"])
            self._ack(m, self._set_mode(rtl, now, q, yaw))
        elif m.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            self._ack(m, self._request_message(p[0]))
        else:
            self._count("unsupported_commands")
            self._ack(m, mavlink.MAV_RESULT_UNSUPPORTED)

    def _cmd_set_mode(self, p: tuple[float, ...], now: float, q: np.ndarray, yaw: float) -> int:
        """MAV_CMD_DO_SET_MODE (params: base mode with CUSTOM_MODE_ENABLED, custom (main) mode,
        PX4 sub mode); the MAV_RESULT."""
        if not (math.isfinite(p[0]) and int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) or not all(math.isfinite(x) for x in p[1:3]):
            return mavlink.MAV_RESULT_UNSUPPORTED
        if self.opts.autopilot == "ardupilot":
            cm = int(p[1])
        else:
            cm = px4_custom_mode(int(p[1]), int(p[2]))
        return self._set_mode(cm, now, q, yaw)

    def _ap_takeoff(self, alt: float, now: float, q: np.ndarray) -> int:
        """ArduCopter MAV_CMD_NAV_TAKEOFF, param7 = altitude above home, m (GCS_Mavlink.cpp;
        takeoff.cpp Mode::do_user_takeoff: refused (MAV_RESULT_FAILED) unless armed, landed
        (land_complete), in a mode with a user takeoff (GUIDED) and the altitude above the current
        one). Starts GUIDED's TakeOff sub-mode (mode_guided.cpp do_user_takeoff_start), which
        climbs at WPNAV_SPEED_UP; any position/velocity/attitude target sent later switches the
        sub-mode and ends the takeoff."""
        in_guided = self.custom_mode == AP_COPTER_MODES["GUIDED"]
        if not (self.armed and self.land_complete and in_guided and math.isfinite(alt)):
            return mavlink.MAV_RESULT_FAILED
        if alt <= q[2] - self.home_enu[2]:
            return mavlink.MAV_RESULT_FAILED  # "can't takeoff downwards"
        self.takeoff_z = float(self.home_enu[2] + alt)
        self.guided_sub = SUB_TAKEOFF
        self.hold_enu = np.array([q[0], q[1], self.takeoff_z])
        # still landed: takeoff.cpp keeps land_complete until the motors have spooled up
        # (MOT_SPOOL_TIME), so a target sent meanwhile finds a landed vehicle (see _ap_guided)
        self.takeoff_t0 = now
        self.last_sp = now
        return mavlink.MAV_RESULT_ACCEPTED

    def _px4_takeoff(self, alt_amsl: float, now: float, q: np.ndarray, yaw: float) -> int:
        """PX4 MAV_CMD_NAV_TAKEOFF: switch to AUTO.TAKEOFF (commander), which climbs at
        MPC_TKO_SPEED to param7 (altitude AMSL, m) or, if NaN, to MIS_TAKEOFF_ALT above home, then
        holds (AUTO.LOITER) (docs.px4.io flight_modes_mc/takeoff; navigator/takeoff.cpp). Disarmed,
        the mode is entered and the climb starts on arming."""
        if self.prearm_failure is not None and not self.armed:
            return mavlink.MAV_RESULT_DENIED
        if math.isfinite(alt_amsl):
            self.takeoff_z = float(alt_amsl - REF_LLA[2])  # AMSL -> swarm ENU z (REF_LLA alt at z = 0)
        else:
            self.takeoff_z = float(self.home_enu[2] + self.ap_params["MIS_TAKEOFF_ALT"])
        return self._set_mode(px4_custom_mode(4, PX4_AUTO_SUB["TAKEOFF"]), now, q, yaw)

    def _request_message(self, msg_id: float) -> int:
        """MAV_CMD_REQUEST_MESSAGE: HOME_POSITION and AUTOPILOT_VERSION are sent; others UNSUPPORTED."""
        if msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            self._pending.append("home")
            return mavlink.MAV_RESULT_ACCEPTED
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._pending.append("version")
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _arm(self, arm: bool, force: bool, now: float, q: np.ndarray, yaw: float) -> int:
        if arm:
            if self.armed:
                return mavlink.MAV_RESULT_ACCEPTED
            k = self.kind()
            if self.prearm_failure is not None and not force:
                # PX4: "Preflight Fail: ..." and DENIED; ArduCopter: "PreArm: ..." and FAILED
                text = ("PreArm: " if self.opts.autopilot == "ardupilot" else "Preflight Fail: ") + self.prearm_failure
                self.conn.mav.statustext_send(mavlink.MAV_SEVERITY_CRITICAL, text.encode()[:50])
                return mavlink.MAV_RESULT_FAILED if self.opts.autopilot == "ardupilot" else mavlink.MAV_RESULT_DENIED
            if k == LAND or k is None or k == RTL:
                return mavlink.MAV_RESULT_DENIED
            if k == OFFBOARD and not self._setpoint_fresh(now) and self.opts.autopilot == "px4" and not force:
                return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            self.armed = True
            self.hold_enu = q.copy()
            self.hold_yaw = float(yaw)
            self.home_enu = q.copy()  # both autopilots set home on arming
            self.landed_since = now
            self._count("arm_accepted")
            return mavlink.MAV_RESULT_ACCEPTED
        if not self.armed:
            return mavlink.MAV_RESULT_ACCEPTED
        if not (self.on_ground or force):
            return mavlink.MAV_RESULT_DENIED  # PX4 refuses to disarm in flight unless forced
        self._disarm()
        self._count("disarmed")
        return mavlink.MAV_RESULT_ACCEPTED

    def _disarm(self) -> None:
        self.armed = False
        self.land_complete = True
        self.guided_sub = None

    def _set_mode(self, custom_mode: int, now: float, q: np.ndarray, yaw: float) -> int:
        k = self.opts.mode_kind(custom_mode)
        if k is None:
            return mavlink.MAV_RESULT_UNSUPPORTED
        if k == OFFBOARD and self.opts.autopilot == "px4" and not self._setpoint_fresh(now):
            self._count("offboard_refused")
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # PX4: no setpoint stream, no OFFBOARD
        if k == TAKEOFF and self.custom_mode != custom_mode and not math.isfinite(self.takeoff_z):
            self.takeoff_z = float(self.home_enu[2] + self.ap_params["MIS_TAKEOFF_ALT"])
        if self.mode_override is None:
            self._enter(custom_mode, q, yaw)
            if k == OFFBOARD and self.opts.autopilot == "ardupilot":
                # ArduCopter ModeGuided::init: starts in velocity control with a zero target
                # (mode_guided.cpp); the GUID_TIMEOUT is counted from here
                self.guided_sub, self.sp_kind, self.last_sp = SUB_VEL, None, now
                self.vel_ned = np.zeros(3)
            if k == RTL:
                self.rtl_phase = "climb"
        return mavlink.MAV_RESULT_ACCEPTED

    def _attitude_target(self, m: Any, now: float) -> None:
        mask = int(m.type_mask)
        vals = list(m.q) + [m.thrust]
        if not all(math.isfinite(x) for x in vals):
            self._count("malformed")
            return
        if not mask & mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE:
            try:
                self.att_q = frames.quat_normalize(list(m.q))
            except ValueError:
                self._count("malformed")
                return
        rates_used = (mask & 0b111) != 0b111
        if mask & mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE and rates_used:
            # attitude ignored, body rates given: a rate setpoint (PX4 mavlink_receiver.cpp
            # handle_message_set_attitude_target -> vehicle_rates_setpoint; ArduCopter
            # GCS_Mavlink.cpp -> ModeGuided::set_angle with ang_vel); an ignored axis is 0 rad/s
            rates = [0.0 if mask & (1 << i) else float(x) for i, x in enumerate((m.body_roll_rate, m.body_pitch_rate, m.body_yaw_rate))]
            if not all(math.isfinite(x) for x in rates):
                self._count("malformed")
                return
            if self.rates_frd is None:
                self.att_int = None  # integrate from the current attitude
            self.rates_frd = np.array(rates)
        elif not mask & mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE:
            self.rates_frd = None
        if not mask & mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE:
            self.att_thrust = min(max(float(m.thrust), 0.0), 1.0)
            if self.opts.autopilot == "ardupilot":
                # ArduCopter GCS_Mavlink.cpp handle SET_ATTITUDE_TARGET: unless GUID_OPTIONS bit 3,
                # thrust is a climb rate: 0.5 = hold altitude, 1 = WPNAV_SPEED_UP, 0 = -WPNAV_SPEED_DN
                u = self.att_thrust
                if u >= 0.5:
                    self.climb_rate = (u - 0.5) * 2.0 * self.ap_params["WPNAV_SPEED_UP"] / 100.0
                else:
                    self.climb_rate = -(0.5 - u) * 2.0 * self.ap_params["WPNAV_SPEED_DN"] / 100.0
        self.sp_kind = "attitude"
        if self.opts.autopilot == "ardupilot":
            self.guided_sub = SUB_ANGLE  # mode_guided.cpp set_angle: angle_control_start()
        self.last_sp = now
        self._count("setpoints")

    def _position_target(self, m: Any, now: float) -> None:
        if m.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
            self._count("unsupported_frame")
            return
        vals = [m.x, m.y, m.z, m.vx, m.vy, m.vz, m.yaw]
        mask = int(m.type_mask)
        pos_use = (mask & 0b111) != 0b111
        vel_use = (mask & 0b111000) != 0b111000
        yaw_use = not mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
        used = (vals[0:3] if pos_use else []) + (vals[3:6] if vel_use else []) + ([vals[6]] if yaw_use else [])
        if not all(math.isfinite(x) for x in used):
            self._count("malformed")
            return
        self.pos_use, self.vel_use = pos_use, vel_use
        self.pos_ned = np.array(vals[0:3]) if pos_use else None
        self.vel_ned = np.array(vals[3:6]) if vel_use else np.zeros(3)
        self.yaw_ned = float(vals[6]) if yaw_use else None
        self.sp_kind = "position"
        if self.opts.autopilot == "ardupilot":
            # ArduCopter GCS_Mavlink.cpp handle SET_POSITION_TARGET_LOCAL_NED -> set_destination /
            # set_velocity / set_destination_posvelaccel: each starts its own sub-mode (pos_control_
            # start, velaccel_control_start, posvelaccel_control_start), ending a TakeOff
            self.guided_sub = SUB_POS if not vel_use else (SUB_VEL if not pos_use else SUB_POSVEL)
        self.last_sp = now
        self._count("setpoints")

    # ------------------------------------------------------------------ autopilot
    def update(self, now: float, q: np.ndarray, v: np.ndarray, rpy: np.ndarray) -> tuple[float, np.ndarray]:
        """Mode logic (failsafe, auto-disarm) and this period's command to the onboard attitude
        controller: (thrust F, N; attitude setpoint [phi, theta, psi], rad, ENU)."""
        k = self._mode_logic(now, q, rpy)
        if not self.armed:
            return 0.0, np.array([0.0, 0.0, rpy[2]])
        if k == OFFBOARD and self.opts.autopilot == "ardupilot":
            return self._ap_guided(now, q, v, rpy)
        if k == OFFBOARD and self.sp_kind == "attitude":
            return float(self.tmap.to_newtons(self.att_thrust)), self._attitude_sp(rpy)
        if k == OFFBOARD and self.sp_kind == "position":
            return self._pd(q, v, self._pos_ref(), frames.ned_to_enu(self.vel_ned), self._yaw_ref(rpy))
        if k == TAKEOFF:
            return self._climb(now, q, v, rpy, self.ap_params["MPC_TKO_SPEED"])
        if k == RTL:
            return self._rtl(now, q, v, rpy)
        if self.hold_enu is None:
            self.hold_enu, self.hold_yaw = q.copy(), float(rpy[2])
        if k == LAND:
            p_ref = np.array([self.hold_enu[0], self.hold_enu[1], math.nan])
            return self._pd(q, v, p_ref, np.array([0.0, 0.0, -self.land_speed]), self.hold_yaw)
        return self._pd(q, v, self.hold_enu, np.zeros(3), self.hold_yaw)  # HOLD (and unknown modes)

    def _pos_ref(self) -> np.ndarray | None:
        """The position setpoint in the swarm's ENU frame (local NED about the vehicle's origin)."""
        return frames.ned_to_enu(self.pos_ned) + self.origin if self.pos_ned is not None else None

    def _yaw_ref(self, rpy: np.ndarray) -> float:
        return float(rpy[2]) if self.yaw_ned is None else float(frames.euler_ned_to_enu([0.0, 0.0, self.yaw_ned])[2])

    def _attitude_sp(self, rpy: np.ndarray) -> np.ndarray:
        """Attitude setpoint, rpy ENU: the target quaternion, or the body rates integrated over the
        loop period from the attitude when they started."""
        if self.rates_frd is None:
            return frames.quat_ned_to_attitude(self.att_q)
        if self.att_int is None:
            self.att_int = np.array(rpy, dtype=float)
        w_flu = frames.flu_to_frd(self.rates_frd)  # the same sign flip both ways (y, z)
        ph, th = self.att_int[0], self.att_int[1]
        # ZYX Euler rates from body rates (eq. 2's kinematics)
        dphi = w_flu[0] + math.tan(th) * (math.sin(ph) * w_flu[1] + math.cos(ph) * w_flu[2])
        dth = math.cos(ph) * w_flu[1] - math.sin(ph) * w_flu[2]
        dpsi = (math.sin(ph) * w_flu[1] + math.cos(ph) * w_flu[2]) / math.cos(th)
        tilt = self.params.max_tilt
        self.att_int = self.att_int + self.period * np.array([dphi, dth, dpsi])
        self.att_int[0:2] = np.clip(self.att_int[0:2], -tilt, tilt)
        return self.att_int.copy()

    def _climb(self, now: float, q: np.ndarray, v: np.ndarray, rpy: np.ndarray, speed: float) -> tuple[float, np.ndarray]:
        """Vertical climb to ``takeoff_z`` at ``speed`` m/s over the takeoff point; at the
        altitude, PX4's AUTO.TAKEOFF hands over to AUTO.LOITER (navigator takeoff.cpp)."""
        assert self.hold_enu is not None
        if not math.isfinite(self.takeoff_z):  # reached: hold there
            return self._pd(q, v, self.hold_enu, np.zeros(3), self.hold_yaw)
        dz = self.takeoff_z - q[2]
        if abs(dz) < 0.05 and abs(v[2]) < 0.2:
            target = np.array([self.hold_enu[0], self.hold_enu[1], self.takeoff_z])
            self.takeoff_z = math.nan
            if self.opts.autopilot == "px4":
                self._enter(self.opts.modes["hold"], target, self.hold_yaw)
            self.hold_enu = target
            return self._pd(q, v, target, np.zeros(3), self.hold_yaw)
        self.land_complete = False
        vz = math.copysign(min(speed, 1.5 * abs(dz) + 0.05), dz)
        p_ref = np.array([self.hold_enu[0], self.hold_enu[1], math.nan])
        return self._pd(q, v, p_ref, np.array([0.0, 0.0, vz]), self.hold_yaw)

    def _rtl(self, now: float, q: np.ndarray, v: np.ndarray, rpy: np.ndarray) -> tuple[float, np.ndarray]:
        """Return: climb to at least the return altitude above home (PX4 RTL_RETURN_ALT,
        ArduCopter RTL_ALT), fly over home, then land there and disarm (PX4 docs
        flight_modes_mc/return; ArduCopter mode_rtl.cpp). PX4's intermediate RTL_DESCEND_ALT loiter
        and ArduCopter's RTL_LOIT_TIME pause are not simulated."""
        home = self.home_enu
        if self.opts.autopilot == "px4":
            ret_z = home[2] + self.ap_params["RTL_RETURN_ALT"]
        else:
            ret_z = home[2] + self.ap_params["RTL_ALT"] / 100.0
        if self.hold_enu is None:
            self.hold_enu = q.copy()
        if self.rtl_phase == "climb":
            self.hold_enu = np.array([self.hold_enu[0], self.hold_enu[1], max(ret_z, self.hold_enu[2])])
            if q[2] >= self.hold_enu[2] - 0.1:
                self.rtl_phase = "return"
            return self._pd(q, v, self.hold_enu, np.zeros(3), self.hold_yaw)
        if self.rtl_phase == "return":
            target = np.array([home[0], home[1], self.hold_enu[2]])
            if float(np.linalg.norm(q[0:2] - home[0:2])) < 0.1 and float(np.linalg.norm(v)) < 0.2:
                self.rtl_phase = "land"
            return self._pd(q, v, target, np.zeros(3), self.hold_yaw)
        p_ref = np.array([home[0], home[1], math.nan])
        return self._pd(q, v, p_ref, np.array([0.0, 0.0, -self.land_speed]), self.hold_yaw)

    def _ap_guided(self, now: float, q: np.ndarray, v: np.ndarray, rpy: np.ndarray) -> tuple[float, np.ndarray]:
        """ArduCopter GUIDED / GUIDED_NOGPS, by sub-mode (mode_guided.cpp *_control_run).

        Landed (land_complete), every sub-mode but TakeOff, and Angle with a positive climb rate
        (or thrust given as thrust), only does ground handling: motors idle, no lift-off.
        Velocity, acceleration and angle targets older than GUID_TIMEOUT are dropped: the
        vehicle stops (zero velocity), or levels out and holds its altitude; a position target
        is held without time limit."""
        level = np.array([0.0, 0.0, rpy[2]])
        sub = self.guided_sub
        timed_out = now - self.last_sp > self.ap_params["GUID_TIMEOUT"]
        thrust_as_thrust = bool(int(self.ap_params["GUID_OPTIONS"]) & _GUID_THRUST_AS_THRUST)
        if sub == SUB_TAKEOFF:
            if self.land_complete:
                if now - self.takeoff_t0 < self.ap_params["MOT_SPOOL_TIME"]:
                    return 0.0, level  # spooling up, still landed (takeoff.cpp auto_takeoff_run)
                self.land_complete = False
            return self._climb(now, q, v, rpy, self.ap_params["WPNAV_SPEED_UP"] / 100.0)
        if sub == SUB_ANGLE:
            if timed_out:
                att, climb, as_thrust = np.array([0.0, 0.0, rpy[2]]), 0.0, False
            else:
                att, climb, as_thrust = self._attitude_sp(rpy), self.climb_rate, thrust_as_thrust
            if self.land_complete:
                if not (climb > 0.0 or (as_thrust and self.att_thrust > 0.0)):
                    return 0.0, level  # make_safe_ground_handling
                self.land_complete = False  # "landed with positive desired climb rate, takeoff"
            if as_thrust:
                return float(self.tmap.to_newtons(self.att_thrust)), att
            # climb-rate control under the commanded attitude
            p = self.params
            az = float(self.opts.pos_kd[2]) * (climb - v[2])
            tilt = math.cos(att[0]) * math.cos(att[1])
            f = p.mass * (p.g + az) / max(tilt, 0.3)
            return float(min(max(f, 0.0), p.max_thrust)), att
        if self.land_complete:
            return 0.0, level  # pos/vel run functions: is_disarmed_or_landed -> ground handling
        if sub == SUB_VEL:
            vel = np.zeros(3) if timed_out or self.sp_kind != "position" else frames.ned_to_enu(self.vel_ned)
            return self._pd(q, v, None, vel, self._yaw_ref(rpy))
        vel = frames.ned_to_enu(self.vel_ned) if sub == SUB_POSVEL and not timed_out else np.zeros(3)
        p_ref = self._pos_ref()
        if p_ref is None:
            p_ref = self.hold_enu if self.hold_enu is not None else q.copy()
        return self._pd(q, v, p_ref, vel, self._yaw_ref(rpy))

    def _mode_logic(self, now: float, q: np.ndarray, rpy: np.ndarray) -> str | None:
        """The autopilot's own mode changes this period (forced mode, offboard-loss failsafe:
        hold then land, auto-disarm after landing); the mode kind it flies in."""
        if self.mode_override is not None and self.custom_mode != self.mode_override:
            self._enter(self.mode_override, q, rpy[2])
        k = self.kind()
        since = now - self.last_sp
        if k == OFFBOARD and since > self.loss_s and self.opts.autopilot == "px4":
            self._enter(self.opts.modes["hold"], q, rpy[2])
            self.failsafe = True  # offboard loss: hold, then land
            self._count("failsafe_hold")
            k = HOLD
        elif self.failsafe and k == HOLD and self.armed and since > self.loss_s + self.opts.failsafe_land_s:
            self._enter(self.opts.modes["land"], q, rpy[2])
            self._count("failsafe_land")
            k = LAND
        landing = k == LAND or (k == RTL and self.rtl_phase == "land")
        if landing and self.armed and self.on_ground and now - self.ground_since >= self.disarm_after_land_s:
            self._disarm()  # landed: auto-disarm (PX4 COM_DISARM_LAND; ArduCopter mode_land.cpp)
            self._count("auto_disarmed")
        if self.opts.autopilot == "ardupilot" and self.armed:
            # the land detector (ArduCopter land_detector.cpp, about 1 s on the ground); landed and
            # armed for DISARM_DELAY s -> disarm (motors.cpp auto_disarm_check)
            if self.on_ground and now - self.ground_since >= 1.0 and self.guided_sub != SUB_TAKEOFF:
                if not self.land_complete:
                    self.land_complete, self.landed_since = True, now
            elif not self.on_ground:
                self.land_complete = False
            if not self.land_complete:
                self.landed_since = now
            delay = self.ap_params["DISARM_DELAY"]
            if delay > 0 and self.land_complete and now - self.landed_since >= delay:
                self._disarm()
                self._count("auto_disarmed")
        return k

    def _pd(self, q: np.ndarray, v: np.ndarray, p_ref: np.ndarray | None, v_ref: np.ndarray, yaw: float) -> tuple[float, np.ndarray]:
        """The vehicle's position loop: a = Kp (p* - p) + Kd (v* - v) (a NaN axis of p* is not
        position-controlled), limited to the tilt and thrust envelope; then F = m |a + g e_z| and
        the attitude of that thrust direction at ``yaw`` (the inversion after eq. 28)."""
        p = self.params
        o = self.opts
        a = np.asarray(o.pos_kd) * (v_ref - v)
        if p_ref is not None:
            e = np.where(np.isnan(p_ref), 0.0, p_ref - q)
            n = float(np.linalg.norm(e))
            if n > o.max_pos_err:
                e *= o.max_pos_err / n
            a += np.asarray(o.pos_kp) * e
        g = p.g
        axy_max = 0.9 * g * math.tan(p.max_tilt)
        nxy = math.hypot(a[0], a[1])
        if nxy > axy_max:
            a[0:2] *= axy_max / nxy
        a[2] = min(max(a[2], -0.7 * g), 0.9 * (p.max_thrust / p.mass - g))
        ux, uy, uz = a[0], a[1], a[2] + g
        norm = math.sqrt(ux * ux + uy * uy + uz * uz)
        s, c = math.sin(yaw), math.cos(yaw)
        phi = math.asin(min(max((ux * s - uy * c) / norm, -1.0), 1.0))
        theta = math.atan2(ux * c + uy * s, uz)
        return p.mass * norm, np.array([phi, theta, yaw])

    # ------------------------------------------------------------------ send
    def send_telemetry(self, now: float, p_ned: np.ndarray, v_ned: np.ndarray, rpy_ned: np.ndarray, w_frd: np.ndarray) -> None:
        if self.muted(now) or not self.peer_seen:
            return
        ms = self._ms(now)
        mav = self.conn.mav
        mav.local_position_ned_send(ms, *map(float, p_ned), *map(float, v_ned))
        mav.attitude_send(ms, *map(float, rpy_ned), *map(float, w_frd))
        if self.opts.autopilot == "px4":
            # PX4 streams ATTITUDE_QUATERNION beside ATTITUDE (mavlink_main.cpp stream lists);
            # ArduPilot only on request
            qn = frames.attitude_to_quat_ned(frames.euler_ned_to_enu(rpy_ned))
            mav.attitude_quaternion_send(ms, *map(float, qn), *map(float, w_frd))
        self.telemetry_sent += 1
        if self.telemetry_sent % 5 == 1:
            # GLOBAL_POSITION_INT at a fifth of the rate: simulated GPS about REF_LLA (flat earth)
            q = frames.ned_to_enu(p_ned) + self.origin
            v = frames.ned_to_enu(v_ned)
            lat, lon, alt = self._lla(q)
            rel = q[2] - self.home_enu[2]
            hdg = int(round(math.degrees(float(rpy_ned[2])) % 360.0 * 100.0)) % 36000
            mav.global_position_int_send(
                ms, lat, lon, int(alt * 1000), int(rel * 1000), int(v[1] * 100), int(v[0] * 100), int(-v[2] * 100), hdg
            )

    def _lla(self, q_enu: np.ndarray) -> tuple[int, int, float]:
        """(lat 1e-7 deg, lon 1e-7 deg, alt AMSL m) of swarm ENU ``q_enu`` about REF_LLA."""
        lat = REF_LLA[0] + math.degrees(float(q_enu[1]) / _EARTH_R)
        lon = REF_LLA[1] + math.degrees(float(q_enu[0]) / (_EARTH_R * math.cos(math.radians(REF_LLA[0]))))
        return int(round(lat * 1e7)), int(round(lon * 1e7)), REF_LLA[2] + float(q_enu[2])

    def landed_state(self) -> int:
        """MAV_LANDED_STATE of EXTENDED_SYS_STATE (PX4 land detector / ArduCopter land_complete)."""
        k = self.kind()
        if not self.armed:
            return int(mavlink.MAV_LANDED_STATE_ON_GROUND)
        if k == TAKEOFF or (self.guided_sub == SUB_TAKEOFF and math.isfinite(self.takeoff_z)):
            return int(mavlink.MAV_LANDED_STATE_TAKEOFF)
        if self.on_ground and (self.opts.autopilot == "px4" or self.land_complete):
            return int(mavlink.MAV_LANDED_STATE_ON_GROUND)
        if k == LAND or (k == RTL and self.rtl_phase == "land"):
            return int(mavlink.MAV_LANDED_STATE_LANDING)
        return int(mavlink.MAV_LANDED_STATE_IN_AIR)

    def send_status_extra(self, now: float) -> None:
        """EXTENDED_SYS_STATE and HOME_POSITION (both autopilots stream them at low rate), and
        any message requested with MAV_CMD_REQUEST_MESSAGE."""
        if self.muted(now) or not self.peer_seen:
            return
        self.conn.mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, self.landed_state())
        self._send_home()

    def send_requested(self, now: float) -> None:
        pending, self._pending = self._pending, []
        if self.muted(now):
            return
        for what in pending:
            if what == "home":
                self._send_home()
            elif what == "version":
                caps = (
                    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
                    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
                    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                )
                if self.opts.autopilot == "px4":
                    caps |= mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                else:
                    caps |= mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
                self.conn.mav.autopilot_version_send(caps, 0, 0, 0, 0, bytes(8), bytes(8), bytes(8), 0, 0, self.sysid, bytes(18))

    def _send_home(self) -> None:
        h = self.home_enu
        lat, lon, alt = self._lla(h)
        x, y, z = (float(c) for c in frames.enu_to_ned(h - self.origin))
        self.conn.mav.home_position_send(lat, lon, int(alt * 1000), x, y, z, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)

    def send_heartbeat(self, now: float) -> None:
        if self.muted(now) or not self.peer_seen:
            return
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if self.kind() == OFFBOARD:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        ap = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA if self.opts.autopilot == "ardupilot" else mavlink.MAV_AUTOPILOT_PX4
        status = mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, ap, base, self.custom_mode, status)

    def send_sys_status(self, now: float) -> None:
        if self.muted(now) or not self.peer_seen:
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
        if self.prearm_failure is not None:
            health &= ~(mavlink.MAV_SYS_STATUS_PREARM_CHECK | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG)
        # load 0.1 %, battery 4.2 V (1S), current and remaining unknown (-1)
        self.conn.mav.sys_status_send(sensors, sensors, health, 100, 4200, -1, -1, 0, 0, 0, 0, 0, 0)

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:  # noqa: BLE001
            pass


def vehicle_options(sc: Any) -> VehicleOptions:
    """The :class:`VehicleOptions` of a scenario's ``[mavlink]`` table (``autopilot``,
    ``telemetry_hz``, ``offboard_loss_s``, ``failsafe_land_s``, ``ground_z``, ``hover_throttle``,
    ``host``)."""
    ms = mavlink_settings(sc)
    return VehicleOptions(
        autopilot="ardupilot" if ms.autopilot == "ardupilot" else "px4",
        telemetry_hz=ms.telemetry_hz,
        offboard_loss_s=ms.offboard_loss_s,
        failsafe_land_s=ms.failsafe_land_s,
        ground_z=ms.ground_z,
        hover_throttle=ms.hover_throttle,
        host=ms.host,
    )


class MavlinkFleet(FleetThread):
    """N simulated quadrotors as MAVLink vehicles, integrated in real time.

    Parameters
    ----------
    q0 : (N, 3) array_like
        Spawn positions, m ENU (z is replaced by ``opts.ground_z``: vehicles start on the ground).
    params : QuadParams
    base_port : int
        Vehicle i (0-based) listens on UDP ``opts.host:base_port + i``.
    opts : VehicleOptions
    sysids : sequence of int or None
        System id of each vehicle (default 1..N).
    physics_hz, chunk : float, int
        Physics sub-step rate and sub-steps per loop period (the loop runs at physics_hz / chunk).
    disturbance : (DisturbanceConfig, numpy Generator) or None

    Use :meth:`start` / :meth:`stop` (a background thread, for tests and embedding) or
    :meth:`run` (in the calling thread, for the CLI). Attribute ``state`` is the
    :class:`zenswarm.plant.quadrotor.PlantState` (ENU, read it, do not write it while running).
    """

    thread_name = "mavlink-fleet"

    def __init__(
        self,
        q0: Any,
        params: QuadParams,
        base_port: int,
        opts: VehicleOptions | None = None,
        sysids: Any = None,
        physics_hz: float = 1000.0,
        chunk: int = 10,
        disturbance: Any = None,
    ) -> None:
        self.opts = opts or VehicleOptions()
        self.params = params
        q = np.array(q0, dtype=float)
        if q.ndim != 2 or q.shape[1] != 3:
            raise ValueError(f"q0 must have shape (N, 3), got {q.shape}")
        q[:, 2] = self.opts.ground_z
        self.n = q.shape[0]
        self.state: PlantState = initial_state(q)
        self.h = 1.0 / float(physics_hz)
        self.chunk = int(chunk)
        self.period = self.chunk * self.h
        self.loop_hz = 1.0 / self.period
        self.tel_every = max(1, round(self.loop_hz / self.opts.telemetry_hz))
        self.hb_every = max(1, round(self.loop_hz / self.opts.heartbeat_hz))
        self.ss_every = max(1, round(self.loop_hz / self.opts.sys_status_hz))
        self.dist = DisturbanceModel(disturbance[0], self.n, disturbance[1]) if disturbance is not None else None
        ids = list(sysids) if sysids is not None else list(range(1, self.n + 1))
        if len(ids) != self.n:
            raise ValueError(f"need {self.n} system ids, got {len(ids)}")
        self.boot = time.monotonic()
        self.vehicles: list[SimVehicle] = []
        try:
            for i in range(self.n):
                veh = SimVehicle(i, int(ids[i]), int(base_port) + i, self.opts, params, self.boot, spawn=q[i])
                veh.period = self.period
                self.vehicles.append(veh)
        except Exception:
            self.close()
            raise
        self.origins = np.array([veh.origin for veh in self.vehicles])
        self.thrust = np.zeros(self.n)
        self.rpy_cmd = np.zeros((self.n, 3))
        self.sim_t = 0.0
        self.ticks = 0
        self.overruns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.error: BaseException | None = None

    @classmethod
    def from_scenario(cls, sc: Any, base_port: int | None = None, opts: VehicleOptions | None = None, **kw: Any) -> MavlinkFleet:
        """Fleet of the scenario: spawn under ``formation.initial_positions``, ``[vehicle]``
        parameters, ``[disturbance]`` (seeded by ``scenario.seed``), timing from ``[timing]``,
        ports/ids/options from ``[mavlink]`` (``base_port``, ``host``, ``sysids``, ``autopilot``,
        ``telemetry_hz``, ``offboard_loss_s``, ``failsafe_land_s``, ``ground_z``,
        ``hover_throttle``); ``opts`` given explicitly wins over the table."""
        ms = mavlink_settings(sc)
        if opts is None:
            opts = vehicle_options(sc)
        params = QuadParams.from_vehicle(sc.vehicle)
        dist = (sc.disturbance, np.random.default_rng(sc.seed)) if sc.disturbance.active else None
        return cls(
            np.asarray(sc.initial_positions, dtype=float),
            params,
            ms.base_port if base_port is None else base_port,
            opts,
            sysids=ms.sysids,
            physics_hz=sc.timing.physics_rate_hz,
            chunk=sc.timing.substeps,
            disturbance=dist,
            **kw,
        )

    # ------------------------------------------------------------------ test / fault hooks
    def silence(self, index: int, seconds: float) -> None:
        """Vehicle ``index`` (0-based) drops all its traffic, both ways, for ``seconds``."""
        self.vehicles[index].muted_until = time.monotonic() + float(seconds)

    def set_prearm_failure(self, index: int, reason: str | None) -> None:
        """Vehicle ``index`` fails its pre-arm checks with ``reason`` (None: passes again): its
        SYS_STATUS says so (PREARM_CHECK and 3D_MAG unhealthy) and arming is refused with a
        STATUSTEXT, as a vehicle with an uncalibrated compass would."""
        self.vehicles[index].prearm_failure = reason

    def set_mode_override(self, index: int, custom_mode: int | None) -> None:
        """Vehicle ``index`` accepts mode requests but reports and flies ``custom_mode``."""
        self.vehicles[index].mode_override = custom_mode

    # ------------------------------------------------------------------ loop
    def tick(self, now: float) -> None:
        """One loop period: receive, autopilot logic, physics chunk, telemetry."""
        st = self.state
        with self._lock:
            for i, veh in enumerate(self.vehicles):
                veh.poll(now, st.q[i], float(st.rpy[i, 2]))
            for i, veh in enumerate(self.vehicles):
                veh.on_ground = bool(st.q[i, 2] <= self.opts.ground_z + 0.01 and abs(st.v[i, 2]) < 0.05)
                if not veh.on_ground:
                    veh.ground_since = math.inf
                elif not math.isfinite(veh.ground_since):
                    veh.ground_since = now
                f, rpy = veh.update(now, st.q[i], st.v[i], st.rpy[i])
                self.thrust[i] = f
                self.rpy_cmd[i] = rpy
            d_p: np.ndarray | None
            d_a: np.ndarray | None
            for j in range(self.chunk):
                if self.dist is not None:
                    d_p, d_a = self.dist.sample(self.sim_t + j * self.h, self.h)
                else:
                    d_p = d_a = None
                step(st, self.thrust, self.rpy_cmd, self.params, self.h, d_p, d_a)
                self._ground()
            self.sim_t += self.period
            self.ticks += 1
            k = self.ticks
            if k % self.tel_every == 0:
                p_ned = frames.enu_to_ned(st.q - self.origins)
                v_ned = frames.enu_to_ned(st.v)
                rpy_ned = frames.euler_enu_to_ned(st.rpy)
                w_frd = frames.flu_to_frd(st.w)
                for i, veh in enumerate(self.vehicles):
                    veh.send_telemetry(now, p_ned[i], v_ned[i], rpy_ned[i], w_frd[i])
            if k % self.hb_every == 1 % self.hb_every:
                for veh in self.vehicles:
                    veh.send_heartbeat(now)
            if k % self.ss_every == 1 % self.ss_every:
                for veh in self.vehicles:
                    veh.send_sys_status(now)
                    veh.send_status_extra(now)
            for veh in self.vehicles:
                if veh._pending:
                    veh.send_requested(now)

    def _ground(self) -> None:
        """Flat ground at ground_z: a vehicle below it is put back on it, at rest and level."""
        st = self.state
        if st.q[:, 2].min() >= self.opts.ground_z:  # the common case, cheap (runs every sub-step)
            return
        below = st.q[:, 2] < self.opts.ground_z
        st.q[below, 2] = self.opts.ground_z
        st.v[below] = 0.0
        st.w[below] = 0.0
        st.rpy[below, 0:2] = 0.0
        st.rate_int[below] = 0.0

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> str:
        """Loop on the wall clock until ``stop`` is set or ``duration_s`` passed; returns why it
        stopped. Late periods are caught up (physics stays on the wall clock); a stall of more
        than 0.5 s resynchronises instead (counted in ``overruns``; the simulation then runs
        behind the wall clock by the stall)."""
        from zenswarm.process.runtime import WallClock

        stop = stop or self._stop
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        clock = WallClock(self.period, stop, first_wait=True, resync_after_s=0.5)
        while True:
            if stop.is_set():
                return "stop requested"
            now = time.monotonic()
            if now >= end:
                return "duration reached"
            self.tick(now)
            resyncs = clock.resyncs
            clock.wait()
            self.overruns += clock.resyncs - resyncs

    def status(self) -> list[dict[str, Any]]:
        """One line of facts per vehicle (for logs and tests)."""
        out = []
        for i, v in enumerate(self.vehicles):
            out.append(
                {
                    "sysid": v.sysid,
                    "port": v.port,
                    "armed": v.armed,
                    "mode": v.mode,
                    "q": self.state.q[i].round(3).tolist(),
                    **v.counters,
                }
            )
        return out


# --------------------------------------------------------------------------- CLI


def run_fleet(
    sc: Any,
    *,
    base_port: int | None = None,
    autopilot: str | None = None,
    telemetry_hz: float | None = None,
    duration: float | None = None,
    own_origin: bool = False,
    sitl_ports: bool = False,
    rt_priority: int | None = None,
) -> int:
    """Run the fleet of scenario ``sc`` in the calling thread until SIGTERM/SIGINT (or
    ``duration`` s). ``base_port``: vehicle i listens on UDP base_port + i - 1 (None: the
    scenario's ``mavlink.base_port``); ``autopilot`` (``px4`` or ``ardupilot``) and
    ``telemetry_hz`` override the scenario's vehicle options; ``own_origin`` and ``sitl_ports`` set
    the options of the same names (:class:`VehicleOptions`); ``rt_priority``: run under
    ``SCHED_FIFO`` at this priority once the fleet is built (:mod:`zenswarm.process.rtsched`; checked
    first, exit 2 if not permitted). The command line (``zenswarm
    mavlink-vehicle``, ``zenswarm plant --mavlink``) is parsed in :mod:`zenswarm.compose.roles`."""
    from zenswarm.process import rtsched
    from zenswarm.process.runtime import gc_policy, gc_startup_done

    gc_policy()  # a bad ZENSWARM_GC: exit 2 before any work
    rtsched.set_requested(rtsched.validate(rt_priority, realtime=True))  # out of range or not permitted: exit 2 now
    opts = vehicle_options(sc)
    opts = replace(
        opts,
        autopilot=autopilot or opts.autopilot,
        telemetry_hz=telemetry_hz or opts.telemetry_hz,
        own_origin=own_origin or opts.own_origin,
        sitl_ports=sitl_ports or opts.sitl_ports,
    )
    # one fleet, its ports bound once (a busy port: ScenarioError naming it, exit 2)
    fleet = MavlinkFleet.from_scenario(sc, base_port=base_port, opts=opts)
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    try:
        print(
            f"mavlink-vehicle: ready: {fleet.n} vehicle(s) ({fleet.opts.autopilot}) "
            + ", ".join(f"sysid {v.sysid} on udp {fleet.opts.host}:{v.port}" for v in fleet.vehicles)
            + f"; physics {1 / fleet.h:g} Hz in chunks of {fleet.chunk}, telemetry {fleet.loop_hz / fleet.tel_every:g} Hz",
            flush=True,
        )
        gc_startup_done()  # sockets open, vehicles built: see zenswarm.process.runtime.GcPolicy (safe points: WallClock.wait)
        rtsched.apply_after_startup(lambda text: print(f"mavlink-vehicle: {text}", flush=True))
        why = fleet.run(stop, duration)
        print(f"mavlink-vehicle: stopped ({why}); overruns {fleet.overruns}; {gc_policy().counters()}; " + str(fleet.status()), flush=True)
    finally:
        fleet.close()
    return 0

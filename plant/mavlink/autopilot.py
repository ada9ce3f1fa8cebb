"""One simulated MAVLink vehicle's autopilot (:class:`SimVehicle`), PX4 or ArduCopter flavoured
(:mod:`zenswarm.plant.mavlink_vehicle` says what it speaks and does, and cites each autopilot's
source next to its code): its modes, arming and pre-arm checks, the commands it accepts (each
answered with a MAV_RESULT), the setpoints it follows, the offboard-loss failsafe, takeoff,
return and landing, the auto-disarm, and the position loop
(:func:`zenswarm.plant.position_control.position_loop`) that turns a setpoint into the thrust and
attitude the plant flies. Its parameters are :mod:`zenswarm.plant.mavlink.params`'; the messages
in and out are its link's (:class:`zenswarm.plant.mavlink.link.MavlinkLink`); the physics the
fleet's (:mod:`zenswarm.plant.mavlink.fleet`).

Frames: the autopilot works in the swarm's ENU frame (positions m, attitude ZYX rad, ``home_enu``
and its estimator ``origin`` m ENU); the setpoints it keeps from the wire stay in MAVLink's local
NED about its origin (``pos_ned``, ``vel_ned``, ``yaw_ned``, ``att_q``; body rates FRD) until it
flies them.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from zenswarm.plant.mavlink.link import REF_LLA, MavlinkLink, decode_attitude_target, decode_position_target, mavlink
from zenswarm.plant.mavlink.options import HOLD, LAND, OFFBOARD, RTL, TAKEOFF, VehicleOptions
from zenswarm.plant.mavlink.params import ParamStore, ardupilot_params, px4_params
from zenswarm.plant.position_control import position_loop
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import AP_COPTER_MODES, PX4_AUTO_SUB, mode_name, px4_custom_mode
from zenswarm.vehicle.params import QuadParams

__all__ = ["SimVehicle", "SUB_TAKEOFF", "SUB_POS", "SUB_POSVEL", "SUB_VEL", "SUB_ANGLE"]

_FORCE_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that forces (dis)arming

# ArduCopter GUIDED sub-modes (ArduCopter/mode.h ModeGuided::SubMode)
SUB_TAKEOFF, SUB_POS, SUB_POSVEL, SUB_VEL, SUB_ANGLE = "TakeOff", "Pos", "PosVelAccel", "VelAccel", "Angle"

_GUID_THRUST_AS_THRUST = 8  # GUID_OPTIONS bit 3 (ArduCopter mode.h ModeGuided::Option::SetAttitudeTarget_ThrustAsThrust)


class SimVehicle:
    """One simulated vehicle: its autopilot's logic, and its MAVLink endpoint (``link``, a
    :class:`MavlinkLink`); not its physics, which
    :class:`zenswarm.plant.mavlink.fleet.MavlinkFleet` integrates for all vehicles at once. Row
    ``index`` of the fleet."""

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
        self.counters: dict[str, int] = {}
        self.link = MavlinkLink(index, sysid, port, opts, boot, self.counters)
        self.conn = self.link.conn  # the link's pymavlink connection
        self.acks = self.link.acks  # (command, result) sent, latest last (bounded): the link's list
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

    # ------------------------------------------------------------------ helpers
    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def kind(self) -> str | None:
        return self.opts.mode_kind(self.custom_mode)

    @property
    def mode(self) -> str:
        """Readable current mode, e.g. ``OFFBOARD``."""
        return mode_name(self.opts.autopilot, self.custom_mode)

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
        """Drain the socket (bounded) and act on every message addressed to this autopilot
        (:meth:`MavlinkLink.receive`). q: (3,) m ENU; yaw: rad ENU."""
        for m in self.link.receive(now, cap):
            self._handle(m, now, q, yaw)

    def _ack(self, m: Any, result: int) -> None:
        self.link.ack(m, result)

    def _handle(self, m: Any, now: float, q: np.ndarray, yaw: float) -> None:
        mtype = m.get_type()
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
            self.link.serve_params(m, self.ap_params)  # the parameter protocol (zenswarm.plant.mavlink.params)
        elif mtype == "TIMESYNC":
            self.link.timesync(m, now)
        else:
            self._count("ignored")

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
                self.link.statustext(text)
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
        t = decode_attitude_target(m)
        if t is None:
            self._count("malformed")
            return
        if t.q_ned is not None:
            self.att_q = t.q_ned
        if t.rates_frd is not None:  # attitude ignored, body rates given: a rate setpoint
            if self.rates_frd is None:
                self.att_int = None  # integrate from the current attitude
            self.rates_frd = t.rates_frd
        elif t.q_ned is not None:
            self.rates_frd = None
        if t.thrust is not None:
            self.att_thrust = t.thrust
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
        t = decode_position_target(m)
        if isinstance(t, str):
            self._count(t)
            return
        pos_use, vel_use = t.pos_ned is not None, t.vel_ned is not None
        self.pos_use, self.vel_use = pos_use, vel_use
        self.pos_ned = t.pos_ned
        self.vel_ned = t.vel_ned if t.vel_ned is not None else np.zeros(3)
        self.yaw_ned = t.yaw_ned
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
        """The vehicle's position loop (:func:`zenswarm.plant.position_control.position_loop`) with
        its options' gains (``pos_kp``, ``pos_kd``, ``max_pos_err``) and the airframe's envelope."""
        p = self.params
        o = self.opts
        return position_loop(q, v, p_ref, v_ref, yaw, kp=np.asarray(o.pos_kp), kd=np.asarray(o.pos_kd), max_pos_err=o.max_pos_err,
                             mass=p.mass, g=p.g, max_tilt=p.max_tilt, max_thrust=p.max_thrust)  # fmt: skip

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

    # ------------------------------------------------------------------ send (the link encodes)
    def send_telemetry(self, now: float, p_ned: np.ndarray, v_ned: np.ndarray, rpy_ned: np.ndarray, w_frd: np.ndarray) -> None:
        """LOCAL_POSITION_NED, ATTITUDE, ... (:meth:`MavlinkLink.telemetry`): ``p_ned`` m about
        this vehicle's origin, ``v_ned`` m/s, ``rpy_ned`` rad, ``w_frd`` rad/s."""
        self.link.telemetry(now, p_ned, v_ned, rpy_ned, w_frd, self.origin, self.home_enu)

    def send_status_extra(self, now: float) -> None:
        """EXTENDED_SYS_STATE and HOME_POSITION (both autopilots stream them at low rate)."""
        self.link.status_extra(now, self.landed_state(), self.home_enu, self.origin)

    def send_requested(self, now: float) -> None:
        """The messages requested with MAV_CMD_REQUEST_MESSAGE since the last call."""
        pending, self._pending = self._pending, []
        self.link.requested(now, pending, self.home_enu, self.origin)

    def send_heartbeat(self, now: float) -> None:
        self.link.heartbeat(now, self.armed, self.kind() == OFFBOARD, self.custom_mode)

    def send_sys_status(self, now: float) -> None:
        self.link.sys_status(now, self.prearm_failure is not None)

    def close(self) -> None:
        self.link.close()

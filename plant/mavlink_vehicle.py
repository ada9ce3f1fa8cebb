"""Simulated quadrotors exposed as MAVLink vehicles over UDP: the subset of a PX4 multicopter
that the MAVLink bridge (:mod:`zenswarm.bridge.mavlink`) uses, so the whole chain agents -> bridge ->
MAVLink/UDP -> vehicles runs on one machine and in CI.

Each UAV i of the scenario is a vehicle with its own system id (default i) listening on its own
UDP port (``udpin:HOST:BASE_PORT + i - 1``; it answers whoever talks to it, as PX4 SITL's
offboard link does once a peer is known). Physics is :func:`zenswarm.plant.quadrotor.step` (eqs 1-5 with
the onboard attitude PID) for all UAVs at once, ``timing.physics_rate_hz`` sub-steps (1 kHz) in
chunks of ``timing.substeps`` (10) at ``timing.control_rate_hz`` (100 Hz) on the wall clock, plus
the scenario's disturbances and a flat ground at ``ground_z`` (vehicles spawn on it below their
scenario initial position).

Spoken (PX4 flavour by default; ``autopilot = "ardupilot"`` switches the mode numbers and the
heartbeat's autopilot to ArduCopter's):

* HEARTBEAT 1 Hz: MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, base_mode = CUSTOM_MODE_ENABLED
  (| SAFETY_ARMED), custom_mode = PX4 ``main << 16 | sub << 24``; SYS_STATUS 1 Hz;
* LOCAL_POSITION_NED and ATTITUDE at ``telemetry_hz`` (50 Hz), NED/FRD via :mod:`zenswarm.frames`;
* COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE (and the SET_MODE message),
  MAV_CMD_NAV_TAKEOFF (ArduPilot flavour), each answered with COMMAND_ACK; other commands get
  MAV_RESULT_UNSUPPORTED;
* SET_ATTITUDE_TARGET (quaternion + normalised thrust through :class:`zenswarm.frames.ThrustMap`)
  and SET_POSITION_TARGET_LOCAL_NED (position/velocity/yaw in MAV_FRAME_LOCAL_NED; the vehicle
  then runs its own PD position loop producing thrust and attitude).

Modes: OFFBOARD (PX4 main 6; ArduCopter GUIDED 4 / GUIDED_NOGPS 20) follows the setpoints; it is
refused (MAV_RESULT_TEMPORARILY_REJECTED) unless a setpoint arrived in the last
``offboard_loss_s`` (PX4 flavour); HOLD (AUTO.LOITER, POSCTL, ALTCTL; LOITER, BRAKE, ...) holds
the position where it was entered; LAND (AUTO.LAND; LAND) descends at ``land_speed`` and disarms
0.5 s after touchdown. Offboard-loss failsafe: no setpoint for ``offboard_loss_s`` (1 s, as PX4's
default ``COM_OF_LOSS_T``) -> HOLD; still none ``failsafe_land_s`` later -> LAND. Arming in OFFBOARD needs
fresh setpoints; disarming needs the vehicle on the ground unless forced (param2 = 21196).

Test hooks (also what a faulty vehicle looks like): :meth:`MavlinkFleet.silence` drops all
traffic of one vehicle both ways for a while (physics goes on); ``mode_override`` makes a vehicle
accept mode requests but keep reporting (and flying) another mode.

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

from zenswarm import frames
from zenswarm.autopilot import (
    AP_COPTER_MODES,
    PX4_AUTO_SUB,
    PX4_HOLD,
    PX4_LAND,
    PX4_MAIN,
    PX4_OFFBOARD,
    load_mavutil,
    mavlink_settings,
    mode_name,
    px4_custom_mode,
    px4_decode,
)
from zenswarm.params import QuadParams
from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.mavlink_params import ParamStore, ardupilot_params, px4_params
from zenswarm.plant.quadrotor import PlantState, initial_state, step

mavutil = load_mavutil()
mavlink = mavutil.mavlink

__all__ = ["VehicleOptions", "SimVehicle", "MavlinkFleet", "run_fleet"]

_FORCE_MAGIC = 21196  # MAV_CMD_COMPONENT_ARM_DISARM param2 that forces (dis)arming

# mode kinds
OFFBOARD, HOLD, LAND = "offboard", "hold", "land"


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
            }.get(int(custom_mode))
        main, sub = px4_decode(custom_mode)
        if main == PX4_MAIN["OFFBOARD"] and sub == 0:
            return OFFBOARD
        if main in (PX4_MAIN["POSCTL"], PX4_MAIN["ALTCTL"]) and sub == 0:
            return HOLD
        if main == PX4_MAIN["AUTO"]:
            return {PX4_AUTO_SUB["LOITER"]: HOLD, PX4_AUTO_SUB["LAND"]: LAND}.get(sub)
        return None


class SimVehicle:
    """One simulated vehicle: its MAVLink endpoint and its autopilot's logic (not its physics,
    which :class:`MavlinkFleet` integrates for all vehicles at once). Row ``index`` of the fleet."""

    def __init__(self, index: int, sysid: int, port: int, opts: VehicleOptions, params: QuadParams, boot: float) -> None:
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
        self.conn = mavutil.mavlink_connection(
            f"udpin:{opts.host}:{port}", source_system=sysid, source_component=mavlink.MAV_COMP_ID_AUTOPILOT1, udp_timeout=5
        )
        self.armed = False
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
        self.peer_seen = False
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
            self.conn.mav.command_ack_send(
                m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()
            )

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
        else:
            self._count("ignored")

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
        elif m.command == mavlink.MAV_CMD_NAV_TAKEOFF and self.opts.autopilot == "ardupilot":
            self._ack(m, self._cmd_takeoff(p[6], now, q))
        else:
            self._count("unsupported_commands")
            self._ack(m, mavlink.MAV_RESULT_UNSUPPORTED)

    def _cmd_set_mode(self, p: tuple[float, ...], now: float, q: np.ndarray, yaw: float) -> int:
        """MAV_CMD_DO_SET_MODE (params: base mode with CUSTOM_MODE_ENABLED, custom (main) mode,
        PX4 sub mode); the MAV_RESULT."""
        if not (math.isfinite(p[0]) and int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) or not all(
            math.isfinite(x) for x in p[1:3]
        ):
            return mavlink.MAV_RESULT_UNSUPPORTED
        if self.opts.autopilot == "ardupilot":
            cm = int(p[1])
        else:
            cm = px4_custom_mode(int(p[1]), int(p[2]))
        return self._set_mode(cm, now, q, yaw)

    def _cmd_takeoff(self, alt: float, now: float, q: np.ndarray) -> int:
        """ArduPilot MAV_CMD_NAV_TAKEOFF to ``alt`` m above the ground (armed, in GUIDED); the
        MAV_RESULT."""
        if not (self.armed and self.kind() == OFFBOARD and math.isfinite(alt) and alt > 0):
            return mavlink.MAV_RESULT_DENIED
        self.pos_ned = frames.enu_to_ned([q[0], q[1], self.opts.ground_z + alt])
        self.vel_ned = np.zeros(3)
        self.pos_use, self.vel_use, self.yaw_ned = True, True, None
        self.sp_kind = "position"
        self.last_sp = now
        return mavlink.MAV_RESULT_ACCEPTED

    def _arm(self, arm: bool, force: bool, now: float, q: np.ndarray, yaw: float) -> int:
        if arm:
            if self.armed:
                return mavlink.MAV_RESULT_ACCEPTED
            k = self.kind()
            if k == LAND or k is None:
                return mavlink.MAV_RESULT_DENIED
            if k == OFFBOARD and not self._setpoint_fresh(now) and self.opts.autopilot == "px4" and not force:
                return mavlink.MAV_RESULT_TEMPORARILY_REJECTED
            self.armed = True
            self.hold_enu = q.copy()
            self.hold_yaw = float(yaw)
            self._count("arm_accepted")
            return mavlink.MAV_RESULT_ACCEPTED
        if not self.armed:
            return mavlink.MAV_RESULT_ACCEPTED
        if not (self.on_ground or force):
            return mavlink.MAV_RESULT_DENIED  # PX4 refuses to disarm in flight unless forced
        self.armed = False
        self._count("disarmed")
        return mavlink.MAV_RESULT_ACCEPTED

    def _set_mode(self, custom_mode: int, now: float, q: np.ndarray, yaw: float) -> int:
        k = self.opts.mode_kind(custom_mode)
        if k is None:
            return mavlink.MAV_RESULT_UNSUPPORTED
        if k == OFFBOARD and self.opts.autopilot == "px4" and not self._setpoint_fresh(now):
            self._count("offboard_refused")
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # PX4: no setpoint stream, no OFFBOARD
        if self.mode_override is None:
            self._enter(custom_mode, q, yaw)
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
        if not mask & mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE:
            self.att_thrust = min(max(float(m.thrust), 0.0), 1.0)
        self.sp_kind = "attitude"
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
        self.last_sp = now
        self._count("setpoints")

    # ------------------------------------------------------------------ autopilot
    def update(self, now: float, q: np.ndarray, v: np.ndarray, rpy: np.ndarray) -> tuple[float, np.ndarray]:
        """Mode logic (failsafe, auto-disarm) and this period's command to the onboard attitude
        controller: (thrust F, N; attitude setpoint [phi, theta, psi], rad, ENU)."""
        k = self._mode_logic(now, q, rpy)
        if not self.armed:
            return 0.0, np.array([0.0, 0.0, rpy[2]])
        if k == OFFBOARD and self.sp_kind == "attitude":
            return float(self.tmap.to_newtons(self.att_thrust)), frames.quat_ned_to_attitude(self.att_q)
        if k == OFFBOARD and self.sp_kind == "position":
            p_ref = frames.ned_to_enu(self.pos_ned) if self.pos_ned is not None else None
            yaw = rpy[2] if self.yaw_ned is None else float(frames.euler_ned_to_enu([0.0, 0.0, self.yaw_ned])[2])
            return self._pd(q, v, p_ref, frames.ned_to_enu(self.vel_ned), yaw)
        if self.hold_enu is None:
            self.hold_enu, self.hold_yaw = q.copy(), float(rpy[2])
        if k == LAND:
            p_ref = np.array([self.hold_enu[0], self.hold_enu[1], math.nan])
            return self._pd(q, v, p_ref, np.array([0.0, 0.0, -self.land_speed]), self.hold_yaw)
        return self._pd(q, v, self.hold_enu, np.zeros(3), self.hold_yaw)  # HOLD (and unknown modes)

    def _mode_logic(self, now: float, q: np.ndarray, rpy: np.ndarray) -> str | None:
        """The autopilot's own mode changes this period (forced mode, offboard-loss failsafe:
        hold then land, auto-disarm after landing); the mode kind it flies in."""
        if self.mode_override is not None and self.custom_mode != self.mode_override:
            self._enter(self.mode_override, q, rpy[2])
        k = self.kind()
        since = now - self.last_sp
        if k == OFFBOARD and since > self.loss_s:
            self._enter(self.opts.modes["hold"], q, rpy[2])
            self.failsafe = True  # offboard loss: hold, then land
            self._count("failsafe_hold")
            k = HOLD
        elif self.failsafe and k == HOLD and self.armed and since > self.loss_s + self.opts.failsafe_land_s:
            self._enter(self.opts.modes["land"], q, rpy[2])
            self._count("failsafe_land")
            k = LAND
        if k == LAND and self.armed and self.on_ground and now - self.ground_since >= self.disarm_after_land_s:
            self.armed = False  # landed: auto-disarm (PX4 COM_DISARM_LAND)
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
        self.telemetry_sent += 1

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
        # load 0.1 %, battery 4.2 V (1S), current and remaining unknown (-1)
        self.conn.mav.sys_status_send(sensors, sensors, sensors, 100, 4200, -1, -1, 0, 0, 0, 0, 0, 0)

    def close(self) -> None:
        try:
            self.conn.close()
        except Exception:  # noqa: BLE001
            pass


class MavlinkFleet:
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
                self.vehicles.append(SimVehicle(i, int(ids[i]), int(base_port) + i, self.opts, params, self.boot))
        except Exception:
            self.close()
            raise
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
            opts = VehicleOptions(
                autopilot="ardupilot" if ms.autopilot == "ardupilot" else "px4",
                telemetry_hz=ms.telemetry_hz,
                offboard_loss_s=ms.offboard_loss_s,
                failsafe_land_s=ms.failsafe_land_s,
                ground_z=ms.ground_z,
                hover_throttle=ms.hover_throttle,
                host=ms.host,
            )
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
                p_ned = frames.enu_to_ned(st.q)
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
        from zenswarm.runtime import WallClock

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

    def start(self) -> MavlinkFleet:
        """Run the loop in a daemon thread."""
        if self._thread is not None:
            raise RuntimeError("fleet already started")

        def target() -> None:
            try:
                self.run(self._stop)
            except BaseException as e:  # noqa: BLE001 - reported through .error
                self.error = e

        self._thread = threading.Thread(target=target, name="mavlink-fleet", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self.close()

    def close(self) -> None:
        for veh in self.vehicles:
            veh.close()

    def __enter__(self) -> MavlinkFleet:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

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
) -> int:
    """Run the fleet of scenario ``sc`` in the calling thread until SIGTERM/SIGINT (or
    ``duration`` s). ``base_port``: vehicle i listens on UDP base_port + i - 1 (None: the
    scenario's ``mavlink.base_port``); ``autopilot`` (``px4`` or ``ardupilot``) and
    ``telemetry_hz`` override the scenario's vehicle options. The command line (``zenswarm
    mavlink-vehicle``, ``zenswarm plant --mavlink``) is parsed in :mod:`zenswarm.compose.roles`."""
    fleet = MavlinkFleet.from_scenario(sc, base_port=base_port)
    if autopilot or telemetry_hz:
        opts = fleet.opts
        fleet.close()
        opts = replace(
            opts,
            autopilot=autopilot or opts.autopilot,
            telemetry_hz=telemetry_hz or opts.telemetry_hz,
        )
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
        why = fleet.run(stop, duration)
        print(f"mavlink-vehicle: stopped ({why}); overruns {fleet.overruns}; " + str(fleet.status()), flush=True)
    finally:
        fleet.close()
    return 0

"""One simulated Crazyflie's firmware (:mod:`zenswarm.plant.crazyflie_vehicle` says what it
answers): its UDP socket and the CRTP services on it (link, platform, memory, localization, and
the log and parameter services it owns: :mod:`zenswarm.plant.crazyflie.log`,
:mod:`zenswarm.plant.crazyflie.params`), the commander (setpoint priorities, the RPYT, generic
and high-level commanders), the supervisor's state machine and the commander watchdog, the
estimator (external positions), and the position controller
(:func:`zenswarm.plant.position_control.position_loop`). It does not move: the fleet
(:mod:`zenswarm.plant.crazyflie.fleet`) integrates the physics and asks :meth:`SimCrazyflie.control`
for the thrust and attitude to fly.

Frames and units: positions and velocities in the positioning system's frame, the swarm's ENU
(m, m/s); the plant's attitude in rad (ENU, ZYX); the wire's in degrees in the firmware's legacy
frame where pitch is inverted (:mod:`zenswarm.vehicle.crazyflie` has every sign); thrust commands
0..65535, thrust in N; times s (monotonic).
"""

from __future__ import annotations

import math
import socket
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.plant.crazyflie.crtp import (
    BIT_CAN_BE_ARMED,
    BIT_CAN_FLY,
    BIT_HL_ACTIVE,
    BIT_HL_DISABLED,
    BIT_IS_ARMED,
    BIT_IS_FLYING,
    BIT_IS_LOCKED,
    CRTP_PROTOCOL_VERSION,
    LOC_EXT_POSE,
    PORT_COMMANDER,
    PORT_GENERIC,
    PORT_HL,
    PORT_LINK,
    PORT_LOCALIZATION,
    PORT_LOG,
    PORT_MEM,
    PORT_PARAM,
    PORT_PLATFORM,
    PORT_SUPERVISOR,
    header,
)
from zenswarm.plant.crazyflie.log import LOG_VARS, LogService
from zenswarm.plant.crazyflie.params import ParamService
from zenswarm.plant.crazyflie.planner import HlPlan
from zenswarm.plant.position_control import position_loop
from zenswarm.vehicle import crazyflie as cfu
from zenswarm.vehicle.params import QuadParams

FIRMWARE_NAME = "zenswarm-sim"
WDT_STABILIZE_S, WDT_SHUTDOWN_S = 0.5, 2.0  # supervisor.c COMMANDER_WDT_TIMEOUT_*
IS_FLYING_HYSTERESIS_S = 2.0  # supervisor.c
LANDING_TIMEOUT_S, PREFLIGHT_TIMEOUT_S = 3.0, 30.0  # platform_defaults.h
ESTIMATOR_DRIFT_M_S = np.array([0.02, 0.02, 0.0])
"""The simulated estimator's velocity bias, m/s, once it follows external positions (:meth:`SimCrazyflie.estimate`)."""
PRIORITY_DISABLE, PRIORITY_LOWEST, PRIORITY_HIGHLEVEL, PRIORITY_CRTP = 0, 1, 1, 2  # commander.h
_KP, _KD = np.array([6.0, 6.0, 8.0]), np.array([4.0, 4.0, 5.0])  # the position controller's gains, 1/s^2 and 1/s


class SimCrazyflie:
    """One simulated Crazyflie: its UDP socket, CRTP services, commander and supervisor. The
    fleet owns the physics; :meth:`control` turns the latest setpoint into the thrust (N) and
    attitude (rad) the plant model flies."""

    def __init__(self, index: int, host: str, port: int, params: QuadParams, boot: float, sock: socket.socket | None = None) -> None:
        self.index = index
        self.port = port
        self.params = params
        self.boot = boot
        if sock is None:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind((host, port))
            except OSError as e:
                sock.close()
                raise ScenarioError("--base-port", f"UDP {host}:{port} (vehicle {index + 1}) cannot be bound: {e.strerror or e}") from None
            sock.setblocking(False)
        self.sock = sock
        self.peer: tuple[str, int] | None = None
        self.muted_until = 0.0
        self.counters: dict[str, int] = {}
        self.param_service = ParamService(self._count)
        self.param_values = self.param_service.values  # the same dict: what the firmware follows
        self.param_names = self.param_service.names
        self.log_service = LogService()
        self.log_index = {name: k for k, (name, _) in enumerate(LOG_VARS)}
        self.blocks = self.log_service.blocks  # the same dict
        # commander
        self.priority = PRIORITY_DISABLE
        self.sp_time = -math.inf  # monotonic s of the last setpoint the commander took
        self.sp_kind = "none"  # none, rpyt, stop, position, velocity, hl
        self.sp_rpyt = (0.0, 0.0, 0.0, 0)  # roll deg, pitch deg (wire), yaw deg or deg/s (wire), thrust cmd
        self.sp_pos = np.zeros(3)
        self.sp_vel = np.zeros(3)
        self.sp_yaw = 0.0  # rad
        self.thrust_locked = True
        self.yaw_des = 0.0  # rad: the attitude controller's yaw setpoint (integrated in RATE mode)
        # high-level commander
        self.hl = HlPlan()
        self.group_mask = 0
        # supervisor
        self.sup = "preflight"  # preflight, armed, flying, level_out, landed, locked
        self.sup_since = boot
        self.armed = False
        self.emergency = False
        self.last_thrust_tick = -math.inf  # when a motor last ran above idle
        self.motor_cmd = 0  # the thrust command driving the motors (0..65535)
        self.last_thrust_n = 0.0
        self.level_thrust = 0  # the thrust kept while levelling out
        self.flight_s = 0.0
        self.vbat = 4.15
        # estimator (external position)
        self.radio_id = (index + 1) & 0xFF  # the radio address's last byte (EXT_POSITION_PACKED's id)
        self.extpos_q: np.ndarray | None = None
        self.extpos_t = 0.0

    # ------------------------------------------------------------------ helpers
    def _count(self, name: str, k: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + k

    def ms(self, now: float) -> int:
        return int((now - self.boot) * 1000.0)

    def send(self, port: int, channel: int, data: bytes, now: float) -> None:
        if self.peer is None or now < self.muted_until:
            return
        try:
            self.sock.sendto(bytes([header(port, channel)]) + data[:30], self.peer)
            self._count("tx")
        except OSError:
            self._count("tx_errors")

    def info_bits(self, now: float) -> int:
        b = 0
        if self.sup == "preflight":
            b |= 1 << BIT_CAN_BE_ARMED
        if self.armed:
            b |= 1 << BIT_IS_ARMED
        if self.sup in ("armed", "flying", "level_out", "landed"):
            b |= 1 << BIT_CAN_FLY
        if self.sup in ("flying", "level_out"):
            b |= 1 << BIT_IS_FLYING
        if self.sup == "locked":
            b |= 1 << BIT_IS_LOCKED
        if self.hl.state in ("flying", "landing"):
            b |= 1 << BIT_HL_ACTIVE
        if self.hl.state == "idle":
            b |= 1 << BIT_HL_DISABLED
        return b

    def _set_sup(self, state: str, now: float) -> None:
        if state != self.sup:
            self.sup = state
            self.sup_since = now
            self._count(f"supervisor_{state}")
            if state not in ("armed", "flying", "level_out", "landed"):
                self.armed = False

    def _take_setpoint(self, priority: int, now: float) -> bool:
        """``commanderSetSetpoint``: a setpoint of at least the active priority is taken (its
        timestamp feeds the watchdog); one above the high-level commander's stops its planner,
        which forgets its state (``commander.c``)."""
        if priority < self.priority:
            if priority > PRIORITY_HIGHLEVEL:
                self._count("setpoints_ignored")
            return False
        self.priority = priority
        self.sp_time = now
        if priority > PRIORITY_HIGHLEVEL and self.hl.state != "idle":
            self.hl.state = "idle"
            self._count("hl_stopped_by_setpoint")
        return True

    # ------------------------------------------------------------------ receive
    def receive(self, now: float, state_q: np.ndarray, state_rpy: np.ndarray, cap: int = 500) -> None:
        for _ in range(cap):
            try:
                data, addr = self.sock.recvfrom(64)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self._count("rx_errors")
                return
            if now < self.muted_until:
                self._count("rx_muted")
                continue
            self.peer = addr
            self._count("rx")
            if not data:
                continue
            try:
                self.handle(data[0], data[1:], now, state_q, state_rpy)
            except (struct.error, IndexError, ValueError, UnicodeDecodeError):
                self._count("rx_malformed")

    def handle(self, header: int, d: bytes, now: float, q: np.ndarray, rpy: np.ndarray) -> None:
        """One CRTP packet (header byte, payload) from the client."""
        if header == 0xFF:  # the UDP driver's scan probe (a null packet)
            self.send(PORT_LINK, 3, b"", now)
            return
        port, ch = header >> 4, header & 0x3
        if port == PORT_LINK:
            self._link(ch, d, now)
        elif port == PORT_PLATFORM:
            self._platform(ch, d, now)
        elif port == PORT_LOG:
            self._log(ch, d, now)
        elif port == PORT_PARAM:
            self._param(ch, d, now)
        elif port == PORT_MEM:
            if ch == 0 and d[:1] == b"\x01":  # CMD_INFO_NBR: no memories
                self.send(PORT_MEM, 0, b"\x01\x00", now)
        elif port == PORT_SUPERVISOR:
            self._supervisor(ch, d, now)
        elif port == PORT_COMMANDER and ch == 0:
            self._rpyt(d, now)
        elif port == PORT_GENERIC:
            self._generic(ch, d, now, rpy)
        elif port == PORT_HL and ch == 0:
            self._high_level(d, now, q, rpy)
        elif port == PORT_LOCALIZATION:
            self._localization(ch, d, now)
        else:
            self._count("rx_unhandled")

    # ---- localization (crtp_localization_service.c)
    def _localization(self, ch: int, d: bytes, now: float) -> None:
        """Port 6: channel 0 EXT_POSITION ``<fff`` (x, y, z m); channel 1 (generic) type 8 EXT_POSE
        ``<B7f`` (x, y, z m, qx, qy, qz, qw: the position is taken, the quaternion ignored);
        channel 2 EXT_POSITION_PACKED, up to 4 items ``<Bhhh`` (id, x, y, z mm), the item whose id
        is this vehicle's (the radio address's last byte; here the vehicle's number i) taken.
        Anything else on the port is counted and ignored."""
        if ch == 0:
            self.feed_position(struct.unpack_from("<fff", d), now)
        elif ch == 1 and d[:1] == bytes([LOC_EXT_POSE]):
            self.feed_position(struct.unpack_from("<fff", d, 1), now)
        elif ch == 2:
            for k in range(0, len(d) - 6, 7):
                ident, x, y, z = struct.unpack_from("<Bhhh", d, k)
                if ident == self.radio_id:
                    self.feed_position((x / 1000.0, y / 1000.0, z / 1000.0), now)
        else:
            self._count("localization_ignored")

    def feed_position(self, xyz: Any, now: float) -> None:
        """An external position measurement (m, the positioning system's frame): the estimator's
        position from now on (see :meth:`estimate`)."""
        p = np.array([float(c) for c in xyz])
        if not np.all(np.isfinite(p)):
            self._count("extpos_rejected")
            return
        self.extpos_q, self.extpos_t = p, now
        self._count("extpos")

    def estimate(self, now: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The estimator's position (m): the true one until an external position arrives; then the
        last measurement dead-reckoned on the velocity with a bias, ``p_ext + (v +
        ESTIMATOR_DRIFT_M_S) (now - t_ext)`` (the Kalman filter's prediction between measurements;
        the bias stands for what a real one drifts without them: 1 cm per half second)."""
        if self.extpos_q is None:
            return q
        return self.extpos_q + (v + ESTIMATOR_DRIFT_M_S) * (now - self.extpos_t)

    def _link(self, ch: int, d: bytes, now: float) -> None:
        if ch == 0:  # echo
            self.send(PORT_LINK, 0, d, now)
        elif ch == 1:  # source
            self.send(PORT_LINK, 1, b"Bitcraze Crazyflie".ljust(30, b"\0"), now)

    def _platform(self, ch: int, d: bytes, now: float) -> None:
        if ch == 1 and d[0] == 0:
            self.send(PORT_PLATFORM, 1, struct.pack("<Bi", 0, CRTP_PROTOCOL_VERSION), now)
        elif ch == 1 and d[0] == 1:
            self.send(PORT_PLATFORM, 1, b"\x01" + FIRMWARE_NAME.encode(), now)
        elif ch == 0 and d[0] == 1 and len(d) >= 2:  # legacy arming request
            self.request_arming(bool(d[1]), now)
        elif ch == 0 and d[0] == 2:
            self._recover(now)

    # ---- log and param (their services: zenswarm.plant.crazyflie.log, zenswarm.plant.crazyflie.params)
    def _log(self, ch: int, d: bytes, now: float) -> None:
        if ch == 0:
            reply = self.log_service.toc(d)
            if reply is not None:
                self.send(PORT_LOG, 0, reply, now)
        elif ch == 1:
            cmd = d[0]
            bid = d[1] if len(d) > 1 else 0
            self.send(PORT_LOG, 1, bytes([cmd, bid, self.log_service.control(cmd, bid, d, now)]), now)

    def send_logs(self, now: float, values: Callable[[int], float]) -> None:
        """Every running block whose period is due (:meth:`LogService.due`)."""
        for data in self.log_service.due(now, values, self.ms):
            self.send(PORT_LOG, 2, data, now)
            self._count("log_packets")

    def _param(self, ch: int, d: bytes, now: float) -> None:
        reply = self.param_service.request(ch, d)
        if reply is not None:
            self.send(PORT_PARAM, ch, reply, now)

    # ---- supervisor and arming
    def request_arming(self, do_arm: bool, now: float) -> bool:
        """``supervisorRequestArming``: arming only from pre-flight-checks-passed; disarming always."""
        if do_arm == self.armed:
            return True
        if do_arm:
            if self.sup != "preflight":
                self._count("arm_refused")
                return False
            self.armed = True
            self._set_sup("armed", now)
            self._count("arm_accepted")
            return True
        self.armed = False
        self._set_sup("preflight" if self.sup != "locked" else "locked", now)
        self._count("disarmed")
        return True

    def _recover(self, now: float) -> bool:
        return False  # crash recovery needs a crash; tumbling is not simulated

    def _supervisor(self, ch: int, d: bytes, now: float) -> None:
        cmd = d[0]
        if ch == 0:
            bits = self.info_bits(now)
            if cmd == 0x0C:
                self.send(PORT_SUPERVISOR, 0, struct.pack("<BH", cmd | 0x80, bits), now)
            elif 1 <= cmd <= 11:
                bit = {1: 0, 2: 1, 3: 2, 4: 3, 5: 4, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9, 11: 10}[cmd]
                self.send(PORT_SUPERVISOR, 0, bytes([cmd | 0x80, (bits >> bit) & 1]), now)
        elif ch == 1:
            if cmd == 0x01 and len(d) >= 2:
                ok = self.request_arming(bool(d[1]), now)
                self.send(PORT_SUPERVISOR, 1, bytes([cmd | 0x80, int(ok), int(self.armed)]), now)
            elif cmd == 0x02:
                ok = self._recover(now)
                self.send(PORT_SUPERVISOR, 1, bytes([cmd | 0x80, int(ok), 0]), now)
            elif cmd == 0x03:
                self.emergency = True
                self._count("emergency_stop")

    # ---- commanders
    def _rpyt(self, d: bytes, now: float) -> None:
        roll, pitch, yaw, thrust = struct.unpack_from("<fffH", d, 0)
        if not all(math.isfinite(x) for x in (roll, pitch, yaw)):
            self._count("rx_malformed")
            return
        if self.priority == PRIORITY_DISABLE:  # crtp_commander_rpyt.c: locked until a zero thrust
            self.thrust_locked = True
        if thrust == 0:
            self.thrust_locked = False
        if not self._take_setpoint(PRIORITY_CRTP, now):
            return
        cmd = 0 if (self.thrust_locked or thrust < cfu.MIN_THRUST) else min(int(thrust), cfu.MAX_THRUST)
        if self.thrust_locked and thrust:
            self._count("thrust_locked")
        self.sp_kind = "rpyt"
        self.sp_rpyt = (roll, pitch, yaw, cmd)
        self._count("setpoints_rpyt")

    def _generic(self, ch: int, d: bytes, now: float, rpy: np.ndarray) -> None:
        if ch == 1:  # meta: notify setpoint stop [0, remain valid ms]
            if d[0] == 0:
                remain = struct.unpack_from("<I", d, 1)[0] / 1000.0 if len(d) >= 5 else 0.0
                self.priority = PRIORITY_LOWEST  # commanderRelaxPriority
                self.sp_time = min(self.sp_time, now - WDT_SHUTDOWN_S + remain)
                self._count("notify_setpoint_stop")
            return
        typ = d[0]
        if typ == 0:  # STOP
            if self._take_setpoint(PRIORITY_CRTP, now):
                self.sp_kind = "stop"
        elif typ == 7:  # POSITION x y z yaw(deg)
            x, y, z, yaw = struct.unpack_from("<ffff", d, 1)
            if self._take_setpoint(PRIORITY_CRTP, now):
                self.sp_kind, self.sp_pos, self.sp_vel, self.sp_yaw = "position", np.array([x, y, z]), np.zeros(3), math.radians(yaw)
        elif typ == 8:  # VELOCITY_WORLD vx vy vz yawrate(deg/s)
            vx, vy, vz, yr = struct.unpack_from("<ffff", d, 1)
            if self._take_setpoint(PRIORITY_CRTP, now):
                self.sp_kind, self.sp_vel = "velocity", np.array([vx, vy, vz])
                self.sp_rpyt = (0.0, 0.0, yr, 0)
        else:
            self._count("generic_unsupported")

    def _high_level(self, d: bytes, now: float, q: np.ndarray, rpy: np.ndarray) -> None:
        cmd = d[0]
        if cmd == 0:
            self.group_mask = d[1]
            return
        mask = d[1]
        if mask != 0 and not (mask & self.group_mask):
            return
        if cmd == 3:  # stop: motors off
            self.hl.state = "idle"
            self._count("hl_stop")
        elif cmd in (7, 8):  # takeoff 2 / land 2: height, yaw, use current yaw, duration
            height, yaw, use_current, duration = struct.unpack_from("<ff?f", d, 2)
            if not (math.isfinite(height) and math.isfinite(yaw) and math.isfinite(duration) and duration > 0):
                self._count("hl_rejected")
                return
            if (cmd == 7 and self.hl.state != "idle") or (cmd == 8 and self.hl.state == "landing"):
                self._count("hl_rejected")  # planner.c: takeoff only from idle, land unless landing
                return
            start = self._hl_start(q, now)
            yaw1 = float(rpy[2]) if use_current else yaw
            self.hl = HlPlan("flying" if cmd == 7 else "landing", start, np.array([start[0], start[1], height]),
                             float(rpy[2]), yaw1, now, duration)  # fmt: skip
            self._count("hl_takeoff" if cmd == 7 else "hl_land")
        elif cmd == 12:  # go to 2: relative, linear, x y z yaw duration
            relative, _linear = d[2], d[3]
            x, y, z, yaw, duration = struct.unpack_from("<fffff", d, 4)
            if self.hl.state != "flying" or not duration > 0:
                self._count("hl_rejected")
                return
            start = self._hl_start(q, now)
            goal = np.array([x, y, z]) + (start if relative else 0.0)
            self.hl = HlPlan("flying", start, goal, self.hl.sample(now)[2], yaw, now, duration)
            self._count("hl_goto")
        else:
            self._count("hl_unsupported")

    def _hl_start(self, q: np.ndarray, now: float) -> np.ndarray:
        """Where a new segment starts: the current plan's position when it flies, else the vehicle's."""
        if self.hl.state in ("flying", "landing"):
            return self.hl.sample(now)[0].copy()
        return np.array(q, dtype=float)

    # ------------------------------------------------------------------ control
    def control(self, now: float, dt: float, q: np.ndarray, v: np.ndarray, rpy: np.ndarray) -> tuple[float, np.ndarray]:
        """The supervisor, the commanders and the watchdog for one loop period: the thrust (N) and
        attitude (phi, theta, psi rad) the plant model flies."""
        # the high-level commander's setpoint enters the commander at its priority every tick: its
        # trajectory, or the null setpoint (motors off) when its planner is stopped
        if self.hl.state == "landing" and self.hl.sample(now)[3]:
            self.hl.state = "idle"  # a finished landing stops the planner (and the motors)
            self._count("hl_landed")
        if self._take_setpoint(PRIORITY_HIGHLEVEL, now):
            self.sp_kind = "hl"
        age = now - self.sp_time
        self._supervise(now, age)
        if self.param_values["kalman.resetEstimation"]:
            self.param_values["kalman.resetEstimation"] = 0.0
        can_fly = self.sup in ("armed", "flying", "level_out", "landed")
        if self.sup == "level_out":  # supervisorOverrideSetpoint: level, yaw rate 0, thrust kept
            thrust_cmd, att = self.level_thrust, np.array([0.0, 0.0, self.yaw_des])
        elif age > WDT_SHUTDOWN_S or self.sp_kind in ("none", "stop") or not can_fly:
            thrust_cmd, att = 0, np.array([0.0, 0.0, self.yaw_des])
        else:
            thrust_cmd, att = self._setpoint(now, dt, q, v)
        if not can_fly:
            thrust_cmd = 0
        if self.sup in ("flying", "armed", "landed"):
            self.level_thrust = thrust_cmd
        if thrust_cmd > 0:
            self.last_thrust_tick = now
            self.flight_s += dt
        self.motor_cmd = thrust_cmd
        self.last_thrust_n = cfu.command_to_thrust(thrust_cmd) if thrust_cmd else 0.0
        self.vbat = max(3.0, 4.15 - 0.0015 * self.flight_s)
        return self.last_thrust_n, att

    def _supervise(self, now: float, age: float) -> None:
        """The supervisor's state machine (``supervisor_state_machine.c``, the part a flight meets);
        ``age``: s since the commander's last setpoint (the watchdog)."""
        if (self.emergency or self.param_values["stabilizer.stop"]) and self.sup in ("flying", "level_out", "armed", "landed"):
            self._set_sup("locked", now)
        if self.sup == "flying" and age > WDT_STABILIZE_S:
            self._set_sup("level_out", now)
        if self.sup == "level_out":
            if age > WDT_SHUTDOWN_S:
                self._set_sup("locked", now)  # ExceptFreeFall -> Locked: motors off, reboot needed
            elif age <= WDT_STABILIZE_S:
                self._set_sup("flying", now)
        flying_recently = now - self.last_thrust_tick < IS_FLYING_HYSTERESIS_S
        if self.sup == "armed" and flying_recently:
            self._set_sup("flying", now)
        elif self.sup == "armed" and now - self.sup_since > PREFLIGHT_TIMEOUT_S:
            self._set_sup("preflight", now)
            self._count("preflight_timeout")
        elif self.sup == "flying" and not flying_recently:
            self._set_sup("landed", now)
        elif self.sup == "landed":
            if flying_recently:
                self._set_sup("flying", now)
            elif now - self.sup_since > LANDING_TIMEOUT_S or not self.armed:
                self._set_sup("preflight", now)  # Reset -> disarmed

    def _setpoint(self, now: float, dt: float, q: np.ndarray, v: np.ndarray) -> tuple[int, np.ndarray]:
        """The thrust command and attitude of the commander's setpoint (rpyt, high-level, position, velocity)."""
        if self.sp_kind == "rpyt":
            roll_d, pitch_d, yaw_w, cmd = self.sp_rpyt
            phi, theta, rate = cfu.rpyt_from_wire(roll_d, pitch_d, yaw_w)
            if self.param_values["flightmode.stabModeYaw"]:
                self.yaw_des = math.radians(yaw_w)  # ANGLE: absolute yaw, not inverted
            else:
                self.yaw_des += rate * dt  # controller_pid: attitudeDesired.yaw += rate * dt
            return int(cmd), np.array([phi, theta, self.yaw_des])
        if self.sp_kind == "hl":
            if self.hl.state == "idle":
                return 0, np.array([0.0, 0.0, self.yaw_des])
            p_ref, v_ref, yaw_ref, _ = self.hl.sample(now)
        elif self.sp_kind == "position":
            p_ref, v_ref, yaw_ref = self.sp_pos, np.zeros(3), self.sp_yaw
        else:  # velocity; VELOCITY_WORLD's yaw rate is not inverted
            p_ref, v_ref = np.full(3, np.nan), self.sp_vel
            yaw_ref = self.yaw_des + math.radians(self.sp_rpyt[2]) * dt
        f_n, att = self._position_loop(q, v, p_ref, v_ref, yaw_ref)
        self.yaw_des = float(att[2])
        return cfu.thrust_to_command(f_n)[0], att

    def _position_loop(self, q: np.ndarray, v: np.ndarray, p_ref: np.ndarray, v_ref: np.ndarray, yaw: float) -> tuple[float, np.ndarray]:
        """The position controller (:func:`zenswarm.plant.position_control.position_loop`): gains
        Kp (6, 6, 8) 1/s^2, Kd (4, 4, 5) 1/s, the position error clipped to 0.5 m, within the
        Crazyflie's thrust (:func:`zenswarm.vehicle.crazyflie.max_thrust_n`)."""
        p = self.params
        return position_loop(q, v, p_ref, v_ref, yaw, kp=_KP, kd=_KD, max_pos_err=0.5, mass=p.mass, g=p.g, max_tilt=p.max_tilt,
                             max_thrust=cfu.max_thrust_n())  # fmt: skip

    def battery_level(self) -> float:
        """pm.batteryLevel, %: linear between 3.0 V (0 %) and 4.2 V (100 %)."""
        return min(100.0, max(0.0, (self.vbat - 3.0) / 1.2 * 100.0))

    def close(self) -> None:
        self.sock.close()

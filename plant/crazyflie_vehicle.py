"""Simulated Crazyflie 2.1 quadrotors that speak CRTP over UDP as cflib's ``udp://`` driver
expects (the transport of Bitcraze's software-in-the-loop firmware): one CRTP packet per UDP
datagram, byte 0 the header ``port << 4 | 0x0C | channel``, then up to 30 bytes of payload.
Vehicle i of the scenario listens on ``udp://HOST:BASE_PORT + i - 1`` (cflib's SITL base port
is 19850) and answers whoever talks to it. Physics is :func:`zenswarm.plant.quadrotor.step`
(eqs 1-5 with the onboard attitude PID) for all vehicles at once, as in
:mod:`zenswarm.plant.mavlink_vehicle`, with a flat ground at z = 0 (vehicles spawn on it below
their initial positions) and positions in the swarm's ENU frame (a positioning system set up
so).

What it answers, from bitcraze's crazyflie-firmware (``src/modules/src``; CRTP protocol version
12, ``crtp.h``), so that unmodified cflib connects, logs, sets parameters and flies it:

* link control (port 15): echo (channel 0), source (1: "Bitcraze Crazyflie"), sink (2), and the
  UDP driver's scan probe (a null packet, 0xFF) answered with an empty link packet
  (``crtpservice.c``);
* platform (port 13): the protocol version (channel 1, command 0) and firmware name (command 1);
  the legacy arming request (channel 0, command 1) (``platformservice.c``);
* log (port 5): the TOC v2 (channel 0: info = count, CRC32, LOG_MAX_OPS, LOG_MAX_BLOCKS; items
  = id, type, group, name), block create/append v2, delete, start (period in 10 ms), stop,
  reset (channel 1, answers ``[cmd, id, errno]``: EEXIST, ENOMEM, E2BIG, ENOENT), data on
  channel 2 as ``[id, 24-bit ms timestamp, values]`` at each block's period (``log.c``);
* param (port 2): the TOC v2, read (channel 1, ``[id, status, value]``), write (channel 2,
  echoed), set by name (channel 3) (``param_logic.c``); read-only parameters refuse writes;
* memory (port 4): no memories (count 0), which ends cflib's memory scan;
* supervisor (port 9, protocol >= 12): the state bitfield (channel 0, ``0x0C``), arm/disarm,
  crash recovery, emergency stop (channel 1; answers ``[cmd | 0x80, success, armed]``)
  (``crtp_supervisor.c``); the state machine of ``supervisor_state_machine.c`` reduced to what a
  flight meets: pre-flight checks passed -> armed (ReadyToFly) -> flying (a motor above idle
  within 2 s) -> landed -> reset (disarmed after LANDING_TIMEOUT 3 s); armed but not flying for
  PREFLIGHT_TIMEOUT 30 s -> disarmed; the motors run only when armed;
* commander (port 3): the legacy RPYT setpoint ``<fffH`` (roll, pitch in degrees; yaw *rate* in
  deg/s, inverted; thrust 0..65535, below MIN_THRUST 1000 -> 0, clamped to MAX_THRUST 60000;
  thrust locked at 0 until a setpoint with thrust 0 arrives, ``crtp_commander_rpyt.c``); the
  firmware's attitude is in the legacy frame where pitch is inverted
  (:mod:`zenswarm.vehicle.crazyflie` has every sign); ``flightmode.stabModeYaw`` = 1 makes the
  yaw absolute;
* generic setpoint (port 7): STOP, POSITION (x, y, z m, yaw deg), VELOCITY_WORLD (m/s, yaw rate
  deg/s), and the meta command notify-setpoint-stop (``crtp_commander_generic.c``);
* high-level commander (port 8): set group mask, takeoff and land (v2: height, yaw, use current
  yaw, duration), go to (v2), stop; takeoff only from a stopped planner, land unless already
  landing, both from the vehicle's state when the planner is stopped; a finished landing stops
  the planner, and a stopped planner sends the null setpoint (motors off)
  (``crtp_commander_high_level.c``, ``planner.c``). Its setpoints have priority 1 and the CRTP
  setpoints 2: a CRTP setpoint stops the planner, and the high-level commander is heard again
  only after notify-setpoint-stop relaxes the priority (``commander.c``): the clean handover back
  is land (or take off), then notify-setpoint-stop;
* the commander watchdog (``supervisor.c``): a flying vehicle that has heard no setpoint for
  COMMANDER_WDT_TIMEOUT_STABILIZE (500 ms) levels out (roll = pitch = 0, yaw rate 0, thrust
  kept); after COMMANDER_WDT_TIMEOUT_SHUTDOWN (2 s) its motors stop and it is *locked* (a
  reboot is needed: :meth:`CrazyflieFleet.reboot`).

Log variables (names, types and units as the firmware's): ``stateEstimate.{x,y,z,vx,vy,vz}``
(m, m/s, float), ``stateEstimate.{roll,pitch,yaw}`` (deg, pitch inverted), ``gyro.{x,y,z}``
(deg/s, body), ``stabilizer.thrust``, ``motor.m1..m4`` (uint16), ``pm.vbat`` (V),
``pm.batteryLevel`` (%), ``pm.state``, ``radio.rssi``, ``supervisor.info``. Parameters: see
:data:`PARAMS`.

* localization (port 6): external position (channel 0 EXT_POSITION ``<fff``, the generic
  channel's EXT_POSE, channel 2 EXT_POSITION_PACKED for this vehicle's id = its number i)
  (``crtp_localization_service.c``). The estimator: the true state until the first external
  position; from then on the last measurement dead-reckoned on the velocity with a small bias
  (:data:`ESTIMATOR_DRIFT_M_S`), so a silent feed drifts. The logged ``stateEstimate.x/y/z``, the
  high-level commander and the position controller use that estimate (the motion is the
  plant's true one).

Not simulated: memories, trajectories in memory, tumble detection, the Kalman filter (the
estimate is the true state, or the external positions as above), the quaternion of EXT_POSE,
radio link statistics (the UDP driver has none), console text.

Test hooks: :meth:`CrazyflieFleet.silence` drops one vehicle's traffic both ways for a while
(physics goes on: a lost link), :meth:`CrazyflieFleet.status`.

``zenswarm crazyflie-vehicle SCENARIO --base-port P`` runs the fleet until SIGTERM/SIGINT; with
``--mocap --swarm S --connect EP`` it is also the motion-capture system: :class:`MocapFeeder`
publishes the true positions on ``swarm/S/mocap/<i>``.
"""

from __future__ import annotations

import errno
import math
import select
import signal
import socket
import struct
import threading
import time
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.plant.fleet import FleetThread
from zenswarm.plant.quadrotor import PlantState, initial_state, step
from zenswarm.vehicle import crazyflie as cfu
from zenswarm.vehicle.params import QuadParams

DEFAULT_BASE_PORT = 19850
"""cflib's UDP driver scans 19850..19859 for simulated Crazyflies."""
CRTP_PROTOCOL_VERSION = 12
FIRMWARE_NAME = "zenswarm-sim"

# CRTP ports (crtp.h)
PORT_CONSOLE, PORT_PARAM, PORT_COMMANDER, PORT_MEM, PORT_LOG = 0x0, 0x2, 0x3, 0x4, 0x5
PORT_LOCALIZATION, PORT_GENERIC, PORT_HL, PORT_SUPERVISOR, PORT_PLATFORM, PORT_LINK = 0x6, 0x7, 0x8, 0x9, 0xD, 0xF

LOG_MAX_OPS, LOG_MAX_BLOCKS = 128, 16  # log.c
LOG_MAX_PAYLOAD = 26  # 30 bytes - block id - 3-byte timestamp
WDT_STABILIZE_S, WDT_SHUTDOWN_S = 0.5, 2.0  # supervisor.c COMMANDER_WDT_TIMEOUT_*
IS_FLYING_HYSTERESIS_S = 2.0  # supervisor.c
LANDING_TIMEOUT_S, PREFLIGHT_TIMEOUT_S = 3.0, 30.0  # platform_defaults.h
LOC_EXT_POSE = 8  # crtp_localization_service.c, the generic channel's EXT_POSE
ESTIMATOR_DRIFT_M_S = np.array([0.02, 0.02, 0.0])
"""The simulated estimator's velocity bias, m/s, once it follows external positions (:meth:`SimCrazyflie.estimate`)."""
PRIORITY_DISABLE, PRIORITY_LOWEST, PRIORITY_HIGHLEVEL, PRIORITY_CRTP = 0, 1, 1, 2  # commander.h

# log types (log.h) -> struct code
LOG_TYPES = {1: "B", 2: "H", 3: "I", 4: "b", 5: "h", 6: "i", 7: "f", 8: "e"}
LOG_UINT8, LOG_UINT16, LOG_INT8, LOG_FLOAT = 1, 2, 4, 7
# param types (param.h): size bits 0-1, float 0x04, unsigned 0x08, read-only 0x40
PARAM_TYPES = {0x08: "B", 0x09: "H", 0x0A: "I", 0x00: "b", 0x01: "h", 0x02: "i", 0x06: "f"}
PARAM_UINT8, PARAM_UINT16, PARAM_UINT32, PARAM_FLOAT, PARAM_RONLY = 0x08, 0x09, 0x0A, 0x06, 0x40

# supervisor info bits (supervisor.c infoBitfield)
BIT_CAN_BE_ARMED, BIT_IS_ARMED, BIT_CAN_FLY, BIT_IS_FLYING, BIT_IS_LOCKED = 0, 1, 3, 4, 6
BIT_HL_ACTIVE, BIT_HL_FINISHED, BIT_HL_DISABLED = 8, 9, 10

PARAMS: dict[str, tuple[int, float]] = {
    "flightmode.stabModeYaw": (PARAM_UINT8, 0),  # 0 RATE (default), 1 ANGLE
    "commander.enHighLevel": (PARAM_UINT8, 1),
    "stabilizer.estimator": (PARAM_UINT8, 2),
    "stabilizer.controller": (PARAM_UINT8, 1),
    "stabilizer.stop": (PARAM_UINT8, 0),  # non-zero: motors off
    "kalman.resetEstimation": (PARAM_UINT8, 0),
    "crtpsrv.echoDelay": (PARAM_UINT16, 0),
    "hlCommander.vtoff": (PARAM_FLOAT, 0.5),
    "hlCommander.vland": (PARAM_FLOAT, 0.2),
    "pm.lowVoltage": (PARAM_FLOAT, 3.2),
    "firmware.revision0": (PARAM_UINT32 | PARAM_RONLY, 0x5A454E53),
}
"""The parameter TOC: name -> (type byte, default). Those the vehicle follows: ``flightmode.stabModeYaw``,
``stabilizer.stop``, ``kalman.resetEstimation``, ``crtpsrv.echoDelay``, ``pm.lowVoltage`` (pm.state)."""

LOG_VARS: list[tuple[str, int]] = [
    *[(f"stateEstimate.{a}", LOG_FLOAT) for a in ("x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw")],
    *[(f"gyro.{a}", LOG_FLOAT) for a in ("x", "y", "z")],
    ("stabilizer.roll", LOG_FLOAT), ("stabilizer.pitch", LOG_FLOAT), ("stabilizer.yaw", LOG_FLOAT),
    ("stabilizer.thrust", LOG_FLOAT),
    *[(f"motor.m{k}", LOG_UINT16) for k in (1, 2, 3, 4)],
    ("pm.vbat", LOG_FLOAT), ("pm.batteryLevel", LOG_UINT8), ("pm.state", LOG_INT8),
    ("radio.rssi", LOG_UINT8), ("supervisor.info", LOG_UINT16),
]  # fmt: skip
"""The log TOC: (group.name, log type)."""


def _toc_crc(entries: list[tuple[str, int]]) -> int:
    """The TOC's CRC32 (a cache key for cflib's TocCache): over every entry's type and name."""
    return zlib.crc32(b"".join(bytes([t]) + n.encode() + b"\0" for n, t in entries)) & 0xFFFFFFFF


def _toc_item(ident: int, name: str, typ: int) -> bytes:
    group, _, var = name.partition(".")
    return struct.pack("<BHB", 2, ident, typ) + group.encode() + b"\0" + var.encode() + b"\0"


def _header(port: int, channel: int) -> int:
    return ((port & 0xF) << 4) | 0x0C | (channel & 0x3)


@dataclass
class LogBlock:
    """One log block: its operations (storage type, fetch type, variable index) and period."""

    ops: list[tuple[int, int]] = field(default_factory=list)  # (fetch log type, variable index)
    period_s: float = 0.0
    running: bool = False
    next_due: float = 0.0
    sent: int = 0

    def size(self) -> int:
        return sum(struct.calcsize("<" + LOG_TYPES[t]) for t, _ in self.ops)


@dataclass
class HlPlan:
    """The high-level commander's plan: a minimum-jerk segment from ``p0`` to ``p1`` (m, ENU)
    and yaw ``yaw0`` -> ``yaw1`` (rad) over ``duration`` s from ``t0``; ``state`` idle, flying,
    landing (the planner's TRAJECTORY_STATE_*)."""

    state: str = "idle"
    p0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p1: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw0: float = 0.0
    yaw1: float = 0.0
    t0: float = 0.0
    duration: float = 1.0

    def sample(self, now: float) -> tuple[np.ndarray, np.ndarray, float, bool]:
        """Position, velocity, yaw at ``now`` and whether the segment is finished."""
        tau = min(max((now - self.t0) / self.duration, 0.0), 1.0)
        s = tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)
        ds = 30.0 * tau * tau * (1.0 - tau) ** 2 / self.duration
        d = self.p1 - self.p0
        dyaw = (self.yaw1 - self.yaw0 + math.pi) % (2 * math.pi) - math.pi
        return self.p0 + s * d, ds * d, self.yaw0 + s * dyaw, tau >= 1.0


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
        self.param_values = {name: float(v) for name, (_, v) in PARAMS.items()}
        self.param_names = list(PARAMS)
        self.log_index = {name: k for k, (name, _) in enumerate(LOG_VARS)}
        self.blocks: dict[int, LogBlock] = {}
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
            self.sock.sendto(bytes([_header(port, channel)]) + data[:30], self.peer)
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

    # ---- log
    def _log(self, ch: int, d: bytes, now: float) -> None:
        if ch == 0:
            cmd = d[0]
            if cmd == 3:  # info v2
                self.send(PORT_LOG, 0, struct.pack("<BHIBB", 3, len(LOG_VARS), _toc_crc(LOG_VARS), LOG_MAX_OPS, LOG_MAX_BLOCKS), now)
            elif cmd == 2:  # item v2
                ident = struct.unpack_from("<H", d, 1)[0]
                if ident < len(LOG_VARS):
                    self.send(PORT_LOG, 0, _toc_item(ident, *LOG_VARS[ident]), now)
        elif ch == 1:
            cmd = d[0]
            bid = d[1] if len(d) > 1 else 0
            self.send(PORT_LOG, 1, bytes([cmd, bid, self._log_control(cmd, bid, d, now)]), now)

    def _log_control(self, cmd: int, bid: int, d: bytes, now: float) -> int:
        """One log control command (``log.c``); the errno it answers (0: done)."""
        blk = self.blocks.get(bid)
        if cmd in (6, 7):  # create / append v2: (type byte, id u16)*
            return self._log_add(cmd, bid, d[2:])
        if cmd == 5:  # reset
            self.blocks.clear()
            return 0
        if cmd not in (2, 3, 4):
            return errno.ENOEXEC
        if blk is None:
            return errno.ENOENT
        if cmd == 2:  # delete
            del self.blocks[bid]
        elif cmd == 3:  # start, period in 10 ms
            blk.period_s = max(1, d[2] if len(d) > 2 else 1) * 0.01
            blk.running = True
            blk.next_due = now
        else:  # stop
            blk.running = False
        return 0

    def _log_add(self, cmd: int, bid: int, body: bytes) -> int:
        """Create (6) or append to (7) block ``bid`` the operations in ``body``; the errno."""
        if cmd == 6 and bid in self.blocks:
            return errno.EEXIST
        if cmd == 6 and len(self.blocks) >= LOG_MAX_BLOCKS:
            return errno.ENOMEM
        if cmd == 7 and bid not in self.blocks:
            return errno.ENOENT
        ops = []
        for k in range(0, len(body) - 2, 3):
            typ, ident = body[k], struct.unpack_from("<H", body, k + 1)[0]
            if ident >= len(LOG_VARS) or (typ & 0x0F) not in LOG_TYPES:
                return errno.ENOENT
            ops.append((typ & 0x0F, ident))
        blk = self.blocks.get(bid) or LogBlock()
        if sum(len(b.ops) for b in self.blocks.values()) + len(ops) > LOG_MAX_OPS:
            return errno.ENOMEM
        trial = LogBlock(ops=blk.ops + ops)
        if trial.size() > LOG_MAX_PAYLOAD:
            return errno.E2BIG
        blk.ops = trial.ops
        self.blocks[bid] = blk
        return 0

    def send_logs(self, now: float, values: Callable[[int], float]) -> None:
        """Every running block whose period is due: ``[id, ms timestamp (24 bit), values]``, the
        timestamp the time the block was due (the values are those of ``now``)."""
        for bid, blk in self.blocks.items():
            if not blk.running or now + 1e-4 < blk.next_due:
                continue
            # stamped when its period was due, as the firmware's periodic log timer stamps it: a
            # loop that ran late sends late, but never two stamps closer than a period (no burst)
            due = min(blk.next_due, now)
            blk.next_due += blk.period_s
            if blk.next_due < now:  # late by more than a period: skip the missed ones, stamp now
                blk.next_due = now + blk.period_s
                due = now
            out = bytearray([bid]) + struct.pack("<I", self.ms(due) & 0xFFFFFF)[:3]
            for typ, ident in blk.ops:
                code = LOG_TYPES[typ]
                v = values(ident)
                if code in "fe":
                    out += struct.pack("<" + code, v)
                else:
                    lo, hi = {"B": (0, 255), "b": (-128, 127), "H": (0, 65535), "h": (-32768, 32767)}.get(code, (-(2**31), 2**31 - 1))
                    out += struct.pack("<" + code, int(min(max(round(v), lo), hi)))
            self.send(PORT_LOG, 2, bytes(out), now)
            blk.sent += 1
            self._count("log_packets")

    # ---- param
    def _param_bytes(self, k: int) -> bytes:
        name = self.param_names[k]
        code = PARAM_TYPES[PARAMS[name][0] & ~PARAM_RONLY]
        v = self.param_values[name]
        return struct.pack("<" + code, v if code == "f" else int(v))

    def _param(self, ch: int, d: bytes, now: float) -> None:
        if ch == 0:
            cmd = d[0]
            if cmd == 3:
                entries = [(n, t) for n, (t, _) in PARAMS.items()]
                self.send(PORT_PARAM, 0, struct.pack("<BHI", 3, len(entries), _toc_crc(entries)), now)
            elif cmd == 2:
                ident = struct.unpack_from("<H", d, 1)[0]
                if ident < len(self.param_names):
                    name = self.param_names[ident]
                    self.send(PORT_PARAM, 0, _toc_item(ident, name, PARAMS[name][0]), now)
        elif ch == 1:  # read
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident >= len(self.param_names):
                self.send(PORT_PARAM, 1, struct.pack("<HB", ident, errno.ENOENT), now)
            else:
                self.send(PORT_PARAM, 1, struct.pack("<HB", ident, 0) + self._param_bytes(ident), now)
        elif ch == 2:  # write: echoes the stored value
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident < len(self.param_names):
                self._set_param(self.param_names[ident], d[2:], now)
                self.send(PORT_PARAM, 2, struct.pack("<H", ident) + self._param_bytes(ident), now)
        elif ch == 3 and d[0] == 0:  # set by name: [0, group\0name\0, type, value]
            parts = d[1:].split(b"\0", 2)
            name = parts[0].decode() + "." + parts[1].decode()
            err = errno.ENOENT
            if name in PARAMS and len(parts) == 3 and parts[2]:
                err = 0 if self._set_param(name, parts[2][1:], now) else errno.EACCES
            self.send(PORT_PARAM, 3, d[: 1 + len(parts[0]) + len(parts[1]) + 2] + bytes([err]), now)

    def _set_param(self, name: str, raw: bytes, now: float) -> bool:
        typ = PARAMS[name][0]
        if typ & PARAM_RONLY:
            self._count("param_readonly")
            return False
        code = PARAM_TYPES[typ]
        v = float(struct.unpack_from("<" + code, raw, 0)[0])
        if not math.isfinite(v):
            return False
        self.param_values[name] = v
        self._count("param_sets")
        return True

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
        """The position controller: a = Kp (p* - p) + Kd (v* - v) within the tilt and thrust
        envelope (a NaN axis of p* is velocity-controlled), then the thrust and the attitude of that
        direction at ``yaw`` (the inversion after eq. 28)."""
        p = self.params
        e = np.where(np.isnan(p_ref), 0.0, p_ref - q)
        n = float(np.linalg.norm(e))
        if n > 0.5:
            e *= 0.5 / n
        a = np.array([6.0, 6.0, 8.0]) * e + np.array([4.0, 4.0, 5.0]) * (v_ref - v)
        g = p.g
        axy_max = 0.9 * g * math.tan(p.max_tilt)
        nxy = math.hypot(a[0], a[1])
        if nxy > axy_max:
            a[0:2] *= axy_max / nxy
        a[2] = min(max(a[2], -0.7 * g), 0.9 * (cfu.max_thrust_n() / p.mass - g))
        ux, uy, uz = a[0], a[1], a[2] + g
        norm = math.sqrt(ux * ux + uy * uy + uz * uz)
        s, c = math.sin(yaw), math.cos(yaw)
        phi = math.asin(min(max((ux * s - uy * c) / norm, -1.0), 1.0))
        theta = math.atan2(ux * c + uy * s, uz)
        return p.mass * norm, np.array([phi, theta, yaw])

    def battery_level(self) -> float:
        """pm.batteryLevel, %: linear between 3.0 V (0 %) and 4.2 V (100 %)."""
        return min(100.0, max(0.0, (self.vbat - 3.0) / 1.2 * 100.0))

    def close(self) -> None:
        self.sock.close()


class CrazyflieFleet(FleetThread):
    """N simulated Crazyflies, integrated in real time; vehicle i (0-based) on UDP
    ``host:base_port + i``. :meth:`start` / :meth:`stop` run it in a background thread (tests,
    embedding), :meth:`run` in the calling thread (the CLI). ``state`` is the plant's
    :class:`zenswarm.plant.quadrotor.PlantState` (ENU; read it, do not write it while running)."""

    thread_name = "crazyflie-fleet"

    def __init__(self, q0: Any, params: QuadParams, base_port: int = DEFAULT_BASE_PORT, host: str = "127.0.0.1",
                 physics_hz: float = 1000.0, chunk: int = 10) -> None:  # fmt: skip
        q = np.array(q0, dtype=float)
        if q.ndim != 2 or q.shape[1] != 3:
            raise ValueError(f"q0 must have shape (N, 3), got {q.shape}")
        q[:, 2] = 0.0
        self.n = q.shape[0]
        self.params = params
        self.state: PlantState = initial_state(q)
        self.h = 1.0 / float(physics_hz)
        self.chunk = int(chunk)
        self.period = self.chunk * self.h
        self.boot = time.monotonic()
        self.host = host
        self.base_port = int(base_port)
        self.vehicles: list[SimCrazyflie] = []
        try:
            for i in range(self.n):
                self.vehicles.append(SimCrazyflie(i, host, self.base_port + i, params, self.boot))
        except Exception:
            self.close()
            raise
        self.thrust = np.zeros(self.n)
        self.rpy_cmd = np.zeros((self.n, 3))
        self.ticks = 0
        self.overruns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.on_tick: Callable[[float], None] | None = None  # called after every tick (the mocap feeder)

    @classmethod
    def from_scenario(cls, sc: Any, base_port: int = DEFAULT_BASE_PORT, host: str = "127.0.0.1") -> CrazyflieFleet:
        """The scenario's fleet: on the ground under ``formation.initial_positions``, ``[vehicle]``
        parameters, physics rate and chunk from ``[timing]``."""
        return cls(np.asarray(sc.initial_positions, dtype=float), QuadParams.from_vehicle(sc.vehicle), base_port, host,
                   physics_hz=sc.timing.physics_rate_hz, chunk=sc.timing.substeps)  # fmt: skip

    def uris(self) -> list[str]:
        return [f"udp://{self.host}:{v.port}" for v in self.vehicles]

    def silence(self, index: int, seconds: float) -> None:
        """Vehicle ``index`` (0-based) drops all its traffic, both ways, for ``seconds`` (a lost link)."""
        self.vehicles[index].muted_until = time.monotonic() + float(seconds)

    def reboot(self, index: int) -> None:
        """Vehicle ``index`` restarts its firmware (unlocks, disarmed, on the ground where it is)."""
        v = self.vehicles[index]
        self.vehicles[index] = SimCrazyflie(index, self.host, v.port, self.params, time.monotonic(), sock=v.sock)

    def _values(self, i: int) -> Callable[[int], float]:
        st = self.state
        veh = self.vehicles[i]
        roll, pitch, yaw = cfu.attitude_to_log(st.rpy[i])
        now = time.monotonic()
        w = np.degrees(st.w[i])
        q = veh.estimate(now, st.q[i], st.v[i])
        table = {
            "stateEstimate.x": q[0], "stateEstimate.y": q[1], "stateEstimate.z": q[2],
            "stateEstimate.vx": st.v[i, 0], "stateEstimate.vy": st.v[i, 1], "stateEstimate.vz": st.v[i, 2],
            "stateEstimate.roll": roll, "stateEstimate.pitch": pitch, "stateEstimate.yaw": yaw,
            "stabilizer.roll": roll, "stabilizer.pitch": pitch, "stabilizer.yaw": yaw,
            "gyro.x": w[0], "gyro.y": w[1], "gyro.z": w[2],
            "stabilizer.thrust": float(veh.motor_cmd),
            "motor.m1": veh.motor_cmd, "motor.m2": veh.motor_cmd, "motor.m3": veh.motor_cmd, "motor.m4": veh.motor_cmd,
            "pm.vbat": veh.vbat, "pm.batteryLevel": veh.battery_level(),
            "pm.state": 3.0 if veh.vbat < veh.param_values["pm.lowVoltage"] else 0.0,
            "radio.rssi": 40.0, "supervisor.info": float(veh.info_bits(now)),
        }  # fmt: skip
        return lambda ident: float(table[LOG_VARS[ident][0]])

    def poll(self, now: float) -> None:
        st = self.state
        for i, veh in enumerate(self.vehicles):
            veh.receive(now, veh.estimate(now, st.q[i], st.v[i]), st.rpy[i])

    def tick(self, now: float) -> None:
        """One loop period: control, a physics chunk, the log blocks that are due."""
        st = self.state
        for i, veh in enumerate(self.vehicles):
            q_est = veh.estimate(now, st.q[i], st.v[i]).copy()  # the controllers fly the estimate
            f, att = veh.control(now, self.period, q_est, st.v[i].copy(), st.rpy[i].copy())
            self.thrust[i] = f
            self.rpy_cmd[i] = att
        for _ in range(self.chunk):
            step(st, self.thrust, self.rpy_cmd, self.params, self.h)
            self._ground()
        self.ticks += 1
        for i, veh in enumerate(self.vehicles):
            if veh.blocks:
                veh.send_logs(now, self._values(i))
        if self.on_tick is not None:
            self.on_tick(now)

    def _ground(self) -> None:
        st = self.state
        if st.q[:, 2].min() >= 0.0:
            return
        below = st.q[:, 2] < 0.0
        st.q[below, 2] = 0.0
        st.v[below] = 0.0
        st.w[below] = 0.0
        st.rpy[below, 0:2] = 0.0
        st.rate_int[below] = 0.0

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> str:
        """Loop on the wall clock until ``stop`` is set or ``duration_s`` passed; between ticks it
        waits on the sockets, so requests (TOC, parameters) are answered at once. A stall of more
        than 0.5 s resynchronises (counted in ``overruns``)."""
        stop = stop or self._stop
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        socks = [v.sock for v in self.vehicles]
        next_tick = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if now >= end:
                return "duration reached"
            self.poll(now)
            if now >= next_tick:
                self.tick(now)
                next_tick += self.period
                if now - next_tick > 0.5:
                    next_tick = now + self.period
                    self.overruns += 1
                continue
            try:
                select.select(socks, [], [], max(0.0, min(next_tick - now, 0.05)))
            except (OSError, ValueError):
                time.sleep(0.001)
        return "stop requested"

    def status(self) -> list[dict[str, Any]]:
        """One line of facts per vehicle (for logs and tests)."""
        return [
            {"port": v.port, "supervisor": v.sup, "armed": v.armed, "hl": v.hl.state, "setpoint": v.sp_kind,
             "q": self.state.q[i].round(3).tolist(), **v.counters}
            for i, v in enumerate(self.vehicles)
        ]  # fmt: skip


class MocapFeeder:
    """A motion-capture system for the simulated fleet: publishes every vehicle's true position
    on ``swarm/<name>/mocap/<i>`` (:mod:`zenswarm.bus.mocap`) at ``rate_hz``, from the fleet's
    loop (:attr:`CrazyflieFleet.on_tick`)."""

    def __init__(self, fleet: CrazyflieFleet, session: Any, prefix: str, rate_hz: float = 100.0) -> None:
        from zenswarm.bus.mocap import mocap_key

        self.fleet = fleet
        self.pubs = [session.declare_publisher(mocap_key(prefix, i + 1)) for i in range(fleet.n)]
        self.period = 1.0 / float(rate_hz)
        self.next_t = 0.0
        self.sent = 0
        self.mute: set[int] = set()  # vehicles (0-based) whose feed is cut (a test hook: a lost marker)

    def __call__(self, now: float) -> None:
        from zenswarm.bus.mocap import encode_mocap

        if now < self.next_t:
            return
        self.next_t = max(self.next_t + self.period, now - self.period)
        t = time.time()
        for i, pub in enumerate(self.pubs):
            if i not in self.mute:
                pub.put(encode_mocap(t, *self.fleet.state.q[i]))
        self.sent += 1

    def close(self) -> None:
        from zenswarm.bus import undeclare

        for pub in self.pubs:
            undeclare(pub)


def run_fleet(
    sc: Any, *, base_port: int = DEFAULT_BASE_PORT, host: str = "127.0.0.1", duration: float | None = None,
    mocap: tuple[str, list[str]] | None = None, mocap_hz: float = 100.0, rt_priority: int | None = None,
    mocap_security: Mapping[str, Any] | None = None,
) -> int:  # fmt: skip
    """Run the fleet of scenario ``sc`` in the calling thread until SIGTERM/SIGINT (or
    ``duration`` s). A port that cannot be bound: :class:`ScenarioError` naming it (exit 2).
    ``mocap`` = (swarm name, Zenoh connect endpoints): also publish the vehicles' true positions
    as a motion-capture feed (:class:`MocapFeeder`) at ``mocap_hz``, its session configured with
    ``mocap_security`` (:func:`zenswarm.process.security.client_fragments`: a secured router's
    credentials; None: an open one). ``rt_priority``: run under
    ``SCHED_FIFO`` at this priority once the fleet is up (:mod:`zenswarm.process.rtsched`; checked
    first, exit 2 if not permitted)."""
    from zenswarm.process import rtsched

    rtsched.set_requested(rtsched.validate(rt_priority, realtime=True))  # out of range or not permitted: exit 2 now
    fleet = CrazyflieFleet.from_scenario(sc, base_port=base_port, host=host)
    if mocap is None:
        return _run_fleet(fleet, duration)
    from zenswarm import bus
    from zenswarm.bus.wire import Keys

    try:
        with bus.open_session(bus.client_config(mocap[1], settings=mocap_security), handle_signals=False) as session:
            feeder = MocapFeeder(fleet, session, Keys(mocap[0]).prefix, mocap_hz)
            fleet.on_tick = feeder
            try:
                return _run_fleet(fleet, duration, f"; mocap on swarm/{mocap[0]}/mocap/<i> at {mocap_hz:g} Hz")
            finally:
                fleet.on_tick = None
                feeder.close()
    finally:
        fleet.close()


def _run_fleet(fleet: CrazyflieFleet, duration: float | None, extra: str = "") -> int:
    from zenswarm.process import rtsched

    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    try:
        print(f"crazyflie-vehicle: ready: {fleet.n} Crazyflie(s) at " + ", ".join(fleet.uris()) + extra, flush=True)
        rtsched.apply_after_startup(lambda text: print(f"crazyflie-vehicle: {text}", flush=True))  # --rt-priority
        why = fleet.run(stop, duration)
        print(f"crazyflie-vehicle: stopped ({why}); overruns {fleet.overruns}; {fleet.status()}", flush=True)
    finally:
        fleet.close()
    return 0

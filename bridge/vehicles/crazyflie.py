"""Crazyflie bridge: fly the swarm's agents on Crazyflie 2.1s (or the simulated ones of
:mod:`zenswarm.plant.crazyflie_vehicle`) through cflib, Bitcraze's own library, without changing a
line of the agents.

``zenswarm bridge crazyflie SCENARIO --swarm S --connect EP [--uri I=URI ...]`` takes the plant's
place on the swarm bus in realtime mode, as the MAVLink bridge does (the mission clock, pacing,
liveliness wait and landing loop are :mod:`zenswarm.bridge.vehicles.mavlink`'s). For each UAV i it opens
cflib's link to its URI (``radio://0/80/2M/E7E7E7E701``, ``udp://HOST:PORT``, ``usb://0``;
:mod:`zenswarm.vehicle.crazyflie_settings`) and then:

1. ``connecting``: waits until cflib has the vehicle's log and parameter tables (and every
   parameter's value); a vehicle that does not answer within ``connect_timeout_s`` is refused
   (``unreachable``), as is one whose link fails;
2. ``logs``: sets ``flightmode.stabModeYaw`` = 0 (the yaw *rate* the bridge flies) and starts
   three log blocks: position and velocity (``stateEstimate.x..vz``) and attitude and body rates
   (``stateEstimate.roll/pitch/yaw``, ``gyro.x/y/z``) at the setpoint rate, battery and supervisor
   (``pm.vbat``, ``pm.batteryLevel``, ``supervisor.info``, ``radio.rssi``) at 10 Hz; waits for both
   state blocks;
3. ``arm``: the supervisor's arming request (cflib ``supervisor.send_arming_request``), repeated
   twice a second until ``supervisor.info`` reports armed (at most 5 times: else refused);
4. ``takeoff`` (``takeoff = true``): one zero-thrust legacy setpoint on the ground (the legacy
   commander's thrust is locked from boot until one arrives) and notify-setpoint-stop, then
   the high-level commander's takeoff to the initial height, then
   a go-to to the initial position if the vehicle is not there; done within
   ``takeoff_tolerance_m`` and slower than 0.2 m/s, refused (and landed) after ``takeoff_timeout_s``;
5. ``ready``: the high-level commander holds the vehicle until the mission clock starts (the
   :class:`zenswarm.bridge.vehicles.mavlink._BridgeLoop`); then every loop the bridge sends each ready UAV
   the legacy RPYT setpoint of its agent's latest command (:func:`rpyt_of`): roll and pitch in
   degrees with the firmware's signs, a yaw rate from the bridge's yaw loop, the thrust through the
   Crazyflie 2.1's thrust map (:mod:`zenswarm.vehicle.crazyflie`), clamped to what the commander
   takes and counted (``thrust_clamped``; said once per UAV). The first setpoint stops the
   high-level planner (the commander's priorities): the handover. A command older than
   ``cmd_timeout_s`` is replaced by a position hold (the generic POSITION setpoint) where the
   vehicle is;
6. a vehicle whose state blocks stop for ``link_timeout_s`` is unhealthy: its state is no longer
   published and the UAV is in the named failsafe ``link_lost`` (diag ``failsafe`` =
   ``"2:link_lost"``, results.json ``failsafe``): the Crazyflie's own commander watchdog levels it
   after 500 ms without setpoints and stops its motors after 2 s. When its blocks come back the UAV
   is healthy again; one that the watchdog locked is ``lost`` (a reboot is needed) and no longer
   commanded. cflib's own link failure (the radio's) makes it ``lost`` at once;
7. at the end of the mission, on SIGTERM/SIGINT, or when the loop stops: ``landing`` — the
   setpoints stop, the high-level commander lands the vehicle (``land``, then notify-setpoint-stop,
   which hands control back to it), and the UAV is ``done`` once ``supervisor.info`` says it is no
   longer flying (at most ``land_timeout_s``); then the links close.

With ``positioning = "extpos"`` the bridge also forwards the external positioning feed
(``swarm/<name>/mocap/<i>``, :mod:`zenswarm.bus.mocap`) to each vehicle as it arrives (cflib
``extpos.send_extpos``), arms a vehicle only once its feed runs, and lands one whose feed is silent
for ``link_timeout_s`` (the named failsafe ``positioning_lost``).

Diagnostics (``diag/bridge``): per UAV its phase, reason, URI, health, battery (V and %),
supervisor bits, link quality (state packets received over those expected in the last second),
state age (ms, from the vehicle's own log timestamps: the clock offset is the fastest delivery
seen), the fed position's age (``extpos_age_ms``) and count (``extpos_sent``) and the traffic
counted both ways (``tx_bytes``, ``rx_bytes``, ``tx_packets``, ``rx_packets``).
"""

from __future__ import annotations

import argparse
import logging
import math
import socket
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm.bridge.vehicles.settings import CrazyflieBridgeSettings, bridge_main, run_bridge
from zenswarm.errors import ScenarioError
from zenswarm.vehicle import crazyflie as cfu
from zenswarm.vehicle.crazyflie_settings import CrazyflieSettings, crazyflie_settings

__all__ = ["CrazyflieBridge", "rpyt_of", "add_crazyflie_parser"]

CONNECTING, LOGS, ARM, TAKEOFF, READY, LANDING, DONE, REFUSED, LOST = (
    "connecting", "logs", "arm", "takeoff", "ready", "landing", "done", "refused", "lost",
)  # fmt: skip
_ARM_RETRY_S, _ARM_ATTEMPTS = 0.5, 5
BIT_ARMED, BIT_FLYING, BIT_LOCKED = 1 << 1, 1 << 4, 1 << 6  # supervisor.info (supervisor.c)


def rpyt_of(thrust_n: float, rpy: Any, yaw_now: float, yaw_gain: float) -> tuple[float, float, float, int, bool]:
    """The legacy setpoint (cflib ``commander.send_setpoint(roll, pitch, yawrate, thrust)``
    arguments) of an agent's command: thrust (N) and attitude (phi, theta, psi rad, the paper's
    ZYX Euler angles in ENU/FLU), at the vehicle's yaw ``yaw_now`` (rad). cflib negates pitch on
    the wire and the firmware inverts the yaw rate (:mod:`zenswarm.vehicle.crazyflie`), so the
    arguments are (deg(phi), deg(theta), -deg(r), cmd) with r the counter-clockwise rate of the
    yaw loop. Returns those four and whether the thrust was clamped."""
    cmd, clamped = cfu.thrust_to_command(thrust_n)
    rate = cfu.yaw_rate_command(float(rpy[2]), yaw_now, yaw_gain)
    return math.degrees(float(rpy[0])), math.degrees(float(rpy[1])), -math.degrees(rate), cmd, clamped


class CfLink:
    """One UAV's Crazyflie: the cflib object, its phase and what its log blocks said (written by
    cflib's threads under ``lock``)."""

    def __init__(self, uav: int, uri: str, q_init: np.ndarray) -> None:
        self.uav = uav
        self.uri = uri
        self.q_init = q_init
        self.cf: Any = None
        self.phase = CONNECTING
        self.reason = ""
        self.phase_t = 0.0
        self.lock = threading.Lock()
        self.connected = False
        self.failed: str | None = None  # cflib's connection_failed / connection_lost message
        self.healthy = True
        self.q = self.v = self.rpy = self.w = None  # type: Any
        self.pos_rx = self.att_rx = -math.inf  # monotonic s of the last block of each
        self.pos_ts_s: float | None = None  # the vehicle's own time of the last position sample, s
        self.offset_s: float | None = None  # bridge clock - vehicle clock, from the fastest delivery
        self.ts_last_ms = 0
        self.ts_wraps = 0
        self.vbat = math.nan
        self.battery_pct = -1
        self.sup_info = -1
        self.rssi = -1
        self.rx_times: deque[float] = deque(maxlen=1000)
        self.arm_tries = 0
        self.arm_t = -math.inf
        self.hl_sent = False
        self.goto_sent = False
        self.streaming = False
        self.clamp_said = False
        self.hold: np.ndarray | None = None
        self.state_age_s: float | None = None
        self.traffic = {"tx_packets": 0, "tx_bytes": 0, "rx_packets": 0, "rx_bytes": 0}
        self.traffic0: dict[str, int] | None = None  # the counts when the mission's stream began
        self.stream_t0 = math.nan
        self.traffic1: dict[str, int] | None = None  # ... and when it ended (landing)
        self.stream_t1 = math.nan
        self.probe: socket.socket | None = None  # udp:// links: the null-packet probe before cflib opens the link
        self.probe_t = -math.inf
        self.opened = False
        self.mocap_rx = -math.inf  # monotonic s of the last fed position (positioning = extpos)
        self.extpos_sent = 0
        self.positioning_lost = False

    def unwrap_ms(self, ts: int) -> float:
        """The 24-bit ms log timestamp as seconds since the vehicle booted (wraps every 4.66 h)."""
        if ts < self.ts_last_ms - (1 << 23):
            self.ts_wraps += 1
        self.ts_last_ms = ts
        return (ts + (self.ts_wraps << 24)) / 1000.0

    def link_quality(self, now: float, rate_hz: float) -> float:
        """State packets received in the last second over those expected (two blocks at ``rate_hz``)."""
        with self.lock:  # cflib's threads append
            times = list(self.rx_times)
        n = sum(1 for t in times if now - t <= 1.0)
        return round(min(1.0, n / (2.0 * rate_hz)), 3)

    def info(self, now: float, rate_hz: float) -> dict[str, Any]:
        """The link's figures at ``now`` (monotonic s). An age is never negative: cflib's and
        zenoh's threads stamp ``pos_rx`` and ``mocap_rx``, and one may land after ``now`` was taken."""
        return {
            "uri": self.uri, "phase": self.phase, "reason": self.reason, "healthy": self.healthy,
            "armed": bool(self.sup_info >= 0 and self.sup_info & BIT_ARMED),
            "flying": bool(self.sup_info >= 0 and self.sup_info & BIT_FLYING),
            "locked": bool(self.sup_info >= 0 and self.sup_info & BIT_LOCKED),
            "supervisor_info": self.sup_info, "vbat": None if math.isnan(self.vbat) else round(self.vbat, 3),
            "battery_pct": self.battery_pct, "rssi": self.rssi, "link_quality": self.link_quality(now, rate_hz),
            "silent_s": round(max(0.0, now - self.pos_rx), 3) if math.isfinite(self.pos_rx) else None,
            "state_age_ms": round(self.state_age_s * 1000.0, 2) if self.state_age_s is not None else -1.0,
            "extpos_sent": self.extpos_sent,
            "extpos_age_ms": round(max(0.0, now - self.mocap_rx) * 1000.0, 1) if math.isfinite(self.mocap_rx) else -1.0,
            **self.traffic,
        }  # fmt: skip


class CrazyflieBridge:
    """Every UAV's Crazyflie link and phase; the interface :class:`zenswarm.bridge.vehicles.mavlink._BridgeLoop`
    drives (poll, advance, send, state_enu, sample_time, info, landing)."""

    def __init__(self, settings: CrazyflieSettings, sc: Any, counters: Any, get_cmd: Any, log: Any) -> None:
        self.s = settings
        self.sc = sc
        self.counters = counters
        self.get_cmd = get_cmd
        self.log = log
        self.params = sc.vehicle
        q0 = np.asarray(sc.initial_positions, dtype=float)
        self.links = [CfLink(i + 1, settings.uris[i], q0[i]) for i in range(settings.n)]
        self.changed = True
        self.started_at = time.monotonic()
        self.period = 1.0 / settings.rate_hz
        self.log_period_ms = max(10, int(round(1000.0 / settings.rate_hz / 10.0)) * 10)
        self.grace_until = -math.inf  # after a stall of our own loop: silence is not judged until then
        self.extpos = settings.positioning == "extpos"

    def on_mocap(self, uav: int, payload: bytes) -> None:
        """A fed position of UAV ``uav`` (``swarm/<name>/mocap/<i>``, :mod:`zenswarm.bus.mocap`):
        forwarded at once to its Crazyflie's estimator (cflib ``extpos.send_extpos``, CRTP port 6)
        once its link is up; on the feed's thread, so at the feed's rate."""
        from zenswarm.bus.mocap import decode_mocap

        if not 1 <= uav <= len(self.links):
            self._count("mocap_unknown_uav")
            return
        try:
            m = decode_mocap(payload)
        except ValueError:  # msgspec's DecodeError and ValidationError are ValueErrors
            self._count("mocap_rejected")
            return
        if not all(math.isfinite(c) for c in (m.x, m.y, m.z)):
            self._count("mocap_rejected")
            return
        link = self.links[uav - 1]
        with link.lock:
            link.mocap_rx = time.monotonic()
            cf = link.cf if link.phase not in (CONNECTING, REFUSED, DONE, LOST) else None
        if cf is not None and cf.is_connected():
            cf.extpos.send_extpos(m.x, m.y, m.z)
            link.extpos_sent += 1
            self._count("extpos_sent")

    # ------------------------------------------------------------------ helpers
    def _count(self, name: str, k: float = 1) -> None:
        self.counters[name] += k

    def _set_phase(self, link: CfLink, phase: str, now: float, reason: str = "") -> None:
        if phase != link.phase or reason != link.reason:
            self.log(f"bridge: uav {link.uav}: {link.phase} -> {phase}" + (f" ({reason})" if reason else ""))
            link.phase, link.reason, link.phase_t = phase, reason, now
            self.changed = True

    def open(self) -> None:
        """Prepare every link: cflib's drivers, and for ``udp://`` a probe socket (cflib's UDP
        driver gives a link up at the first ICMP "port unreachable", so the link is opened only
        once the vehicle answers the null packet cflib's own scan sends)."""
        import cflib.crtp

        logging.getLogger("cflib").setLevel(logging.CRITICAL)  # its link errors are reported here, in one line
        cflib.crtp.init_drivers()
        now = time.monotonic()
        for link in self.links:
            link.phase_t = now
            if link.uri.startswith("udp://"):
                link.probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                link.probe.setblocking(False)
            else:
                self._open_link(link)

    def _open_link(self, link: CfLink) -> None:
        from cflib.crazyflie import Crazyflie

        cf = Crazyflie(rw_cache=None)
        link.cf = cf
        cf.fully_connected.add_callback(lambda uri, lk=link: self._on_connected(lk))
        cf.connection_failed.add_callback(lambda uri, msg, lk=link: self._on_failed(lk, f"connection failed: {msg}"))
        cf.connection_lost.add_callback(lambda uri, msg, lk=link: self._on_failed(lk, f"connection lost: {msg}"))
        cf.packet_sent.add_callback(lambda pk, lk=link: self._traffic(lk, "tx", pk))
        cf.packet_received.add_callback(lambda pk, lk=link: self._traffic(lk, "rx", pk))
        link.opened = True
        cf.open_link(link.uri)

    def _probe(self, link: CfLink, now: float) -> None:
        """A ``udp://`` vehicle that answers the null packet (0xFF) gets its cflib link."""
        from urllib.parse import urlparse

        assert link.probe is not None
        try:
            link.probe.recvfrom(64)
        except OSError:
            if now - link.probe_t >= 0.2:
                link.probe_t = now
                u = urlparse(link.uri)
                try:
                    link.probe.sendto(b"\xff", (u.hostname or "127.0.0.1", int(u.port or 0)))
                except OSError:
                    pass
            return
        link.probe.close()
        link.probe = None
        self._open_link(link)

    def _traffic(self, link: CfLink, way: str, pk: Any) -> None:
        link.traffic[f"{way}_packets"] += 1
        link.traffic[f"{way}_bytes"] += 1 + len(pk.data)

    def _on_connected(self, link: CfLink) -> None:
        with link.lock:
            link.connected = True

    def _on_failed(self, link: CfLink, msg: str) -> None:
        first = str(msg).split("Traceback")[0]  # cflib puts the driver's traceback in the message
        with link.lock:
            link.failed = " ".join(first.split())[:200]

    def _on_pos(self, link: CfLink, ts: int, d: dict[str, float]) -> None:
        now = time.monotonic()
        with link.lock:
            link.q = np.array([d["stateEstimate.x"], d["stateEstimate.y"], d["stateEstimate.z"]])
            link.v = np.array([d["stateEstimate.vx"], d["stateEstimate.vy"], d["stateEstimate.vz"]])
            t_vehicle = link.unwrap_ms(ts)
            off = now - t_vehicle
            link.offset_s = off if link.offset_s is None else min(link.offset_s, off)
            link.pos_ts_s = t_vehicle
            link.pos_rx = now
            link.rx_times.append(now)
        self._count("log_state_packets")

    def _on_att(self, link: CfLink, ts: int, d: dict[str, float]) -> None:
        now = time.monotonic()
        with link.lock:
            link.rpy = cfu.attitude_from_log(d["stateEstimate.roll"], d["stateEstimate.pitch"], d["stateEstimate.yaw"])
            link.w = np.radians([d["gyro.x"], d["gyro.y"], d["gyro.z"]])
            link.att_rx = now
            link.rx_times.append(now)
        self._count("log_state_packets")

    def _on_status(self, link: CfLink, ts: int, d: dict[str, float]) -> None:
        with link.lock:
            link.vbat = float(d["pm.vbat"])
            link.battery_pct = int(d["pm.batteryLevel"])
            link.sup_info = int(d["supervisor.info"])
            link.rssi = int(d["radio.rssi"])

    def _start_logs(self, link: CfLink) -> None:
        from cflib.crazyflie.log import LogConfig

        cf = link.cf
        cf.param.set_value("flightmode.stabModeYaw", 0)  # the legacy setpoint's yaw is a rate
        blocks = [
            ("pos", self.log_period_ms, [f"stateEstimate.{a}" for a in ("x", "y", "z", "vx", "vy", "vz")], self._on_pos),
            ("att", self.log_period_ms, [f"stateEstimate.{a}" for a in ("roll", "pitch", "yaw")] + [f"gyro.{a}" for a in "xyz"],
             self._on_att),
            ("status", 100, ["pm.vbat", "pm.batteryLevel", "supervisor.info", "radio.rssi"], self._on_status),
        ]  # fmt: skip
        for name, period, names, cb in blocks:
            lc = LogConfig(name=f"zenswarm_{name}", period_in_ms=period)
            for v in names:
                lc.add_variable(v)
            cf.log.add_config(lc)
            lc.data_received_cb.add_callback(lambda ts, data, conf, lk=link, f=cb: f(lk, ts, data))
            lc.start()

    # ------------------------------------------------------------------ loop interface
    def note_stall(self, gap_s: float) -> None:
        """A gap of the bridge's own loop of 0.25 s or more (an overloaded host): the log blocks
        that arrived meanwhile are still queued in cflib's threads, so link silence is not judged
        for ``link_timeout_s`` after it (no false ``link_lost``)."""
        if gap_s >= 0.25:
            self._count("loop_stalls")
            self.grace_until = time.monotonic() + self.s.link_timeout_s

    def poll(self, now: float) -> None:
        """Link health from the log blocks: silent for ``link_timeout_s`` -> unhealthy
        (``link_lost``), talking again -> healthy; cflib's link failure -> lost."""
        for link in self.links:
            with link.lock:
                failed = link.failed
                silent = now - max(link.pos_rx, link.phase_t if link.pos_rx == -math.inf else -math.inf)
            if failed and link.phase not in (REFUSED, LOST, DONE):
                if link.phase == CONNECTING:
                    self._set_phase(link, REFUSED, now, f"unreachable: {failed}")
                else:
                    self._set_phase(link, LOST, now, failed)
                    self._count("link_lost")
                continue
            if link.phase in (CONNECTING, LOGS, REFUSED, DONE) or link.pos_rx == -math.inf:
                continue
            if link.healthy and silent > self.s.link_timeout_s and now >= self.grace_until:
                link.healthy = False
                self.changed = True
                self._count("link_lost")
                self.log(f"bridge: uav {link.uav}: link lost (no state for {silent:.2f} s): failsafe link_lost, "
                         "the Crazyflie's watchdog levels it after 0.5 s without setpoints and stops its motors after 2 s")  # fmt: skip
            elif not link.healthy and silent <= self.s.link_timeout_s:
                link.healthy = True
                self.changed = True
                self._count("link_recovered")
                self.log(f"bridge: uav {link.uav}: link back")
            if link.healthy and link.sup_info >= 0 and link.sup_info & BIT_LOCKED and link.phase in (READY, TAKEOFF, ARM):
                self._set_phase(link, LOST, now, "locked by its commander watchdog (a reboot is needed)")
            elif self.extpos and link.phase in (TAKEOFF, READY) and now >= self.grace_until:
                quiet = now - link.mocap_rx
                if quiet > self.s.link_timeout_s and link.healthy:
                    link.positioning_lost = True
                    self._count("positioning_lost")
                    self.log(f"bridge: uav {link.uav}: no external position for {quiet:.2f} s: failsafe positioning_lost, "
                             "landed by its high-level commander on its own (drifting) estimate")  # fmt: skip
                    self._land(link, now, "positioning lost")

    def advance(self, now: float) -> None:
        for link in self.links:
            getattr(self, f"_step_{link.phase}", lambda lk, t: None)(link, now)

    def _step_connecting(self, link: CfLink, now: float) -> None:
        if not link.opened and link.probe is not None and now - link.phase_t <= self.s.connect_timeout_s:
            self._probe(link, now)
        if link.connected:
            self._set_phase(link, LOGS, now)
            try:
                self._start_logs(link)
            except (KeyError, AttributeError, Exception) as e:  # noqa: BLE001 - a firmware without the variables
                self._set_phase(link, REFUSED, now, f"log blocks refused: {e}")
        elif now - link.phase_t > self.s.connect_timeout_s:
            self._set_phase(link, REFUSED, now, f"unreachable: no answer from {link.uri} within {self.s.connect_timeout_s:g} s")

    def _step_logs(self, link: CfLink, now: float) -> None:
        if link.q is not None and link.rpy is not None and link.sup_info >= 0:
            self._set_phase(link, ARM, now)
        elif now - link.phase_t > self.s.connect_timeout_s:
            self._set_phase(link, REFUSED, now, "no state from the log blocks")

    def _step_arm(self, link: CfLink, now: float) -> None:
        if self.extpos and now - link.mocap_rx > self.s.link_timeout_s:  # never arm without a position
            if now - link.phase_t > self.s.connect_timeout_s:
                self._set_phase(link, REFUSED, now, f"no external position on mocap/{link.uav} within {self.s.connect_timeout_s:g} s")
            return
        if link.sup_info & BIT_ARMED:
            self._count("armed")
            if self.s.takeoff:
                self._set_phase(link, TAKEOFF, now)
            else:
                self._set_phase(link, READY, now, "armed, no takeoff")
            return
        if now - link.arm_t >= _ARM_RETRY_S:
            if link.arm_tries >= _ARM_ATTEMPTS:
                self._set_phase(link, REFUSED, now, f"did not arm (supervisor.info 0x{link.sup_info:04x})")
                return
            link.arm_tries += 1
            link.arm_t = now
            link.cf.supervisor.send_arming_request(True)
            self._count("arm_requests")

    def _step_takeoff(self, link: CfLink, now: float) -> None:
        hl = link.cf.high_level_commander
        target = link.q_init
        if not link.hl_sent:
            # the legacy commander's thrust is locked from boot until a setpoint with thrust 0
            # (crtp_commander_rpyt.c): unlock it on the ground, then give the high-level
            # commander its priority back, so the handover at the mission start is one setpoint
            link.cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)
            link.cf.commander.send_notify_setpoint_stop()
            hl.takeoff(float(target[2]), self.s.takeoff_duration_s, yaw=float(self.sc.controller.yaw))
            link.hl_sent = True
            self._count("takeoff_requests")
            return
        err = float(np.linalg.norm(link.q - target))
        if (
            not link.goto_sent
            and now - link.phase_t > self.s.takeoff_duration_s
            and abs(link.q[2] - target[2]) < 0.1
            and err > self.s.takeoff_tolerance_m
        ):
            hl.go_to(float(target[0]), float(target[1]), float(target[2]), float(self.sc.controller.yaw), self.s.takeoff_duration_s)
            link.goto_sent = True
        if err <= self.s.takeoff_tolerance_m and float(np.linalg.norm(link.v)) < 0.2 and now - link.phase_t >= self.s.takeoff_duration_s:
            self._set_phase(link, READY, now, "hovering at its initial position (high-level commander)")
        elif now - link.phase_t > self.s.takeoff_timeout_s:
            self._land(link, now, f"takeoff not done after {self.s.takeoff_timeout_s:g} s ({err:.3f} m away)", REFUSED)

    @property
    def settled(self) -> bool:
        return all(link.phase not in (CONNECTING, LOGS, ARM, TAKEOFF) for link in self.links)

    @property
    def ready(self) -> list[CfLink]:
        return [link for link in self.links if link.phase == READY]

    # ------------------------------------------------------------------ setpoints out
    def send(self, now: float) -> None:
        """The setpoint of every ready UAV once the mission runs (its agent's command, or a hold)."""
        for link in self.links:
            if link.phase != READY:
                continue
            cmd, age = self.get_cmd(link.uav)
            if cmd is not None and age <= self.s.cmd_timeout_s and link.rpy is not None:
                roll, pitch, yawrate, thrust, clamped = rpyt_of(cmd.thrust, cmd.rpy, float(link.rpy[2]), self.s.yaw_gain)
                if clamped:
                    self._count("thrust_clamped")
                    if not link.clamp_said:
                        link.clamp_said = True
                        self.log(f"bridge: uav {link.uav}: thrust {cmd.thrust:.3f} N outside what the Crazyflie's commander "
                                 f"takes ({cfu.command_to_thrust(cfu.MIN_THRUST):.3f}..{cfu.max_thrust_n():.3f} N): clamped to {thrust} "
                                 "(counted in thrust_clamped)")  # fmt: skip
                if link.traffic0 is None:
                    link.traffic0, link.stream_t0 = dict(link.traffic), now
                link.cf.commander.send_setpoint(roll, pitch, yawrate, thrust)
                link.streaming = True
                link.hold = None
                self._count("setpoints_rpyt")
            elif link.streaming:
                # a stale command after the handover: hold where the vehicle is (generic POSITION)
                if link.hold is None and link.q is not None:
                    link.hold = link.q.copy()
                if link.hold is not None:
                    link.cf.commander.send_position_setpoint(*map(float, link.hold), math.degrees(float(self.sc.controller.yaw)))
                self._count("cmd_stale_ticks")

    # ------------------------------------------------------------------ state in
    def state_enu(self, link: CfLink, now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """(q, v, rpy, w) of the UAV (ENU/FLU; the Crazyflie's world frame is the swarm's), or None
        if unhealthy or its blocks are older than ``link_timeout_s``."""
        with link.lock:
            if link.q is None or link.rpy is None or not link.healthy:
                return None
            if now - link.pos_rx > self.s.link_timeout_s or now - link.att_rx > self.s.link_timeout_s:
                return None
            if link.pos_ts_s is not None and link.offset_s is not None:
                link.state_age_s = now - (link.pos_ts_s + link.offset_s)
            return link.q.copy(), link.v.copy(), link.rpy.copy(), link.w.copy()

    def sample_time(self, link: CfLink) -> float | None:
        """When the vehicle measured its latest position, on the bridge's clock, s: the log
        block's own timestamp plus the clock offset of the fastest delivery seen."""
        with link.lock:
            if link.pos_ts_s is None or link.offset_s is None:
                return None
            return link.pos_ts_s + link.offset_s

    def failsafe(self) -> str:
        """The named failsafe for the collector: ``"2:link_lost,3:lost"``, or ``"none"``."""
        parts = [f"{lk.uav}:link_lost" for lk in self.links if not lk.healthy and lk.phase not in (DONE, REFUSED)]
        parts += [f"{lk.uav}:lost" for lk in self.links if lk.phase == LOST]
        parts += [f"{lk.uav}:positioning_lost" for lk in self.links if lk.positioning_lost]
        return ",".join(parts) or "none"

    def info(self, now: float) -> dict[str, Any]:
        uavs = {str(lk.uav): lk.info(now, self.s.rate_hz) for lk in self.links}
        return {
            "phases": ",".join(f"{lk.uav}:{lk.phase}" for lk in self.links),
            "armed_uavs": sum(1 for u in uavs.values() if u["armed"]),
            "airborne_uavs": sum(1 for u in uavs.values() if u["flying"]),
            "unhealthy_uavs": sum(1 for lk in self.links if not lk.healthy),
            "max_state_age_ms": max((u["state_age_ms"] for u in uavs.values()), default=-1.0),
            "positioning": self.s.positioning,
            "max_extpos_age_ms": max((u["extpos_age_ms"] for u in uavs.values()), default=-1.0),
            "failsafe": self.failsafe(),
            "refused": sum(1 for lk in self.links if lk.phase == REFUSED),
            "link_lost": int(self.counters["link_lost"]),
            **self._mission_traffic(now),
            "uav": uavs,
            "ready": [lk.uav for lk in self.links if lk.phase == READY],
        }

    def _mission_traffic(self, now: float) -> dict[str, float]:
        """What went over the links since each UAV's mission stream began, summed over the UAVs
        (``mission_*``: packets and bytes, CRTP header included, both ways) and the UAV-seconds
        it covers: per vehicle and second = ``mission_tx_bytes / mission_uav_s``."""
        out = {"mission_tx_packets": 0.0, "mission_tx_bytes": 0.0, "mission_rx_packets": 0.0, "mission_rx_bytes": 0.0, "mission_uav_s": 0.0}
        for lk in self.links:
            if lk.traffic0 is None:
                continue
            end, t1 = (lk.traffic1, lk.stream_t1) if lk.traffic1 is not None else (lk.traffic, now)
            for k in ("tx_packets", "tx_bytes", "rx_packets", "rx_bytes"):
                out[f"mission_{k}"] += end[k] - lk.traffic0[k]
            out["mission_uav_s"] += t1 - lk.stream_t0
        return out

    # ------------------------------------------------------------------ landing
    def _land(self, link: CfLink, now: float, why: str, phase: str = LANDING) -> None:
        """The handover back: stop the stream, the high-level commander's land, then
        notify-setpoint-stop so its setpoints are heard again (``commander.c``)."""
        link.streaming = False
        if link.traffic0 is not None and link.traffic1 is None:  # the mission's traffic ends here
            link.traffic1, link.stream_t1 = dict(link.traffic), now
        if link.cf is not None and link.cf.is_connected():
            link.cf.high_level_commander.land(0.0, self.s.land_duration_s)
            link.cf.commander.send_notify_setpoint_stop()
            self._count("land_requests")
        self._set_phase(link, phase, now, why)

    def begin_landing(self, now: float, why: str) -> None:
        for link in self.links:
            if link.phase in (READY, TAKEOFF, ARM) and not link.healthy:
                self._set_phase(link, LOST, now, f"{why}; link lost: left to its own commander watchdog")
            elif link.phase in (READY, TAKEOFF, ARM) or (link.phase == LOST and link.healthy and link.sup_info & BIT_FLYING):
                self._land(link, now, why)
            elif link.phase not in (DONE, REFUSED, LOST):
                self._set_phase(link, DONE, now, f"{why}; never flown")

    def land_step(self, now: float) -> bool:
        """One step of landing; True when every landing UAV is down and disarmed (or given up).
        Down: on the ground and ``supervisor.info`` no longer says flying (the firmware says so
        2 s after its motors stopped); then the bridge disarms it (``send_arming_request(False)``,
        twice a second until the vehicle reports disarmed)."""
        busy = False
        for link in self.links:
            if link.phase != LANDING:
                continue
            down = link.q is not None and link.q[2] < 0.05 and link.sup_info >= 0 and not link.sup_info & BIT_FLYING
            if down and not link.sup_info & BIT_ARMED and now - link.phase_t >= self.s.land_duration_s:
                self._set_phase(link, DONE, now, "landed by the high-level commander and disarmed")
                self._count("landed")
                continue
            busy = True
            if down and now - link.arm_t >= _ARM_RETRY_S:
                link.arm_t = now
                link.cf.supervisor.send_arming_request(False)
                self._count("disarm_requests")
        return not busy

    def give_up_landing(self, now: float) -> None:
        for link in self.links:
            if link.phase == LANDING:
                self._set_phase(link, DONE, now, f"not down after {self.s.land_timeout_s:g} s of landing; left to the high-level commander")
                self._count("land_timeouts")

    def close(self) -> None:
        for link in self.links:
            if link.probe is not None:
                link.probe.close()
            if link.cf is not None:
                try:
                    # cflib's latency pings first (joined from here): a ping sent on the link being
                    # closed fails in the ping thread, whose error callback then joins itself
                    # (RuntimeError "cannot join current thread", a traceback at the flight's end)
                    stats = getattr(link.cf, "link_statistics", None)
                    if stats is not None:
                        stats.stop()
                    link.cf.close_link()
                except Exception as e:  # noqa: BLE001 - closing is best effort; say why
                    self.log(f"bridge: uav {link.uav}: closing the link: {e}")


# --------------------------------------------------------------------------- process


def _run(proc: Any) -> int:
    from zenswarm.bridge.vehicles.mavlink import _BridgeLoop
    from zenswarm.link import FaultState

    sc = proc.scenario
    settings = crazyflie_settings(sc, proc.args.overrides())
    cmd_keys = [proc.keys.cmd(i + 1) for i in range(sc.n)]
    inbox = proc.inbox

    def latest(i: int) -> tuple[Any, float]:
        m = inbox.latest.get(cmd_keys[i - 1])
        if m is None:
            return None, math.inf
        return m, time.monotonic() - inbox.latest_rx.get(cmd_keys[i - 1], -math.inf)

    plan = proc.options.fault_plan(sc)
    if plan is not None:  # agent i's link to the bridge is the plant's `agent:i -> plant` cmd link
        proc.use_delay_line(FaultState(plan), {key: (f"agent:{i + 1}", "plant", "cmd") for i, key in enumerate(cmd_keys)})
    for key in cmd_keys:
        proc.subscribe(key, "cmd")
    bridge = CrazyflieBridge(settings, sc, proc.counters, latest, proc.log)
    proc.announce()
    mocap_sub = None
    if bridge.extpos:  # the external positioning feed, forwarded to each vehicle (zenswarm.bus.mocap)
        from zenswarm.bus.mocap import mocap_all

        def on_mocap(sample: Any) -> None:
            tail = str(sample.key_expr).rsplit("/", 1)[-1]
            if tail.isdigit():
                bridge.on_mocap(int(tail), sample.payload.to_bytes())

        mocap_sub = proc._zenoh().declare_subscriber(mocap_all(proc.keys.prefix), on_mocap)
        proc.log(f"bridge: positioning extpos: forwarding {mocap_all(proc.keys.prefix)} to the vehicles")
    loop = _BridgeLoop(proc, bridge, settings)  # type: ignore[arg-type]
    proc.log(
        f"bridge: {sc.n} Crazyflie(s), {1 / loop.period:g} Hz setpoints, " + ", ".join(f"uav {lk.uav}: {lk.uri}" for lk in bridge.links)
    )
    t_end: float | None = None
    try:
        bridge.open()
        loop.fly()
        loop.land()
        t_end = time.monotonic()  # the final figures (ages) as of the end of the flight, not after closing the links
    finally:
        if mocap_sub is not None:
            from zenswarm.bus import undeclare

            undeclare(mocap_sub)
        bridge.close()
    proc.publish_diag(
        max(loop.k_tick, 0) * loop.dt_ns, {**bridge.info(t_end or time.monotonic()), "finished": loop.finished, "closed": True}
    )
    return loop.code


def _cli_overrides(args: argparse.Namespace) -> dict[str, Any]:
    uris: dict[int, str] = {}
    for s in getattr(args, "uri", None) or []:
        i, sep, val = s.partition("=")
        if not sep or not i.strip().isdigit() or not val:
            raise ScenarioError("--uri", f"expected I=URI (I = UAV number), got {s!r}")
        if int(i) in uris:
            raise ScenarioError("--uri", f"UAV {int(i)} given twice")
        uris[int(i)] = val
    return {
        "uri": uris,
        "base_port": getattr(args, "base_port", None),
        "host": getattr(args, "cf_host", None),
        "rate_hz": getattr(args, "rate", None),
        "takeoff": False if getattr(args, "no_takeoff", False) else None,
        "link_timeout_s": getattr(args, "link_timeout", None),
        "land_timeout_s": getattr(args, "land_timeout", None),
        "connect_timeout_s": getattr(args, "connect_timeout", None),
        "start_timeout_s": getattr(args, "start_timeout", None),
        "positioning": getattr(args, "positioning", None),
    }


def bridge_settings(args: argparse.Namespace) -> CrazyflieBridgeSettings:
    """``zenswarm bridge crazyflie``'s flags as :class:`CrazyflieBridgeSettings`: the scenario
    file parsed (none given: fetched from the leader's mission), realtime; a bad file or flag is
    a ScenarioError naming it."""
    from zenswarm.bridge.args import process_settings
    from zenswarm.scenario.config import load_scenario

    path = args.scenario_path if getattr(args, "scenario_path", None) is not None else args.scenario
    sc = None if path is None else load_scenario(path)
    return CrazyflieBridgeSettings(process=process_settings(args, "bridge", sc, realtime=True), no_wait_alive=bool(args.no_wait_alive),
                                   **_cli_overrides(args))  # fmt: skip


def _no_cflib() -> bool:
    """cflib is not installed (said, exit 2)."""
    try:
        import cflib  # noqa: F401
    except ImportError:
        print("bridge: error: cflib is not installed: pip install 'zenswarm[crazyflie]'", file=sys.stderr, flush=True)
        return True
    return False


def run(s: CrazyflieBridgeSettings) -> int:
    """Run the bridge with these settings (its command's flags, or ``zenswarm up``'s on its
    standard input). Without cflib, or with bad ``[crazyflie]`` settings or overrides: exit 2
    naming the field before any work."""
    return 2 if _no_cflib() else run_bridge(s, crazyflie_settings, _run)


_main_flags = bridge_main(bridge_settings, run)


def _main_args(args: argparse.Namespace) -> int:
    return 2 if _no_cflib() else _main_flags(args)


def add_crazyflie_parser(bridge_sub: argparse._SubParsersAction) -> None:
    """Add ``crazyflie`` to the ``bridge`` command's subcommands."""
    from zenswarm.bridge.args import add_process_args

    p = bridge_sub.add_parser(
        "crazyflie",
        help="fly the swarm's agents on Crazyflies through cflib (or `crazyflie-vehicle`)",
        description=(__doc__ or "").split("\n\n")[0],
    )
    p.add_argument(
        "scenario_path", nargs="?", type=Path, metavar="SCENARIO", help="scenario TOML (its [crazyflie] table configures the links)"
    )
    add_process_args(p)
    g = p.add_argument_group("Crazyflie")
    g.add_argument("--uri", action="append", metavar="I=URI",
                   help="cflib link URI of UAV I: radio://0/80/2M/E7E7E7E701, udp://127.0.0.1:19850, usb://0 (repeatable; "
                   "overrides crazyflie.uris)")  # fmt: skip
    g.add_argument("--base-port", type=int, help="default URIs udp://HOST:P+i-1 (overrides crazyflie.base_port)")
    g.add_argument("--cf-host", help="host of the default URIs (overrides crazyflie.host)")
    g.add_argument("--rate", type=float, metavar="HZ", help="setpoint rate, >= 10 Hz (default the control rate)")
    g.add_argument("--no-takeoff", action="store_true", help="do not take off to the initial positions before the mission")
    g.add_argument("--link-timeout", type=float, metavar="S", help="log silence after which a vehicle is unhealthy (link_lost)")
    g.add_argument("--connect-timeout", type=float, metavar="S", help="give a vehicle up if cflib has not connected after S")
    g.add_argument("--land-timeout", type=float, metavar="S", help="wait at most S for the vehicles to land")
    g.add_argument("--start-timeout", type=float, metavar="S", help="start the mission after S even if some UAV is not ready")
    g.add_argument("--positioning", choices=("onboard", "extpos"),
                   help="extpos: forward swarm/<name>/mocap/<i> to each vehicle (overrides crazyflie.positioning)")  # fmt: skip
    g.add_argument("--no-wait-alive", action="store_true", help="start the mission clock without waiting for the leader and agents")
    g.add_argument("--expect", action="append", metavar="PROCESS", help="also wait for this process before starting the mission clock")
    p.set_defaults(func=_main_args)

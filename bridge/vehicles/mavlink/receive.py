"""What the MAVLink bridge reads (:class:`Receiver`): every endpoint drained each loop, each
message checked (bad CRC, unknown ids, other systems, non-finite fields: counted and ignored)
and stored in its UAV's telemetry: HEARTBEAT, LOCAL_POSITION_NED, ATTITUDE(_QUATERNION),
COMMAND_ACK, SYS_STATUS, EXTENDED_SYS_STATE, PARAM_VALUE, TIMESYNC (round trip and clock
offset); then each link's health (silent longer than ``link_timeout_s``: unhealthy)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

from zenswarm.bridge.vehicles.mavlink.core import BridgeCore
from zenswarm.bridge.vehicles.mavlink.link import CONNECTING, Endpoint, UavLink, mavlink
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import autopilot_name, param_value

__all__ = ["Receiver"]


def _finite(*xs: float) -> bool:
    return all(math.isfinite(x) for x in xs)


class Receiver(BridgeCore):
    """The bridge's receive side (see the module)."""

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

    _RX: ClassVar[dict[str, Callable[[Receiver, UavLink, Any, float], bool]]] = {
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

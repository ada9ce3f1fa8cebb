"""What the MAVLink bridge sends each loop (:class:`Setpoints`): a heartbeat per connection, a
TIMESYNC request per vehicle once a second, and one setpoint per engaged UAV: its agent's command
as SET_ATTITUDE_TARGET (or its reference as SET_POSITION_TARGET_LOCAL_NED), else a hold where the
vehicle is; and what it reads back out for the swarm: a UAV's state in the swarm frame and when
the vehicle measured it (on the bridge's clock, through the TIMESYNC offset)."""

from __future__ import annotations

from typing import Any

import numpy as np

from zenswarm.bridge.vehicles.mavlink.core import BridgeCore
from zenswarm.bridge.vehicles.mavlink.link import (
    CONNECTING,
    DONE,
    GROUNDED,
    LANDING,
    PARAMS,
    READY,
    REFUSED,
    RELEASED,
    TAKEOFF,
    UavLink,
    mavlink,
    vehicle_to_swarm,
)
from zenswarm.vehicle import frames

__all__ = ["Setpoints", "ATT_MASK", "POS_MASK"]

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
_TIMESYNC_S = 1.0  # TIMESYNC request period per vehicle (link latency)


class Setpoints(BridgeCore):
    """The bridge's send side and its states out (see the module)."""

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

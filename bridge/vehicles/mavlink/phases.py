"""The per-UAV phase machine of the MAVLink bridge (:class:`PhaseMachine`): connecting (the
first heartbeat), params (the autopilot's parameters read and checked, GUID_OPTIONS written on
ArduCopter), stream (setpoints before asking for the offboard mode), mode (asked, and seen in a
later heartbeat), arm (never a vehicle in a mode not asked for, nor one that reports itself
unhealthy: :func:`health_problem`), takeoff (to the initial position; ArduCopter's
NAV_TAKEOFF first), ready; and what a ready or climbing UAV does when its vehicle leaves the mode
or disarms (re-engage after a link loss, released, grounded)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import ClassVar

import numpy as np

from zenswarm.bridge.vehicles.mavlink.core import BridgeCore
from zenswarm.bridge.vehicles.mavlink.link import (
    ARM,
    CONNECTING,
    GROUNDED,
    MODE,
    PARAMS,
    READY,
    RELEASED,
    STREAM,
    TAKEOFF,
    UavLink,
    mavlink,
)
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import AUTOPILOT_PARAMS, GUID_OPTIONS_THRUST_AS_THRUST, VehicleParams, _same_mode, mode_name, vehicle_params

__all__ = ["PhaseMachine", "health_problem"]

_PARAM_RETRY_S = 0.5  # PARAM_REQUEST_READ / PARAM_SET repeated this often until answered
_SYS_STATUS_WAIT_S = 3.0  # ARM: no SYS_STATUS this long -> refused (health unknown)
_TAKEOFF_RETRY_S = 1.0
_MODE_RETRY_S = 1.0
_MODE_ATTEMPTS = 8
_ARM_RETRY_S = 1.0
_ARM_ATTEMPTS = 5
_MISMATCH_HEARTBEATS = 2  # heartbeats reporting another mode after an accepted request -> refuse

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


class PhaseMachine(BridgeCore):
    """The bridge's phase machine (see the module)."""

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
    _PHASE_STEPS: ClassVar[dict[str, Callable[[PhaseMachine, UavLink, float], None]]] = {
        CONNECTING: _step_connecting,
        PARAMS: _step_params,
        STREAM: _step_stream,
        MODE: _step_mode,
        ARM: _step_arm,
        TAKEOFF: _step_takeoff,
        READY: _step_ready,
    }

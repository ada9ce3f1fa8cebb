"""The MAVLink bridge's landing (:class:`Landing`): at the end of the mission or on a stop, every
vehicle it armed is switched to the land mode (PX4 AUTO.LAND, ArduPilot LAND) and waited for
until it reports disarmed (its own auto-disarm after touchdown); a normal disarm only once it is
in the land mode and still; never a forced one."""

from __future__ import annotations

import math

import numpy as np

from zenswarm.bridge.vehicles.mavlink.core import BridgeCore
from zenswarm.bridge.vehicles.mavlink.link import CONNECTING, DONE, LANDING, REFUSED, RELEASED, mavlink
from zenswarm.vehicle.autopilot import _same_mode, mode_name

__all__ = ["Landing"]


class Landing(BridgeCore):
    """The bridge's landing (see the module)."""

    def begin_landing(self, now: float, why: str) -> None:
        for link in self.links:
            if link.phase in (REFUSED, RELEASED, DONE, CONNECTING) or not link.armed_by_us:
                if link.phase != DONE and link.phase not in (REFUSED, RELEASED):
                    self._set_phase(link, DONE, now, f"{why}; never armed by the bridge")
                continue
            self._set_phase(link, LANDING, now, why)
            link.land_req_t = -math.inf

    def land_step(self, now: float) -> bool:
        """One step of landing; True when every landing UAV is disarmed (or given up).

        Asks for the land mode once a second until the vehicle reports it, then waits for the
        vehicle's own auto-disarm after touchdown. A normal (non-forced) disarm is sent only
        once the vehicle has been in the land mode and still (|v| < 0.1 m/s) for 2 s, so a
        vehicle that is still flying is never asked to stop its motors.
        """
        busy = False
        for link in self.links:
            if link.phase != LANDING:
                continue
            t = link.tel
            if not t.armed and t.hb_rx > link.phase_t:
                self._set_phase(link, DONE, now, "landed and disarmed")
                self._count("landed")
                continue
            busy = True
            in_land = _same_mode(link.autopilot, t.custom_mode, self._land_mode(link))
            still = in_land and t.vel_ned is not None and float(np.linalg.norm(t.vel_ned)) < 0.1
            if not still:
                link.still_since = math.inf
            elif not math.isfinite(link.still_since):
                link.still_since = now
            if now - link.land_req_t >= 1.0:
                link.land_req_t = now
                if not in_land:
                    self._request_mode(link, self._land_mode(link), now)
                elif now - link.still_since >= 2.0:
                    self._command(link, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0)
                    self._count("disarm_requests")
        return not busy

    def give_up_landing(self, now: float) -> None:
        """Landing timed out: report it. The vehicles are left in their land mode (they land and
        disarm by themselves); the bridge never force-disarms a vehicle that may be flying."""
        for link in self.links:
            if link.phase == LANDING:
                self._set_phase(
                    link, DONE, now,
                    f"still armed after {self.s.land_timeout_s:g} s of landing; left in "
                    f"{mode_name(link.autopilot, link.tel.custom_mode)}",
                )
                self._count("land_timeouts")

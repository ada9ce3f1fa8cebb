"""The MAVLink bridge's core (:class:`BridgeCore`): its links, one per UAV, on shared endpoints;
phase changes, the commands it sends (COMMAND_LONG, telemetry rates, mode requests), what it
knows of each vehicle (acknowledgements, airborne, ready), and the diag ``info`` map. What it
reads (:mod:`.receive`), the phase machine (:mod:`.phases`), the setpoints (:mod:`.setpoints`)
and the landing (:mod:`.landing`) build on it; :class:`zenswarm.bridge.vehicles.mavlink.bridge.Bridge`
is all of them."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from zenswarm.bridge.vehicles.mavlink.link import (
    ARM,
    CONNECTING,
    MODE,
    PARAMS,
    READY,
    REFUSED,
    STREAM,
    TAKEOFF,
    Endpoint,
    UavLink,
    mavlink,
    swarm_to_vehicle,
)
from zenswarm.scenario.config import Scenario
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import AP_COPTER_MODES, PX4_LAND, PX4_OFFBOARD, MavlinkSettings, mode_request_params

__all__ = ["BridgeCore"]

_PENDING = (CONNECTING, PARAMS, STREAM, MODE, ARM, TAKEOFF)
# MAV_LANDED_STATE (MAVLink common.xml, sent in EXTENDED_SYS_STATE): IN_AIR, TAKEOFF, LANDING
_AIRBORNE_STATES = (2, 3, 4)
_STALL_S = 0.25  # a bridge loop gap this long may have tripped an offboard-loss failsafe


class BridgeCore:
    """The bridge's core: its links and what the receive side, the phase machine, the setpoints
    and the landing share. The bus side is injected.

    Parameters
    ----------
    settings : MavlinkSettings
    scenario : Scenario
    counters : dict[str, float]
        Incremented in place (the process's diag counters).
    get_cmd, get_ref : callable(uav) -> (message or None, age s)
        The latest ``uav/<i>/cmd`` / ``uav/<i>/ref`` of the swarm and its age.
    log : callable(str)
    clock : callable() -> float
        Monotonic clock, s (time.monotonic).
    """

    def __init__(
        self,
        settings: MavlinkSettings,
        scenario: Scenario,
        counters: dict[str, float],
        get_cmd: Callable[[int], tuple[Any, float]],
        get_ref: Callable[[int], tuple[Any, float]],
        log: Callable[[str], None] = print,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        from zenswarm.vehicle.params import QuadParams

        self.s = settings
        self.sc = scenario
        self.counters = counters
        self.get_cmd = get_cmd
        self.get_ref = get_ref
        self.log = log
        self.clock = clock
        params = QuadParams.from_vehicle(scenario.vehicle)
        self.hover_thrust = params.hover_thrust
        self.max_thrust = params.max_thrust
        # until a vehicle's parameters are read: the hover_throttle setting, else thrust / max_thrust
        self.tmap = frames.ThrustMap(params.max_thrust, params.hover_thrust, settings.hover_throttle)
        self.yaw_ned = float(frames.euler_enu_to_ned([0.0, 0.0, scenario.controller.yaw])[2])
        self.endpoints: dict[str, Endpoint] = {}
        self.links: list[UavLink] = []
        self.boot = clock()
        self.changed = False  # a phase or health transition since the last diag (publish it now)
        self.warned_grounded = False  # the ArduCopter takeoff = false + position warning was given
        for i in range(settings.n):
            url = settings.connections[i]
            ep = self.endpoints.get(url)
            if ep is None:
                ep = self.endpoints[url] = Endpoint(url, settings.source_system)
            link = UavLink(
                uav=i + 1,
                sysid=settings.sysids[i],
                endpoint=ep,
                origin=np.array(settings.origins[i], dtype=float),
                takeoff_enu=np.array(scenario.initial_positions[i], dtype=float),
                phase_t=self.boot,
            )
            if settings.autopilot != "auto":
                link.autopilot = settings.autopilot
            ep.links[link.sysid] = link
            self.links.append(link)

    # ------------------------------------------------------------------ helpers
    def _count(self, name: str, k: float = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + k

    def _ms(self, now: float) -> int:
        return int((now - self.boot) * 1000.0) & 0xFFFFFFFF

    def _set_phase(self, link: UavLink, phase: str, now: float, reason: str | None = None) -> None:
        if link.phase != phase:
            self.changed = True
            if phase in (TAKEOFF, READY):
                link.hold_ned = None  # the pre-arm hold (on the ground) must not outlive its phase
            self.log(f"bridge: uav {link.uav}: {link.phase} -> {phase}" + (f" ({reason})" if reason else ""))
            link.phase = phase
            link.phase_t = now
        if reason is not None:
            link.reason = reason

    def _mav(self, link: UavLink) -> Any:
        c = link.endpoint.conn
        return None if c is None else c.mav

    def _ack(self, link: UavLink, command: int, since: float) -> int | None:
        for t, c, r in reversed(link.acks):
            if c == command and t >= since:
                return r
        return None

    # ------------------------------------------------------------------ commands
    def _command(self, link: UavLink, command: int, *params: float) -> None:
        mav = self._mav(link)
        if mav is None:
            return
        p = list(params) + [0.0] * (7 - len(params))
        mav.command_long_send(link.sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, command, 0, *p)

    def _request_telemetry(self, link: UavLink) -> None:
        """Ask the vehicle for LOCAL_POSITION_NED and ATTITUDE at ``telemetry_hz``
        (MAV_CMD_SET_MESSAGE_INTERVAL, param1 = message id, param2 = interval in us). PX4's onboard
        link streams both by default (30 and 100 Hz); ArduPilot sends on a port only what its
        SRn_* parameters or such a request ask for. The answer is not waited for."""
        if not self.s.request_telemetry:
            return
        interval_us = 1e6 / self.s.telemetry_hz
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            self._command(link, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)
        self._count("telemetry_requests")

    def _request_mode(self, link: UavLink, mode: int, now: float) -> None:
        self._command(link, mavlink.MAV_CMD_DO_SET_MODE, *mode_request_params(link.autopilot, mode))
        link.mode_req_t = now
        self._count("mode_requests")

    def _offboard_mode(self, link: UavLink) -> int:
        if link.autopilot == "ardupilot":
            need_pos = self.s.setpoint == "position" or (self.s.takeoff and not link.engaged_once)
            return AP_COPTER_MODES["GUIDED" if need_pos else "GUIDED_NOGPS"]
        return PX4_OFFBOARD

    def _land_mode(self, link: UavLink) -> int:
        return AP_COPTER_MODES["LAND"] if link.autopilot == "ardupilot" else PX4_LAND

    def note_stall(self, gap_s: float) -> None:
        """The bridge's own loop stopped for ``gap_s`` seconds (overloaded host, suspended
        process). Its setpoint streams were interrupted, so a vehicle that left the offboard mode
        meanwhile did so because of us: treat it like a link loss (re-engage), not like a pilot
        taking over."""
        if gap_s < _STALL_S:
            return
        self._count("loop_stalls")
        self.log(f"bridge: loop stalled for {gap_s:.2f} s (setpoints interrupted)")
        for link in self.links:
            if link.phase in (READY, TAKEOFF):
                link.was_lost = True
                link.recovered_t = max(link.recovered_t, self.clock())

    def _ack_time(self, link: UavLink) -> float:
        for t, c, _result in reversed(link.acks):
            if c == mavlink.MAV_CMD_DO_SET_MODE and t >= link.mode_req_t:
                return t
        return math.inf

    def _refuse(self, link: UavLink, now: float, reason: str) -> None:
        self._count("refused")
        self._set_phase(link, REFUSED, now, reason)

    def _needs_position(self, link: UavLink) -> bool:
        return not (link.autopilot == "ardupilot" and link.wanted_mode == AP_COPTER_MODES["GUIDED_NOGPS"])

    def _takeoff_ned(self, link: UavLink) -> np.ndarray:
        return swarm_to_vehicle(link.takeoff_enu, link.origin)

    def _airborne(self, link: UavLink) -> bool:
        """The vehicle is flying: EXTENDED_SYS_STATE's landed state if the vehicle sends it
        (IN_AIR, TAKEOFF, LANDING), else whether it took off under the bridge or was adopted in
        flight. Hover throttle is only ever sent to an airborne vehicle."""
        ls = link.tel.landed_state
        if ls is not None and ls != 0:  # 0: MAV_LANDED_STATE_UNDEFINED
            return ls in _AIRBORNE_STATES
        return link.airborne_known

    @property
    def settled(self) -> bool:
        """Every UAV ready or given up on (the mission clock may start)."""
        return all(link.phase not in _PENDING for link in self.links)

    @property
    def ready(self) -> list[UavLink]:
        return [link for link in self.links if link.phase == READY]

    def info(self, now: float) -> dict[str, Any]:
        """The diag ``info`` map: ``uav`` (per-UAV details), plus flat scalars that survive into
        the supervisor's results.json (``phases`` = ``"1:ready,2:ready,..."``, ``armed_uavs`` =
        how many vehicles report armed, ``unhealthy_uavs``)."""
        return {
            "phases": ",".join(f"{link.uav}:{link.phase}" for link in self.links),
            "armed_uavs": sum(1 for link in self.links if link.tel.armed),
            "unhealthy_uavs": sum(1 for link in self.links if not link.healthy),
            "airborne_uavs": sum(1 for link in self.links if self._airborne(link)),
            "max_latency_ms": max((round(lk.tel.rtt_s * 500.0, 2) for lk in self.links if lk.tel.rtt_s is not None), default=-1.0),
            "max_state_age_ms": max(
                (round(lk.state_age_s * 1000.0, 2) for lk in self.links if lk.state_age_s is not None), default=-1.0
            ),
            "uav": {str(link.uav): link.info(now) for link in self.links},
            "unhealthy": [link.uav for link in self.links if not link.healthy],
            "ready": [link.uav for link in self.links if link.phase == READY],
        }

    def close(self) -> None:
        for ep in self.endpoints.values():
            ep.close()

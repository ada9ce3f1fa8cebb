"""What a simulated MAVLink vehicle (:mod:`zenswarm.plant.mavlink_vehicle`) is configured with:
:class:`VehicleOptions` (the autopilot flavour, PX4 or ArduCopter; rates, failsafe times, the
vehicle's own position loop's gains, its UDP endpoint), the kinds of mode it flies (each flavour's
custom modes mapped to offboard, hold, land, takeoff, rtl: :meth:`VehicleOptions.mode_kind`), and
the options of a scenario's ``[mavlink]`` table (:func:`vehicle_options`).

Units inline; positions (``ground_z``) in the swarm's ENU frame, m (the MAVLink side is NED: see
:mod:`zenswarm.plant.mavlink.link`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from zenswarm.vehicle.autopilot import (
    AP_COPTER_MODES,
    PX4_AUTO_SUB,
    PX4_HOLD,
    PX4_LAND,
    PX4_MAIN,
    PX4_OFFBOARD,
    mavlink_settings,
    px4_decode,
)

__all__ = ["VehicleOptions", "vehicle_options", "OFFBOARD", "HOLD", "LAND", "TAKEOFF", "RTL"]

# mode kinds
OFFBOARD, HOLD, LAND, TAKEOFF, RTL = "offboard", "hold", "land", "takeoff", "rtl"


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
    own_origin: each vehicle's local NED origin is where it booted (its estimator origin, as on a
        real autopilot); False: every vehicle reports NED about the swarm's ENU origin (legacy).
    sitl_ports: PX4 SITL's UDP direction: vehicle i (0-based) sends from ``base_port + 40 + i``
        to ``base_port + i`` (PX4 SITL: from 14580+i to 14540+i) from boot on, and a ground
        station listens with ``udpin``; False: the vehicle listens on ``base_port + i``.
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
    own_origin: bool = False
    sitl_ports: bool = False

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
                AP_COPTER_MODES["RTL"]: RTL,
            }.get(int(custom_mode))
        main, sub = px4_decode(custom_mode)
        if main == PX4_MAIN["OFFBOARD"] and sub == 0:
            return OFFBOARD
        if main in (PX4_MAIN["POSCTL"], PX4_MAIN["ALTCTL"]) and sub == 0:
            return HOLD
        if main == PX4_MAIN["AUTO"]:
            return {
                PX4_AUTO_SUB["LOITER"]: HOLD,
                PX4_AUTO_SUB["LAND"]: LAND,
                PX4_AUTO_SUB["TAKEOFF"]: TAKEOFF,
                PX4_AUTO_SUB["RTL"]: RTL,
            }.get(sub)
        return None


def vehicle_options(sc: Any) -> VehicleOptions:
    """The :class:`VehicleOptions` of a scenario's ``[mavlink]`` table (``autopilot``,
    ``telemetry_hz``, ``offboard_loss_s``, ``failsafe_land_s``, ``ground_z``, ``hover_throttle``,
    ``host``)."""
    ms = mavlink_settings(sc)
    return VehicleOptions(
        autopilot="ardupilot" if ms.autopilot == "ardupilot" else "px4",
        telemetry_hz=ms.telemetry_hz,
        offboard_loss_s=ms.offboard_loss_s,
        failsafe_land_s=ms.failsafe_land_s,
        ground_z=ms.ground_z,
        hover_throttle=ms.hover_throttle,
        host=ms.host,
    )

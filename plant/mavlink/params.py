"""The parameters of the simulated MAVLink vehicles (:mod:`zenswarm.plant.mavlink_vehicle`) and
their MAVLink parameter protocol, for a PX4 and for an ArduCopter vehicle.

Only the parameters whose value the simulated vehicle follows, or that a ground station or the
bridge reads before flying, are present; their names, types and defaults are the autopilots'
(cited per parameter). A few defaults are the *vehicle's* rather than the firmware's (a tuned
vehicle): ``MPC_THR_HOVER`` / ``MOT_THST_HOVER`` are the simulated airframe's real hover
throttle, and the system-id parameters are the vehicle's id.

Protocol (https://mavlink.io/en/services/parameter.html): PARAM_REQUEST_LIST -> every
PARAM_VALUE in index order; PARAM_REQUEST_READ by name (``param_index`` = -1) or by index ->
that PARAM_VALUE, nothing for an unknown parameter (both autopilots stay silent); PARAM_SET of
a known name -> the value is stored (clamped to the parameter's range, integers rounded) and
echoed with PARAM_VALUE; an unknown name is ignored.

Value encoding in the float field of PARAM_VALUE / PARAM_SET differs between the autopilots:
PX4 copies the bytes of an INT32 parameter into the float (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_
BYTEWISE; PX4 ``src/modules/mavlink/mavlink_parameters.cpp``: ``memcpy(&msg.param_value, &i,
sizeof(int32_t))``), ArduPilot sends the numeric value cast to float whatever the type
(MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST; ``libraries/GCS_MAVLink/GCS_Param.cpp``,
``AP_Param::cast_to_float``). :func:`encode` / :func:`decode` do both.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

__all__ = ["ParamSpec", "ParamStore", "px4_params", "ardupilot_params", "encode", "decode", "REAL32", "INT32"]

REAL32 = 9  # MAV_PARAM_TYPE_REAL32
INT32 = 6  # MAV_PARAM_TYPE_INT32


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: name (at most 16 characters), MAV_PARAM_TYPE (REAL32 or INT32), default,
    range [lo, hi] (values set are clamped to it), unit, and where the default comes from."""

    name: str
    type: int
    default: float
    lo: float = -math.inf
    hi: float = math.inf
    unit: str = ""
    source: str = ""


def px4_params(sysid: int, hover_throttle: float, offboard_loss_s: float, land_speed: float | None) -> list[ParamSpec]:
    """The PX4 parameters the simulated PX4 vehicle has (and follows).

    hover_throttle: the airframe's hover throttle (MPC_THR_HOVER of a tuned vehicle; the firmware
    default is 0.5). offboard_loss_s: COM_OF_LOSS_T (firmware default 1.0 s). land_speed:
    MPC_LAND_SPEED, None for the firmware default."""
    mpc = "PX4 src/modules/mc_pos_control/multicopter_*_params.c"
    return [
        # MAVLink system id (src/modules/mavlink/mavlink_params.c: MAV_SYS_ID, default 1)
        ParamSpec("MAV_SYS_ID", INT32, float(sysid), 1, 250, "", "src/modules/mavlink/mavlink_params.c"),
        # Hover thrust: the position controller's thrust at zero acceleration (default 0.5)
        ParamSpec("MPC_THR_HOVER", REAL32, float(hover_throttle), 0.1, 0.8, "norm", mpc),
        # Offboard loss timeout: no setpoint this long in OFFBOARD -> failsafe (default 1.0 s;
        # src/modules/commander/commander_params.c)
        ParamSpec("COM_OF_LOSS_T", REAL32, float(offboard_loss_s), 0.0, 60.0, "s", "src/modules/commander/commander_params.c"),
        # Takeoff altitude above home of MAV_CMD_NAV_TAKEOFF without an altitude (default 2.5 m;
        # src/modules/navigator/mission_params.c; docs.px4.io flight_modes_mc/takeoff)
        ParamSpec("MIS_TAKEOFF_ALT", REAL32, 2.5, 0.0, 100.0, "m", "src/modules/navigator/mission_params.c"),
        # Takeoff climb rate (default 1.5 m/s; docs.px4.io flight_modes_mc/takeoff)
        ParamSpec("MPC_TKO_SPEED", REAL32, 1.5, 1.0, 5.0, "m/s", mpc),
        # Land descent rate (default 0.7 m/s; docs.px4.io flight_modes_mc/land)
        ParamSpec("MPC_LAND_SPEED", REAL32, 0.7 if land_speed is None else float(land_speed), 0.1, 5.0, "m/s", mpc),
        # Auto-disarm this long after landing (default 2.0 s; commander_params.c)
        ParamSpec("COM_DISARM_LAND", REAL32, 2.0, -1.0, 20.0, "s", "src/modules/commander/commander_params.c"),
        # Return mode: climb to at least this altitude above home (default 60 m), then descend
        # over home to RTL_DESCEND_ALT (30 m) and land (docs.px4.io flight_modes_mc/return;
        # src/modules/navigator/rtl_params.c)
        ParamSpec("RTL_RETURN_ALT", REAL32, 60.0, 0.0, 150.0, "m", "src/modules/navigator/rtl_params.c"),
        ParamSpec("RTL_DESCEND_ALT", REAL32, 30.0, 0.0, 100.0, "m", "src/modules/navigator/rtl_params.c"),
        # Maximum ascent / descent velocity in auto modes (defaults 3 m/s, 1.5 m/s)
        ParamSpec("MPC_Z_VEL_MAX_UP", REAL32, 3.0, 0.5, 8.0, "m/s", mpc),
        ParamSpec("MPC_Z_VEL_MAX_DN", REAL32, 1.5, 0.5, 4.0, "m/s", mpc),
    ]


def ardupilot_params(sysid: int, hover_throttle: float, land_speed: float | None) -> list[ParamSpec]:
    """The ArduCopter parameters the simulated ArduCopter vehicle has (and follows).

    hover_throttle: MOT_THST_HOVER of a vehicle that has learnt it (firmware default 0.35).
    land_speed: LAND_SPEED in m/s, None for the firmware default (50 cm/s)."""
    params_cpp = "ArduCopter/Parameters.cpp"
    return [
        # MAVLink system id (default 1) and the ground station's (default 255)
        ParamSpec("SYSID_THISMAV", INT32, float(sysid), 1, 255, "", params_cpp),
        ParamSpec("SYSID_MYGCS", INT32, 255.0, 1, 255, "", params_cpp),
        # Guided mode options bitmask (default 0). Bit 3 (8) "SetAttitudeTarget interprets Thrust
        # As Thrust": unset, SET_ATTITUDE_TARGET.thrust is a climb rate, 0.5 = hold altitude
        # (ArduCopter/mode.h ModeGuided::Option::SetAttitudeTarget_ThrustAsThrust,
        # mode_guided.cpp set_attitude_target_provides_thrust, GCS_Mavlink.cpp)
        ParamSpec("GUID_OPTIONS", INT32, 0.0, 0, 2**31 - 1, "", params_cpp),
        # Guided timeout: velocity / acceleration / angle / rate targets older than this are
        # dropped (stop, or level out and hold altitude) (default 3 s; mode_guided.cpp get_timeout_ms)
        ParamSpec("GUID_TIMEOUT", REAL32, 3.0, 0.1, 5.0, "s", params_cpp),
        # Climb / descent rate that thrust 1.0 / 0.0 means when the thrust field is a climb rate,
        # and the takeoff climb rate (AC_WPNav: defaults 250 cm/s and 150 cm/s)
        ParamSpec("WPNAV_SPEED_UP", REAL32, 250.0, 10.0, 1000.0, "cm/s", "libraries/AC_WPNav/AC_WPNav.cpp"),
        ParamSpec("WPNAV_SPEED_DN", REAL32, 150.0, 10.0, 500.0, "cm/s", "libraries/AC_WPNav/AC_WPNav.cpp"),
        # Final descent rate of LAND (default 50 cm/s)
        ParamSpec("LAND_SPEED", REAL32, 50.0 if land_speed is None else 100.0 * float(land_speed), 30.0, 200.0, "cm/s", params_cpp),
        # Auto-disarm after this long landed with the motors idle (default 10 s)
        ParamSpec("DISARM_DELAY", INT32, 10.0, 0, 127, "s", params_cpp),
        ParamSpec("MOT_SPOOL_TIME", REAL32, 0.5, 0.0, 2.0, "s", "libraries/AP_Motors/AP_MotorsMulticopter.cpp"),
        # RTL: climb to at least this altitude above home (default 1500 cm), return, land
        ParamSpec("RTL_ALT", INT32, 1500.0, 200, 300000, "cm", params_cpp),
        # Learnt hover throttle (libraries/AP_Motors/AP_MotorsMulticopter.cpp, default 0.35)
        ParamSpec("MOT_THST_HOVER", REAL32, float(hover_throttle), 0.125, 0.6875, "norm", "libraries/AP_Motors/AP_MotorsMulticopter.cpp"),
    ]


def encode(value: float, ptype: int, bytewise: bool) -> float:
    """The float that carries ``value`` in PARAM_VALUE / PARAM_SET: the value itself (REAL32, or
    ArduPilot's C cast), or for a PX4 INT32 the int32's bytes read as a float32."""
    if ptype == INT32 and bytewise:
        return float(struct.unpack("<f", struct.pack("<i", int(round(value))))[0])
    return float(value)


def decode(carrier: float, ptype: int, bytewise: bool) -> float:
    """Inverse of :func:`encode`."""
    if ptype == INT32 and bytewise:
        return float(struct.unpack("<i", struct.pack("<f", carrier))[0])
    return float(carrier)


class ParamStore:
    """The parameter values of one vehicle, in index order. ``bytewise``: PX4's INT32 encoding."""

    def __init__(self, specs: list[ParamSpec], bytewise: bool) -> None:
        names = [s.name for s in specs]
        if len(set(names)) != len(names) or any(len(n) > 16 for n in names):
            raise ValueError(f"parameter names must be unique and at most 16 characters: {names}")
        self.specs = list(specs)
        self.bytewise = bool(bytewise)
        self.index = {s.name: i for i, s in enumerate(specs)}
        self.values = [float(s.default) for s in specs]
        self.sets = 0  # PARAM_SETs accepted

    def __len__(self) -> int:
        return len(self.specs)

    def __contains__(self, name: object) -> bool:
        return name in self.index

    def __getitem__(self, name: str) -> float:
        return self.values[self.index[name]]

    def set(self, name: str, value: float) -> bool:
        """Store ``value`` (clamped to the range, INT32 rounded); False for an unknown name or a
        non-finite value (nothing stored)."""
        i = self.index.get(name)
        if i is None or not math.isfinite(value):
            return False
        s = self.specs[i]
        v = min(max(float(value), s.lo), s.hi)
        self.values[i] = float(round(v)) if s.type == INT32 else v
        self.sets += 1
        return True

    def value_msg(self, i: int) -> tuple[bytes, float, int, int, int]:
        """(param_id, encoded value, param_type, param_count, param_index) of parameter ``i``:
        the fields of PARAM_VALUE."""
        s = self.specs[i]
        return s.name.encode("ascii"), encode(self.values[i], s.type, self.bytewise), s.type, len(self.specs), i

    def lookup(self, param_id: str | bytes, param_index: int) -> int | None:
        """Index of the parameter a PARAM_REQUEST_READ names (by name when ``param_index`` is -1,
        else by index), None if unknown."""
        if param_index >= 0:
            return param_index if param_index < len(self.specs) else None
        return self.index.get(_name(param_id))

    def handle_set(self, param_id: str | bytes, carrier: float) -> int | None:
        """A PARAM_SET: store the decoded value; the index to echo, None if unknown (ignored)."""
        name = _name(param_id)
        i = self.index.get(name)
        if i is None:
            return None
        if not self.set(name, decode(carrier, self.specs[i].type, self.bytewise)):
            return None
        return i


def _name(param_id: str | bytes) -> str:
    if isinstance(param_id, bytes):
        param_id = param_id.decode("ascii", errors="replace")
    return param_id.split("\x00", 1)[0]

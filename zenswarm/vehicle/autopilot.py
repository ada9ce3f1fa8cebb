"""What a zenswarm process needs to know about PX4 and ArduPilot, without speaking MAVLink.

The flight-mode tables of both autopilots (HEARTBEAT ``custom_mode`` numbers, as the vehicles
report them and as MAV_CMD_DO_SET_MODE asks for them) and the scenario's ``[mavlink]`` table
(:func:`mavlink_settings`). Both the MAVLink bridge (``bridge/vehicles/mavlink/``) and the simulated
MAVLink vehicles (``plant/mavlink_vehicle.py``) use them, so they live in the base layer.
Standard library only; :func:`load_mavutil` imports pymavlink when called.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from zenswarm.errors import ScenarioError
from zenswarm.schema import MavlinkTable, ScenarioTables, convert, to_builtins

__all__ = [
    "SITL_SEND_OFFSET",
    "PX4_MAIN",
    "PX4_AUTO_SUB",
    "AP_COPTER_MODES",
    "px4_custom_mode",
    "px4_decode",
    "PX4_OFFBOARD",
    "PX4_HOLD",
    "PX4_LAND",
    "PX4_POSCTL",
    "mode_name",
    "mode_request_params",
    "autopilot_name",
    "MavlinkSettings",
    "mavlink_settings",
    "load_mavutil",
    "AUTOPILOT_PARAMS",
    "GUID_OPTIONS_THRUST_AS_THRUST",
    "VehicleParams",
    "vehicle_params",
    "param_value",
]

SITL_SEND_OFFSET = 40
"""Simulated MAVLink vehicle i (0-based) on UDP ``base_port + i`` sends from ``base_port + 40 + i``
(PX4 SITL: 14580+i -> 14540+i): the bridge, ``zenswarm up`` and the simulated vehicles agree on it."""


def load_mavutil() -> Any:
    """pymavlink's ``mavutil``, speaking MAVLink 2: sets ``MAVLINK20=1`` in the environment before
    the import (PX4 and ArduPilot both speak MAVLink 2), so every connection of the process does."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil as mu

    if getattr(mu.mavlink, "WIRE_PROTOCOL_VERSION", "1.0") != "2.0":
        mu.set_dialect(mu.current_dialect)
    return mu

# --------------------------------------------------------------------------- MAVLink modes

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
"""``MAV_AUTOPILOT`` of ArduPilot in HEARTBEAT.autopilot (MAVLink common.xml)."""

MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
"""``MAV_MODE_FLAG`` bit saying ``custom_mode`` is meaningful (MAVLink common.xml)."""

PX4_MAIN: dict[str, int] = {
    "MANUAL": 1,
    "ALTCTL": 2,
    "POSCTL": 3,
    "AUTO": 4,
    "ACRO": 5,
    "OFFBOARD": 6,
    "STABILIZED": 7,
    "RATTITUDE": 8,
}
"""PX4 custom main modes (``PX4_CUSTOM_MAIN_MODE`` in PX4's ``px4_custom_mode.h``)."""

PX4_AUTO_SUB: dict[str, int] = {"READY": 1, "TAKEOFF": 2, "LOITER": 3, "MISSION": 4, "RTL": 5, "LAND": 6}
"""PX4 sub modes of main mode AUTO (``PX4_CUSTOM_SUB_MODE_AUTO``)."""

AP_COPTER_MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "LAND": 9,
    "POSHOLD": 16,
    "BRAKE": 17,
    "GUIDED_NOGPS": 20,
}
"""ArduCopter flight mode numbers (HEARTBEAT.custom_mode, DO_SET_MODE param2)."""


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 HEARTBEAT.custom_mode for (main, sub): the union ``{uint16 reserved; uint8 main_mode;
    uint8 sub_mode}`` read as a little-endian uint32: ``main << 16 | sub << 24``."""
    return ((int(main) & 0xFF) << 16) | ((int(sub) & 0xFF) << 24)


def px4_decode(custom_mode: int) -> tuple[int, int]:
    """(main_mode, sub_mode) of a PX4 custom_mode."""
    return (int(custom_mode) >> 16) & 0xFF, (int(custom_mode) >> 24) & 0xFF


PX4_OFFBOARD = px4_custom_mode(PX4_MAIN["OFFBOARD"])
PX4_HOLD = px4_custom_mode(PX4_MAIN["AUTO"], PX4_AUTO_SUB["LOITER"])
PX4_LAND = px4_custom_mode(PX4_MAIN["AUTO"], PX4_AUTO_SUB["LAND"])
PX4_POSCTL = px4_custom_mode(PX4_MAIN["POSCTL"])

_PX4_MAIN_NAME = {v: k for k, v in PX4_MAIN.items()}
_PX4_SUB_NAME = {v: k for k, v in PX4_AUTO_SUB.items()}
_AP_NAME = {v: k for k, v in AP_COPTER_MODES.items()}


def autopilot_name(mav_autopilot: int) -> str:
    """'px4' for MAV_AUTOPILOT_PX4, 'ardupilot' for MAV_AUTOPILOT_ARDUPILOTMEGA, else 'px4'
    (a generic autopilot is driven like PX4)."""
    return "ardupilot" if int(mav_autopilot) == MAV_AUTOPILOT_ARDUPILOTMEGA else "px4"


def mode_name(autopilot: str, custom_mode: int | None) -> str:
    """Readable mode, e.g. ``OFFBOARD``, ``AUTO.LOITER``, ``GUIDED_NOGPS``, ``?(1234)``."""
    if custom_mode is None:
        return "unknown"
    if autopilot == "ardupilot":
        return _AP_NAME.get(int(custom_mode), f"?({custom_mode})")
    main, sub = px4_decode(custom_mode)
    name = _PX4_MAIN_NAME.get(main)
    if name is None:
        return f"?({custom_mode})"
    if main == PX4_MAIN["AUTO"]:
        return f"AUTO.{_PX4_SUB_NAME.get(sub, str(sub))}"
    return name


def mode_request_params(autopilot: str, custom_mode: int) -> tuple[float, float, float]:
    """(param1, param2, param3) of MAV_CMD_DO_SET_MODE for ``custom_mode``: param1 =
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED; PX4: param2 = main mode, param3 = sub mode; ArduPilot:
    param2 = mode number."""
    flag = float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    if autopilot == "ardupilot":
        return flag, float(custom_mode), 0.0
    main, sub = px4_decode(custom_mode)
    return flag, float(main), float(sub)


def _same_mode(autopilot: str, a: int | None, b: int | None) -> bool:
    if a is None or b is None:
        return False
    if autopilot == "ardupilot":
        return int(a) == int(b)
    ma, sa = px4_decode(a)
    mb, sb = px4_decode(b)
    if ma != mb:
        return False
    return ma != PX4_MAIN["AUTO"] or sa == sb  # the sub mode matters only for AUTO


# --------------------------------------------------------------------------- settings

_MAV_KEYS: dict[str, str] = {
    "connections": "list of pymavlink connection strings, one per UAV (default udpout:HOST:BASE_PORT+i-1)",
    "sysids": "list of MAVLink system ids, one per UAV (default 1..N)",
    "origins": "list of [x, y, z], m ENU: where each vehicle's local NED origin is in the swarm frame (default 0)",
    "host": "host of the simulated vehicles (default 127.0.0.1)",
    "base_port": "UDP port of vehicle 1; vehicle i on base_port + i - 1 (default 14540)",
    "autopilot": "px4 | ardupilot | auto (bridge: from the vehicle's heartbeat; default auto)",
    "setpoint": "attitude (SET_ATTITUDE_TARGET from uav/<i>/cmd) | position (SET_POSITION_TARGET_LOCAL_NED from uav/<i>/ref)",
    "rate_hz": "minimum setpoint rate, Hz, >= 20 (default max(20, control rate))",
    "hover_throttle": (
        "normalised throttle at which the vehicle hovers, (0, 1): overrides the vehicle's MPC_THR_HOVER / MOT_THST_HOVER "
        "(default: read from the vehicle; before that, thrust / max_thrust)"
    ),
    "takeoff": "fly to the scenario's initial positions before the mission (default true)",
    "takeoff_tolerance_m": "takeoff done within this distance, m (default 0.08)",
    "takeoff_timeout_s": "give up a takeoff after this long, s (default 30)",
    "link_timeout_s": (
        "a vehicle silent this long is unhealthy, s (default 0.5); must be below the simulated vehicles' offboard_loss_s "
        "and, checked on each vehicle before arming, below PX4 COM_OF_LOSS_T / ArduPilot GUID_TIMEOUT"
    ),
    "params_timeout_s": "give up reading (or setting) a vehicle's parameters after this long: the UAV is refused, s (default 5)",
    "stream_s": "setpoints streamed before asking for the offboard mode, s (default 1.0)",
    "cmd_timeout_s": "an agent command older than this is replaced by a position hold, s (default 0.5)",
    "land_timeout_s": "wait at most this long for the vehicles to land and disarm, s (default 15)",
    "start_timeout_s": "start the mission clock after this long even if some UAV is not ready, s (default 60)",
    "reengage": "after a link loss, ask a still-armed vehicle for the offboard mode again (default true)",
    "source_system": "the bridge's MAVLink system id (default 245)",
    "telemetry_hz": (
        "LOCAL_POSITION_NED and ATTITUDE rate, Hz: the simulated vehicles send at it, the bridge asks real ones for it (default 50)"
    ),
    "request_telemetry": (
        "ask each vehicle for telemetry_hz with MAV_CMD_SET_MESSAGE_INTERVAL on connect and after a link loss (default true)"
    ),
    "offboard_loss_s": "simulated vehicle: no setpoint this long -> hold (PX4 COM_OF_LOSS_T, whose default is also 1 s), s (default 1.0)",
    "failsafe_land_s": "simulated vehicle: hold this long after the loss, then land, s (default 5)",
    "ground_z": "simulated vehicle: ground height, m ENU (default 0)",
}


@dataclass(frozen=True)
class MavlinkSettings:
    """Validated ``[mavlink]`` table plus command-line overrides (see ``_MAV_KEYS`` for units)."""

    n: int
    connections: tuple[str, ...]
    sysids: tuple[int, ...]
    origins: tuple[tuple[float, float, float], ...]
    host: str = "127.0.0.1"
    base_port: int = 14540
    autopilot: str = "auto"
    setpoint: str = "attitude"
    rate_hz: float = 20.0
    hover_throttle: float | None = None
    takeoff: bool = True
    takeoff_tolerance_m: float = 0.08
    takeoff_timeout_s: float = 30.0
    link_timeout_s: float = 0.5
    params_timeout_s: float = 5.0
    stream_s: float = 1.0
    cmd_timeout_s: float = 0.5
    land_timeout_s: float = 15.0
    start_timeout_s: float = 60.0
    reengage: bool = True
    source_system: int = 245
    telemetry_hz: float = 50.0
    request_telemetry: bool = True
    offboard_loss_s: float = 1.0
    failsafe_land_s: float = 5.0
    ground_z: float = 0.0


def _int(fieldname: str, x: Any, lo: int, hi: int) -> int:
    if isinstance(x, bool) or not isinstance(x, int) or not lo <= x <= hi:
        raise ScenarioError(fieldname, f"expected an integer in {lo}..{hi}, got {x!r}")
    return int(x)


_URL_SCHEMES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")


def _check_url(fieldname: str, url: Any) -> str:
    """A pymavlink connection string for a live link (not a log file): udpin:, udpout:, udp:,
    udpbcast:, tcp:, tcpin: HOST:PORT, or a serial device (``/dev/...`` or ``COMn``, optionally
    ``,BAUD``)."""
    if not isinstance(url, str) or not url:
        raise ScenarioError(fieldname, f"expected a connection string, got {url!r}")
    if url.startswith(_URL_SCHEMES):
        host, sep, port = url.split(":", 1)[1].rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ScenarioError(fieldname, f"expected SCHEME:HOST:PORT, got {url!r}")
        return url
    dev = url.split(",", 1)[0]
    if dev.startswith("/dev/") or (dev.upper().startswith("COM") and dev[3:].isdigit()):
        return url
    raise ScenarioError(
        fieldname, f"{url!r} is not a live MAVLink link: use udpin:/udpout:/tcp:HOST:PORT or a serial device /dev/...[,BAUD]"
    )


def _per_uav(t: MavlinkTable, name: str, n: int, what: str) -> None:
    v = getattr(t, name)
    if v is not None and len(v) != n:
        raise ScenarioError(f"mavlink.{name}", f"expected a list of {n} {what} (one per UAV), got {len(v)}")


def _table_with(sc: ScenarioTables, cli: dict[str, Any]) -> MavlinkTable:
    """The scenario's ``[mavlink]`` table with the command-line overrides (None values ignored)
    applied, validated by the schema; the per-UAV lists have N entries."""
    t = sc.mavlink or MavlinkTable()
    over = {k: v for k, v in cli.items() if v is not None}
    for k in over:
        if k not in _MAV_KEYS:
            raise ScenarioError(f"--{k}", "unknown setting")
    if over:
        t = convert({**to_builtins(t, omit_defaults=True), **over}, MavlinkTable, "mavlink")
    n = sc.n
    if t.base_port > 65535 - n + 1:
        raise ScenarioError("mavlink.base_port", f"expected an integer in 1..{65535 - n + 1} ({n} UAVs), got {t.base_port}")
    _per_uav(t, "connections", n, "connection strings")
    _per_uav(t, "sysids", n, "system ids")
    _per_uav(t, "origins", n, "[x, y, z] points, m ENU")
    if not t.link_timeout_s < t.offboard_loss_s:
        # the bridge must notice a silent vehicle before the vehicle's own offboard-loss failsafe
        # fires, or the failsafe's mode change looks like a pilot taking over (docs/mavlink.md)
        raise ScenarioError(
            "mavlink.link_timeout_s",
            f"must be below mavlink.offboard_loss_s ({t.offboard_loss_s:g} s, the vehicles' offboard-loss time), got {t.link_timeout_s:g}",
        )
    return t


def _override(flag: str, values: list[Any], over: dict[int, Any], check: Any) -> None:
    """Replace values[i - 1] by check(flag, over[i]) for each UAV i of ``over`` (1-based)."""
    for i, v in over.items():
        if not 1 <= i <= len(values):
            raise ScenarioError(flag, f"UAV {i} is not in 1..{len(values)}")
        values[i - 1] = check(flag, v)


def _check_origin(flag: str, o: Any) -> tuple[float, float, float]:
    import math

    if not isinstance(o, (tuple, list)) or len(o) != 3 or not all(isinstance(c, (int, float)) and math.isfinite(c) for c in o):
        raise ScenarioError(flag, f"expected X,Y,Z (m, ENU, finite), got {o!r}")
    return (float(o[0]), float(o[1]), float(o[2]))


def _links(t: MavlinkTable, n: int, conn_over: dict[int, str], sysid_over: dict[int, int]) -> tuple[list[str], list[int]]:
    """Connection string and system id of each UAV; a (connection, id) pair names one vehicle."""
    conns = list(t.connections or [f"udpout:{t.host}:{t.base_port + i}" for i in range(n)])
    for k, url in enumerate(conns):
        _check_url(f"mavlink.connections[{k}]", url)
    _override("--conn", conns, conn_over, _check_url)
    sysids = list(t.sysids or range(1, n + 1))
    _override("--sysid", sysids, sysid_over, lambda f, s: _int(f, s, 1, 254))
    seen: dict[int, int] = {}
    for i, s in enumerate(sysids):
        # MAVLink system ids must be unique on a network (routers and ground stations tell the
        # vehicles apart by id alone), whether or not the vehicles share a connection
        if s in seen:
            where = "share connection " + repr(conns[i]) + " and" if conns[i] == conns[seen[s]] else "have the same"
            raise ScenarioError("mavlink.sysids", f"UAV {seen[s] + 1} and UAV {i + 1} {where} system id {s}: give each vehicle its own")
        if s == t.source_system:
            raise ScenarioError(
                "mavlink.sysids",
                f"UAV {i + 1} has system id {s}, the bridge's own (mavlink.source_system): the bridge would take "
                "its own messages for the vehicle's; change one of them",
            )
        seen[s] = i
    return conns, sysids


# --------------------------------------------------------------------------- parameters

AUTOPILOT_PARAMS: dict[str, tuple[str, ...]] = {
    "px4": ("MPC_THR_HOVER", "COM_OF_LOSS_T"),
    "ardupilot": ("GUID_OPTIONS", "GUID_TIMEOUT", "MOT_THST_HOVER"),
}
"""Parameters the bridge reads (PARAM_REQUEST_READ) from each vehicle before arming.

PX4: ``MPC_THR_HOVER`` (hover thrust, normalised 0..1: the throttle of SET_ATTITUDE_TARGET at
which the vehicle hovers; PX4 ``mc_pos_control`` parameters) and ``COM_OF_LOSS_T`` (s without
offboard setpoints before the offboard-loss failsafe; PX4 ``commander`` parameters).
ArduCopter: ``GUID_OPTIONS`` (bitmask; bit 3 ``SetAttitudeTarget_ThrustAsThrust``, ArduCopter
``mode.h``), ``GUID_TIMEOUT`` (s without guided setpoints before the vehicle stops following
them: levels out / holds; ArduCopter ``Parameters.cpp``) and ``MOT_THST_HOVER`` (the learnt
hover throttle, 0..1; ``AP_MotorsMulticopter.cpp``: with thrust as thrust, SET_ATTITUDE_TARGET's
thrust is that throttle)."""

GUID_OPTIONS_THRUST_AS_THRUST = 1 << 3
"""ArduCopter ``GUID_OPTIONS`` bit 3 (``ModeGuided::Option::SetAttitudeTarget_ThrustAsThrust``,
ArduCopter ``mode.h``): SET_ATTITUDE_TARGET.thrust is a thrust (0..1 throttle). Clear (the
default) it is a climb rate: 0.5 holds the altitude, less descends
(``ModeGuided::set_attitude_target_provides_thrust`` in ``mode_guided.cpp``)."""

_PX4_INT_TYPES = (1, 2, 3, 4, 5, 6)  # MAV_PARAM_TYPE_UINT8..INT32: PX4 sends their bytes in the float


def param_value(autopilot: str, param_type: int, value: float) -> float:
    """A PARAM_VALUE's ``param_value`` as a number. ArduPilot casts integers to float (C cast);
    PX4 copies an integer's bytes into the float field (``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE``),
    so they are read back bytewise."""
    if autopilot == "px4" and int(param_type) in _PX4_INT_TYPES:
        import struct

        return float(struct.unpack("<i", struct.pack("<f", float(value)))[0])
    return float(value)


@dataclass(frozen=True)
class VehicleParams:
    """What the bridge does with one vehicle's parameters (:func:`vehicle_params`).

    hover_throttle: SET_ATTITUDE_TARGET throttle at which the vehicle hovers, (0, 1), or None
    (the scenario's ``thrust / max_thrust``). loss_timeout_s: the vehicle's own setpoint-loss
    time, s. set_guid_options: ArduCopter only: the ``GUID_OPTIONS`` value to write (PARAM_SET)
    before arming, or None if it is right already. error: why the vehicle must not be flown, or
    "". notes: what was decided, for the log."""

    hover_throttle: float | None
    loss_timeout_s: float
    set_guid_options: int | None = None
    error: str = ""
    notes: str = ""


def vehicle_params(
    autopilot: str, params: dict[str, float], link_timeout_s: float, setpoint: str, hover_throttle: float | None = None
) -> VehicleParams:
    """Decide the thrust mapping and check the link timeout from a vehicle's parameters
    (the names of :data:`AUTOPILOT_PARAMS`; all present).

    PX4: the hover throttle is ``MPC_THR_HOVER`` unless the ``hover_throttle`` setting overrides
    it; the loss time is ``COM_OF_LOSS_T``. ArduCopter: with ``setpoint = "attitude"`` the
    bridge sends thrusts, so ``GUID_OPTIONS`` must have bit 3 set (else 0.444, the scenario's
    hover thrust, would be read as "descend"): if it is clear, ``set_guid_options`` asks the
    bridge to set it (the documented choice, docs/mavlink.md); the hover throttle is
    ``MOT_THST_HOVER`` unless the ``hover_throttle`` setting overrides it. The loss time is
    ``GUID_TIMEOUT``. ``link_timeout_s`` must be below the loss time, or ``error`` says so.
    """
    set_opts: int | None = None
    if autopilot == "ardupilot":
        loss = float(params["GUID_TIMEOUT"])
        opts = int(params["GUID_OPTIONS"])
        notes = f"GUID_TIMEOUT {loss:g} s, GUID_OPTIONS {opts}"
        if setpoint == "attitude" and not opts & GUID_OPTIONS_THRUST_AS_THRUST:
            set_opts = opts | GUID_OPTIONS_THRUST_AS_THRUST
            notes += f" (thrust would be a climb rate: setting GUID_OPTIONS = {set_opts}, thrust as thrust)"
        hover_name, name = "MOT_THST_HOVER", "GUID_TIMEOUT"
    else:
        loss = float(params["COM_OF_LOSS_T"])
        notes = f"COM_OF_LOSS_T {loss:g} s"
        hover_name, name = "MPC_THR_HOVER", "COM_OF_LOSS_T"
    thr = float(params[hover_name])
    notes += f", {hover_name} {thr:g}"
    if not 0.0 < thr < 1.0:
        return VehicleParams(None, loss, None, f"{hover_name} = {thr:g} is not a hover throttle in (0, 1)", notes)
    if hover_throttle is not None and abs(hover_throttle - thr) > 1e-6:
        notes += f" (mavlink.hover_throttle {hover_throttle:g} overrides it)"
    hover = hover_throttle if hover_throttle is not None else thr
    if not link_timeout_s < loss:
        err = (
            f"mavlink.link_timeout_s ({link_timeout_s:g} s) is not below the vehicle's {name} ({loss:g} s): the bridge "
            f"would not notice a lost link before the vehicle's failsafe; lower link_timeout_s or raise {name}"
        )
        return VehicleParams(hover, loss, set_opts, err, notes)
    return VehicleParams(hover, loss, set_opts, "", notes)


def mavlink_settings(sc: ScenarioTables, cli: dict[str, Any] | None = None) -> MavlinkSettings:
    """The scenario's ``[mavlink]`` table (``Scenario.mavlink``, typed by
    :class:`zenswarm.schema.MavlinkTable`), with command-line overrides applied.

    cli: optional overrides with the same keys as the table (None values are ignored), plus
    ``conn`` ({uav: url}), ``sysid`` ({uav: id}) and ``origin`` ({uav: (x, y, z)}, m ENU) for
    single UAVs. Errors are
    :class:`ScenarioError` naming the field (``mavlink.<key>`` or the flag). Keys of the table:

    """
    cli = dict(cli or {})
    conn_over: dict[int, str] = cli.pop("conn", None) or {}
    sysid_over: dict[int, int] = cli.pop("sysid", None) or {}
    origin_over: dict[int, Any] = cli.pop("origin", None) or {}
    t = _table_with(sc, cli)
    n = sc.n
    conns, sysids = _links(t, n, conn_over, sysid_over)
    origins = [tuple(float(c) for c in o) for o in (t.origins or [(0.0, 0.0, 0.0)] * n)]
    _override("--origin", origins, origin_over, _check_origin)
    plain = {k: getattr(t, k) for k in _MAV_KEYS if k not in ("connections", "sysids", "origins", "rate_hz")}
    return MavlinkSettings(
        n=n,
        connections=tuple(conns),
        sysids=tuple(sysids),
        origins=tuple(origins),  # type: ignore[arg-type]
        rate_hz=t.rate_hz if t.rate_hz is not None else max(20.0, sc.timing.control_rate_hz),
        **plain,
    )


mavlink_settings.__doc__ = (mavlink_settings.__doc__ or "") + "".join(
    f"    ``{k}``: {v}\n" for k, v in _MAV_KEYS.items()
)

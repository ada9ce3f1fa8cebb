"""The MAVLink bridge's decisions without a network (issue 16): parameter-based thrust mapping
and timeout checks, configuration validation, pre-arm health gating, per-vehicle origins,
ArduCopter's takeoff sequence, no hover throttle on the ground, ACK addressing, vehicle time.

The bridge is built in process and its connection replaced by a recorder of what it would send;
messages from the vehicle are handed to its receive handlers as plain objects. Milliseconds.
"""

from __future__ import annotations

import math
import struct
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from zenswarm.bridge.vehicles import mavlink as mavlink_mod
from zenswarm.bridge.vehicles.mavlink import (
    AP_COPTER_MODES,
    PX4_OFFBOARD,
    Bridge,
    health_problem,
    mavlink,
    mavlink_settings,
    swarm_to_vehicle,
    vehicle_to_swarm,
)
from zenswarm.errors import ScenarioError
from zenswarm.scenario.config import scenario_from_dict
from zenswarm.vehicle.autopilot import GUID_OPTIONS_THRUST_AS_THRUST, param_value, vehicle_params

EX1 = Path(__file__).resolve().parents[1] / "compose" / "scenarios" / "paper_example1.toml"


def _sc(mav: dict[str, Any]) -> Any:
    d = tomllib.loads(EX1.read_text())
    d["mavlink"] = mav
    return scenario_from_dict(d)


class Recorder:
    """Stands in for pymavlink's ``conn.mav``: records every ``*_send`` call."""

    def __init__(self) -> None:
        self.sent: list[tuple[str, tuple[Any, ...]]] = []

    def __getattr__(self, name: str) -> Any:
        if not name.endswith("_send"):
            raise AttributeError(name)
        return lambda *a: self.sent.append((name.removesuffix("_send"), a))

    def names(self) -> list[str]:
        return [n for n, _ in self.sent]

    def commands(self) -> list[int]:
        return [a[2] for n, a in self.sent if n == "command_long"]


def _bridge(mav: dict[str, Any], cmd: Any = None) -> tuple[Bridge, list[Recorder], list[str]]:
    sc = _sc({"connections": [f"udpout:127.0.0.1:{9 + k}" for k in range(3)], **mav})
    logs: list[str] = []
    age = 0.0 if cmd is not None else math.inf
    b = Bridge(mavlink_settings(sc), sc, {}, lambda i: (cmd, age), lambda i: (None, math.inf), log=logs.append)
    recs = []
    for lk in b.links:
        r = Recorder()
        lk.endpoint.conn = SimpleNamespace(mav=r)
        recs.append(r)
    return b, recs, logs


def _msg(mtype: str, src: int = 1, comp: int = 1, **fields: Any) -> Any:
    return SimpleNamespace(get_type=lambda: mtype, get_srcSystem=lambda: src, get_srcComponent=lambda: comp, **fields)


def _heartbeat(b: Bridge, uav: int, autopilot: int, custom_mode: int, armed: bool = False, now: float = 0.0) -> None:
    lk = b.links[uav - 1]
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    b._handle(lk.endpoint, _msg("HEARTBEAT", src=lk.sysid, autopilot=autopilot, base_mode=base, custom_mode=custom_mode), now)


def _param(b: Bridge, uav: int, name: str, value: float, ptype: int = mavlink.MAV_PARAM_TYPE_REAL32, now: float = 0.0) -> None:
    lk = b.links[uav - 1]
    b._handle(lk.endpoint, _msg("PARAM_VALUE", src=lk.sysid, param_id=name, param_value=value, param_type=ptype), now)


def _advance(b: Bridge, now: float, links: Any = None) -> None:
    """One phase step at ``now`` of vehicles that keep talking (their links healthy)."""
    for lk in links or b.links:
        if lk.tel.hb_count:
            lk.tel.last_rx = now
            b._update_health(lk, now)
        b._advance(lk, now)


# --------------------------------------------------------------------------- thrust mapping, timeouts


def test_vehicle_params_px4_hover_thrust_and_offboard_loss():
    vp = vehicle_params("px4", {"MPC_THR_HOVER": 0.62, "COM_OF_LOSS_T": 1.0}, 0.5, "attitude")
    assert vp.hover_throttle == 0.62 and vp.loss_timeout_s == 1.0 and not vp.error and vp.set_guid_options is None
    vp = vehicle_params("px4", {"MPC_THR_HOVER": 0.62, "COM_OF_LOSS_T": 1.0}, 0.5, "attitude", hover_throttle=0.5)
    assert vp.hover_throttle == 0.5 and "overrides" in vp.notes
    vp = vehicle_params("px4", {"MPC_THR_HOVER": 0.62, "COM_OF_LOSS_T": 0.5}, 0.5, "attitude")
    assert "link_timeout_s" in vp.error and "COM_OF_LOSS_T" in vp.error  # equal is not below
    assert "MPC_THR_HOVER" in vehicle_params("px4", {"MPC_THR_HOVER": 0.0, "COM_OF_LOSS_T": 1.0}, 0.5, "attitude").error


def test_vehicle_params_ardupilot_guid_options_thrust_bit():
    def ap(opts: int, timeout: float = 3.0, setpoint: str = "attitude") -> Any:
        return vehicle_params("ardupilot", {"GUID_OPTIONS": opts, "GUID_TIMEOUT": timeout, "MOT_THST_HOVER": 0.35}, 0.5, setpoint)

    # default GUID_OPTIONS = 0: thrust would be a climb rate (0.5 = hold) -> the bridge sets bit 3
    vp = ap(0)
    assert vp.set_guid_options == GUID_OPTIONS_THRUST_AS_THRUST == 8 and vp.loss_timeout_s == 3.0 and not vp.error
    assert vp.hover_throttle == 0.35  # with thrust as thrust, the throttle that hovers is MOT_THST_HOVER
    assert ap(1).set_guid_options == 9  # the other bits are kept
    assert ap(8).set_guid_options is None
    assert ap(0, setpoint="position").set_guid_options is None  # position targets: thrust unused
    assert "GUID_TIMEOUT" in ap(8, timeout=0.4).error


def test_param_value_decoding():
    assert param_value("ardupilot", mavlink.MAV_PARAM_TYPE_INT32, 8.0) == 8.0  # C cast
    as_float = struct.unpack("<f", struct.pack("<i", 8))[0]  # PX4: the int's bytes in the float
    assert param_value("px4", mavlink.MAV_PARAM_TYPE_INT32, as_float) == 8.0
    assert param_value("px4", mavlink.MAV_PARAM_TYPE_REAL32, 0.5) == 0.5


# --------------------------------------------------------------------------- configuration


@pytest.mark.parametrize(
    "mav, cli, field",
    [
        ({"sysids": [1, 2, 1]}, {}, "mavlink.sysids"),  # duplicate ids on separate links
        ({"sysids": [1, 245, 3]}, {}, "mavlink.sysids"),  # the bridge's own id (and MAVSDK's GCS default)
        ({"source_system": 7, "sysids": [7, 2, 3]}, {}, "mavlink.sysids"),
        ({}, {"sysid": {3: 2}}, "mavlink.sysids"),
        ({"link_timeout_s": 1.0}, {}, "mavlink.link_timeout_s"),  # equals the vehicles' 1 s loss time
        ({"link_timeout_s": 0.4, "offboard_loss_s": 0.3}, {}, "mavlink.link_timeout_s"),
        ({}, {"link_timeout_s": 2.0}, "mavlink.link_timeout_s"),
    ],
)
def test_settings_reject_ids_and_timeouts(mav, cli, field):
    with pytest.raises(ScenarioError) as e:
        mavlink_settings(_sc(mav), cli)
    assert e.value.field == field, e.value


def test_settings_default_link_timeout_below_vehicle_loss():
    s = mavlink_settings(_sc({}))
    assert s.link_timeout_s == 0.5 < s.offboard_loss_s == 1.0 and s.source_system not in s.sysids


# --------------------------------------------------------------------------- health, origins


def test_health_problem_names_the_subsystem_and_prearm():
    gyro, gps, pre = mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO, mavlink.MAV_SYS_STATUS_SENSOR_GPS, mavlink.MAV_SYS_STATUS_PREARM_CHECK
    allb = gyro | gps | pre
    assert health_problem(allb, allb, allb) == ""
    assert health_problem(allb, allb, allb & ~pre) == "pre-arm checks failing"
    assert "gps" in health_problem(allb, allb, allb & ~gps)
    assert health_problem(allb, allb & ~gps, allb & ~gps) == ""  # not enabled: not required


def test_per_vehicle_origins_into_the_swarm_frame():
    o = np.array([10.0, -2.0, 0.5])  # vehicle's local origin in the swarm's ENU frame
    p_ned = np.array([1.0, 2.0, -3.0])  # 1 m north, 2 m east, 3 m up of that origin
    np.testing.assert_allclose(vehicle_to_swarm(p_ned, o), [12.0, -1.0, 3.5])
    np.testing.assert_allclose(swarm_to_vehicle(vehicle_to_swarm(p_ned, o), o), p_ned)
    # each vehicle its own origin: the same swarm point is a different local point per vehicle
    origins = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, -3.0, 0.2]]
    b, _, _ = _bridge({"origins": origins})
    for k, lk in enumerate(b.links):
        np.testing.assert_allclose(vehicle_to_swarm(b._takeoff_ned(lk), origins[k]), b.sc.initial_positions[k])
        lk.tel.pos_ned, lk.tel.vel_ned, lk.tel.rpy_ned, lk.tel.rates_frd = p_ned, np.zeros(3), np.zeros(3), np.zeros(3)
        lk.tel.pos_rx = lk.tel.att_rx = 0.0
        q = b.state_enu(lk, 0.0)[0]
        np.testing.assert_allclose(q, np.array([2.0, 1.0, 3.0]) + origins[k])


def test_bridge_refuses_to_arm_an_unhealthy_vehicle():
    b, recs, _ = _bridge({})
    lk = b.links[0]
    lk.phase, lk.wanted_mode, lk.phase_t = "arm", PX4_OFFBOARD, 0.0
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_PX4, PX4_OFFBOARD, now=0.1)
    lk.healthy = True
    b._advance(lk, 0.2)
    assert mavlink.MAV_CMD_COMPONENT_ARM_DISARM not in recs[0].commands()  # no SYS_STATUS yet: wait
    allb = mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_PREARM_CHECK
    b._handle(lk.endpoint, _msg("SYS_STATUS", onboard_control_sensors_present=allb, onboard_control_sensors_enabled=allb,
                                onboard_control_sensors_health=mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO), 0.3)
    b._advance(lk, 0.4)
    assert lk.phase == "refused" and "pre-arm checks failing" in lk.reason
    assert mavlink.MAV_CMD_COMPONENT_ARM_DISARM not in recs[0].commands()
    # a healthy one is armed
    lk2 = b.links[1]
    lk2.phase, lk2.wanted_mode, lk2.phase_t, lk2.healthy = "arm", PX4_OFFBOARD, 0.0, True
    _heartbeat(b, 2, mavlink.MAV_AUTOPILOT_PX4, PX4_OFFBOARD, now=0.1)
    b._handle(lk2.endpoint, _msg("SYS_STATUS", src=2, onboard_control_sensors_present=allb, onboard_control_sensors_enabled=allb,
                                 onboard_control_sensors_health=allb), 0.3)
    b._advance(lk2, 0.4)
    assert recs[1].commands() == [mavlink.MAV_CMD_COMPONENT_ARM_DISARM]


def test_bridge_refuses_without_sys_status():
    b, _, _ = _bridge({})
    lk = b.links[0]
    lk.phase, lk.wanted_mode, lk.phase_t, lk.healthy = "arm", PX4_OFFBOARD, 0.0, True
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_PX4, PX4_OFFBOARD, now=0.1)
    b._advance(lk, 3.5)
    assert lk.phase == "refused" and "no SYS_STATUS" in lk.reason


# --------------------------------------------------------------------------- parameter protocol


def test_params_phase_reads_px4_parameters_and_maps_thrust():
    b, recs, logs = _bridge({})
    lk = b.links[0]
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_PX4, 0)
    _advance(b, 0.0)
    assert lk.phase == "params"
    _advance(b, 0.01)
    asked = sorted(a[2] for n, a in recs[0].sent if n == "param_request_read")
    assert asked == [b"COM_OF_LOSS_T", b"MPC_THR_HOVER"]
    _param(b, 1, "MPC_THR_HOVER", 0.6)
    _param(b, 1, "COM_OF_LOSS_T", 1.0)
    _advance(b, 0.1)
    assert lk.phase == "stream" and lk.vparams is not None and lk.vparams.hover_throttle == 0.6
    assert lk.tmap.to_normalized(b.hover_thrust) == pytest.approx(0.6)  # hover thrust -> MPC_THR_HOVER


def test_params_missing_or_bad_refuse_with_the_reason():
    b, _, _ = _bridge({"params_timeout_s": 1.0})
    lk = b.links[0]
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_PX4, 0)
    _advance(b, 0.0)
    _param(b, 1, "MPC_THR_HOVER", 0.6)
    _advance(b, 1.5)
    assert lk.phase == "refused" and "COM_OF_LOSS_T not received" in lk.reason
    lk2 = b.links[1]
    _heartbeat(b, 2, mavlink.MAV_AUTOPILOT_PX4, 0)
    _advance(b, 0.0, [lk2])
    _param(b, 2, "MPC_THR_HOVER", 0.6)
    _param(b, 2, "COM_OF_LOSS_T", 0.5)  # not above the 0.5 s link timeout
    _advance(b, 0.1, [lk2])
    assert lk2.phase == "refused" and "COM_OF_LOSS_T" in lk2.reason and "link_timeout_s" in lk2.reason


def test_params_phase_sets_ardupilot_thrust_bit_and_waits_for_the_echo():
    b, recs, _ = _bridge({})
    lk = b.links[0]
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, AP_COPTER_MODES["STABILIZE"])
    _advance(b, 0.0)
    _param(b, 1, "GUID_OPTIONS", 0.0, mavlink.MAV_PARAM_TYPE_INT32)
    _param(b, 1, "GUID_TIMEOUT", 3.0)
    _param(b, 1, "MOT_THST_HOVER", 0.35)
    _advance(b, 0.1)
    sets = [a for n, a in recs[0].sent if n == "param_set"]
    assert lk.phase == "params" and sets and sets[0][2] == b"GUID_OPTIONS" and sets[0][3] == 8.0
    _param(b, 1, "GUID_OPTIONS", 8.0, mavlink.MAV_PARAM_TYPE_INT32)  # the vehicle's echo
    _advance(b, 0.2)
    assert lk.phase == "stream" and lk.vparams.loss_timeout_s == 3.0


# --------------------------------------------------------------------------- ArduCopter takeoff, throttle


def _ardupilot_takeoff(b: Bridge, lk: Any) -> None:
    _heartbeat(b, lk.uav, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, AP_COPTER_MODES["GUIDED"], armed=True, now=1.0)
    lk.autopilot, lk.wanted_mode, lk.armed_by_us, lk.healthy = "ardupilot", AP_COPTER_MODES["GUIDED"], True, True
    lk.tel.pos_ned, lk.tel.vel_ned, lk.tel.rpy_ned = np.zeros(3), np.zeros(3), np.zeros(3)
    lk.phase = "arm"
    lk.phase_t = 0.5
    b._advance(lk, 1.1)  # armed -> takeoff


def test_ardupilot_takeoff_sends_no_position_target_until_the_altitude():
    b, recs, _ = _bridge({})
    lk, rec = b.links[0], recs[0]
    _ardupilot_takeoff(b, lk)
    assert lk.phase == "takeoff"
    for k in range(5):  # 0.5 s on the ground: NAV_TAKEOFF, and nothing else
        now = 1.2 + 0.1 * k
        b._advance(lk, now)
        b._send_setpoint(lk, now)
    assert rec.commands() == [mavlink.MAV_CMD_NAV_TAKEOFF]
    alt = rec.sent[[n for n, _ in rec.sent].index("command_long")][1][10]
    assert alt == pytest.approx(b.sc.initial_positions[0][2])
    assert "set_position_target_local_ned" not in rec.names()
    b._handle(lk.endpoint, _msg("COMMAND_ACK", command=mavlink.MAV_CMD_NAV_TAKEOFF, result=0, target_system=245, target_component=191), 1.7)
    b._advance(lk, 2.5)
    assert rec.commands() == [mavlink.MAV_CMD_NAV_TAKEOFF]  # acknowledged: not repeated
    lk.tel.pos_ned = np.array([0.0, 0.0, -alt])  # the altitude is reached
    b._advance(lk, 3.0)
    b._send_setpoint(lk, 3.0)
    assert lk.climbed and rec.names()[-1] == "set_position_target_local_ned"


def test_no_hover_throttle_to_a_vehicle_on_the_ground():
    b, recs, _ = _bridge({"takeoff": False})
    lk, rec = b.links[0], recs[0]
    lk.autopilot, lk.wanted_mode, lk.phase = "ardupilot", AP_COPTER_MODES["GUIDED_NOGPS"], "ready"
    lk.tel.rpy_ned = np.zeros(3)
    b._send_setpoint(lk, 1.0)
    assert rec.sent[-1][0] == "set_attitude_target" and rec.sent[-1][1][-1] == 0.0  # on the ground: 0
    b._handle(lk.endpoint, _msg("EXTENDED_SYS_STATE", vtol_state=0, landed_state=mavlink.MAV_LANDED_STATE_IN_AIR), 1.0)
    b._send_setpoint(lk, 1.1)
    assert rec.sent[-1][1][-1] == pytest.approx(b.tmap.to_normalized(b.hover_thrust))  # flying: hover


def test_acks_filtered_by_system_and_component():
    b, _, _ = _bridge({})
    lk = b.links[0]
    for tsys, tcomp, ours in ((245, 191, True), (245, 0, True), (0, 0, True), (245, 190, False), (246, 191, False)):
        lk.acks.clear()
        b._handle(lk.endpoint, _msg("COMMAND_ACK", command=400, result=0, target_system=tsys, target_component=tcomp), 1.0)
        assert bool(lk.acks) == ours, (tsys, tcomp)


def test_vehicle_time_stamps_and_latency():
    b, recs, _ = _bridge({})
    lk = b.links[0]
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_PX4, 0, now=10.0)
    # without TIMESYNC: offset from the fastest delivery; a later, slower sample is 30 ms old
    b._handle(lk.endpoint, _msg("LOCAL_POSITION_NED", time_boot_ms=5000, x=0.0, y=0.0, z=-1.0, vx=0.0, vy=0.0, vz=0.0), 10.0)
    b._handle(lk.endpoint, _msg("LOCAL_POSITION_NED", time_boot_ms=5100, x=0.0, y=0.0, z=-1.0, vx=0.0, vy=0.0, vz=0.0), 10.13)
    lk.tel.rpy_ned, lk.tel.rates_frd, lk.tel.att_rx = np.zeros(3), np.zeros(3), 10.13
    b.state_enu(lk, 10.13)
    assert lk.state_age_s == pytest.approx(0.03, abs=1e-6)
    # TIMESYNC: request sent, answer gives the round trip
    b._timesync(lk, 11.0)
    ts = [a for n, a in recs[0].sent if n == "timesync"]
    assert ts and ts[-1][0] == 0 and ts[-1][1] == int(11.0 * 1e9)
    b._handle(lk.endpoint, _msg("TIMESYNC", tc1=int(5.95e9), ts1=int(11.0 * 1e9)), 11.02)
    assert lk.tel.rtt_s == pytest.approx(0.02) and lk.tel.clock_from_timesync
    assert lk.info(11.02)["latency_ms"] == pytest.approx(10.0)
    assert b.info(11.02)["max_latency_ms"] == pytest.approx(10.0)


def test_state_stamp_is_the_vehicle_time_on_the_mission_clock():
    """The published state's ``ts``: LOCAL_POSITION_NED.time_boot_ms through the TIMESYNC clock
    offset, in ns since mission time 0; none before a TIMESYNC answer (the fallback offset is for
    the diagnostic only)."""
    from zenswarm.bridge.vehicles.mavlink import _BridgeLoop
    from zenswarm.bus import wire

    b, _, _ = _bridge({})
    lk = b.links[0]
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_PX4, 0, now=10.0)
    b._handle(lk.endpoint, _msg("LOCAL_POSITION_NED", time_boot_ms=5100, x=0.0, y=0.0, z=-1.0, vx=0.0, vy=0.0, vz=0.0), 10.13)
    loop = SimpleNamespace(bridge=b, t0=10.0)
    assert b.sample_time(lk) is None and _BridgeLoop.stamp_ns(loop, lk) is None  # type: ignore[arg-type]
    # the vehicle's clock read 5.95 s at bridge time 11.01 (the middle of the round trip)
    b._timesync(lk, 11.0)
    b._handle(lk.endpoint, _msg("TIMESYNC", tc1=int(5.95e9), ts1=int(11.0 * 1e9)), 11.02)
    assert b.sample_time(lk) == pytest.approx(11.01 - 0.85)  # measured 0.85 s of vehicle time earlier
    assert _BridgeLoop.stamp_ns(loop, lk) == round((11.01 - 0.85 - 10.0) * 1e9)  # type: ignore[arg-type]
    loop.t0 = 10.5  # measured before mission time 0: negative
    stamp = _BridgeLoop.stamp_ns(loop, lk)  # type: ignore[arg-type]
    assert stamp is not None and stamp == pytest.approx(-0.34e9, abs=1e3)
    st = wire.State(t=0, seq=1, q=[0, 0, 1], v=[0, 0, 0], rpy=[0, 0, 0], w=[0, 0, 0], stamp=stamp)
    assert wire.decode("state", wire.encode(st)).stamp == stamp


def test_clock_offset_from_the_fastest_recent_timesync_answer():
    """A slow, lopsided round trip (load: the answer waited 40 ms on the way back) must not move
    the clock offset: the fastest of the recent answers sets it, so states are never dated after
    they arrived; a vehicle reboot (offset jump) starts the window over."""
    b, _, _ = _bridge({})
    lk = b.links[0]
    _heartbeat(b, 1, mavlink.MAV_AUTOPILOT_PX4, 0, now=10.0)
    # vehicle clock = bridge clock - 5.0 s exactly; fast answer: 2 ms each way
    b._handle(lk.endpoint, _msg("TIMESYNC", tc1=int(5.002e9), ts1=int(10.0 * 1e9)), 10.004)
    assert lk.tel.clock_offset_s == pytest.approx(-5.0, abs=1e-9)
    # slow answer: 1 ms out, 40 ms back -> this answer alone would say offset = -5.0195
    b._handle(lk.endpoint, _msg("TIMESYNC", tc1=int(6.001e9), ts1=int(11.0 * 1e9)), 11.041)
    assert lk.tel.rtt_s == pytest.approx(0.041)  # the latency diagnostic is the latest round trip
    assert lk.tel.clock_offset_s == pytest.approx(-5.0, abs=1e-9)
    b._handle(lk.endpoint, _msg("LOCAL_POSITION_NED", time_boot_ms=6030, x=0.0, y=0.0, z=-1.0, vx=0.0, vy=0.0, vz=0.0), 11.031)
    lk.tel.rpy_ned, lk.tel.rates_frd, lk.tel.att_rx = np.zeros(3), np.zeros(3), 11.031
    b.state_enu(lk, 11.031)
    assert lk.state_age_s == pytest.approx(0.001, abs=1e-6)  # with the slow answer's offset: -18.5 ms
    # the fast answer leaves the window after _TIMESYNC_WINDOW newer ones: the offset follows drift
    for i in range(mavlink_mod._TIMESYNC_WINDOW):
        sent = 12.0 + i
        b._handle(lk.endpoint, _msg("TIMESYNC", tc1=int((sent - 4.999 + 0.003) * 1e9), ts1=int(sent * 1e9)), sent + 0.006)
    assert lk.tel.clock_offset_s == pytest.approx(-4.999, abs=1e-9)
    # reboot: the vehicle's clock starts again near 0
    b._handle(lk.endpoint, _msg("TIMESYNC", tc1=int(0.5e9), ts1=int(30.0 * 1e9)), 30.05)
    assert lk.tel.clock_offset_s == pytest.approx(0.5 - 30.025, abs=1e-9)


def test_origin_flag_overrides_one_uav():
    s = mavlink_settings(_sc({"origins": [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 2.0, 0.0]]}), {"origin": {2: (5.0, -1.0, 0.25)}})
    assert s.origins == ((0.0, 0.0, 0.0), (5.0, -1.0, 0.25), (2.0, 2.0, 0.0))
    with pytest.raises(ScenarioError) as e:
        mavlink_settings(_sc({}), {"origin": {4: (0.0, 0.0, 0.0)}})
    assert e.value.field == "--origin"
    with pytest.raises(ScenarioError):
        mavlink_settings(_sc({}), {"origin": {1: (0.0, math.nan, 0.0)}})


def test_ardupilot_without_takeoff_and_position_setpoints_warns_once():
    """ArduCopter, takeoff = false, setpoint = "position": the bridge arms the vehicle on the
    ground and sends position targets, which GUIDED never lifts off with; it says so once, clearly
    (and counts each such vehicle), and not for PX4, attitude setpoints or a vehicle in the air."""
    b, _, logs = _bridge({"takeoff": False, "setpoint": "position"})
    for lk in b.links:
        lk.autopilot, lk.armed_by_us = "ardupilot", True
    b._armed(b.links[0], 1.0)
    b._armed(b.links[1], 1.0)
    warn = [line for line in logs if "WARNING" in line]
    assert len(warn) == 1 and "uav 1" in warn[0] and "will not take off" in warn[0] and "takeoff = true" in warn[0], logs
    assert b.counters["grounded_position"] == 2 and b.links[0].phase == "ready"
    b2, _, logs2 = _bridge({"takeoff": False, "setpoint": "position"})
    b2.links[0].autopilot, b2.links[0].armed_by_us = "px4", True  # PX4 offboard takes off by itself
    b2.links[1].autopilot, b2.links[1].armed_by_us = "ardupilot", True
    b2._handle(b2.links[1].endpoint, _msg("EXTENDED_SYS_STATE", src=2, vtol_state=0, landed_state=mavlink.MAV_LANDED_STATE_IN_AIR), 1.0)
    assert b2.links[1].tel.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
    b2._armed(b2.links[0], 1.0)
    b2._armed(b2.links[1], 1.0)  # already in the air: flies the targets
    b3, _, logs3 = _bridge({"takeoff": False})  # attitude setpoints: GUIDED_NOGPS, the agents' thrust lifts it
    b3.links[0].autopilot, b3.links[0].armed_by_us = "ardupilot", True
    b3._armed(b3.links[0], 1.0)
    assert not [line for line in logs2 + logs3 if "WARNING" in line] and "grounded_position" not in b2.counters

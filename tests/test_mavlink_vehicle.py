"""The simulated MAVLink vehicle's PX4 and ArduCopter behaviours, driven by a plain pymavlink
ground station over UDP on 127.0.0.1 (the vehicles run in a thread of the test process).

Each test flies a few seconds at most; the behaviours and their sources are documented in
:mod:`zenswarm.plant.mavlink_vehicle` and :mod:`zenswarm.plant.mavlink.params`.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

from zenswarm.plant.mavlink.params import INT32, REAL32, ParamStore, decode, encode, px4_params
from zenswarm.plant.mavlink_vehicle import MavlinkFleet, VehicleOptions, mavlink, mavutil
from zenswarm.vehicle.params import QuadParams

P = QuadParams()


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(pred: Callable[[], Any], timeout: float, what: str, poll: float = 0.02) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(poll)


class Gcs:
    """A minimal ground station (system 255) talking to vehicle ``sysid`` at udp ``port``."""

    def __init__(self, port: int, sysid: int = 1) -> None:
        self.c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        self.sysid = sysid
        self.c.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def recv(self, mtype: str | list[str], timeout: float, cond: Callable[[Any], bool] | None = None) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.c.recv_match(type=mtype, blocking=True, timeout=0.05)
            if m is not None and (cond is None or cond(m)):
                return m
        return None

    def param_read(self, name: str, timeout: float = 1.0) -> Any:
        self.c.mav.param_request_read_send(self.sysid, 1, name.encode(), -1)
        return self.recv("PARAM_VALUE", timeout, lambda m: m.param_id == name)

    def param_set(self, name: str, carrier: float, ptype: int, timeout: float = 1.0) -> Any:
        self.c.mav.param_set_send(self.sysid, 1, name.encode(), carrier, ptype)
        return self.recv("PARAM_VALUE", timeout, lambda m: m.param_id == name)

    def close(self) -> None:
        self.c.close()


@pytest.fixture(params=["px4", "ardupilot"])
def vehicle(request: pytest.FixtureRequest) -> Iterator[tuple[MavlinkFleet, Gcs]]:
    port = free_udp_port()
    fleet = MavlinkFleet([[0.0, 0.0, 0.0]], P, port, VehicleOptions(autopilot=request.param)).start()
    gcs = Gcs(port)
    try:
        assert gcs.recv("HEARTBEAT", 3.0) is not None, "the vehicle never answered"
        yield fleet, gcs
    finally:
        gcs.close()
        fleet.stop()
    assert fleet.error is None


# =========================================================================== pure


@pytest.mark.parametrize("sitl_ports", [True, False])
def test_busy_vehicle_port_is_named(sitl_ports: bool) -> None:
    """A port a simulated vehicle cannot bind (its send port P+40+i with PX4 SITL's direction,
    else its own P+i) is a ScenarioError naming it (exit 2 from the command line), and the
    vehicles built before it are closed."""
    from zenswarm.bus import free_udp_block
    from zenswarm.errors import ScenarioError

    base = free_udp_block(2, also=(40,))
    busy = base + (41 if sitl_ports else 1)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", busy))
        with pytest.raises(ScenarioError) as e:
            MavlinkFleet([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], P, base, VehicleOptions(sitl_ports=sitl_ports))
    assert e.value.field == "--base-port" and f"127.0.0.1:{busy}" in str(e.value) and "vehicle 2" in str(e.value)
    fleet = MavlinkFleet([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], P, base, VehicleOptions(sitl_ports=sitl_ports))  # vehicle 1 was closed
    fleet.close()


def test_param_encoding_px4_bytewise_and_ardupilot_cast() -> None:
    """PX4 carries an INT32's bytes in the float; ArduPilot casts; REAL32 is the value."""
    assert encode(8, INT32, bytewise=False) == 8.0
    carrier = encode(8, INT32, bytewise=True)
    assert carrier != 8.0 and 0 < carrier < 1e-40  # int32 8 read as a float32 is a denormal
    assert decode(carrier, INT32, bytewise=True) == 8.0
    assert decode(0.25, REAL32, bytewise=True) == 0.25


def test_param_store_clamps_rounds_and_ignores_unknown() -> None:
    store = ParamStore(px4_params(3, 0.44, 1.0, None), bytewise=True)
    assert store["MAV_SYS_ID"] == 3 and store["MPC_THR_HOVER"] == pytest.approx(0.44)
    assert store["MIS_TAKEOFF_ALT"] == 2.5 and store["COM_OF_LOSS_T"] == 1.0 and store["MPC_LAND_SPEED"] == 0.7
    assert store.handle_set(b"MPC_THR_HOVER", 5.0) is not None and store["MPC_THR_HOVER"] == 0.8  # range 0.1..0.8
    assert store.handle_set("NO_SUCH_PARAM", 1.0) is None
    assert store.set("COM_OF_LOSS_T", math.nan) is False and store["COM_OF_LOSS_T"] == 1.0
    assert store.lookup("MIS_TAKEOFF_ALT", -1) == store.index["MIS_TAKEOFF_ALT"] and store.lookup("", 999) is None


# =========================================================================== over UDP


@pytest.mark.swarm
def test_parameter_protocol_read_list_set(vehicle: tuple[MavlinkFleet, Gcs]) -> None:
    """PARAM_REQUEST_READ by name, PARAM_REQUEST_LIST (every index once, count right), PARAM_SET
    echoed and followed by the vehicle; an unknown name gets no answer."""
    fleet, gcs = vehicle
    veh = fleet.vehicles[0]
    px4 = veh.opts.autopilot == "px4"
    hover = "MPC_THR_HOVER" if px4 else "MOT_THST_HOVER"
    pv = gcs.param_read(hover)
    assert pv is not None and pv.param_type == REAL32
    assert pv.param_value == pytest.approx(P.hover_thrust / P.max_thrust, abs=1e-6)  # the airframe's hover throttle
    assert gcs.param_read("NO_SUCH_PARAM", 0.5) is None
    gcs.c.mav.param_request_list_send(1, 1)
    seen: dict[int, str] = {}
    while (m := gcs.recv("PARAM_VALUE", 1.0)) is not None and len(seen) < m.param_count:
        seen[m.param_index] = m.param_id
    assert len(seen) == len(veh.ap_params) and sorted(seen) == list(range(len(veh.ap_params)))
    if px4:
        for name, default in (("COM_OF_LOSS_T", 1.0), ("MIS_TAKEOFF_ALT", 2.5)):
            assert gcs.param_read(name).param_value == pytest.approx(default)
        sysid = gcs.param_read("MAV_SYS_ID")
        assert sysid.param_type == INT32 and decode(sysid.param_value, INT32, True) == 1  # bytewise
        pv = gcs.param_set("COM_OF_LOSS_T", 0.3, REAL32)
        assert pv is not None and pv.param_value == pytest.approx(0.3) and veh.loss_s == pytest.approx(0.3)
    else:
        opts = gcs.param_read("GUID_OPTIONS")
        assert opts.param_type == INT32 and opts.param_value == 0.0  # C cast
        assert gcs.param_read("GUID_TIMEOUT").param_value == pytest.approx(3.0)
        pv = gcs.param_set("GUID_OPTIONS", 8.0, INT32)
        assert pv is not None and pv.param_value == 8.0 and veh.ap_params["GUID_OPTIONS"] == 8


# =========================================================================== independent clients


def _free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.swarm
def test_mavsdk_flies_the_simulated_px4_vehicle() -> None:
    """MAVSDK-Python (its own mavsdk_server) as a PX4 user script: connects with ``udpin`` to a
    vehicle sending as PX4 SITL does, waits for health (armable, home), reads and sets
    MIS_TAKEOFF_ALT, arms, takes off, flies an offboard position segment, lands, and sees the
    auto-disarm; the vehicle reports NED about where it booted (3, 4, 0 ENU)."""
    import asyncio

    mavsdk = pytest.importorskip("mavsdk", reason="MAVSDK-Python is in the test extra")
    from mavsdk.offboard import PositionNedYaw
    from mavsdk.telemetry import LandedState

    port = free_udp_port()
    fleet = MavlinkFleet([[3.0, 4.0, 0.0]], P, port, VehicleOptions(own_origin=True, sitl_ports=True)).start()

    async def first(stream: Any, pred: Callable[[Any], bool]) -> Any:
        async for x in stream:
            if pred(x):
                return x
        raise AssertionError("stream ended")

    async def fly() -> None:
        drone = mavsdk.System(port=_free_tcp_port())
        await drone.connect(system_address=f"udpin://127.0.0.1:{port}")
        await first(drone.core.connection_state(), lambda s: s.is_connected)
        h = await first(drone.telemetry.health(), lambda h: h.is_armable and h.is_home_position_ok)
        assert h.is_local_position_ok and h.is_global_position_ok and h.is_gyrometer_calibration_ok
        assert await drone.action.get_takeoff_altitude() == pytest.approx(2.5)  # PX4's MIS_TAKEOFF_ALT
        await drone.action.set_takeoff_altitude(1.0)
        assert fleet.vehicles[0].ap_params["MIS_TAKEOFF_ALT"] == pytest.approx(1.0)
        await drone.action.arm()
        await drone.action.takeoff()
        await first(drone.telemetry.landed_state(), lambda s: s == LandedState.IN_AIR)
        pv = await first(drone.telemetry.position_velocity_ned(), lambda pv: pv.position.down_m < -0.95)
        assert abs(pv.position.north_m) < 0.05 and abs(pv.position.east_m) < 0.05  # own origin: boot point
        await first(drone.telemetry.flight_mode(), lambda m: m.name == "HOLD")  # takeoff done -> Hold
        await drone.offboard.set_position_ned(PositionNedYaw(1.0, 0.5, -1.5, 0.0))
        await drone.offboard.start()
        await first(
            drone.telemetry.position_velocity_ned(),
            lambda pv: (
                abs(pv.position.north_m - 1.0) < 0.05 and abs(pv.position.east_m - 0.5) < 0.05 and abs(pv.position.down_m + 1.5) < 0.05
            ),
        )
        q = await first(drone.telemetry.attitude_quaternion(), lambda q: True)
        assert all(math.isfinite(c) for c in (q.w, q.x, q.y, q.z))
        await drone.offboard.stop()
        await drone.action.land()
        await first(drone.telemetry.armed(), lambda a: not a)  # COM_DISARM_LAND after touchdown
        assert await first(drone.telemetry.landed_state(), lambda s: True) == LandedState.ON_GROUND

    try:
        asyncio.run(asyncio.wait_for(fly(), 40.0))
    finally:
        fleet.stop()
    assert fleet.error is None
    # where MAVSDK's local frame says (1.0, 0.5) NED from the boot point: ENU (3.5, 5.0)
    np.testing.assert_allclose(fleet.snapshot().q[0], [3.5, 5.0, 0.0], atol=0.08)
    assert fleet.vehicles[0].counters.get("takeoff_requests") == 1


class ApGcs(Gcs):
    """An ArduPilot ground station's calls (Mission Planner / MAVProxy style)."""

    def command(self, cmd: int, *params: float, timeout: float = 1.0) -> int | None:
        p = list(params) + [0.0] * (7 - len(params))
        while self.c.recv_msg() is not None:  # drop the telemetry queued meanwhile
            pass
        self.c.mav.command_long_send(self.sysid, 1, cmd, 0, *p)
        ack = self.recv("COMMAND_ACK", timeout, lambda a: a.command == cmd)
        return None if ack is None else int(ack.result)

    def set_mode(self, mode: int) -> int | None:
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)

    def position_target(self, ned: list[float]) -> None:
        mask = 0b0000_1111_1111_1000  # position only (velocity, acceleration, yaw, yaw rate ignored)
        self.c.mav.set_position_target_local_ned_send(0, self.sysid, 1, mavlink.MAV_FRAME_LOCAL_NED, mask, *ned, 0, 0, 0, 0, 0, 0, 0, 0)

    def local(self) -> Any:
        """The newest LOCAL_POSITION_NED (older queued ones dropped)."""
        last = self.recv("LOCAL_POSITION_NED", 1.0)
        while (m := self.c.recv_match(type="LOCAL_POSITION_NED", blocking=False)) is not None:
            last = m
        return last


GUIDED, GUIDED_NOGPS, LAND = 4, 20, 9


@pytest.fixture
def copter() -> Iterator[tuple[MavlinkFleet, ApGcs]]:
    port = free_udp_port()
    fleet = MavlinkFleet([[0.0, 0.0, 0.0]], P, port, VehicleOptions(autopilot="ardupilot")).start()
    gcs = ApGcs(port)
    try:
        hb = gcs.recv("HEARTBEAT", 3.0)
        assert hb is not None and hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        yield fleet, gcs
    finally:
        gcs.close()
        fleet.stop()
    assert fleet.error is None


@pytest.mark.swarm
def test_pymavlink_ardupilot_gcs_flies_the_simulated_copter(copter: tuple[MavlinkFleet, ApGcs]) -> None:
    """As an ArduPilot ground station: pre-arm healthy, GUID_OPTIONS / GUID_TIMEOUT read, GUIDED,
    arm, MAV_CMD_NAV_TAKEOFF and no target until the altitude is reached, a position-target
    segment, then MAV_CMD_NAV_LAND: lands and disarms."""
    fleet, gcs = copter
    veh = fleet.vehicles[0]
    ss = gcs.recv("SYS_STATUS", 2.0)
    assert ss.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert gcs.param_read("GUID_OPTIONS").param_value == 0 and gcs.param_read("GUID_TIMEOUT").param_value == pytest.approx(3.0)
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[0.0] * 6, 1.0) == mavlink.MAV_RESULT_FAILED  # disarmed
    assert gcs.set_mode(GUIDED) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[0.0] * 6, 1.0) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.recv("EXTENDED_SYS_STATE", 2.0, lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF) is not None
    wait_until(lambda: (lp := gcs.local()) is not None and lp.z < -0.95 and abs(lp.vz) < 0.1, 5.0, "the takeoff altitude")
    assert veh.mode == "GUIDED"
    t_end = time.monotonic() + 3.0
    while time.monotonic() < t_end and not ((lp := gcs.local()) and abs(lp.x - 1.0) < 0.05 and abs(lp.z + 1.5) < 0.05):
        gcs.position_target([1.0, 0.5, -1.5])
        time.sleep(0.05)
    lp = gcs.local()
    assert (lp.x, lp.y, lp.z) == pytest.approx((1.0, 0.5, -1.5), abs=0.06)
    assert gcs.command(mavlink.MAV_CMD_NAV_LAND) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.recv("HEARTBEAT", 2.0, lambda h: h.custom_mode == LAND) is not None
    wait_until(lambda: not veh.armed, 8.0, "the disarm after landing")
    assert fleet.snapshot().q[0, 2] == pytest.approx(0.0, abs=0.01)
    assert gcs.recv("EXTENDED_SYS_STATE", 2.0, lambda m: m.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND) is not None


@pytest.mark.swarm
def test_ardupilot_position_targets_while_landed_do_not_lift_off(copter: tuple[MavlinkFleet, ApGcs]) -> None:
    """ArduCopter mode_guided.cpp: a position target sent while landed switches the guided
    sub-mode away from TakeOff, whose replacement only does ground handling: sending targets in
    the same pass as MAV_CMD_NAV_TAKEOFF leaves the vehicle on the ground."""
    fleet, gcs = copter
    assert gcs.set_mode(GUIDED) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[0.0] * 6, 1.0) == mavlink.MAV_RESULT_ACCEPTED
    for _ in range(30):
        gcs.position_target([0.0, 0.0, -1.0])
        time.sleep(0.05)
    assert fleet.snapshot().q[0, 2] < 0.2  # at most the first instants of the climb
    assert fleet.vehicles[0].guided_sub == "Pos" and fleet.vehicles[0].land_complete
    assert fleet.vehicles[0].mode == "GUIDED"


@pytest.mark.swarm
def test_ardupilot_guided_nogps_thrust_is_climb_rate_and_guid_timeout(copter: tuple[MavlinkFleet, ApGcs]) -> None:
    """GUIDED_NOGPS without setpoints stays in the mode (disarmed too, no LOITER after 1 s);
    with the default GUID_OPTIONS thrust 0.5 holds altitude and 0.444 descends; once no
    target came for GUID_TIMEOUT the vehicle levels out, holds altitude and stays in the mode."""
    fleet, gcs = copter
    veh = fleet.vehicles[0]
    assert gcs.set_mode(GUIDED_NOGPS) == mavlink.MAV_RESULT_ACCEPTED
    time.sleep(1.5)
    assert veh.mode == "GUIDED_NOGPS"
    assert gcs.param_set("GUID_TIMEOUT", 0.5, REAL32) is not None
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    mask = 0b0000_0111  # body rates ignored: attitude + thrust

    def att(thrust: float, seconds: float, pitch_deg: float = 0.0) -> None:
        q = [math.cos(math.radians(pitch_deg) / 2), 0.0, math.sin(math.radians(pitch_deg) / 2), 0.0]
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            gcs.c.mav.set_attitude_target_send(0, 1, 1, mask, q, 0, 0, 0, thrust)
            time.sleep(0.05)

    att(0.8, 1.0)  # climb at 0.6 * 2.5 m/s
    z1 = float(fleet.snapshot().q[0, 2])
    assert z1 > 0.5
    att(0.5, 1.0)  # hold
    z2 = float(fleet.snapshot().q[0, 2])
    assert abs(float(fleet.snapshot().v[0, 2])) < 0.1
    att(0.444, 1.0)  # the bridge's hover throttle: a descent of 0.17 m/s
    assert float(fleet.snapshot().q[0, 2]) < z2 - 0.08 and float(fleet.snapshot().v[0, 2]) < -0.1
    att(0.5, 0.5, pitch_deg=-10.0)  # nose down: accelerating north
    assert float(fleet.snapshot().v[0, 1]) > 0.2
    time.sleep(1.5)  # > GUID_TIMEOUT without targets: level, hold altitude, still GUIDED_NOGPS
    assert abs(float(fleet.snapshot().rpy[0, 1])) < 0.03 and abs(float(fleet.snapshot().v[0, 2])) < 0.1
    assert veh.mode == "GUIDED_NOGPS" and veh.armed


@pytest.mark.swarm
def test_px4_addressing_prearm_body_rates_and_rtl() -> None:
    """PX4 flavour: a command for another component gets no answer; a failed pre-arm check shows
    in SYS_STATUS and refuses arming with a STATUSTEXT; body-rate setpoints turn the vehicle;
    MAV_CMD_NAV_RETURN_TO_LAUNCH climbs to RTL_RETURN_ALT, returns over home, lands, disarms."""
    port = free_udp_port()
    fleet = MavlinkFleet([[0.0, 0.0, 0.0]], P, port, VehicleOptions()).start()
    gcs = ApGcs(port)
    veh = fleet.vehicles[0]
    try:
        assert gcs.recv("HEARTBEAT", 3.0) is not None
        gcs.c.mav.command_long_send(1, 100, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)  # a camera
        assert gcs.recv("COMMAND_ACK", 0.5) is None and not veh.armed and veh.counters["other_component"] == 1
        fleet.set_prearm_failure(0, "Compass not calibrated")
        assert gcs.recv("SYS_STATUS", 5.0, lambda s: not s.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK)
        gcs.c.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        text = gcs.recv("STATUSTEXT", 2.0)  # sent before the COMMAND_ACK, as PX4 does
        ack = gcs.recv("COMMAND_ACK", 2.0)
        assert text is not None and "Preflight Fail" in text.text and ack.result == mavlink.MAV_RESULT_DENIED
        fleet.set_prearm_failure(0, None)
        assert gcs.param_set("MIS_TAKEOFF_ALT", 1.0, REAL32) is not None
        assert gcs.param_set("RTL_RETURN_ALT", 1.5, REAL32) is not None
        assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7) == mavlink.MAV_RESULT_ACCEPTED
        wait_until(lambda: veh.mode == "AUTO.LOITER", 4.0, "takeoff done -> hold")
        assert float(fleet.snapshot().q[0, 2]) == pytest.approx(1.0, abs=0.06)
        # body rates only (attitude ignored): yaw at 0.5 rad/s FRD (clockwise seen from above)
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            gcs.c.mav.set_attitude_target_send(0, 1, 1, 0b1000_0000, [1, 0, 0, 0], 0, 0, 0.5, 0.444)
            time.sleep(0.05)
        assert gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0, timeout=2.0) == mavlink.MAV_RESULT_ACCEPTED  # OFFBOARD
        yaw0 = float(fleet.snapshot().rpy[0, 2])
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            gcs.c.mav.set_attitude_target_send(0, 1, 1, 0b1000_0000, [1, 0, 0, 0], 0, 0, 0.5, float(P.hover_thrust / P.max_thrust))
            time.sleep(0.05)
        # the rate setpoint is integrated at 0.5 rad/s (scheduling slack); the airframe's slow yaw
        # loop follows it clockwise (ENU yaw decreasing)
        assert veh.att_int is not None and -0.65 < float(veh.att_int[2]) - yaw0 < -0.3
        assert float(fleet.snapshot().rpy[0, 2]) - yaw0 < -0.05
        assert gcs.command(mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH) == mavlink.MAV_RESULT_ACCEPTED
        wait_until(lambda: float(fleet.snapshot().q[0, 2]) > 1.4, 3.0, "the climb to RTL_RETURN_ALT")
        wait_until(lambda: not veh.armed, 12.0, "the landing and disarm at home")
        assert np.linalg.norm(fleet.snapshot().q[0, 0:2]) < 0.1 and veh.mode == "AUTO.RTL"
    finally:
        gcs.close()
        fleet.stop()
    assert fleet.error is None

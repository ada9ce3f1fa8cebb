"""The simulated Crazyflie (:mod:`zenswarm.plant.crazyflie_vehicle`) driven by real, unmodified
cflib over its ``udp://`` driver on 127.0.0.1, as a user's script would: connect (TOCs with CRC,
parameters read), read and set a parameter, a log block at the requested rate, arming, the
high-level commander's takeoff and landing, attitude setpoints the vehicle follows, and the
commander watchdog (level out after 500 ms, motors off and locked after 2 s). The fleet runs in
a thread of the test process; each test has its own ports.

Plus the pure firmware units (:mod:`zenswarm.vehicle.crazyflie`): the thrust map and the signs.
"""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cflib", reason="cflib is not installed (pip install -e '.[crazyflie]')")

import cflib.crtp
from cflib.crazyflie import Crazyflie
from cflib.crazyflie.log import LogConfig
from cflib.crazyflie.syncCrazyflie import SyncCrazyflie

from zenswarm.bus import free_udp_block
from zenswarm.plant.crazyflie.crtp import LOG_FLOAT
from zenswarm.plant.crazyflie.log import LOG_VARS, LogService
from zenswarm.plant.crazyflie_vehicle import CrazyflieFleet
from zenswarm.vehicle import crazyflie as cfu
from zenswarm.vehicle.params import QuadParams

cflib.crtp.init_drivers()


def wait_until(pred: Callable[[], Any], timeout: float, what: str, poll: float = 0.02) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        v = pred()
        if v:
            return v
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(poll)


@pytest.fixture
def fleet() -> Iterator[CrazyflieFleet]:
    f = CrazyflieFleet([[0.3, -0.2, 0.5]], QuadParams(), base_port=free_udp_block(1)).start()
    try:
        yield f
    finally:
        f.stop()
        assert f.error is None, f.error


@pytest.fixture
def scf(fleet: CrazyflieFleet, tmp_path: Any) -> Iterator[SyncCrazyflie]:
    with SyncCrazyflie(fleet.uris()[0], cf=Crazyflie(rw_cache=str(tmp_path))) as s:
        yield s


def stream(cf: Crazyflie, seconds: float, roll: float, pitch: float, yawrate: float, thrust: int, hz: float = 50.0) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        cf.commander.send_setpoint(roll, pitch, yawrate, thrust)
        time.sleep(1.0 / hz)


# --------------------------------------------------------------------------- pure units


def test_thrust_map_is_bitcrazes_table_and_inverts() -> None:
    # the table's own points: 50 % PWM -> 24.4 g, 93.75 % -> 57.9 g
    assert cfu.command_to_thrust(0.5 * 65535) == pytest.approx(24.4e-3 * 9.81)
    assert cfu.command_to_thrust(0.9375 * 65535) == pytest.approx(57.9e-3 * 9.81)
    for f in (0.05, 0.2, 0.265, 0.4, 0.5):
        cmd, clamped = cfu.thrust_to_command(f)
        assert not clamped and abs(cfu.command_to_thrust(cmd) - f) < 2e-5
    # a 27 g Crazyflie hovers near 54 % (about 35 000)
    hover, _ = cfu.thrust_to_command(0.027 * 9.81)
    assert 34_000 < hover < 37_000


def test_thrust_map_clamps_and_says_so() -> None:
    assert cfu.thrust_to_command(10.0) == (cfu.MAX_THRUST, True)
    assert cfu.thrust_to_command(1e-4) == (cfu.MIN_THRUST, True)
    assert cfu.thrust_to_command(0.0) == (0, False)
    assert cfu.thrust_to_command(float("nan")) == (0, False)
    assert cfu.max_thrust_n() == pytest.approx(cfu.command_to_thrust(60000))


def test_signs_roundtrip_and_pitch_is_inverted() -> None:
    r, p, y = cfu.rpyt_wire(0.1, 0.2, 0.3)
    assert r == pytest.approx(math.degrees(0.1)) and p == pytest.approx(-math.degrees(0.2)) and y == pytest.approx(-math.degrees(0.3))
    assert cfu.rpyt_from_wire(r, p, y) == pytest.approx((0.1, 0.2, 0.3))
    rpy = np.array([0.1, -0.2, 1.0])
    assert cfu.attitude_from_log(*cfu.attitude_to_log(rpy)) == pytest.approx(rpy)
    assert cfu.yaw_rate_command(0.0, 0.1) < 0 and cfu.yaw_rate_command(3.0, -3.0) < 0  # the short way round


# --------------------------------------------------------------------------- cflib, as a user


@pytest.mark.slow
def test_connect_read_and_set_a_parameter(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    cf = scf.cf
    assert cf.platform.get_protocol_version() == 12
    assert cf.param.get_value("flightmode.stabModeYaw") == "0"
    assert float(cf.param.get_value("hlCommander.vland")) == pytest.approx(0.2)
    changed: list[tuple[str, str]] = []
    cf.param.add_update_callback(group="crtpsrv", name="echoDelay", cb=lambda n, v: changed.append((n, v)))
    cf.param.set_value("crtpsrv.echoDelay", 7)
    wait_until(lambda: changed, 2.0, "the parameter's echo")
    assert changed[-1] == ("crtpsrv.echoDelay", "7")
    assert fleet.vehicles[0].param_values["crtpsrv.echoDelay"] == 7
    with pytest.raises(AttributeError):  # read-only in the TOC
        cf.param.set_value("firmware.revision0", 1)
    assert len(cf.log.toc.toc["stateEstimate"]) == 9


@pytest.mark.slow
def test_log_block_arrives_at_the_requested_rate(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    got: list[tuple[int, dict]] = []
    lc = LogConfig("pose", period_in_ms=20)
    for a in ("x", "y", "z", "yaw"):
        lc.add_variable(f"stateEstimate.{a}", "float")
    lc.add_variable("pm.vbat", "float")
    lc.data_received_cb.add_callback(lambda ts, data, conf: got.append((ts, data)))
    scf.cf.log.add_config(lc)
    lc.start()
    wait_until(lambda: got, 2.0, "the first log packet")
    n0, t0 = len(got), time.monotonic()
    time.sleep(2.0)
    rate = (len(got) - n0) / (time.monotonic() - t0)
    lc.stop()
    # 50 Hz asked. The schedule itself is checked on a synthetic clock (the test below); here, through
    # real UDP and cflib, on a loaded machine (the fleet's loop is one thread of a busy process): the
    # rate in a generous band (27 Hz was seen in CI beside a swarm flight), never a burst
    assert 20.0 <= rate <= 55.0, rate
    ts = [t for t, _ in got[-40:]]
    assert 18.0 <= (ts[-1] - ts[0]) / (len(ts) - 1) <= 50.0, ts  # the firmware's ms stamps, 20 ms apart
    assert all(b - a >= 18 for a, b in zip(ts, ts[1:])), ts  # never a burst
    d = got[-1][1]
    assert d["stateEstimate.x"] == pytest.approx(0.3, abs=1e-6) and d["stateEstimate.z"] == 0.0
    assert 3.0 < d["pm.vbat"] <= 4.2


def test_log_block_is_due_every_period_and_a_late_loop_never_bursts() -> None:
    """The log service on a synthetic clock (no thread, no socket): a 20 ms block polled by a
    100 Hz loop sends every second tick, stamped 20 ms apart; a loop late by less than a period
    sends late with the stamp of when it was due; late by more, it skips what it missed and stamps
    now. Never two stamps closer than a period."""
    svc = LogService()
    x = [name for name, _ in LOG_VARS].index("stateEstimate.x")
    assert svc.control(6, 1, bytes([6, 1]) + struct.pack("<BH", LOG_FLOAT, x), 0.0) == 0  # create block 1
    assert svc.control(3, 1, bytes([3, 1, 2]), 0.0) == 0  # start it, period 2 x 10 ms

    def stamps(ticks_ms: list[int]) -> list[int]:
        out = []
        for t in ticks_ms:
            for pkt in svc.due(t / 1000.0, lambda ident: 0.5, lambda s: round(1000 * s)):
                assert pkt[0] == 1 and struct.unpack_from("<f", pkt, 4)[0] == 0.5
                out.append(int.from_bytes(pkt[1:4], "little"))
        return out

    assert stamps(list(range(0, 1000, 10))) == list(range(0, 1000, 20))  # 100 Hz loop: 50 Hz, on time
    # late by 15 ms (due at 1000, polled at 1015): sent then, stamped 1000; the next on its period
    assert stamps([1015, 1020, 1030, 1040]) == [1000, 1020, 1040]
    # stalled from 1040 to 1105 (due at 1060, 1080, 1100 missed): one packet, stamped now; then 20 ms on
    assert stamps([1105, 1115, 1125, 1135]) == [1105, 1125]


@pytest.mark.slow
def test_log_block_too_big_is_refused(scf: SyncCrazyflie) -> None:
    lc = LogConfig("big", period_in_ms=100)
    for a in ("x", "y", "z", "vx", "vy", "vz", "roll"):
        lc.add_variable(f"stateEstimate.{a}", "float")  # 28 bytes > 26
    with pytest.raises(AttributeError):
        scf.cf.log.add_config(lc)


@pytest.mark.slow
def test_arm_take_off_and_land_with_the_high_level_commander(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    cf = scf.cf
    assert cf.supervisor.can_be_armed and not cf.supervisor.is_armed
    cf.high_level_commander.takeoff(0.5, 1.5)
    time.sleep(0.5)
    assert fleet.snapshot().q[0, 2] == 0.0  # not armed: the motors do not run
    cf.high_level_commander.stop()
    cf.supervisor.send_arming_request(True)
    wait_until(lambda: cf.supervisor.is_armed, 1.0, "armed")
    cf.high_level_commander.takeoff(0.5, 1.5)
    wait_until(lambda: abs(fleet.snapshot().q[0, 2] - 0.5) < 0.05 and abs(fleet.snapshot().v[0, 2]) < 0.1, 6.0, "hover at 0.5 m")
    assert cf.supervisor.is_flying
    assert np.allclose(fleet.snapshot().q[0, :2], [0.3, -0.2], atol=0.05)
    cf.high_level_commander.land(0.0, 1.5)
    wait_until(lambda: fleet.snapshot().q[0, 2] == 0.0, 6.0, "on the ground")
    wait_until(lambda: fleet.vehicles[0].motor_cmd == 0, 2.0, "motors stopped after the landing")
    # the supervisor: landed after 2 s without thrust, then disarmed after the landing timeout
    wait_until(lambda: not cf.supervisor.is_armed, 8.0, "disarmed after landing")


@pytest.mark.slow
def test_attitude_setpoints_are_followed_with_the_firmwares_signs(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    cf = scf.cf
    cf.supervisor.send_arming_request(True)
    wait_until(lambda: cf.supervisor.is_armed, 1.0, "armed")
    cf.commander.send_setpoint(0, 0, 0, 0)  # unlock the thrust, as every cflib example does
    stream(cf, 0.3, 0, 0, 0, 45000)  # climb
    stream(cf, 0.2, 0, 0, 0, 36000)
    assert fleet.snapshot().q[0, 2] > 0.02
    x0 = fleet.snapshot().q[0].copy()
    stream(cf, 0.4, 0.0, 8.0, 0.0, 38000)  # cflib pitch +8 deg: nose down, accelerates along +x
    assert fleet.snapshot().rpy[0, 1] == pytest.approx(math.radians(8.0), abs=0.02)
    assert fleet.snapshot().v[0, 0] > 0.05 and fleet.snapshot().q[0, 0] > x0[0]
    stream(cf, 0.4, 8.0, 0.0, 0.0, 38000)  # roll +8 deg: right wing down, accelerates along -y
    assert fleet.snapshot().rpy[0, 0] == pytest.approx(math.radians(8.0), abs=0.02)
    assert fleet.snapshot().v[0, 1] < -0.05
    yaw0 = fleet.snapshot().rpy[0, 2]
    stream(cf, 0.5, 0.0, 0.0, 30.0, 36000)  # cflib yaw rate +30 deg/s: the firmware inverts it, clockwise
    assert fleet.snapshot().rpy[0, 2] < yaw0 - math.radians(8.0)
    assert cf.supervisor.is_flying


@pytest.mark.slow
def test_thrust_is_locked_until_a_zero_thrust_setpoint(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    cf = scf.cf
    cf.supervisor.send_arming_request(True)
    wait_until(lambda: cf.supervisor.is_armed, 1.0, "armed")
    stream(cf, 0.3, 0, 0, 0, 45000)
    assert fleet.vehicles[0].motor_cmd == 0 and fleet.snapshot().q[0, 2] == 0.0
    cf.commander.send_setpoint(0, 0, 0, 0)
    stream(cf, 0.3, 0, 0, 0, 45000)
    assert fleet.vehicles[0].motor_cmd == 45000 and fleet.snapshot().q[0, 2] > 0.0


def test_a_snapshot_is_taken_between_physics_chunks(fleet: CrazyflieFleet) -> None:
    # On the ground with the motors off, every sub-step pulls the vehicle g*h^2 below the ground
    # and the ground contact puts it back. Read from this thread, ``fleet.state`` catches it in
    # between a few % of the time (what made the thrust-lock test flaky); a snapshot never does.
    end = time.monotonic() + 1.0
    reads = 0
    ticks0 = fleet.ticks
    while time.monotonic() < end:
        snap = fleet.snapshot()
        assert snap.q[0, 2] == 0.0 and snap.v[0, 2] == 0.0, (reads, snap.q[0], snap.v[0])
        reads += 1
    assert fleet.ticks - ticks0 > 20 and reads > 1000  # the loop ran, and we read through it


@pytest.mark.slow
def test_watchdog_levels_out_then_stops_the_motors(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    cf = scf.cf
    cf.supervisor.send_arming_request(True)
    wait_until(lambda: cf.supervisor.is_armed, 1.0, "armed")
    cf.commander.send_setpoint(0, 0, 0, 0)
    stream(cf, 0.6, 0, 0, 0, 44000)
    stream(cf, 0.3, 6.0, 0.0, 0.0, 44000)  # tilted when the setpoints stop
    assert abs(fleet.snapshot().rpy[0, 0]) > math.radians(4.0)
    veh = fleet.vehicles[0]
    stopped = time.monotonic()
    wait_until(lambda: veh.sup == "level_out", 1.5, "the watchdog's level-out")
    assert 0.4 <= time.monotonic() - stopped <= 0.8
    time.sleep(0.4)
    assert abs(fleet.snapshot().rpy[0, 0]) < math.radians(1.0)  # levelled
    assert veh.motor_cmd == 44000  # thrust kept while levelling out
    wait_until(lambda: veh.motor_cmd == 0, 2.5, "the watchdog's motor stop")
    assert 1.8 <= time.monotonic() - stopped <= 2.5
    assert cf.supervisor.is_locked and not cf.supervisor.is_armed
    cf.supervisor.send_arming_request(True)  # locked: a reboot is needed
    time.sleep(0.2)
    assert not cf.supervisor.is_armed


@pytest.mark.slow
def test_streamed_setpoints_take_priority_then_hand_back_to_a_landing(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    cf = scf.cf
    cf.supervisor.send_arming_request(True)
    wait_until(lambda: cf.supervisor.is_armed, 1.0, "armed")
    cf.commander.send_setpoint(0, 0, 0, 0)
    stream(cf, 0.4, 0, 0, 0, 44000)
    cf.high_level_commander.takeoff(1.0, 1.0)  # the next streamed setpoint stops the planner again
    stream(cf, 0.3, 0, 0, 0, 36000)
    veh = fleet.vehicles[0]
    assert veh.sp_kind == "rpyt" and veh.hl.state == "idle"
    z = fleet.snapshot().q[0, 2]
    assert z > 0.05
    # the handover: stop streaming, land, relax the priority
    cf.high_level_commander.land(0.0, 1.5)
    cf.commander.send_notify_setpoint_stop()
    time.sleep(0.3)
    assert veh.sp_kind == "hl" and veh.hl.state == "landing" and veh.sup == "flying"
    wait_until(lambda: fleet.snapshot().q[0, 2] == 0.0, 4.0, "landed by the high-level commander")
    assert veh.counters.get("supervisor_locked", 0) == 0  # no watchdog trip on the way


@pytest.mark.slow
def test_silenced_vehicle_drops_the_link_both_ways(fleet: CrazyflieFleet) -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.settimeout(0.3)
    try:
        s.sendto(bytes([0xF0 | 0x0C | 0]) + b"ping", ("127.0.0.1", fleet.vehicles[0].port))  # link echo
        assert s.recv(64)[1:] == b"ping"
        fleet.silence(0, 0.5)
        s.sendto(bytes([0xFC]) + b"ping", ("127.0.0.1", fleet.vehicles[0].port))
        with pytest.raises(socket.timeout):
            s.recv(64)
        time.sleep(0.5)
        s.sendto(bytes([0xFC]) + b"pong", ("127.0.0.1", fleet.vehicles[0].port))
        assert s.recv(64)[1:] == b"pong"
    finally:
        s.close()


def _logged_positions(cf: Crazyflie) -> tuple[LogConfig, list[dict]]:
    got: list[dict] = []
    lc = LogConfig("extpos", period_in_ms=20)
    for a in ("x", "y", "z"):
        lc.add_variable(f"stateEstimate.{a}", "float")
    lc.data_received_cb.add_callback(lambda ts, data, conf: got.append(data))
    cf.log.add_config(lc)
    lc.start()
    return lc, got


def _xyz(d: dict) -> np.ndarray:
    return np.array([d["stateEstimate.x"], d["stateEstimate.y"], d["stateEstimate.z"]])


def test_logged_position_follows_extpos_sent_with_cflibs_api(scf: SyncCrazyflie, fleet: CrazyflieFleet) -> None:
    """crtp_localization_service.c: EXT_POSITION feeds the estimator, whose position is logged."""
    cf = scf.cf
    lc, got = _logged_positions(cf)
    wait_until(lambda: got, 2.0, "the first log packet")
    assert np.allclose(_xyz(got[-1]), [0.3, -0.2, 0.0], atol=1e-6)  # no external position yet: the true state
    for target in ([1.25, -0.5, 0.75], [-2.0, 3.5, 0.1]):
        for _ in range(5):
            cf.extpos.send_extpos(*target)
            time.sleep(0.02)
        n = len(got)
        wait_until(lambda n=n: len(got) > n + 2, 2.0, "log packets after the extpos")
        # the vehicle stands still on the ground: the estimate is the fed position (+ the drift bias)
        assert np.allclose(_xyz(got[-1]), target, atol=0.01), (got[-1], target)
    assert fleet.snapshot().q[0].tolist() == pytest.approx([0.3, -0.2, 0.0])  # the true state did not move
    # EXT_POSE (the generic channel), as cflib's send_extpose sends it
    cf.extpos.send_extpose(0.5, 0.6, 0.7, 0.0, 0.0, 0.0, 1.0)
    n = len(got)
    wait_until(lambda: len(got) > n + 2, 2.0, "log packets after the extpose")
    assert np.allclose(_xyz(got[-1]), [0.5, 0.6, 0.7], atol=0.01)
    # a silent feed: the estimate drifts (dead reckoning with a bias)
    time.sleep(1.0)
    drift = _xyz(got[-1]) - [0.5, 0.6, 0.7]
    assert 0.01 < np.hypot(drift[0], drift[1]) < 0.2, drift
    lc.stop()
    assert fleet.vehicles[0].counters.get("extpos", 0) == 11


def test_extpos_packed_takes_the_item_with_the_vehicles_id(fleet: CrazyflieFleet) -> None:
    """EXT_POSITION_PACKED (port 6, channel 2): items <Bhhh (id, mm); only this vehicle's id counts."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        items = struct.pack("<Bhhh", 7, 9000, 9000, 9000) + struct.pack("<Bhhh", 1, 1500, -250, 800)
        s.sendto(bytes([(6 << 4) | 0x0C | 2]) + items, ("127.0.0.1", fleet.vehicles[0].port))
        wait_until(lambda: fleet.vehicles[0].counters.get("extpos", 0) == 1, 2.0, "the packed extpos")
    finally:
        s.close()
    v = fleet.vehicles[0]
    assert v.extpos_q is not None and np.allclose(v.extpos_q, [1.5, -0.25, 0.8])

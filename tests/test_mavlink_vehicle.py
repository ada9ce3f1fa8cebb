"""The simulated MAVLink vehicle's PX4 and ArduCopter behaviours, driven by a plain pymavlink
ground station over UDP on 127.0.0.1 (the vehicles run in a thread of the test process).

Each test flies a few seconds at most; the behaviours and their sources are documented in
:mod:`zenswarm.plant.mavlink_vehicle` and :mod:`zenswarm.plant.mavlink_params`.
"""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from zenswarm.params import QuadParams
from zenswarm.plant.mavlink_params import INT32, REAL32, ParamStore, decode, encode, px4_params
from zenswarm.plant.mavlink_vehicle import MavlinkFleet, VehicleOptions, mavlink, mavutil

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

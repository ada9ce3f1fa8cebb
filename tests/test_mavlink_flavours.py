"""The bridge against the simulated vehicle's PX4 and ArduCopter behaviours (issue 16), in
process over real UDP on 127.0.0.1: no bus, the agents' commands stood in by callables.

- ArduCopter, attitude setpoints: the bridge reads GUID_OPTIONS / GUID_TIMEOUT / MOT_THST_HOVER,
  sets GUID_OPTIONS bit 3 (thrust as thrust; left clear, the hover throttle 0.444 would be a
  descent), takes off with MAV_CMD_NAV_TAKEOFF and no position target until the altitude is
  reached, then holds altitude on the agent's hover thrust.
- PX4 with each vehicle's own estimator origin and PX4 SITL's port direction (the vehicle sends
  from base+40+i to base+i; the bridge listens with ``udpin``): the ``origins`` setting puts the
  vehicles where the scenario wants them in the common ENU frame, and the states the bridge
  publishes are the vehicles' true positions.

A few seconds each; the vehicles are threads of the test process (``MavlinkFleet``).
"""

from __future__ import annotations

import math
import time
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from zenswarm.bridge.vehicles.mavlink import AP_COPTER_MODES, Bridge, mavlink_settings
from zenswarm.bus import free_udp_block, wire
from zenswarm.plant.mavlink_vehicle import MavlinkFleet, VehicleOptions
from zenswarm.scenario.config import scenario_from_dict
from zenswarm.vehicle.params import QuadParams

pytestmark = pytest.mark.swarm  # real sockets and vehicle threads, wall-clock seconds

EX1 = Path(__file__).resolve().parents[1] / "compose" / "scenarios" / "paper_example1.toml"


def _sc(mav: dict[str, Any]) -> Any:
    d = tomllib.loads(EX1.read_text())
    d["mavlink"] = mav
    return scenario_from_dict(d)


def _spin(b: Bridge, seconds: float, done: Callable[[], bool]) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        now = time.monotonic()
        b.poll(now)
        b.advance(now)
        b.send(now)
        if done():
            return True
        time.sleep(0.01)
    return False


def test_ardupilot_attitude_flight_sets_thrust_bit_and_takes_off_with_nav_takeoff():
    base = free_udp_block(3)
    sc = _sc({"base_port": base, "setpoint": "attitude", "takeoff": True, "stream_s": 0.2})
    fleet = MavlinkFleet.from_scenario(sc, opts=VehicleOptions(autopilot="ardupilot")).start()
    hover = QuadParams.from_vehicle(sc.vehicle).hover_thrust
    flying = {"on": False}
    z_ref = [q[2] for q in sc.initial_positions]

    def agent(i: int) -> tuple[Any, float]:
        """The agents' stand-in: level, thrust from a PD altitude loop around the hover thrust (N)."""
        if not flying["on"]:
            return None, math.inf
        st = fleet.snapshot()
        thrust = hover * (1.0 + 4.0 * (z_ref[i - 1] - st.q[i - 1, 2]) - 2.0 * st.v[i - 1, 2])
        return wire.Cmd(t=0, seq=1, thrust=thrust, rpy=[0.0, 0.0, sc.controller.yaw], u=[0.0] * 3, d_hat=[0.0] * 3), 0.0

    counters: dict[str, float] = {}
    logs: list[str] = []
    b = Bridge(
        mavlink_settings(sc), sc, counters,
        get_cmd=agent,
        get_ref=lambda i: (None, math.inf),
        log=logs.append,
    )
    try:
        assert _spin(b, 25.0, lambda: b.settled), (logs, fleet.status())
        assert [lk.phase for lk in b.links] == ["ready"] * 3, (logs, fleet.status())
        for k, lk in enumerate(b.links):
            veh = fleet.vehicles[k]
            assert veh.ap_params["GUID_OPTIONS"] == 8, "the bridge did not set GUID_OPTIONS bit 3"
            assert veh.custom_mode == AP_COPTER_MODES["GUIDED"] and veh.armed
            assert lk.vparams is not None and lk.vparams.loss_timeout_s == 3.0  # GUID_TIMEOUT read
            np.testing.assert_allclose(fleet.snapshot().q[k], sc.initial_positions[k], atol=0.1)
        assert any("takeoff altitude" in s for s in logs) and counters["takeoff_requests"] == 3
        flying["on"] = True
        _spin(b, 2.5, lambda: False)  # 2.5 s of thrust commands as SET_ATTITUDE_TARGET
        assert counters["setpoints_attitude"] > 100
        # thrust as thrust: the loop holds its altitude (read as a climb rate, the same numbers
        # would settle where the throttle is 0.5, about 3 cm higher, only after seconds of drift)
        np.testing.assert_allclose(fleet.snapshot().q[:, 2], z_ref, atol=0.03)
    finally:
        b.close()
        fleet.stop()
    assert fleet.error is None


def test_px4_own_origins_and_sitl_port_direction():
    base = free_udp_block(3)
    probe = _sc({})
    ground = [[q[0], q[1], 0.0] for q in probe.initial_positions]  # each vehicle's origin: where it booted
    sc = _sc({
        "connections": [f"udpin:127.0.0.1:{base + i}" for i in range(3)],  # PX4 SITL: the vehicle sends to us
        "origins": ground, "setpoint": "position", "takeoff": True, "stream_s": 0.3,
    })
    fleet = MavlinkFleet.from_scenario(sc, base_port=base, opts=VehicleOptions(autopilot="px4", own_origin=True, sitl_ports=True)).start()
    logs: list[str] = []
    b = Bridge(mavlink_settings(sc), sc, {}, get_cmd=lambda i: (None, math.inf), get_ref=lambda i: (None, math.inf), log=logs.append)
    try:
        assert _spin(b, 25.0, lambda: b.settled), (logs, fleet.status())
        assert [lk.phase for lk in b.links] == ["ready"] * 3, (logs, fleet.status())
        now = time.monotonic()
        for k, lk in enumerate(b.links):
            # the vehicle reports NED about its own origin: near zero horizontally at the takeoff point
            assert np.linalg.norm(lk.tel.pos_ned[:2]) < 0.1, lk.tel.pos_ned
            np.testing.assert_allclose(fleet.snapshot().q[k], sc.initial_positions[k], atol=0.1)  # true position
            st = b.state_enu(lk, now)
            assert st is not None
            np.testing.assert_allclose(st[0], fleet.snapshot().q[k], atol=0.05)  # published = true, common frame
        # the vehicles answer TIMESYNC as PX4 does: the bridge measures the link's latency
        assert all(lk.tel.rtt_s is not None for lk in b.links), [lk.tel.rtt_s for lk in b.links]
        assert 0.0 <= b.info(time.monotonic())["max_latency_ms"] < 100.0
    finally:
        b.close()
        fleet.stop()
    assert fleet.error is None

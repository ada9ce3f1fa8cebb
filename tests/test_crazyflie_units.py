"""The Crazyflie bridge's pure parts: the legacy setpoint of an agent's command (signs, yaw loop,
thrust clamp) and the ``[crazyflie]`` settings (URIs checked, overrides, errors naming the
field). No process, no link."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from zenswarm.bridge.vehicles.crazyflie import CfLink, rpyt_of
from zenswarm.errors import ScenarioError
from zenswarm.scenario.config import load_scenario
from zenswarm.schema import CrazyflieTable
from zenswarm.vehicle import crazyflie as cfu
from zenswarm.vehicle.crazyflie_settings import check_uri, crazyflie_settings

from swarmtest import SCENARIOS

SC = load_scenario(SCENARIOS / "paper_example1.toml")


def test_rpyt_of_an_agent_command() -> None:
    hover = 0.027 * 9.81
    roll, pitch, yawrate, thrust, clamped = rpyt_of(hover, (0.1, -0.05, 0.0), 0.2, 4.0)
    assert roll == pytest.approx(math.degrees(0.1)) and pitch == pytest.approx(math.degrees(-0.05))  # cflib negates pitch itself
    assert yawrate == pytest.approx(math.degrees(0.8))  # yaw 0.2 rad left of the reference: turn clockwise, cflib's positive
    assert thrust == cfu.thrust_to_command(hover)[0] and not clamped
    *_, thrust, clamped = rpyt_of(0.596, (0.0, 0.0, 0.0), 0.0, 4.0)  # the scenario's max_thrust
    assert thrust == cfu.MAX_THRUST and clamped
    *_, thrust, clamped = rpyt_of(-1.0, (0.0, 0.0, 0.0), 0.0, 4.0)
    assert thrust == 0 and not clamped


def test_default_uris_are_the_simulated_vehicles() -> None:
    s = crazyflie_settings(SC)
    assert s.uris == ("udp://127.0.0.1:19850", "udp://127.0.0.1:19851", "udp://127.0.0.1:19852")
    assert s.rate_hz == SC.timing.control_rate_hz and s.link_timeout_s == 0.5
    s = crazyflie_settings(SC, {"uri": {2: "radio://0/80/2M/E7E7E7E702"}, "base_port": 20000, "rate_hz": 50})
    assert s.uris == ("udp://127.0.0.1:20000", "radio://0/80/2M/E7E7E7E702", "udp://127.0.0.1:20002") and s.rate_hz == 50


@pytest.mark.parametrize(
    "uri", ["radio://0/80/2M/E7E7E7E701", "radio://1/125/250K", "udp://127.0.0.1:19850", "udp://cf-sim.lab:1", "usb://0"]
)
def test_good_uris(uri: str) -> None:
    assert check_uri("f", uri) == uri


@pytest.mark.parametrize(
    ("uri", "why"),
    [
        ("radio://0/126/2M/E7E7E7E701", "channel"),
        ("radio://0/80/3M/E7E7E7E701", "not a Crazyflie link URI"),
        ("radio://0/80/2M/E7E7E7", "not a Crazyflie link URI"),
        ("udp://127.0.0.1:70000", "port"),
        ("udp://127.0.0.1", "not a Crazyflie link URI"),
        ("tcp://127.0.0.1:5000", "not a Crazyflie link URI"),
        ("", "not a Crazyflie link URI"),
    ],
)
def test_bad_uris_name_the_field(uri: str, why: str) -> None:
    with pytest.raises(ScenarioError, match=why) as e:
        check_uri("crazyflie.uris[0]", uri)
    assert e.value.field == "crazyflie.uris[0]"


def test_duplicates_and_missing_uavs_are_errors() -> None:
    with pytest.raises(ScenarioError, match="UAVs 1 and 3 have the same URI") as e:
        crazyflie_settings(
            replace(SC, crazyflie=CrazyflieTable(uris=("radio://0/80/2M/E7E7E7E701", "usb://0", "radio://0/80/2M/e7e7e7e701")))
        )
    assert e.value.field == "crazyflie.uris"
    with pytest.raises(ScenarioError, match="UAV 4 does not exist") as e:
        crazyflie_settings(SC, {"uri": {4: "usb://0"}})
    assert e.value.field == "--uri"
    with pytest.raises(ScenarioError, match="expected 3 URIs"):
        crazyflie_settings(replace(SC, crazyflie=CrazyflieTable(uris=("usb://0",))))
    with pytest.raises(ScenarioError, match="same URI"):
        crazyflie_settings(SC, {"uri": {1: "udp://127.0.0.1:19851"}})  # UAV 2's default


def test_mocap_message_roundtrips_and_rejects_garbage() -> None:
    import msgspec

    from zenswarm.bus.mocap import decode_mocap, encode_mocap, mocap_key

    m = decode_mocap(encode_mocap(1.5, 0.25, -1.0, 0.75))
    assert (m.t, m.x, m.y, m.z) == (1.5, 0.25, -1.0, 0.75)
    assert decode_mocap(msgspec.msgpack.encode([2.0, 1, 2, 3])).z == 3.0  # what a lab's feeder publishes
    assert mocap_key("swarm/demo", 2) == "swarm/demo/mocap/2"
    for bad in (b"\x00", msgspec.msgpack.encode([1.0, 2.0]), msgspec.msgpack.encode({"x": 1.0})):
        with pytest.raises(ValueError):
            decode_mocap(bad)


def test_a_stall_of_the_landing_loop_is_no_link_lost() -> None:
    """The end of the mission: the other processes end at once and the loaded host starves the
    bridge for 0.6 s; the log blocks that came meanwhile are still queued in cflib's threads.
    The landing loop must treat that as its own stall (``note_stall``), as the flight loop does,
    not as three vehicles falling silent at once (``link_lost`` x 3)."""
    import collections
    import threading
    import time
    from types import SimpleNamespace

    from zenswarm.bridge.vehicles.crazyflie import READY, CrazyflieBridge
    from zenswarm.bridge.vehicles.mavlink import _BridgeLoop

    settings = replace(crazyflie_settings(SC), land_timeout_s=0.2)
    counters: collections.Counter = collections.Counter()
    bridge = CrazyflieBridge(settings, SC, counters, lambda i: (None, math.inf), lambda s: None)
    proc = SimpleNamespace(scenario=SC, args=SimpleNamespace(), stop=threading.Event(), counters=counters,
                           log=lambda s: None, publish_diag=lambda t, d: None)  # fmt: skip
    loop = _BridgeLoop(proc, bridge, settings)  # type: ignore[arg-type]
    now = time.monotonic()
    for link in bridge.links:  # flying; their last state arrived just before the stall
        link.phase, link.phase_t, link.pos_rx = READY, now - 10.0, now - 0.6
    loop.finished = True
    loop.last = now - 0.6  # the loop's last iteration, before the host starved it
    loop.land()
    assert counters["link_lost"] == 0 and all(lk.healthy for lk in bridge.links), counters
    assert counters["loop_stalls"] == 1


def test_link_ages_are_never_negative_when_a_stamp_lands_after_now() -> None:
    """cflib's and zenoh's threads stamp a link's last position and last fed mocap; a summary that
    took ``now`` just before reads an age of 0, not -0.2 ms (seen in a flight under load)."""
    link = CfLink(1, "udp://127.0.0.1:1", np.zeros(3))
    assert link.info(10.0, 50.0)["extpos_age_ms"] == -1.0 and link.info(10.0, 50.0)["silent_s"] is None  # never stamped
    link.mocap_rx = link.pos_rx = 10.0002
    info = link.info(10.0, 50.0)
    assert info["extpos_age_ms"] == 0.0 and info["silent_s"] == 0.0
    link.mocap_rx = link.pos_rx = 9.75
    info = link.info(10.0, 50.0)
    assert info["extpos_age_ms"] == 250.0 and info["silent_s"] == 0.25

"""Issue 46 end to end: agents -> Crazyflie bridge -> cflib -> CRTP over UDP -> simulated
Crazyflies, started by ``zenswarm up --plant crazyflie`` (realtime, on the wall clock); a link
lost mid-flight (the test's own fleet, external vehicles); and bad input (malformed, duplicate
and out-of-range URIs, an unreachable vehicle), each with no traceback and nothing left behind.

Each test has its own swarm name, router port and UDP ports. Bounds are generous: realtime flight
on a loaded 2-core host.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import pytest

pytest.importorskip("cflib", reason="cflib is not installed (pip install -e '.[crazyflie]')")

from zenswarm.bus import free_port, free_udp_block
from zenswarm.plant.crazyflie_vehicle import CrazyflieFleet
from zenswarm.scenario.config import load_scenario
from zenswarm.scenario.generate import to_toml

from swarmtest import (
    ROOT,
    SCENARIOS,
    kill_mentioning,
    processes_mentioning,
    read_results,
    udp_ports_free,
    unique_swarm,
    wait_port_free,
    zenswarm,
)

pytestmark = pytest.mark.swarm  # starts processes: zenoh routers, swarm processes or CLI subprocesses

N_UAV = 3


def _scenario(tmp: Path, crazyflie: dict | None = None, **timing: float) -> Path:
    d = tomllib.loads((SCENARIOS / "paper_example1.toml").read_text())
    d["timing"].update(timing)
    if crazyflie is not None:
        d["crazyflie"] = crazyflie
    p = tmp / "cf.toml"
    p.write_text(to_toml(d))
    return p


def _no_traceback(text: str) -> None:
    assert "Traceback" not in text, text[-3000:]


def _up(scenario: Path, out: Path, swarm: str, port: int, *extra: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    try:
        return zenswarm(
            "up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
            "--plant", "crazyflie", "--progress-every", "5", *extra, timeout=timeout,
        )  # fmt: skip
    finally:
        leftovers = processes_mentioning(f"--swarm {swarm}")
        kill_mentioning(f"--swarm {swarm}")
        assert not leftovers, f"processes left behind: {leftovers}"
        assert wait_port_free(port), f"router port {port} still bound after exit"


def test_example1_through_the_crazyflie_bridge_reaches_the_goal_and_lands(tmp_path: Path) -> None:
    swarm, port, base = unique_swarm("cf"), free_port(), free_udp_block(N_UAV)
    out = tmp_path / "run"
    try:
        cp = _up(SCENARIOS / "paper_example1.toml", out, swarm, port, "--crazyflie-base-port", str(base), "--stop-at-goal")
    finally:
        left = processes_mentioning(f"--base-port {base}")
        kill_mentioning(f"--base-port {base}")
    assert not left, f"vehicles left behind: {left}"
    assert udp_ports_free(base, N_UAV), "the simulated Crazyflies' ports are still bound"
    _no_traceback(cp.stdout)
    res = read_results(out)
    assert cp.returncode == 0, cp.stdout[-4000:]
    assert res["mode"] == "realtime"
    assert res["goal_reached"] and res["success"], {k: v for k, v in res.items() if k != "diagnostics"}
    assert res["min_obstacle_clearance_m"] > 0 and not res["obstacle_collision"]
    assert res["min_inter_uav_distance_m"] > 0.05 and not res["uav_collision"]
    assert res["rms_tracking_error_m"] < 0.1  # the formation was flown through cflib (the sim plant: 0.006 m)
    assert res["decoder_rejects"]["rejected"] == 0
    veh = res["vehicles"]
    assert veh["phases"] == "1:done,2:done,3:done" and veh["link_lost"] == 0 and veh["armed_uavs"] == 0, veh
    assert 0 <= veh["max_state_age_ms"] < 1000, veh  # from the vehicles' own log timestamps
    d = res["diagnostics"]["bridge"]
    assert d["setpoints_rpyt"] > 1000 and d["states_published"] > 1000, d
    assert "mission clock started with UAV(s) [1, 2, 3]" in cp.stdout
    assert "landed by the high-level commander" in cp.stdout


def test_rt_priority_raises_the_crazyflie_bridge_and_its_simulated_vehicles(tmp_path: Path) -> None:
    """``--plant crazyflie --rt-priority P``: the Crazyflie bridge (its diagnostics) and the
    simulated Crazyflies (their log line) run under ``SCHED_FIFO`` P once started, as the leader
    and the agents do, and the flight is flown and landed. Needs the privilege (skipped, with the
    reason, where this user may not use ``SCHED_FIFO``)."""
    from zenswarm.process import rtsched

    try:
        rtsched.probe(7)
    except rtsched.RtPriorityError as e:
        print(f"skipped: this user may not use SCHED_FIFO ({e})")
        pytest.skip(f"missing privilege: {e}")
    swarm, port, base = unique_swarm("cfrt"), free_port(), free_udp_block(N_UAV)
    out = tmp_path / "run"
    try:
        cp = _up(SCENARIOS / "paper_example1.toml", out, swarm, port, "--crazyflie-base-port", str(base), "--duration", "4",
                 "--rt-priority", "7")  # fmt: skip
    finally:
        left = processes_mentioning(f"--base-port {base}")
        kill_mentioning(f"--base-port {base}")
    assert not left, f"vehicles left behind: {left}"
    _no_traceback(cp.stdout)
    res = read_results(out)
    diag = res["diagnostics"]
    for name in ["bridge", "leader"] + [f"agent:{i}" for i in range(1, N_UAV + 1)]:
        assert diag[name]["rt.priority"] == 7 and diag[name]["rt.threads"] >= 2, (name, diag[name])
    assert "crazyflie-vehicle: real-time scheduling: " in cp.stdout and "threads under SCHED_FIFO priority 7" in cp.stdout
    assert res["vehicles"]["phases"] == "1:done,2:done,3:done", res["vehicles"]
    assert "mission clock started with UAV(s) [1, 2, 3]" in cp.stdout


def test_link_lost_mid_flight_is_the_named_failsafe_and_results_are_written(tmp_path: Path) -> None:
    sc = load_scenario(SCENARIOS / "paper_example1.toml")
    base = free_udp_block(N_UAV)
    fleet = CrazyflieFleet.from_scenario(sc, base_port=base).start()
    scenario = _scenario(tmp_path, {"uris": fleet.uris()})
    swarm, port, out = unique_swarm("cfl"), free_port(), tmp_path / "run"
    cut: dict[str, float] = {}

    def cut_link() -> None:  # once UAV 2 flies its agent's setpoints, its link goes silent for good
        veh_deadline = time.monotonic() + 120.0
        while time.monotonic() < veh_deadline:
            if fleet.vehicles[1].counters.get("setpoints_rpyt", 0) > 200:
                fleet.silence(1, 1e6)
                cut["at"] = time.monotonic()
                return
            time.sleep(0.05)

    t = threading.Thread(target=cut_link, daemon=True)
    t.start()
    try:
        cp = _up(scenario, out, swarm, port, "--external", "vehicles", "--duration", "8")
    finally:
        fleet.stop()
    assert "at" in cut, "the flight never started"
    _no_traceback(cp.stdout)
    res = read_results(out)
    fs = [e for e in res["failsafe"] if e["uav"] == 2]
    assert fs and "link_lost" in fs[0]["modes"], res["failsafe"]
    assert res["vehicles"]["link_lost"] >= 1
    assert "failsafe: UAV 2 link_lost" in cp.stdout
    # the vehicle's own watchdog: level out, then the motors stopped and it is locked
    assert fleet.vehicles[1].sup == "locked", fleet.status()[1]
    assert fleet.vehicles[1].counters.get("supervisor_level_out", 0) == 1
    assert cp.returncode == 1 and not res["success"]  # UAV 2 never reached its slot
    # the others landed; the lost one is left to its own watchdog
    assert res["vehicles"]["phases"] == "1:done,2:lost,3:done", res["vehicles"]


def _bridge(scenario: Path, *flags: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    swarm = unique_swarm("cfb")
    try:
        return zenswarm("bridge", "crazyflie", str(scenario), "--swarm", swarm, *flags, timeout=timeout)
    finally:
        left = processes_mentioning(f"--swarm {swarm}")
        kill_mentioning(f"--swarm {swarm}")
        assert not left, left


@pytest.mark.parametrize(
    ("flags", "table", "needle"),
    [
        (["--uri", "1=radio://0/200/2M/E7E7E7E701"], None, "radio channel must be 0..125"),
        (["--uri", "2=udp://127.0.0.1"], None, "not a Crazyflie link URI"),
        (["--uri", "1=udp://127.0.0.1:19850", "--uri", "2=udp://127.0.0.1:19850"], None, "same URI"),
        (["--uri", "4=udp://127.0.0.1:19853"], None, "UAV 4 does not exist"),
        ([], {"uris": ["udp://127.0.0.1:1", "udp://127.0.0.1:2"]}, "expected 3 URIs"),
        ([], {"uris": ["radio://0/80/2M/E7E7E7E701", "radio://0/80/2M/e7e7e7e701", "usb://0"]}, "same URI"),
    ],
)
def test_bad_uris_exit_2_naming_them(tmp_path: Path, flags: list[str], table: dict | None, needle: str) -> None:
    cp = _bridge(_scenario(tmp_path, table), *flags)
    assert cp.returncode == 2, cp.stdout
    assert needle in cp.stdout
    _no_traceback(cp.stdout)


def test_bad_uri_in_the_scenario_is_refused_by_up_before_anything_starts(tmp_path: Path) -> None:
    swarm, port = unique_swarm("cfu"), free_port()
    cp = _up(_scenario(tmp_path, {"uris": ["udp://127.0.0.1:1", "bogus", "udp://127.0.0.1:3"]}), tmp_path / "o", swarm, port)
    assert cp.returncode == 2 and "crazyflie.uris[1]" in cp.stdout, cp.stdout
    _no_traceback(cp.stdout)
    assert not (tmp_path / "o" / "results.json").exists()


def test_unreachable_vehicle_is_named_and_the_run_ends_cleanly(tmp_path: Path) -> None:
    base = free_udp_block(N_UAV)  # nobody listens there
    scenario = _scenario(tmp_path, {"uris": [f"udp://127.0.0.1:{base + i}" for i in range(N_UAV)], "connect_timeout_s": 2.0})
    swarm, port, out = unique_swarm("cfn"), free_port(), tmp_path / "run"
    cp = _up(scenario, out, swarm, port, "--external", "vehicles", "--duration", "5", timeout=120.0)
    _no_traceback(cp.stdout)
    assert "unreachable: no answer from udp://127.0.0.1:" in cp.stdout, cp.stdout[-3000:]
    assert cp.returncode == 3, cp.stdout[-3000:]  # the bridge had no UAV to fly
    res = read_results(out)
    assert res["vehicles"]["phases"] == "1:refused,2:refused,3:refused"


def test_crazyflie_vehicle_busy_port_is_exit_2(tmp_path: Path) -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    busy = s.getsockname()[1]
    try:
        cp = subprocess.run(
            [sys.executable, "-m", "zenswarm", "crazyflie-vehicle", str(SCENARIOS / "paper_example1.toml"), "--base-port", str(busy)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT, timeout=60,
        )  # fmt: skip
    finally:
        s.close()
    assert cp.returncode == 2 and "--base-port" in cp.stdout and "cannot be bound" in cp.stdout, cp.stdout
    _no_traceback(cp.stdout)


def test_flight_with_extpos_forwards_the_mocap_feed_to_the_vehicles(tmp_path: Path) -> None:
    """positioning = "extpos": the simulated vehicles are the mocap system too (``crazyflie-vehicle
    --mocap``, swarm/<name>/mocap/<i>), the bridge forwards each position with cflib's extpos."""
    swarm, port, base = unique_swarm("cfx"), free_port(), free_udp_block(N_UAV)
    out = tmp_path / "run"
    # link_timeout_s 2 s (default 0.5 s): the simulated Crazyflies and their feed are one Python process
    # sharing 2 cores with the other tests; a stall of it under load is not what this test is about
    scenario = _scenario(tmp_path, {"positioning": "extpos", "link_timeout_s": 2.0})
    try:
        cp = _up(scenario, out, swarm, port, "--crazyflie-base-port", str(base), "--duration", "6")
    finally:
        left = processes_mentioning(f"--base-port {base}")
        kill_mentioning(f"--base-port {base}")
    assert not left, f"vehicles left behind: {left}"
    _no_traceback(cp.stdout)
    assert f"mocap on swarm/{swarm}/mocap/<i>" in cp.stdout, cp.stdout[-3000:]
    assert "positioning extpos: forwarding" in cp.stdout
    res = read_results(out)
    veh = res["vehicles"]
    # no failsafe at all: the feed never stopped, and the end of the mission (landing) is no link_lost
    assert veh["positioning"] == "extpos" and not res["failsafe"], (veh, res["failsafe"])
    assert veh["phases"] == "1:done,2:done,3:done", veh  # armed only with a fed position, flown, landed
    assert 0 <= veh["max_extpos_age_ms"] < 1000, veh  # the feed went on to the end
    # forwarded at the feed's rate (100 Hz) to 3 vehicles through takeoff, about 6 s of mission and the landing
    assert res["diagnostics"]["bridge"]["extpos_sent"] > 900, res["diagnostics"]["bridge"]
    assert res["decoder_rejects"]["rejected"] == 0
    assert "mission clock started with UAV(s) [1, 2, 3]" in cp.stdout


@pytest.mark.parametrize(("flag", "said"), [("--secure", "user/password"), ("--tls", "mutual TLS")])
def test_secure_flight_with_extpos_feeds_the_mocap_as_its_own_user(tmp_path: Path, flag: str, said: str) -> None:
    """``--secure`` (and ``--tls``) with positioning = "extpos": the simulated vehicles' mocap feed
    joins the secured router as its own user (``mocap@<swarm>``, or the certificate ``mocap``; put
    ``mocap/<i>`` only), the bridge may subscribe to it, and the feed reaches every vehicle as in
    the open flight (before: the feed had no keys, its session timed out and the vehicles died)."""
    swarm, port, base = unique_swarm("cfs"), free_port(), free_udp_block(N_UAV)
    out = tmp_path / "run"
    # link_timeout_s 2 s (default 0.5 s): the simulated Crazyflies and their feed are one Python process
    # sharing 2 cores with the other tests; a stall of it under load is not what this test is about
    scenario = _scenario(tmp_path, {"positioning": "extpos", "link_timeout_s": 2.0})
    try:
        cp = _up(scenario, out, swarm, port, "--crazyflie-base-port", str(base), "--duration", "6", flag)
    finally:
        left = processes_mentioning(f"--base-port {base}")
        kill_mentioning(f"--base-port {base}")
    assert not left, f"vehicles left behind: {left}"
    _no_traceback(cp.stdout)
    assert f"secure mode: {said}" in cp.stdout, cp.stdout[-3000:]
    assert (out / "keys" / "mocap" / "credentials.json").exists()
    assert f"mocap on swarm/{swarm}/mocap/<i>" in cp.stdout, cp.stdout[-3000:]
    res = read_results(out)
    veh = res["vehicles"]
    assert veh["positioning"] == "extpos" and not res["failsafe"], (veh, res["failsafe"])
    assert veh["phases"] == "1:done,2:done,3:done", veh  # armed only with a fed position, flown, landed
    assert 0 <= veh["max_extpos_age_ms"] < 1000, veh
    assert res["diagnostics"]["bridge"]["extpos_sent"] > 900, res["diagnostics"]["bridge"]
    assert "mission clock started with UAV(s) [1, 2, 3]" in cp.stdout


def test_bad_positioning_exits_2_naming_it(tmp_path: Path) -> None:
    cp = _bridge(_scenario(tmp_path, {"positioning": "vicon"}))
    assert cp.returncode == 2, cp.stdout
    assert "crazyflie.positioning" in cp.stdout and "vicon" in cp.stdout, cp.stdout
    _no_traceback(cp.stdout)


def test_feed_lost_mid_flight_is_positioning_lost_and_the_vehicle_lands(tmp_path: Path) -> None:
    """UAV 2's mocap feed stops mid-flight: the named failsafe positioning_lost, and the bridge
    lands it with its high-level commander (the others fly on)."""
    from zenswarm import bus
    from zenswarm.bus.wire import Keys
    from zenswarm.plant.crazyflie_vehicle import MocapFeeder

    sc = load_scenario(SCENARIOS / "paper_example1.toml")
    base = free_udp_block(N_UAV)
    fleet = CrazyflieFleet.from_scenario(sc, base_port=base).start()
    scenario = _scenario(tmp_path, {"uris": fleet.uris(), "positioning": "extpos"})
    swarm, port, out = unique_swarm("cfp"), free_port(), tmp_path / "run"
    cut: dict[str, float] = {}
    done = threading.Event()

    def feed() -> None:  # the lab's motion-capture system, on the swarm's router
        conf = bus.client_config([f"tcp/127.0.0.1:{port}"], connect_timeout_s=60.0)
        with bus.open_session(conf, handle_signals=False) as session:
            feeder = MocapFeeder(fleet, session, Keys(swarm).prefix, 100.0)
            fleet.on_tick = feeder
            try:
                deadline = time.monotonic() + 120.0
                while time.monotonic() < deadline and not done.is_set():
                    if "at" not in cut and fleet.vehicles[1].counters.get("setpoints_rpyt", 0) > 200:
                        feeder.mute.add(1)
                        cut["at"] = time.monotonic()
                    time.sleep(0.05)
            finally:
                fleet.on_tick = None
                feeder.close()

    t = threading.Thread(target=feed, daemon=True)
    t.start()
    try:
        cp = _up(scenario, out, swarm, port, "--external", "vehicles", "--duration", "8")
    finally:
        done.set()
        t.join(10.0)
        fleet.stop()
    assert "at" in cut, "the flight never started"
    _no_traceback(cp.stdout)
    res = read_results(out)
    fs = [e for e in res["failsafe"] if e["uav"] == 2]
    assert fs and "positioning_lost" in fs[0]["modes"], res["failsafe"]
    assert "uav 2: no external position for" in cp.stdout
    assert not [e for e in res["failsafe"] if e["uav"] != 2], res["failsafe"]
    # landed by its high-level commander, not cut by the watchdog
    assert fleet.vehicles[1].counters.get("hl_land", 0) >= 1 and fleet.vehicles[1].sup != "locked", fleet.status()[1]
    assert fleet.snapshot().q[1, 2] == 0.0, fleet.status()[1]
    assert res["vehicles"]["phases"] == "1:done,2:done,3:done", res["vehicles"]

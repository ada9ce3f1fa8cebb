"""Paths a new user drives that the rest of the suite did not walk (an audit of the command line
after the package splits): each test failed before its fix. Every case runs ``python -m zenswarm``
for real; the flights are real swarms (router, processes, simulated vehicles) on their own swarm
names and ports, and leave no process behind.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from zenswarm.bus import free_port, free_udp_block
from zenswarm.vehicle.autopilot import SITL_SEND_OFFSET

from swarmtest import (
    ROOT,
    SCENARIOS,
    kill_mentioning,
    processes_mentioning,
    read_results,
    start_zenswarm,
    unique_swarm,
    wait_port_free,
    zenswarm,
)

pytestmark = pytest.mark.swarm  # starts processes: zenoh routers, swarm processes or CLI subprocesses

EX1 = SCENARIOS / "paper_example1.toml"
N_UAV = 3  # paper example 1


def _bad(r: subprocess.CompletedProcess, *needles: str) -> None:
    """Exit status 2, no traceback, every needle in the output."""
    assert r.returncode == 2, r.stdout
    assert "Traceback" not in r.stdout, r.stdout
    for n in needles:
        assert n in r.stdout, f"{n!r} not in {r.stdout!r}"


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 1 s lockstep flight of paper example 1, recorded by ``zenswarm up --record``."""
    tmp = tmp_path_factory.mktemp("rec")
    swarm = unique_swarm("aud")
    rec = tmp / "flight.mcap"
    try:
        r = zenswarm("up", str(EX1), "--swarm", swarm, "--out", str(tmp / "out"), "--record", str(rec), "--duration", "1",
                     "--quiet", timeout=120)  # fmt: skip
    finally:
        left = processes_mentioning(swarm)
        kill_mentioning(swarm)
    assert not left, left
    assert r.returncode == 1, r.stdout  # 1 s: the goal is not reached (timeout), the flight is whole
    assert rec.is_file()
    return rec


# ----------------------------------------------------------------------------- recordings


def test_export_refuses_to_overwrite_the_recording_it_reads(recording: Path, tmp_path: Path) -> None:
    """``export --foxglove F --out F`` replaced the recording by its own export (exit 0, the
    flight lost); the same through a symbolic link, and ``--rerun F``. Now exit 2 naming the flag,
    the recording untouched."""
    rec = tmp_path / "f.mcap"
    rec.write_bytes(recording.read_bytes())
    before = rec.read_bytes()
    _bad(zenswarm("export", "--foxglove", str(rec), "--out", str(rec), timeout=60), "--out", "is the recording being exported")
    link = tmp_path / "link.mcap"
    link.symlink_to(rec)
    _bad(zenswarm("export", str(rec), "--out", str(link), timeout=60), "--out")
    _bad(zenswarm("export", str(rec), "--rerun", str(rec), timeout=60), "--rerun")
    assert rec.read_bytes() == before
    # another file is fine
    r = zenswarm("export", "--foxglove", str(rec), "--out", str(tmp_path / "fg.mcap"), timeout=60)
    assert r.returncode == 0, r.stdout


def test_verify_strict_on_a_cut_recording_names_the_flag(recording: Path, tmp_path: Path) -> None:
    """``verify --strict`` on a truncated file told a command-line user to read it "with
    strict=False" (a Python argument); without --strict the file's problems were printed once per
    agent. Now the message names --strict and each problem is said once."""
    cut = tmp_path / "cut.mcap"
    data = recording.read_bytes()
    # cut where the summary starts: every chunk whole (a cut at 2/3 of the bytes could leave only a
    # first chunk written before agent 1's first command: flaky), the summary and footer gone. The
    # MCAP footer: opcode, length, summary_start, summary_offset_start, crc; then the 8-byte magic.
    summary_start = struct.unpack("<BQQQI", data[-8 - 29 : -8])[2]
    assert 0 < summary_start < len(data), summary_start
    cut.write_bytes(data[:summary_start])
    _bad(zenswarm("verify", "--strict", str(cut), timeout=60), "without --strict", "zenswarm recover")
    r = zenswarm("verify", str(cut), timeout=60)
    assert r.returncode == 0, r.stdout
    warnings = [line for line in r.stdout.splitlines() if line.startswith("verify: warning:")]
    assert warnings, r.stdout
    assert len(warnings) == len(set(warnings)), r.stdout
    assert r.stdout.count("verified") == N_UAV, r.stdout


def test_a_closed_standard_output_is_not_a_traceback(recording: Path) -> None:
    """``zenswarm info F | head`` ended in a BrokenPipeError traceback when head had gone; now the
    command stops quietly with 141 (128 + SIGPIPE, as a shell reports it)."""
    for args in (["plugins", "list"], ["info", str(recording)], ["info", "--json", str(recording)]):
        r_fd, w_fd = os.pipe()
        os.close(r_fd)  # the reader is gone before the first line
        try:
            p = subprocess.run([sys.executable, "-m", "zenswarm", *args], stdout=w_fd, stderr=subprocess.PIPE, text=True,
                               timeout=60, cwd=ROOT)  # fmt: skip
        finally:
            os.close(w_fd)
        assert "Traceback" not in p.stderr, (args, p.stderr)
        assert p.returncode == 141, (args, p.returncode, p.stderr)


# ----------------------------------------------------------------------------- bad input


def test_simulated_mavlink_vehicles_refuse_a_base_port_beyond_65535() -> None:
    """``mavlink-vehicle S --base-port 99999`` (and ``plant --mavlink``) crashed with an
    OverflowError traceback, exit 1; now exit 2 naming --base-port (as crazyflie-vehicle)."""
    _bad(zenswarm("mavlink-vehicle", str(EX1), "--base-port", "99999", timeout=60), "--base-port", "65536")
    _bad(zenswarm("plant", "--mavlink", "--scenario", str(EX1), "--base-port", "65500", "--sitl-ports", timeout=60), "--base-port")
    _bad(zenswarm("mavlink-vehicle", str(EX1), "--base-port", "0", timeout=60), "--base-port")


def test_sweep_margin_refuses_an_unwritable_json_before_the_search(tmp_path: Path) -> None:
    """``sweep margin --json /proc/x/y.json`` ran the whole search, then died in a traceback
    (exit 1) writing the file; now exit 2 naming --json at once."""
    _bad(zenswarm("sweep", "margin", "paper_example1", "--json", "/proc/x/y.json", timeout=120), "--json", "/proc/x/y.json")
    _bad(zenswarm("sweep", "margin", "paper_example1", "--json", str(tmp_path), timeout=120), "--json", "is a directory")


# ----------------------------------------------------------------------------- external MAVLink vehicles


def _fly_with_external_vehicles(tmp_path: Path, scenario: Path, vehicles_args: list[str], up_args: list[str]) -> dict:
    """Start simulated MAVLink vehicles by hand (``mavlink-vehicle``), then ``zenswarm up
    --plant mavlink --external vehicles`` next to them for 2 s; results.json of the flight."""
    swarm = unique_swarm("xv")
    port = free_port()
    mark = f"--swarm {swarm}"
    vehicles = start_zenswarm("mavlink-vehicle", str(scenario), *vehicles_args, "--duration", "120")
    try:
        assert vehicles.stdout is not None
        first = vehicles.stdout.readline()  # the ready line: its ports are bound
        assert "ready" in first, first
        r = zenswarm("up", str(scenario), "--swarm", swarm, "--out", str(tmp_path / "out"), "--listen", f"tcp/127.0.0.1:{port}",
                     "--plant", "mavlink", "--external", "vehicles", "--duration", "2", "--quiet", *up_args, timeout=240)  # fmt: skip
    finally:
        vehicles.terminate()
        vehicles.wait(timeout=30)
        left = [p for p in processes_mentioning(mark) if p[0] != vehicles.pid]
        kill_mentioning(mark)
    assert not left, f"processes left behind: {left}"
    assert wait_port_free(port)
    assert r.returncode == 1, r.stdout  # 2 s: timeout, not a dead bridge (3) nor bad input (2)
    res = read_results(tmp_path / "out")
    causes = {f["cause"] for f in res["failures"]}
    assert causes <= {"timeout", "off_slot"}, res["failures"]
    assert res["sim_time_s"] >= 1.9, res["sim_time_s"]  # the vehicles flew the whole 2 s
    return res


def test_up_external_mavlink_vehicles_are_found_through_the_scenarios_table(tmp_path: Path) -> None:
    """docs/mavlink.md: ``zenswarm up S --plant mavlink --external vehicles`` starts the bridge
    for vehicles of your own, which the scenario's ``[mavlink]`` table locates. The bridge was
    given the ports of simulated vehicles of its own instead (udpin on free ports), never heard
    the real ones and died (exit 3). Here the "real" vehicles are ``mavlink-vehicle`` on the
    table's base_port."""
    base = free_udp_block(N_UAV)
    sc = tmp_path / "ext.toml"
    sc.write_text(EX1.read_text() + f"\n[mavlink]\nbase_port = {base}\nstart_timeout_s = 15.0\n")
    _fly_with_external_vehicles(tmp_path, sc, [], [])


def test_up_external_mavlink_vehicles_at_the_given_base_port(tmp_path: Path) -> None:
    """``--mavlink-base-port P`` with ``--external vehicles`` started as ``zenswarm up`` starts
    its own (``mavlink-vehicle --sitl-ports --own-origin``, sending from P+40+i): up refused them
    because their own send ports were in use (exit 2). Only the bridge's ports are checked now."""
    base = free_udp_block(N_UAV, also=(SITL_SEND_OFFSET,))
    _fly_with_external_vehicles(
        tmp_path, EX1, ["--base-port", str(base), "--sitl-ports", "--own-origin"], ["--mavlink-base-port", str(base)]
    )


def test_up_external_crazyflies_at_the_given_base_port(tmp_path: Path) -> None:
    """``--plant crazyflie --external vehicles --crazyflie-base-port P`` next to ``zenswarm
    crazyflie-vehicle S --base-port P``: up refused the vehicles' own ports as busy (exit 2) and
    would have given the bridge none of them. Now the bridge dials udp://127.0.0.1:P+i."""
    base = free_udp_block(N_UAV)
    swarm = unique_swarm("xc")
    port = free_port()
    vehicles = start_zenswarm("crazyflie-vehicle", str(EX1), "--base-port", str(base), "--duration", "120")
    try:
        assert vehicles.stdout is not None
        first = vehicles.stdout.readline()  # the ready line: its ports are bound
        assert "ready" in first, first
        r = zenswarm("up", str(EX1), "--swarm", swarm, "--out", str(tmp_path / "out"), "--listen", f"tcp/127.0.0.1:{port}",
                     "--plant", "crazyflie", "--external", "vehicles", "--crazyflie-base-port", str(base), "--duration", "2",
                     "--quiet", timeout=240)  # fmt: skip
    finally:
        vehicles.terminate()
        vehicles.wait(timeout=30)
        left = processes_mentioning(f"--swarm {swarm}")
        kill_mentioning(f"--swarm {swarm}")
    assert not left, f"processes left behind: {left}"
    assert wait_port_free(port)
    assert r.returncode == 1, r.stdout  # 2 s: timeout, not bad input (2) nor a dead bridge (3)
    res = read_results(tmp_path / "out")
    assert {f["cause"] for f in res["failures"]} <= {"timeout", "off_slot"}, res["failures"]
    assert res["sim_time_s"] >= 1.9, res["sim_time_s"]


# ----------------------------------------------------------------------------- the processes' own flags


def test_a_role_names_its_missing_scenario_before_asking_for_the_router() -> None:
    """``zenswarm plant --scenario nofile.toml`` (leader, agent) with no router up waited for the
    router and then said "cannot open zenoh session": the scenario was read only once connected.
    Now the file is named at once, exit 2, whether a router answers or not."""
    port = free_port()  # nothing listens there
    for role in (["plant"], ["leader"], ["agent", "--id", "1"]):
        r = zenswarm(*role, "--scenario", "nofile.toml", "--swarm", unique_swarm("ns"), "--connect", f"tcp/127.0.0.1:{port}",
                     timeout=60)  # fmt: skip
        _bad(r, "nofile.toml", "not found")
        assert "zenoh" not in r.stdout, r.stdout  # the session was never asked for (was: "cannot open zenoh session")


def test_an_agent_id_outside_the_scenario_names_the_flag(tmp_path: Path) -> None:
    """``zenswarm agent --id 9`` of a 3-UAV scenario said "agent index 9 out of range 1..3",
    without the process's error prefix or the flag; now ``agent:9: error: --id: ...``, exit 2."""
    port = free_port()
    router = subprocess.Popen([sys.executable, "-m", "zenswarm.compose.router", "--listen", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)  # fmt: skip
    try:
        assert router.stdout is not None
        assert router.stdout.readline().startswith("ready"), "the router did not start"
        r = zenswarm("agent", "--id", "9", "--scenario", str(EX1), "--swarm", unique_swarm("id"), "--connect",
                     f"tcp/127.0.0.1:{port}", timeout=60)  # fmt: skip
    finally:
        router.terminate()
        router.wait(timeout=30)
    _bad(r, "agent:9: error: --id", "1..3")
    assert wait_port_free(port)


def test_a_bad_connect_endpoint_is_named_by_every_command(recording: Path, tmp_path: Path) -> None:
    """``--connect bogus`` reached zenoh, whose message (a Json5Err with the path of its build)
    named neither the flag nor the form; a port beyond 65535 waited for the connect timeout. Now
    every client (replay, record, the roles, the bridges) says ``--connect: 'bogus' is not a zenoh
    endpoint``, exit 2, at once."""
    cases = [
        ["replay", str(recording), "--connect", "bogus"],
        ["record", "--swarm", "x", "--out", str(tmp_path / "r.mcap"), "--connect", "bogus"],
        ["plant", "--scenario", str(EX1), "--swarm", "x", "--connect", "bogus"],
        ["agent", "--id", "1", "--scenario", str(EX1), "--swarm", "x", "--connect", "tcp/127.0.0.1:99999"],
        ["bridge", "mavlink", str(EX1), "--swarm", "x", "--connect", "tcp/nohostport"],
    ]
    for args in cases:
        r = zenswarm(*args, timeout=60)
        _bad(r, "--connect")
        assert "Json5Err" not in r.stdout and "cargo" not in r.stdout, r.stdout


def test_keys_names_days_and_refuses_a_validity_past_9999(tmp_path: Path) -> None:
    """``keys --days 0`` named ``days`` (the library's argument), and ``--days 100000000`` died in
    an OverflowError traceback; now both exit 2 naming ``--days``, nothing written."""
    _bad(zenswarm("keys", str(EX1), "--out", str(tmp_path / "k0"), "--days", "0", timeout=60), "--days")
    _bad(zenswarm("keys", str(EX1), "--out", str(tmp_path / "k1"), "--days", "100000000", timeout=60), "--days", "9999")
    assert not (tmp_path / "k0").exists() and not (tmp_path / "k1").exists()


def test_fly_names_a_bad_swarm_name_or_port_before_anything_starts() -> None:
    """``api.fly(..., mode="swarm", swarm="bad/name")`` started ``zenswarm up`` and raised
    :class:`FlightError` from its exit 2 (docs/testing.md: bad input is a ScenarioError naming the
    argument, nothing flown); ``port=99999`` was named ``--listen``. Now ``swarm`` and ``port``."""
    from zenswarm import api
    from zenswarm.errors import ScenarioError

    for kwargs, field in (({"swarm": "bad/name"}, "swarm"), ({"port": 99999}, "port"), ({"port": "7447"}, "port")):
        with pytest.raises(ScenarioError) as e:  # not FlightError: refused before a supervisor starts
            api.fly("paper_example1", mode="swarm", duration=1.0, **kwargs)
        assert e.value.field == field, (kwargs, e.value)


def test_up_report_without_record_is_refused(tmp_path: Path) -> None:
    """``zenswarm up S --report`` without ``--record`` flew the whole flight and wrote no report,
    silently (the report is made from the recording). Now exit 2 naming --report and --record,
    before anything starts."""
    swarm = unique_swarm("rp")
    out = tmp_path / "out"
    r = zenswarm("up", str(EX1), "--swarm", swarm, "--out", str(out), "--report", "--duration", "1", "--quiet", timeout=120)
    _bad(r, "--report", "--record")
    assert "[supervisor]" not in r.stdout, r.stdout  # the router never opened
    assert processes_mentioning(swarm) == []
    assert not out.exists()

"""Paths a new user drives that the rest of the suite did not walk (an audit of the command line
after the package splits): each test failed before its fix. Every case runs ``python -m zenswarm``
for real; the flights are real swarms (router, processes, simulated vehicles) on their own swarm
names and ports, and leave no process behind.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
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
    cut.write_bytes(data[: len(data) * 2 // 3])
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
    t0 = time.monotonic()
    _bad(zenswarm("sweep", "margin", "paper_example1", "--json", "/proc/x/y.json", timeout=120), "--json", "/proc/x/y.json")
    _bad(zenswarm("sweep", "margin", "paper_example1", "--json", str(tmp_path), timeout=120), "--json", "is a directory")
    assert time.monotonic() - t0 < 30


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

"""docs/protocol.md is enough to write a plant: ``tests/spec_plant.py`` (zenoh + msgpack + numpy,
no zenswarm import) flies paper example 1 in lockstep with zenswarm's leader and agents, started by
``zenswarm up ... --external plant``, and the supervisor's verdict is success.

Real processes on loopback, each test with its own swarm name and router port, none left behind.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from zenswarm.bus import free_port

from swarmtest import ROOT, SCENARIOS, read_results, scenario_variant, start_zenswarm, stop_swarm, unique_swarm

SPEC_PLANT = Path(__file__).with_name("spec_plant.py")


def test_spec_plant_imports_no_zenswarm_module() -> None:
    """The plant is written from the spec alone: only zenoh, msgpack, numpy and the standard library."""
    tree = ast.parse(SPEC_PLANT.read_text())
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"relative import in {SPEC_PLANT.name}"
            imported.add((node.module or "").split(".")[0])
    third_party = imported - set(sys.stdlib_module_names)
    assert third_party == {"zenoh", "msgpack", "numpy"}, third_party
    assert "__import__" not in SPEC_PLANT.read_text() and "importlib" not in imported


def _fly(
    tmp_path: Path, *extra_up: str, expect: tuple[str, ...] = (), scenario: Path = SCENARIOS / "paper_example1.toml", up_rc: int = 0
) -> tuple[dict, str, str]:
    swarm = unique_swarm("p")
    port = free_port()
    out = tmp_path / "out"
    sup = start_zenswarm("up", str(scenario), "--out", str(out), "--swarm", swarm,
                         "--listen", f"tcp/127.0.0.1:{port}", "--external", "plant", "--quiet-children",
                         "--progress-every", "5", *extra_up)
    plant = subprocess.Popen(
        [sys.executable, str(SPEC_PLANT), "--connect", f"tcp/127.0.0.1:{port}", "--swarm", swarm,
         *(w for p in expect for w in ("--expect", p))],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
    )
    try:
        p_out = plant.communicate(timeout=400)[0]
        s_out = sup.communicate(timeout=120)[0]
    finally:
        stop_swarm([sup, plant], swarm, port)
    assert plant.returncode == 0, p_out[-3000:]
    assert sup.returncode == up_rc, s_out[-3000:] + "\n--- plant:\n" + p_out[-2000:]
    return read_results(out), s_out, p_out


@pytest.mark.swarm
def test_spec_plant_flies_paper_example1_in_lockstep(tmp_path: Path) -> None:
    res, s_out, p_out = _fly(tmp_path)
    assert res["success"] is True, res.get("failures")
    assert res["mode"] == "lockstep" and res["process_deaths"] == []
    assert "flew 7000 ticks, 0 command timeouts" in p_out, p_out[-2000:]
    assert res["foreign_samples"] == {}, res["foreign_samples"]  # our SourceInfo + sender token were taken
    # every agent ran every tick on real inputs (the clock(0) and the leader's refs were there in time)
    # and rejected nothing we sent
    for i in (1, 2, 3):
        d = res["diagnostics"][f"agent:{i}"]
        assert d.get("finished") is True, d
        assert d.get("forced_ticks", 0) == 0 and d.get("input_timeouts", 0) == 0, d
        assert d.get("rejected", 0) == 0, d
    lead = res["diagnostics"]["leader"]
    assert lead.get("finished") is True and lead.get("rejected", 0) == 0, lead
    assert res["diagnostics"]["plant"].get("implementation") == "tests/spec_plant.py"


@pytest.mark.swarm
def test_spec_plant_in_a_recorded_run_waits_for_the_recorder(tmp_path: Path) -> None:
    """With ``--record`` the supervisor starts the recorder; a plant that waits for its token too
    (``--expect recorder``) gets every tick, from 0, into the recording. A 3 s mission: the goal is
    not reached (exit 1, ``timeout``), which is not what this test is about."""
    from zenswarm.bridge.recording.mcapio import read_recording

    rec = tmp_path / "flight.mcap"
    scen = scenario_variant(tmp_path, time_limit_s=3.0)
    res, _, _ = _fly(tmp_path, "--record", str(rec), expect=("recorder",), scenario=scen, up_rc=1)
    assert [f["cause"] for f in res["failures"]] == ["timeout"], res["failures"]
    assert res.get("recording_loss") is None and rec.stat().st_size > 0
    ticks: dict[str, set[int]] = {}
    for m in read_recording(rec).messages(topics=lambda t: t.endswith("/state")):
        ticks.setdefault(m.topic.split("/")[-2], set()).add(round(m.publish_time / 1e7))
    assert sorted(ticks) == ["1", "2", "3"], sorted(ticks)
    for uav, got in ticks.items():
        assert got == set(range(301)), f"UAV {uav}: ticks missing from the recording: {sorted(set(range(301)) - got)[:10]}"

"""`zenswarm up --external ROLE`: a role started elsewhere (another host, a namespace, by hand) is
known to the supervisor only through its liveliness token. One that dies ends the swarm like a
process of ours that died (exit 3, named, in ``process_deaths``); one that never shows up is given
up on after ``--external-timeout``; one that finishes its flight is not a death.

Real processes on loopback, each test with its own swarm name and router port, none left behind.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from zenswarm.bus import free_port

from swarmtest import (
    read_results,
    scenario_variant,
    start_zenswarm,
    stop_swarm,
    unique_swarm,
    zenswarm,
)


class Lines:
    """Reads a process's output on a thread, each line with its arrival time (monotonic s)."""

    def __init__(self, p: subprocess.Popen) -> None:
        self.lines: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self._t = threading.Thread(target=self._read, args=(p,), daemon=True)
        self._t.start()

    def _read(self, p: subprocess.Popen) -> None:
        assert p.stdout is not None
        for line in p.stdout:
            with self._lock:
                self.lines.append((time.monotonic(), line.rstrip()))

    def first(self, pattern: str) -> tuple[float, str] | None:
        with self._lock:
            return next(((t, s) for t, s in self.lines if re.search(pattern, s)), None)

    def wait(self, pattern: str, timeout: float) -> tuple[float, str] | None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hit = self.first(pattern)
            if hit is not None:
                return hit
            time.sleep(0.02)
        return None

    def text(self, last: int = 40) -> str:
        with self._lock:
            return "\n".join(s for _, s in self.lines[-last:])

    def join(self) -> None:
        self._t.join(timeout=5)


@pytest.mark.swarm
def test_external_plant_killed_ends_the_swarm_with_exit_3(tmp_path: Path) -> None:
    """The plant runs outside the supervisor (`up --only plant`) and is SIGKILLed mid-flight: the
    supervisor names it, records the death and exits 3 within seconds (it froze forever before,
    every role shown up, the agents and the leader waiting for a clock that never came)."""
    scenario = scenario_variant(tmp_path, time_limit_s=30.0, settle_time_s=1.0)
    swarm = unique_swarm("e")
    port = free_port()
    out = tmp_path / "out"
    sup = start_zenswarm("up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
                         "--external", "plant", "--progress-every", "0.2", "--quiet-children")
    plant = None
    lines = Lines(sup)
    try:
        # until the plant is started, progress shows it waiting
        assert lines.wait(r"plant:waiting\(external\)", 60), lines.text()
        plant = start_zenswarm("up", str(scenario), "--only", "plant", "--swarm", swarm,
                               "--connect", f"tcp/127.0.0.1:{port}")
        assert lines.wait(r"t=\s*[1-9][\d.]*/30 s.*plant:up\(external\)", 60), lines.text()
        os.kill(plant.pid, signal.SIGKILL)
        t_kill = time.monotonic()
        plant.wait(timeout=10)
        sup.wait(timeout=60)
        t_exit = time.monotonic()
        lines.join()
    finally:
        stop_swarm([sup, plant], swarm, port)
    log = lines.text()
    assert sup.returncode == 3, log
    died = lines.first(r"process plant died \(external: its liveliness token went away\) at sim time [\d.]+ s")
    assert died is not None, log
    assert died[0] - t_kill < 5.0, f"noticed {died[0] - t_kill:.1f} s after the kill\n{log}"
    assert t_exit - t_kill < 15.0, log
    res = read_results(out)
    assert res["success"] is False
    assert [(f["cause"], f.get("process")) for f in res["failures"]] == [("process_died", "plant")], res["failures"]
    [death] = res["process_deaths"]
    assert death["process"] == "plant" and "liveliness" in death["how"] and 1.0 <= death["sim_time_s"] < 30.0, death


@pytest.mark.swarm
def test_external_role_that_never_appears_is_given_up_on(tmp_path: Path) -> None:
    """`--external agent:3` never started: progress shows it waiting, and after
    `--external-timeout` the supervisor says so, naming the role and how to start it, and exits 3."""
    scenario = scenario_variant(tmp_path, time_limit_s=5.0, settle_time_s=1.0)
    swarm = unique_swarm("w")
    port = free_port()
    out = tmp_path / "out"
    t0 = time.monotonic()
    try:
        cp = zenswarm("up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
                      "--external", "agent:3", "--external-timeout", "4", "--progress-every", "0.5", "--quiet-children",
                      timeout=120)
    finally:
        stop_swarm([], swarm, port)
    elapsed = time.monotonic() - t0
    assert cp.returncode == 3, cp.stdout[-3000:]
    assert "agent:3:waiting(external)" in cp.stdout, cp.stdout[-3000:]
    assert "external role agent:3 never announced itself within 4 s (--external-timeout)" in cp.stdout, cp.stdout[-3000:]
    assert f"--only agent:3 --swarm {swarm} --connect tcp/127.0.0.1:{port}" in cp.stdout
    assert elapsed < 40.0, elapsed  # the plant itself would wait 60 s
    res = read_results(out)
    assert res["success"] is False
    assert [d["process"] for d in res["process_deaths"]] == ["agent:3"], res["process_deaths"]
    assert "never announced" in res["process_deaths"][0]["how"]


@pytest.mark.swarm
def test_external_plant_that_finishes_is_not_a_death(tmp_path: Path) -> None:
    """The external plant's token also goes away when it finishes: that is the end of the flight,
    not a death. The run ends normally and equals the in-process simulator."""
    from test_swarm import _assert_equal_to_sim

    scenario = scenario_variant(tmp_path, time_limit_s=3.0, settle_time_s=1.0)
    swarm = unique_swarm("f")
    port = free_port()
    out = tmp_path / "out"
    sup = start_zenswarm("up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
                         "--external", "plant", "--progress-every", "0.2", "--quiet-children")
    plant = start_zenswarm("up", str(scenario), "--only", "plant", "--swarm", swarm, "--connect", f"tcp/127.0.0.1:{port}")
    try:
        p_out = plant.communicate(timeout=120)[0]
        s_out = sup.communicate(timeout=120)[0]
    finally:
        stop_swarm([sup, plant], swarm, port)
    assert plant.returncode == 0, p_out[-2000:]
    assert sup.returncode in (0, 1), s_out[-3000:]  # 3 s cannot reach the goal: exit 1 is fine
    assert "died" not in s_out, s_out[-3000:]
    res = read_results(out)
    assert res["process_deaths"] == [], res["process_deaths"]
    _assert_equal_to_sim(scenario, out)


@pytest.mark.swarm
def test_bad_external_flags_exit_2_before_starting(tmp_path: Path) -> None:
    scenario = scenario_variant(tmp_path, time_limit_s=1.0)
    swarm = unique_swarm("b")
    out = tmp_path / "out"
    try:
        bad_role = zenswarm("up", str(scenario), "--out", str(out), "--swarm", swarm, "--external", "agent:9", timeout=60)
        bad_timeout = zenswarm("up", str(scenario), "--out", str(out), "--swarm", swarm, "--external", "plant",
                               "--external-timeout", "0", timeout=60)
    finally:
        stop_swarm([], swarm)
    assert bad_role.returncode == 2, bad_role.stdout
    assert "zenswarm: error: --external: unknown role 'agent:9'" in bad_role.stdout, bad_role.stdout
    assert "plant, leader, agent:1, agent:2, agent:3" in bad_role.stdout
    assert bad_timeout.returncode == 2, bad_timeout.stdout
    assert "--external-timeout" in bad_timeout.stdout and "positive" in bad_timeout.stdout, bad_timeout.stdout
    assert "Traceback" not in bad_role.stdout + bad_timeout.stdout
    assert not out.exists()


def test_external_watch_logic_without_processes(tmp_path: Path) -> None:
    """The supervisor's view of external roles, from liveliness events alone (no swarm): waiting,
    up, a short absence, a death, a normal end; an external plant may be the MAVLink bridge run
    by hand (it announces itself as ``bridge``)."""
    from types import SimpleNamespace

    from zenswarm.bus import wire
    from zenswarm.compose.cli import build_parser
    from zenswarm.compose.supervisor import EXIT_PROCESS_FAILED, EXTERNAL_GONE_GRACE_S, Supervisor
    from zenswarm.compose.up import up_options
    from zenswarm.process.collector import Collector
    from zenswarm.scenario.config import load_scenario

    scenario = scenario_variant(tmp_path, time_limit_s=2.0)
    sc = load_scenario(scenario)

    def supervisor(*extra: str) -> tuple[Supervisor, Collector]:
        args = build_parser().parse_args(["up", str(scenario), "--swarm", "u", *extra])
        sup = Supervisor(up_options(args), sc)
        sup.connect_endpoints = ["tcp/127.0.0.1:7447"]
        sup.collector = Collector(sc, sup.keys)
        return sup, sup.collector

    def token(sup: Supervisor, process: str, up: bool) -> None:
        kind = "SampleKind.PUT" if up else "SampleKind.DELETE"
        sup._on_liveliness(SimpleNamespace(key_expr=wire.Keys("u").alive(process), kind=kind))

    sup, col = supervisor("--external", "plant", "--external", "agent:2", "--external-timeout", "5")
    assert sup.external.names == ["plant", "agent:2"] and "agent:2" not in sup.started
    t0 = 1000.0
    assert sup._watch_external(col, t0 + 4.9, t0) is None
    assert sup._health().endswith("plant:waiting(external) agent:2:waiting(external)")
    token(sup, "bridge", True)  # the bridge in the plant's place
    token(sup, "agent:2", True)
    assert sup._watch_external(col, t0 + 6, t0) is None
    assert sup._health().endswith("plant:up(external) agent:2:up(external)")
    col.sim_t_ns = wire.t_ns(1.0)
    token(sup, "agent:2", False)
    now = sup.gone_at["agent:2"][0]
    assert sup._watch_external(col, now + EXTERNAL_GONE_GRACE_S / 2, t0) is None  # within the grace
    assert "agent:2:gone(external)" in sup._health()
    assert sup._watch_external(col, now + EXTERNAL_GONE_GRACE_S + 0.01, t0) == EXIT_PROCESS_FAILED
    assert sup.deaths == [{"process": "agent:2", "how": "liveliness token gone (external)", "sim_time_s": 1.0}]

    # a normal end: finished diagnostics, or the clock at the time limit
    sup, col = supervisor("--external", "agent:2")
    token(sup, "agent:2", True)
    col.diag["agent:2"] = {"finished": True}
    token(sup, "agent:2", False)
    assert sup._watch_external(col, time.monotonic() + 10, t0) is None
    sup, col = supervisor("--external", "plant")
    token(sup, "plant", True)
    col.sim_t_ns = wire.t_ns(sc.timing.time_limit_s)
    token(sup, "plant", False)
    assert sup._watch_external(col, time.monotonic() + 10, t0) is None and sup.deaths == []

    # never announced
    sup, col = supervisor("--external", "leader", "--external-timeout", "2")
    assert sup._watch_external(col, t0 + 2.5, t0) == EXIT_PROCESS_FAILED
    assert sup.deaths[0]["process"] == "leader" and "never announced" in sup.deaths[0]["how"]


@pytest.mark.swarm
def test_external_agent_whose_plug_in_fails_is_named_like_a_child(tmp_path: Path) -> None:
    """An ``--external`` agent's plug-in fails (issue 27): the supervisor learns it from the
    agent's diagnostics, names the same ``plugin_error`` as the simulator, exits 4."""
    import tomllib

    from zenswarm import api
    from zenswarm.scenario.generate import to_toml

    tests = str(Path(__file__).parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    doc = tomllib.loads(scenario_variant(tmp_path, time_limit_s=1.0).read_text())
    doc["agents"] = {"controller": "plugin_fixtures:MisbehavingController", "params": {"how": "nan", "tick": 33, "uav": 2}}
    scenario = tmp_path / "bad.toml"
    scenario.write_text(to_toml(doc))
    swarm, port, out = unique_swarm("pe"), free_port(), tmp_path / "out"
    sup = start_zenswarm("up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
                         "--external", "agent:2", "--quiet-children", env=env)
    agent = start_zenswarm("up", str(scenario), "--only", "agent:2", "--swarm", swarm, "--connect", f"tcp/127.0.0.1:{port}", env=env)
    try:
        s_out = sup.communicate(timeout=120)[0]
        a_out = agent.communicate(timeout=60)[0]
    finally:
        stop_swarm([sup, agent], swarm, port)
    assert sup.returncode == 4, s_out[-3000:]
    assert agent.returncode == 4 and "plugin_error" in a_out and "Traceback" not in a_out, a_out[-2000:]
    import sys

    sys.path.insert(0, tests)
    try:
        sim = api.fly(doc, mode="sim")
    finally:
        sys.path.remove(tests)
    assert read_results(out)["failures"] == sim.results["failures"] and sim.results["failures"][0]["tick"] == 33

"""Issue 30: what real machines do to a swarm. Real processes, a real router on loopback (or in a
network namespace the test creates), real MCAP files.

* the supervisor SIGKILLed mid-flight: no process of the swarm outlives it by 10 s, and a second
  ``up`` on the same router port right after works;
* a frozen agent (SIGSTOP for 3 s, then SIGCONT): lockstep waits for it and succeeds; realtime
  names what happened (the plant's failsafe held the UAV, results.json ``failsafe_events``);
* two flights at once with default settings (one ``--secure``) never see each other's traffic.

See docs/faults.md ("Machine faults") and docs/security.md for what is guaranteed.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from zenswarm.bus import free_port

from swarmtest import (
    ROOT,
    SCENARIOS,
    kill_mentioning,
    processes_mentioning,
    read_results,
    scenario_variant,
    stop_swarm,
    unique_swarm,
    wait_port_free,
)

pytestmark = pytest.mark.swarm  # starts processes: zenoh routers, swarm processes or CLI subprocesses

EX1 = SCENARIOS / "paper_example1.toml"
FREEZE_S = 3.0  # wall seconds an agent stays frozen (SIGSTOP)
LEASE_S = 10.0  # zenoh's session lease: a cut link is noticed this long after the cut
LOST_HOST_EXIT_S = 2 * LEASE_S + 10.0  # lease, then zenoh's close of the dead link (~10 s), and margin


class Up:
    """A ``zenswarm up`` run in the background, its output read line by line (sim time parsed
    from the progress lines)."""

    def __init__(self, *args: str, env: dict[str, str] | None = None) -> None:
        self.p = subprocess.Popen(
            [sys.executable, "-m", "zenswarm", "up", *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, cwd=ROOT, env=env,
        )
        self.lines: list[str] = []
        self.sim_t = 0.0
        self.t0 = time.monotonic()
        self.reader = threading.Thread(target=self._pump, daemon=True)
        self.reader.start()

    def _pump(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            self.lines.append(f"{time.monotonic() - self.t0:7.2f} {line.rstrip()}")
            m = re.search(r"t=\s*([\d.]+)/", line)
            if m:
                self.sim_t = float(m.group(1))

    def wait_sim_time(self, t: float, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while self.sim_t < t and self.p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert self.sim_t >= t, self.log()

    def wait(self, timeout: float) -> int:
        rc = self.p.wait(timeout=timeout)
        self.reader.join(timeout=5)
        return rc

    def log(self, n: int = 60) -> str:
        return "\n".join(self.lines[-n:])

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()


def _pid_of(swarm: str, role_words: str) -> int:
    """The pid of the swarm's process whose command line has ``role_words`` (e.g. ``agent --id 2``)."""
    found = [pid for pid, cmd in processes_mentioning(f"--swarm {swarm}") if role_words in cmd and " up " not in cmd]
    assert len(found) == 1, (role_words, processes_mentioning(f"--swarm {swarm}"))
    return found[0]


def _freeze(pid: int, seconds: float) -> None:
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)


def _no_leftovers(swarm: str) -> None:
    left = processes_mentioning(f"--swarm {swarm}")
    kill_mentioning(f"--swarm {swarm}")
    assert not left, f"processes left behind: {left}"


def test_supervisor_sigkill_takes_the_swarm_down_and_frees_its_ports(tmp_path: Path) -> None:
    """SIGKILL of the supervisor of a realtime flight (plant, leader, 3 agents, recorder): every
    child is gone within 10 s (PR_SET_PDEATHSIG), the recording is readable up to the kill, and a
    second ``up`` on the same router port right after flies."""
    swarm, port = unique_swarm("k"), free_port()
    rec = tmp_path / "flight.mcap"
    scenario = scenario_variant(tmp_path, time_limit_s=30.0)
    up = Up(str(scenario), "--swarm", swarm, "--out", str(tmp_path / "a"), "--realtime", "--listen",
            f"tcp/127.0.0.1:{port}", "--record", str(rec), "--progress-every", "0.2", "--quiet-children")
    try:
        up.wait_sim_time(1.0)
        children = [pid for pid, cmd in processes_mentioning(f"--swarm {swarm}") if pid != up.p.pid]
        assert len(children) == 6, children  # plant, leader, 3 agents, recorder
        up.p.send_signal(signal.SIGKILL)
        up.wait(10)
        t_kill = time.monotonic()
        while processes_mentioning(f"--swarm {swarm}") and time.monotonic() - t_kill < 10.0:
            time.sleep(0.05)
        gone_after = time.monotonic() - t_kill
        left = processes_mentioning(f"--swarm {swarm}")
    finally:
        up.kill()
        kill_mentioning(f"--swarm {swarm}")
    assert not left, f"outlived the supervisor by 10 s: {left}"
    assert wait_port_free(port, 5.0), f"router port {port} still bound after the supervisor's death"
    from zenswarm.bridge.recording.mcapio import read_recording

    n_msgs = sum(1 for _ in read_recording(rec).messages(lambda topic: topic.endswith("/state")))
    assert n_msgs > 0
    # a second flight right after, on the same port, with the same swarm name
    short = scenario_variant(tmp_path, time_limit_s=2.0)
    again = Up(str(short), "--swarm", swarm, "--out", str(tmp_path / "b"), "--listen", f"tcp/127.0.0.1:{port}",
               "--quiet-children")
    try:
        rc = again.wait(120)
    finally:
        again.kill()
        _no_leftovers(swarm)
    assert rc in (0, 1), again.log()  # 2 s do not reach the goal: 1 (mission failed) is the verdict
    res = read_results(tmp_path / "b")
    assert res["process_deaths"] == [] and res["sim_time_s"] == pytest.approx(2.0), again.log()
    print(f"\nsupervisor SIGKILLed: its children gone {gone_after:.2f} s later; recording kept {n_msgs} states; "
          f"a second up on port {port} flew (exit {rc})")


def test_frozen_agent_in_lockstep_succeeds(tmp_path: Path) -> None:
    """Agent 2 frozen (SIGSTOP) for 3 s at sim time 5 s, then resumed (SIGCONT), in lockstep: the
    swarm waits for it (a frozen process keeps its liveliness token and its TCP link, and 3 s
    are under the 5 s lockstep timeout), nothing is dropped and the mission succeeds."""
    swarm = unique_swarm("f")
    out = tmp_path / "out"
    up = Up(str(EX1), "--swarm", swarm, "--out", str(out), "--progress-every", "0.2", "--quiet-children", "--stop-at-goal")
    try:
        up.wait_sim_time(5.0)
        _freeze(_pid_of(swarm, "agent --id 2"), FREEZE_S)
        rc = up.wait(240)
    finally:
        up.kill()
        _no_leftovers(swarm)
    assert rc == 0, up.log()
    res = read_results(out)
    assert res["success"] and res["process_deaths"] == [], up.log()
    assert res["diagnostics"]["plant"].get("cmd_timeouts", 0) == 0, res["diagnostics"]["plant"]


def test_the_plant_stays_until_every_agent_ran_its_last_tick(tmp_path: Path) -> None:
    """With delay on the command links the plant's last tick needs older commands only, so the
    plant can finish while an agent is still ticking: here agent 1 takes 40 ms of wall time a
    tick and the delay (600 ms) is longer than the 0.4 s flight, so the plant needs none of its
    commands. The plant then stays, token held, until agent 1's command of the last tick has
    arrived: the leader and the agents leave once the plant is gone, and an agent still ticking
    must not see them go (a sender whose token is gone is not waited for; under load its token's
    removal overtook its last messages in the router and the swarm differed from the simulator
    at the last ticks: issue 30). The flight equals the simulator's, bit for bit."""
    import tomllib

    import zenoh

    from zenswarm import api, bus
    from zenswarm.bus import wire
    from zenswarm.judge.metrics import TimeSeries, flight_differences
    from zenswarm.scenario.generate import to_toml

    tests = str(Path(__file__).parent)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])}
    doc = tomllib.loads(scenario_variant(tmp_path, time_limit_s=0.4).read_text())
    doc["agents"] = {"controller": "plugin_fixtures:SlowController", "params": {"uav": 1, "sleep_s": 0.04}}
    scenario = tmp_path / "slow.toml"
    scenario.write_text(to_toml(doc))
    dt = 1.0 / doc["timing"]["control_rate_hz"]
    T = round(0.4 / dt)
    swarm, port, out = unique_swarm("ls"), free_port(), tmp_path / "out"
    keys = wire.Keys(swarm)
    plant_up: list[bool] = []  # the plant's token, as this session last saw it
    at_last_cmd: list[bool] = []  # the plant's token when agent 1's command of the last tick arrived

    def on_plant(sample: Any) -> None:
        plant_up.append(sample.kind == zenoh.SampleKind.PUT)

    def on_cmd(sample: Any) -> None:
        if wire.decode("cmd", sample.payload.to_bytes()).t == (T - 1) * wire.t_ns(dt):
            at_last_cmd.append(bool(plant_up and plant_up[-1]))

    up = Up(str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}", "--link-delay", "600ms",
            "--quiet-children", env=env)
    try:
        deadline = time.monotonic() + 60
        while not any("router on" in ln for ln in up.lines) and up.p.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        with bus.open_session(bus.client_config([f"tcp/127.0.0.1:{port}"]), handle_signals=False) as s:
            subs = [s.liveliness().declare_subscriber(keys.alive("plant"), on_plant, history=True),
                    s.declare_subscriber(keys.cmd(1), on_cmd)]
            rc = up.wait(180)
            for sub in subs:
                sub.undeclare()
    finally:
        up.kill()
        stop_swarm([], swarm, port)
    log = up.log()
    assert rc == 1, log  # 0.4 s do not reach the goal
    assert plant_up, "this test's session never saw the plant's token: it connected too late\n" + log
    assert at_last_cmd == [True], f"the plant had left before agent 1's command of tick {T - 1} arrived: {at_last_cmd}\n" + log
    sim = api.fly(scenario, link_delay="600ms")
    res = read_results(out)
    assert flight_differences(sim.series, sim.results, TimeSeries.load(str(out / "timeseries.npz")), res) == []
    assert all(d.get("forced_ticks", 0) == 0 for d in res["diagnostics"].values()), res["diagnostics"]


def test_verify_names_a_lockstep_timeout_as_the_cause_of_a_difference(tmp_path: Path) -> None:
    """Agent 2 frozen for 2 s with ``--lockstep-timeout 0.5``, recorded: its neighbours wait out
    the timeout and tick on held references, so the recording (which has agent 2's late
    references) cannot reproduce those ticks. `verify` says so: each agent either verifies every
    tick, or its difference comes with a note naming the tick it waited out the timeout (from its
    diagnostics), never an unexplained mismatch. An agent that never timed out verifies."""
    from zenswarm.judge.metrics import lockstep_stalls

    from swarmtest import zenswarm as run_zenswarm

    swarm = unique_swarm("vt")
    out, rec = tmp_path / "out", tmp_path / "flight.mcap"
    scenario = scenario_variant(tmp_path, time_limit_s=4.0)
    up = Up(str(scenario), "--swarm", swarm, "--out", str(out), "--record", str(rec), "--lockstep-timeout", "0.5",
            "--progress-every", "0.2", "--quiet-children")
    try:
        up.wait_sim_time(1.0)
        _freeze(_pid_of(swarm, "agent --id 2"), 2.0)
        rc = up.wait(240)
    finally:
        up.kill()
        _no_leftovers(swarm)
    assert rc in (0, 1), up.log()
    diag = read_results(out)["diagnostics"]
    timed_out = {i for i in (1, 2, 3) if diag.get(f"agent:{i}", {}).get("input_timeouts", 0) > 0}
    assert timed_out, f"no agent waited out the timeout: the test did not stall anyone ({diag})"
    stalls = lockstep_stalls(read_results(out))  # what the plug-in check names as a difference's cause
    assert {f"agent:{i}" for i in timed_out} <= set(stalls), (stalls, diag)
    cp = run_zenswarm("verify", str(rec), "--agent", "all")
    explained = 0
    for i in (1, 2, 3):
        verified = f"agent {i}: verified " in cp.stdout
        note = re.search(rf"agent {i}: note: agent {i} waited out --lockstep-timeout at tick \d+", cp.stdout)
        assert verified or note, f"agent {i}: a difference without its cause named:\n{cp.stdout}"
        assert i in timed_out or verified, f"agent {i} never timed out, yet differs:\n{cp.stdout}"
        explained += bool(note)
    print(f"\nagents that waited out the timeout: {sorted(timed_out)}; differences explained by it: {explained}")


def test_frozen_agent_in_realtime_is_named(tmp_path: Path) -> None:
    """Agent 2 frozen for 3 s in a realtime flight: the clock does not wait for it. The plant's
    failsafe holds UAV 2 (its commands are stale), gives it back when they are fresh again, and
    results.json names the interval (``failsafe``) and agent 2's stalled loop (``jitter_max_ms``);
    the flight ends at its time limit, never hangs."""
    swarm = unique_swarm("r")
    out = tmp_path / "out"
    scenario = scenario_variant(tmp_path, time_limit_s=10.0, settle_time_s=5.0)
    up = Up(str(scenario), "--swarm", swarm, "--out", str(out), "--realtime", "--progress-every", "0.2")
    try:
        up.wait_sim_time(3.0)
        t_freeze = up.sim_t
        _freeze(_pid_of(swarm, "agent --id 2"), FREEZE_S)
        rc = up.wait(60)
    finally:
        up.kill()
        _no_leftovers(swarm)
    assert rc in (0, 1), up.log()  # 10 s do not reach the goal: 1 is the verdict, not a crash
    res = read_results(out)
    assert res["sim_time_s"] == pytest.approx(10.0, abs=0.05) and res["process_deaths"] == [], up.log()
    fs = res["failsafe"]
    assert [e["uav"] for e in fs] == [2], (fs, up.log())
    e = fs[0]
    assert e["modes"][0] == "hover" and e["to_s"] is not None, fs
    # held from about hover_after_s after the freeze until agent 2's commands came back
    assert t_freeze < e["from_s"] < t_freeze + 1.5 and FREEZE_S - 1.0 < e["to_s"] - e["from_s"] < FREEZE_S + 1.5, (t_freeze, fs)
    assert res["diagnostics"]["agent:2"]["jitter_max_ms"] > 1e3 * (FREEZE_S - 0.5), res["diagnostics"]["agent:2"]
    assert any("failsafe: UAV 2 flown by the plant (hover" in ln for ln in up.lines), up.log()
    print(f"\nrealtime freeze of agent 2 at sim {t_freeze:.2f} s for {FREEZE_S:g} s: failsafe {fs}, exit {rc}")


from test_netsplit import netns  # noqa: E402,F401 - the namespace fixture, shared (skips without iproute2)


def test_remote_host_lost_for_good(tmp_path: Path, netns) -> None:  # noqa: F811 - the fixture imported above
    """Agent 2 on another host (a network namespace, over a veth pair); mid-flight its link is cut
    for good. The supervisor ends with exit 3 (agent 2's token goes when the session lease, 10 s,
    runs out), the recording closed and readable, results.json written; the remote agent, which
    lost the router, ends too."""
    scenario = scenario_variant(tmp_path, time_limit_s=60.0)
    swarm = unique_swarm("h")
    port, lport = free_port(netns.root_ip), free_port()
    out, rec = tmp_path / "out", tmp_path / "flight.mcap"
    up = Up(str(scenario), "--out", str(out), "--swarm", swarm, "--record", str(rec),
            "--listen", f"tcp/{netns.root_ip}:{port}", "--listen", f"tcp/127.0.0.1:{lport}",
            "--connect", f"tcp/127.0.0.1:{lport}", "--external", "agent:2", "--insecure", "--progress-every", "0.2",
            "--quiet-children", "--lockstep-timeout", "0.5")
    agent = subprocess.Popen(
        ["ip", "netns", "exec", netns.name, sys.executable, "-m", "zenswarm", "up", str(scenario),
         "--only", "agent:2", "--connect", f"tcp/{netns.root_ip}:{port}", "--swarm", swarm, "--lockstep-timeout", "0.5",
         "--router-lost-timeout", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
    )
    ended: dict[str, float] = {}
    try:
        up.wait_sim_time(3.0)
        netns.link(False)
        t_cut = time.monotonic()
        while not ("up" in ended and "agent" in ended) and time.monotonic() - t_cut < 60:
            for tag, p in (("up", up.p), ("agent", agent)):
                if tag not in ended and p.poll() is not None:
                    ended[tag] = time.monotonic() - t_cut
            if "results" not in ended and (out / "results.json").exists():
                ended["results"] = time.monotonic() - t_cut
            time.sleep(0.05)
    finally:
        up.kill()
        if agent.poll() is None:
            agent.kill()
        alog = agent.communicate(timeout=10)[0]
        _no_leftovers(swarm)
    log = up.log() + "\n--- agent 2 ---\n" + alog[-3000:]
    # the supervisor: agent 2's token goes with its session's lease (10 s), then exit 3
    assert up.p.returncode == 3 and ended["up"] < LOST_HOST_EXIT_S, (ended, log)
    assert ended["results"] < LEASE_S + 5.0, (ended, log)  # written before the router's slow close
    res = read_results(out)
    assert [(d["process"], d["how"]) for d in res["process_deaths"]] == [("agent:2", "liveliness token gone (external)")], res
    assert [f["cause"] for f in res["failures"]] == ["process_died"], res["failures"]
    # the recording was closed: readable as it is (strict), and it ends where the flight did
    from zenswarm.bridge.recording.mcapio import read_recording

    recording = read_recording(rec)
    states = [m.publish_time / 1e9 for m in recording.messages(lambda topic: topic.endswith("/uav/1/state"))]
    assert states and states[-1] >= 3.0, states[-3:]
    # the remote agent lost its router for good: it gives up after --router-lost-timeout, exit 3
    assert agent.returncode == 3 and ended["agent"] < LOST_HOST_EXIT_S, (ended, log)
    assert "giving up, exit 3" in alog, alog
    print(f"\nremote host lost: results after {ended['results']:.1f} s, supervisor exit 3 after {ended['up']:.1f} s, "
          f"remote agent exit 3 after {ended['agent']:.1f} s; recording readable, {len(states)} states of UAV 1")


@pytest.fixture
def small_fs(tmp_path: Path):
    """A 160 KiB tmpfs mounted for the test (root only), unmounted after."""
    d = tmp_path / "small"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=160k", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {r.stderr.strip()}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], check=False)


def test_disk_full_while_recording(tmp_path: Path, small_fs: Path) -> None:
    """The recording's filesystem fills up mid-flight: the recorder says so (ENOSPC) and stops,
    the flight goes on to its end (results.json written, ``recording_loss`` names the cause), and
    the MCAP file is readable up to the cut."""
    swarm = unique_swarm("d")
    out, rec = tmp_path / "out", small_fs / "flight.mcap"
    scenario = scenario_variant(tmp_path, time_limit_s=8.0)
    up = Up(str(scenario), "--swarm", swarm, "--out", str(out), "--record", str(rec), "--progress-every", "0.5")
    try:
        rc = up.wait(120)
    finally:
        up.kill()
        _no_leftovers(swarm)
    assert rc in (0, 1), up.log()  # 8 s do not reach the goal: 1 is the verdict
    res = read_results(out)
    assert res["sim_time_s"] == pytest.approx(8.0) and res["process_deaths"] == [], up.log()
    loss = res["recording_loss"]
    assert "No space left on device" in loss["error"] and "end marker and footer written" in loss["error"], loss
    # the recording: readable as it is (strict), every message up to the cut, the stop reason named
    from zenswarm.bridge.recording.mcapio import read_recording

    recording = read_recording(rec)
    states = sorted(m.publish_time / 1e9 for m in recording.messages(lambda topic: topic.endswith("/uav/1/state")))
    # the end marker (read once the scan has passed it: the file has no summary to index it)
    assert "No space left on device" in recording.metadata["zenswarm"]["recorder_stop_reason"], recording.metadata
    assert states and states[-1] <= loss["died_at_sim_time_s"] + 0.5, (states[-3:], loss)
    ticks = [round(t * 100) for t in states]
    assert ticks == list(range(len(ticks))), "a gap in the recorded states before the cut"
    print(f"\ndisk full at sim time {loss['died_at_sim_time_s']:.2f} s: flight flew on to 8 s; recording readable, "
          f"{len(states)} states of UAV 1 (to {states[-1]:.2f} s); {loss['error']}")


def test_two_flights_at_once_with_default_settings(tmp_path: Path) -> None:
    """Two lockstep flights at once on this machine, both with the default swarm name and
    router port (a free one each), one ``--secure``: neither sees the other's traffic (no
    foreign sample, no reject), and both fly the same trajectory bit for bit, as alone. A third
    flight into the first one's ``--out`` while it runs is refused (exit 2 naming --out)."""
    import numpy as np

    from zenswarm.judge.metrics import TimeSeries, lockstep_stalls

    # 20 s of flight, not the goal (44.9 s): long enough that the first flight still holds its --out
    # when the third, started once both routers are up, gets there on a loaded host (6 s was not)
    scenario = scenario_variant(tmp_path, time_limit_s=20.0)
    outs = [tmp_path / "open", tmp_path / "secure"]
    ups = [Up(str(scenario), "--out", str(outs[0]), "--quiet-children"),
           Up(str(scenario), "--out", str(outs[1]), "--secure", "--quiet-children")]
    try:
        deadline = time.monotonic() + 30
        while not all(any("router on" in ln for ln in u.lines) for u in ups) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert all(any("router on" in ln for ln in u.lines) for u in ups), "\n=====\n".join(u.log() for u in ups)
        third = subprocess.run([sys.executable, "-m", "zenswarm", "up", str(scenario), "--out", str(outs[0])],
                               capture_output=True, text=True, cwd=ROOT, timeout=60)
        rcs = [u.wait(180) for u in ups]
    finally:
        for u in ups:
            u.kill()
        # the swarm name is "default": find the supervisors by their scenario, their roles by their supervisor
        marks = [str(scenario)] + [f"--supervisor {u.p.pid} " for u in ups]
        left = [found for mark in marks for found in processes_mentioning(mark)]
        for mark in marks:
            kill_mentioning(mark)
    assert not left, f"processes left behind: {left}"
    logs = "\n=====\n".join(u.log() for u in ups)
    assert rcs == [1, 1], logs  # 20 s do not reach the goal: the verdict, the same for both
    assert third.returncode == 2 and "--out" in third.stderr and "another flight" in third.stderr, third
    ports = {re.search(r"router on \S+:(\d+)", ln).group(1) for u in ups for ln in u.lines if "router on" in ln}
    assert len(ports) == 2, ports
    series, stalls = [], {}
    for out in outs:
        res = read_results(out)
        stalls[out.name] = lockstep_stalls(res)  # a lockstep timeout is the one way the two may differ
        assert res["swarm"] == "default" and res["process_deaths"] == [], res
        assert res["foreign_samples"] == {} and res["decoder_rejects"]["rejected"] == 0, res
        for name, d in res["diagnostics"].items():
            assert d.get("rejected", 0) == 0, (out.name, name, d.get("last_reject"))
        series.append(TimeSeries.load(str(out / "timeseries.npz")))
    same = np.array_equal(series[0].q, series[1].q, equal_nan=True) and np.array_equal(series[0].u, series[1].u, equal_nan=True)
    assert same, f"the two flights differ; processes that waited out the lockstep timeout: {stalls}"
    print(f"\ntwo flights at once (swarm 'default', routers on ports {sorted(ports)}, one --secure): no foreign "
          f"sample, identical series; a third into the same --out refused")


def _listening(pids: set[int]) -> list[tuple[int, str, str]]:
    """(pid, protocol, local address) of every socket the processes ``pids`` listen on (TCP) or
    hold bound (UDP), from ``ss``."""
    r = subprocess.run(["ss", "-H", "-lntup"], capture_output=True, text=True, check=True)
    found = []
    for line in r.stdout.splitlines():
        cols = line.split()
        for pid in map(int, re.findall(r"pid=(\d+)", line)):
            if pid in pids:
                found.append((pid, cols[0], cols[4]))
    return sorted(set(found))


def test_every_listening_port_is_loopback_only(tmp_path: Path) -> None:
    """A flight with ``--record`` and ``--live``: the only sockets listening are the supervisor's
    router and the live view's server (docs/security.md, "Listening ports"), both on 127.0.0.1;
    the swarm's processes listen on nothing. The live view refuses a browser page from another
    site (its ``Origin``), and takes the Foxglove app."""
    import asyncio

    from websockets.asyncio.client import connect
    from websockets.exceptions import InvalidStatus

    swarm, port, live = unique_swarm("p"), free_port(), free_port()
    scenario = scenario_variant(tmp_path, time_limit_s=20.0)
    up = Up(str(scenario), "--swarm", swarm, "--out", str(tmp_path / "out"), "--realtime", "--record",
            str(tmp_path / "f.mcap"), "--live", str(live), "--listen", f"tcp/127.0.0.1:{port}", "--progress-every", "0.2",
            "--quiet-children")
    try:
        up.wait_sim_time(1.0)
        pids = {pid for pid, _ in processes_mentioning(f"--swarm {swarm}")}
        socks = _listening(pids)

        async def origin(value: str | None) -> str:
            headers = {} if value is None else {"Origin": value}
            try:
                async with connect(f"ws://127.0.0.1:{live}", subprotocols=["foxglove.websocket.v1"],  # type: ignore[list-item]
                                   additional_headers=headers, open_timeout=10) as ws:
                    return f"open {ws.subprotocol}"
            except InvalidStatus as e:
                return f"refused {e.response.status_code}"

        seen = {o: asyncio.run(origin(o)) for o in (None, "https://app.foxglove.dev", "https://evil.example")}
        up.p.send_signal(signal.SIGINT)
        up.wait(60)
    finally:
        up.kill()
        _no_leftovers(swarm)
    assert len(pids) == 7, pids  # supervisor (with the live view), recorder, plant, leader, 3 agents
    assert socks and all(addr.rsplit(":", 1)[0] in ("127.0.0.1", "[::1]") for _, _, addr in socks), socks
    owners = {pid for pid, _, _ in socks}
    assert owners == {up.p.pid}, socks  # the children listen on nothing
    ports = sorted(int(addr.rsplit(":", 1)[1]) for _, proto, addr in socks if proto == "tcp")
    assert ports == sorted([port, live]), socks  # the router and the live view: nothing else
    assert not [s for s in socks if s[1] != "tcp"], socks  # no UDP (no scouting)
    assert seen == {None: "open foxglove.websocket.v1", "https://app.foxglove.dev": "open foxglove.websocket.v1",
                    "https://evil.example": "refused 403"}, seen
    print(f"\nlistening sockets of the flight: {socks}; the live view by Origin: {seen}")

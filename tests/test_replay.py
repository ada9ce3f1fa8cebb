"""``zenswarm replay`` with rosbag2's controls, and ``zenswarm info``.

Most tests replay a small synthetic recording (written by the recorder's McapSink, no Zenoh) into
a fake session that notes every put and when; the ``swarm`` tests record a 2 s lockstep flight
once per module and replay it through a router, one of them into a live agent process."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import termios
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from zenswarm.bridge.recording.info import scan
from zenswarm.bridge.recording.recorder import McapSink, build_metadata
from zenswarm.bridge.replay.playback import Controls, KeyboardControls, TopicFilter, parse_keys, restamp
from zenswarm.bridge.replay.replay import replay
from zenswarm.bus import wire
from zenswarm.compose.cli import main
from zenswarm.errors import RecordingError, ScenarioError
from zenswarm.scenario.config import load_scenario, scenario_to_dict

from swarmtest import ROOT, scenario_variant, unique_swarm

EX1 = ROOT / "compose" / "scenarios" / "paper_example1.toml"
DT = 10_000_000  # ns, 100 Hz
LT0 = 1_700_000_000_000_000_000


# --------------------------------------------------------------------------- a synthetic recording


def synthetic(path: Path, swarm: str = "syn", mode: str = "lockstep", ticks: int = 200, wall_per_tick: int = DT // 4) -> Path:
    """A lockstep-like recording: per tick states of 3 UAVs, their refs, a clock every 4 ticks
    and one undecodable payload; sim time 100 Hz, receive time 4x faster than sim time."""
    keys = wire.Keys(swarm)
    sc = scenario_to_dict(load_scenario(EX1))
    sink = McapSink(path, keys, chunk_size=4096, metadata=build_metadata(swarm, mode, sc, "test"))
    sink.start()
    z = np.zeros(3)
    for k in range(ticks + 1):
        lt = LT0 + k * wall_per_tick
        for i in (1, 2, 3):
            sink.put(lt + i, keys.state(i), wire.encode(wire.State(t=k * DT, seq=k + 1, q=[i, k, 1.0], v=z, rpy=z, w=z)))
            sink.put(lt + 10 + i, keys.ref(i), wire.encode(wire.Ref(t=k * DT, seq=2 * k + 1, q=[i, k, 0.5], v=z)))
        if k % 4 == 0:
            sink.put(lt + 20, keys.clock, wire.encode(wire.Clock(t=k * DT, seq=k + 1)))
        if k == 50:
            sink.put(lt + 30, f"{keys.prefix}/extra", b"\xc1 not msgpack")
    sink.stop_reason = "test"
    sink.close()
    assert sink.error is None
    return path


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthetic(tmp_path_factory.mktemp("replay") / "syn.mcap")


class FakePub:
    def __init__(self, key: str, log: list[tuple[float, str, bytes]]) -> None:
        self.key = key
        self.log = log
        self.matching_status = type("M", (), {"matching": True})()

    def put(self, payload: bytes, **kw: Any) -> None:
        self.log.append((time.monotonic(), self.key, bytes(payload)))


class FakeSession:
    """Notes (monotonic time, key, payload) of every put."""

    def __init__(self) -> None:
        self.log: list[tuple[float, str, bytes]] = []

    def declare_publisher(self, key: str, **kw: Any) -> FakePub:
        return FakePub(key, self.log)


def play(path: Path, **kw: Any) -> tuple[Any, list[tuple[float, str, bytes]]]:
    s = FakeSession()
    kw.setdefault("linger_s", 0)
    kw.setdefault("rate", 0)
    st = replay(path, connect=["tcp/127.0.0.1:1"], session=s, **kw)
    return st, s.log


def sim_t(payload: bytes) -> int:
    return int(msgpack.unpackb(payload)["t"])


# --------------------------------------------------------------------------- pacing and clocks


def test_sim_clock_is_the_default_for_lockstep_and_paces_by_sim_time(rec: Path) -> None:
    st, log = play(rec, rate=4.0)  # 2 s of sim time at 4x: 0.5 s (receive time spans 0.5 s / 4)
    assert st.clock == "sim" and st.stopped_by == "end of recording"
    assert 0.45 < log[-1][0] - log[0][0] < 0.9, log[-1][0] - log[0][0]
    assert st.published == 3 * 2 * 201 + 51 + 1


def test_wall_clock_paces_by_receive_time_and_is_the_default_for_realtime(rec: Path, tmp_path: Path) -> None:
    st, log = play(rec, rate=1.0, clock="wall")  # receive times span 0.5 s
    assert st.clock == "wall" and 0.45 < log[-1][0] - log[0][0] < 0.9
    rt = synthetic(tmp_path / "rt.mcap", mode="realtime", ticks=20)
    st, _ = play(rt)
    assert st.clock == "wall"


def test_window_in_sim_seconds_and_topic_filters(rec: Path) -> None:
    st, log = play(rec, start_s=0.5, end_s=1.0, topics=["uav/*/state", "swarm/syn/uav/[13]/ref"], exclude=["*/3/*"])
    keys = {k for _, k, _ in log}
    assert keys == {"swarm/syn/uav/1/state", "swarm/syn/uav/2/state", "swarm/syn/uav/1/ref"}
    ts = [sim_t(p) for _, _, p in log]
    assert min(ts) == 50 * DT and max(ts) == 100 * DT and len(log) == 3 * 51


def test_bad_options_name_the_flag(rec: Path) -> None:
    cases = [
        ({"start_s": 2.5}, "--start", "spans 0 to 2.000 s of sim time"),
        ({"end_s": -1.0}, "--end", ">= 0"),
        ({"start_s": 1.0, "end_s": 0.5}, "--end", "before --start"),
        ({"topics": ["uav/9/*"]}, "--topic", "swarm/syn/uav/1/state"),
        ({"exclude": ["nothing/here"]}, "--exclude", "matches none"),
        ({"exclude": ["**"]}, "--exclude", "leave none"),
        ({"rate": -1.0}, "--rate", ">= 0"),
        ({"clock_rate": 0.0}, "--clock-rate", "> 0"),
        ({"loops": 0}, "--loops", ">= 1"),
        ({"wait_for": ["nobody"]}, "--wait-for", "invalid process name"),
    ]
    for kw, flag, words in cases:
        with pytest.raises(ScenarioError) as e:
            play(rec, **kw)
        assert e.value.field == flag and words in e.value.message, (kw, e.value)


def test_loop_restamps_t_and_seq_so_every_pass_continues_the_stream(rec: Path) -> None:
    st, log = play(rec, loops=3, topics=["uav/2/state", "clock", "extra"])
    assert st.loops == 3 and st.restamped == 2 * (201 + 51) and st.not_restamped == 2
    states = [wire.decode("state", p) for _, k, p in log if k.endswith("/state")]
    assert [s.t for s in states] == [k * DT for k in range(3 * 201)]  # one tick on at each pass
    assert all(b.seq > a.seq for a, b in zip(states, states[1:], strict=False))
    assert all(np.array_equal(s.q, states[i % 201].q) for i, s in enumerate(states))  # the rest as recorded
    clocks = [wire.decode("clock", p) for _, k, p in log if k.endswith("/clock")]
    assert all(b.seq > a.seq and b.t > a.t for a, b in zip(clocks, clocks[1:], strict=False))


def test_restamp_changes_only_t_and_seq() -> None:
    z = np.array([0.1, -2.5e-7, 3.0])
    m = wire.Ref(t=5 * DT, seq=9, q=z, v=z * np.pi)
    out = wire.decode("ref", restamp(wire.encode(m), 100 * DT, 1000))
    assert out.t == 105 * DT and out.seq == 1009 and np.array_equal(out.q, m.q) and np.array_equal(out.v, m.v)
    assert restamp(b"\xc1 garbage", 1, 1) is None
    assert restamp(msgpack.packb({"t": 1}), 1, 1) is None  # no seq
    assert restamp(wire.encode(m), wire.MAX_T_NS, 1) is None  # past the largest sim time


def test_clock_rate_publishes_the_played_sim_time_instead_of_the_recorded_clock(rec: Path) -> None:
    st, log = play(rec, rate=2.0, clock_rate=50.0, topics=["uav/1/state", "clock"])
    clocks = [wire.decode("clock", p) for _, k, p in log if k == "swarm/syn/clock"]
    assert st.skipped >= 51 and 15 <= st.clocks == len(clocks) <= 80, st.clocks  # ~1 s at 50 Hz, not the 51 recorded
    assert all(c.t % DT == 0 for c in clocks) and [c.seq for c in clocks] == list(range(1, len(clocks) + 1))
    assert all(b.t > a.t for a, b in zip(clocks, clocks[1:], strict=False))


def test_start_paused_then_step_and_resume(rec: Path) -> None:
    c = Controls(paused=True)
    s = FakeSession()
    done = threading.Event()
    out: dict[str, Any] = {}

    def run() -> None:
        out["st"] = replay(rec, connect=["x"], session=s, rate=0, linger_s=0, controls=c, topics=["uav/*/state"])
        done.set()

    th = threading.Thread(target=run)
    th.start()
    time.sleep(0.3)
    assert s.log == []  # paused: nothing yet
    parse_keys(b"s", c)
    _wait_until(lambda: len(s.log) >= 3)
    time.sleep(0.1)  # a wrong step would let more through meanwhile
    assert sorted(sim_t(p) for _, _, p in s.log) == [0, 0, 0]  # one step = one tick (3 states)
    parse_keys(b"\x1b[C", c)
    _wait_until(lambda: len(s.log) >= 6)
    time.sleep(0.1)
    assert len(s.log) == 6
    parse_keys(b" ", c)  # resume
    assert done.wait(10)
    th.join()
    assert out["st"].published == 3 * 201


def _wait_until(cond: Callable[[], bool], timeout_s: float = 5.0) -> None:
    """Poll ``cond`` until it holds (a generous bound: the machine may be loaded)."""
    deadline = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < deadline:
        time.sleep(0.01)


def test_keyboard_controls_restore_the_terminal() -> None:
    master, slave = os.openpty()
    try:
        before = termios.tcgetattr(slave)
        c = Controls()
        with KeyboardControls(c, slave):
            assert termios.tcgetattr(slave)[3] & termios.ICANON == 0  # cbreak: keys arrive at once
            os.write(master, b" ")
            deadline = time.monotonic() + 3
            while not c.paused and time.monotonic() < deadline:
                time.sleep(0.01)
            assert c.paused
            os.write(master, b"q")
            while not c.quit and time.monotonic() < deadline:
                time.sleep(0.01)
            assert c.quit
        assert termios.tcgetattr(slave) == before
    finally:
        os.close(master)
        os.close(slave)


def test_start_paused_without_a_terminal_is_bad_input(rec: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any) -> None:
    monkeypatch.setattr(sys, "stdin", io.StringIO(""))
    assert main(["replay", str(rec), "--start-paused"]) == 2
    assert "--start-paused: stdin is not a terminal" in capsys.readouterr().err


def test_topic_filter_patterns() -> None:
    f = TopicFilter(["uav/*/ref", "swarm/a/**/state"], ["*/2/*"])
    assert f("swarm/a/uav/1/ref") and f("swarm/a/uav/3/state") and not f("swarm/a/uav/2/ref") and not f("swarm/a/clock")
    assert TopicFilter(["*state"])("swarm/a/uav/1/state")  # a glob crosses /
    assert TopicFilter()("anything")


# --------------------------------------------------------------------------- info


def test_info_complete_truncated_and_not_mcap(rec: Path, tmp_path: Path, capsys: Any) -> None:
    i = scan(rec)
    assert i.complete and i.end_marker and i.recorder_stop_reason == "test" and i.mode == "lockstep"
    assert i.scenario_name == "paper_example1" and len(i.scenario_hash or "") == 16 and i.uavs == 3
    assert i.sim_s == 2.0 and abs((i.wall_s or 0) - 0.5) < 0.01 and i.messages == 3 * 2 * 201 + 51 + 1
    st = i.channel("swarm/syn/uav/1/state")
    assert st is not None and st.messages == 201 and abs((st.rate_sim_hz or 0) - 100) < 1e-6
    assert abs((st.rate_wall_hz or 0) - 400) < 1 and i.recorder_stats["recorded"] == i.messages
    assert main(["info", str(rec)]) == 0
    text = capsys.readouterr().out
    assert "complete:   yes" in text and "hash " + str(i.scenario_hash) in text and "swarm/syn/uav/1/state" in text
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(rec.read_bytes()[: rec.stat().st_size // 2])
    assert main(["info", str(cut), "--json"]) == 1
    d = json.loads(capsys.readouterr().out)
    assert d["complete"] is False and d["finalized"] is False and not d["end_marker"] and 0 < d["messages"] < i.messages
    assert d["swarm"] == "syn" and d["scenario_hash"] == i.scenario_hash
    (tmp_path / "x.txt").write_text("hello")
    assert main(["info", str(tmp_path / "x.txt")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    with pytest.raises(RecordingError):
        scan(tmp_path / "missing.mcap")


# --------------------------------------------------------------------------- a real flight


@contextlib.contextmanager
def router() -> Iterator[str]:
    from zenswarm.bus import free_port, open_session, router_config, tcp_endpoint

    ep = tcp_endpoint(free_port())
    with open_session(router_config([ep]), handle_signals=False):
        yield ep


def test_cli_loop_stopped_by_ctrl_c_says_so_and_exits_130(rec: Path) -> None:
    """``--loop`` ends only by a signal: the last line is printed, and the exit status is 130, as
    every zenswarm command interrupted (README). A signal before the first message is published
    is an interruption too, not "nothing selected in the window" (the signal lands at once here)."""
    import signal

    with router() as ep:
        proc = subprocess.Popen(
            [sys.executable, "-m", "zenswarm", "replay", str(rec), "--connect", ep, "--loop", "--wait-subscribers", "0"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            assert proc.stderr is not None
            first = proc.stderr.readline()  # the first progress line: it is playing
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    assert proc.returncode == 130, first + err
    assert err.strip().splitlines()[-1].startswith("replay: interrupted: "), first + err


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, Path]:
    """A 2 s lockstep flight of paper example 1, recorded; and a 10 s variant of its scenario."""
    from zenswarm.bus import free_port, tcp_endpoint

    tmp = tmp_path_factory.mktemp("flight")
    swarm = unique_swarm("rp")
    sc = scenario_variant(tmp, time_limit_s=2.0, settle_time_s=0.5)
    out = tmp / "flight.mcap"
    cp = subprocess.run(
        [sys.executable, "-m", "zenswarm", "up", str(sc), "--swarm", swarm, "--listen", tcp_endpoint(free_port()),
         "--record", str(out), "--out", str(tmp / "up"), "--quiet", "--quiet-children"],
        cwd=ROOT, capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert cp.returncode in (0, 1) and out.exists(), cp.stdout + cp.stderr
    return out, swarm, scenario_variant(tmp, time_limit_s=10.0, settle_time_s=0.5)


@pytest.mark.swarm
def test_cli_rate_paces_a_lockstep_flight_by_sim_time_and_live_serves_it(flight: tuple[Path, str, Path]) -> None:
    """``--rate 4``: 2 s of sim time in about 0.5 s. With ``--live PORT`` (one replay for both,
    to keep the suite short): a Foxglove client offering ``foxglove.websocket.v1`` only connects
    and subscribes; only then does the test declare the liveliness token the replay's
    ``--wait-for bridge`` waits for, so the client sees the whole replay. Its frames show the
    recorded flight in sim time, up to its end; the server stops with the replay."""
    import asyncio

    from test_live import TOPICS, check_channels, watch

    from zenswarm.bus import client_config, free_port, open_session

    path, swarm, _ = flight
    info = scan(path)
    assert info.complete and info.end_marker and info.mode == "lockstep" and info.sim_s == 2.0
    port = free_port()
    tokens: list[Any] = []
    with router() as ep, open_session(client_config([ep]), handle_signals=False) as s:
        proc = subprocess.Popen(
            [sys.executable, "-m", "zenswarm", "replay", str(path), "--connect", ep, "--rate", "4", "--wait-subscribers", "0",
             "--live", str(port), "--wait-for", "bridge"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, stdin=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            on_subscribed = lambda: tokens.append(s.liveliness().declare_token(wire.Keys(swarm).alive("bridge")))  # noqa: E731
            channels, got = asyncio.run(watch(f"ws://127.0.0.1:{port}", time.monotonic() + 60.0, on_subscribed))
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
            for tok in tokens:
                tok.undeclare()
    assert proc.returncode == 0, err
    line = err.strip().splitlines()[-1]
    assert "by sim time, 2.000 s played in" in line, line
    wall = float(line.split(" played in ")[1].split(" s wall")[0])
    assert 0.4 < wall < 1.2, line  # 2 s of sim time at 4x
    # --live
    assert tokens, "the client never subscribed to every topic"
    assert f"ws://127.0.0.1:{port}" in out and "Foxglove" in out, out
    check_channels(channels)
    assert all(got[t] for t in TOPICS), {t: len(m) for t, m in got.items()}
    ts = [json.loads(data)["t"] for _, data in got["/metrics"]]
    assert ts == sorted(ts) and ts[0] >= 0.0 and ts[-1] == pytest.approx(2.0, abs=0.02), ts  # the last frame: the end


@pytest.mark.swarm
def test_replay_into_one_live_agent_reproduces_its_references_and_loops_are_accepted(flight: tuple[Path, str, Path]) -> None:
    """Agent 2 alone, lockstep: the recorded plant state of UAV 2, the neighbours' and the
    leader's references replayed to it; its references and commands equal the recorded ones bit
    for bit in the first pass, and it ticks on through the re-stamped second pass."""
    from zenswarm.bridge.recording.mcapio import read_recording
    from zenswarm.bus import client_config, open_session

    path, swarm, long_sc = flight
    keys = wire.Keys(swarm)
    recorded: dict[str, list[bytes]] = {}
    for m in read_recording(path).messages(topics=lambda t: t in (keys.ref(2), keys.cmd(2))):
        recorded.setdefault(m.topic, []).append(m.payload)
    got: dict[str, list[bytes]] = {keys.ref(2): [], keys.cmd(2): []}
    with router() as ep, open_session(client_config([ep]), handle_signals=False) as s:
        subs = [s.declare_subscriber(k, lambda smp, k=k: got[k].append(smp.payload.to_bytes())) for k in got]
        agent = subprocess.Popen(
            [sys.executable, "-m", "zenswarm", "agent", "--id", "2", "--scenario", str(long_sc), "--swarm", swarm, "--connect", ep],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        try:
            cp = subprocess.run(
                [sys.executable, "-m", "zenswarm", "replay", str(path), "--connect", ep, "--rate", "0", "--loops", "2",
                 "--wait-for", "agent:2", "--topic", "uav/2/state", "--topic", "uav/*/ref", "--topic", "leader/ref",
                 "--exclude", "uav/2/ref"],
                cwd=ROOT, capture_output=True, text=True, timeout=90, stdin=subprocess.DEVNULL,
            )  # fmt: skip
            assert cp.returncode == 0, cp.stderr
            deadline = time.monotonic() + 30
            while len(got[keys.cmd(2)]) < 2 * 201 and time.monotonic() < deadline:
                time.sleep(0.05)
        finally:
            agent.kill()
            agent.wait(10)
        for sub in subs:
            sub.undeclare()
    n_ref, n_cmd = len(recorded[keys.ref(2)]), len(recorded[keys.cmd(2)])
    assert got[keys.ref(2)][:n_ref] == recorded[keys.ref(2)]  # bit for bit, first pass
    assert got[keys.cmd(2)][:n_cmd] == recorded[keys.cmd(2)]
    # the recorded agent stopped at its time limit (tick 199); this one also ticks on state(200),
    # then on every state of the re-stamped second pass: ticks 201 to 401, none refused
    rest = [wire.decode("cmd", p).t for p in got[keys.cmd(2)][n_cmd:]]
    assert rest == [k * DT for k in range(200, 402)], (len(rest), rest[:3])


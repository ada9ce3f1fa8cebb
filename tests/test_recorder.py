"""Flight recorder: ``zenswarm record``, ``replay``, ``recover`` and ``replay --verify``.

Real processes and a real router on loopback: every test has its own router port(s) and swarm
name, and kills and waits for every process it starts (in ``finally``). Timing figures are in
``bench/recorder_throughput.py``, not here.
"""

from __future__ import annotations

import contextlib
import signal
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from zenswarm import __version__
from zenswarm.bridge.recording.mcapio import METADATA_NAME, file_is_complete, read_recording
from zenswarm.bridge.recording.recorder import McapSink, build_metadata, sim_time
from zenswarm.bridge.recording.recover import recover
from zenswarm.bridge.replay.replay import verify_agent
from zenswarm.bus import AliveWatcher, client_config, free_port, open_session, router_config, tcp_endpoint, wire
from zenswarm.errors import RecordingError
from zenswarm.scenario.config import load_scenario, scenario_to_dict

REPO = Path(__file__).resolve().parents[1]
EX1 = REPO / "compose" / "scenarios" / "paper_example1.toml"


# --------------------------------------------------------------------------- helpers


def swarm_name() -> str:
    return "rec" + uuid.uuid4().hex[:10]


@contextlib.contextmanager
def router(*extra_listen: str) -> Iterator[str]:
    """An in-process router on a free loopback port; yields its endpoint."""
    ep = tcp_endpoint(free_port())
    with open_session(router_config([ep, *extra_listen]), handle_signals=False):
        yield ep


class Proc:
    """A ``python -m zenswarm ...`` child; its output is collected by a thread."""

    def __init__(self, *args: object) -> None:
        self.argv = [sys.executable, "-m", "zenswarm", *map(str, args)]
        self.popen = subprocess.Popen(
            self.argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True
        )
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._pump, daemon=True)
        self._t.start()

    def _pump(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.append(line.rstrip("\n"))

    @property
    def output(self) -> str:
        return "\n".join(self.lines)

    def stop(self, timeout: float = 30.0) -> int:
        """SIGTERM and wait: a clean stop."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGTERM)
        rc = self.popen.wait(timeout=timeout)
        self._t.join(5.0)
        return rc

    def reap(self) -> None:
        if self.popen.poll() is None:
            self.popen.kill()
        self.popen.wait(timeout=10)
        self._t.join(5.0)


@contextlib.contextmanager
def processes() -> Iterator[list[Proc]]:
    started: list[Proc] = []
    try:
        yield started
    finally:
        for p in started:
            p.reap()


def start_recorder(procs: list[Proc], ep: str, swarm: str, out: Path, *extra: object) -> Proc:
    p = Proc("record", "--swarm", swarm, "--connect", ep, "--out", out, *extra)
    procs.append(p)
    return p


def wait_alive(session: zenoh.Session, swarm: str, process: str = "recorder", timeout: float = 30.0) -> None:
    with AliveWatcher(session, wire.Keys(swarm)) as w:
        assert w.wait_for(process, timeout=timeout), f"{process} of swarm {swarm} never announced itself"


def wait_recorded(session: zenoh.Session, swarm: str, n: int, timeout: float = 30.0) -> None:
    """Wait until the recorder reports (diag/recorder counters) at least ``n`` recorded messages
    beyond its own diag messages."""
    done = threading.Event()

    def on_diag(sample: zenoh.Sample) -> None:
        d = wire.decode("diag", sample.payload.to_bytes())
        if d.counters["recorded"] >= n + d.seq - 1:
            done.set()

    sub = session.declare_subscriber(wire.Keys(swarm).diag("recorder"), on_diag)
    try:
        assert done.wait(timeout), f"the recorder did not record {n} messages within {timeout} s"
    finally:
        sub.undeclare()


def publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)


def short_scenario(tmp_path: Path, seconds: float = 3.0) -> Path:
    """paper_example1 with a short time limit, as a TOML file in tmp_path."""
    text = EX1.read_text()
    lines = []
    for line in text.splitlines():
        if line.startswith("time_limit_s"):
            line = f"time_limit_s = {seconds}"
        elif line.startswith("settle_time_s"):
            line = f"settle_time_s = {seconds / 3}"
        lines.append(line)
    p = tmp_path / "short.toml"
    p.write_text("\n".join(lines) + "\n")
    assert load_scenario(p).timing.time_limit_s == seconds
    return p


def synthetic_traffic(swarm: str, n_each: int, scenario: dict) -> list[tuple[str, bytes]]:
    """``n_each`` messages of every wire kind on several keys, plus undecodable payloads and a key
    outside the swarm layout; in publication order."""
    keys = wire.Keys(swarm)
    rng = np.random.default_rng(7)
    out: list[tuple[str, bytes]] = []
    for k in range(n_each):
        t = k * 10_000_000
        i = 1 + k % 3
        v = rng.normal(size=(4, 3))
        out.append((keys.clock, wire.encode(wire.Clock(t=t, seq=k + 1))))
        out.append((keys.state(i), wire.encode(wire.State(t=t, seq=k + 1, q=v[0], v=v[1], rpy=v[2], w=v[3]))))
        out.append((keys.ref(i), wire.encode(wire.Ref(t=t, seq=k + 1, q=v[0], v=v[1]))))
        out.append((keys.leader_ref, wire.encode(wire.Ref(t=t, seq=k + 1, q=v[2], v=v[3]))))
        out.append((keys.cmd(i), wire.encode(wire.Cmd(t=t, seq=k + 1, thrust=float(v[0, 0]), rpy=v[1], u=v[2], d_hat=v[3]))))
        out.append(
            (keys.diag(f"agent:{i}"), wire.encode(wire.Diag(t=t, seq=k + 1, process=f"agent:{i}", counters={"n": k}, info={"k": [k]})))
        )
        if k % 100 == 0:
            out.append((keys.mission, wire.encode(wire.Mission(t=t, seq=k + 1, scenario=scenario))))
        if k % 50 == 0:
            out.append((keys.cmd(2), bytes([0xC1, k % 256]) + b"not msgpack"))  # undecodable
            out.append((f"{keys.prefix}/extra/thing", msgpack.packb({"t": t, "x": k})))  # outside the layout
    return out


def fake_recording(path: Path, swarm: str, n: int, scenario: dict, chunk_size: int = 4096) -> list[tuple[str, int, int, bytes]]:
    """A recording written by the recorder's McapSink without Zenoh (small chunks, many of them).
    Returns the expected (topic, log_time, publish_time, payload) in order."""
    keys = wire.Keys(swarm)
    sink = McapSink(path, keys, chunk_size=chunk_size, metadata=build_metadata(swarm, "lockstep", scenario, "test"))
    sink.start()
    expected = []
    lt0 = 1_700_000_000_000_000_000
    for k in range(n):
        t = k * 10_000_000
        key = keys.state(1 + k % 3)
        payload = wire.encode(wire.State(t=t, seq=k + 1, q=[k, 0, 1], v=[0, k, 1], rpy=[0, 0, 0], w=[1, 2, 3]))
        sink.put(lt0 + k * 1000, key, payload)
        expected.append((key, lt0 + k * 1000, t, payload))
    sink.close()
    assert sink.error is None
    return expected


# --------------------------------------------------------------------------- (a) record


@pytest.mark.swarm
def test_record_synthetic_traffic_every_payload_in_order(tmp_path: Path) -> None:
    swarm = swarm_name()
    scenario = scenario_to_dict(load_scenario(EX1))
    traffic = synthetic_traffic(swarm, 2000, scenario)
    out = tmp_path / "a.mcap"
    with router() as ep, processes() as procs, open_session(client_config([ep]), handle_signals=False) as s:
        rec = start_recorder(procs, ep, swarm, out, "--scenario", EX1)
        wait_alive(s, swarm)
        pubs = {key: publisher(s, key) for key in dict.fromkeys(k for k, _ in traffic)}
        for key, payload in traffic:
            pubs[key].put(payload)
        wait_recorded(s, swarm, len(traffic))
        assert rec.stop() == 0, rec.output
    undecodable = sum(1 for k, p in traffic if sim_time(p) is None)
    assert f"{undecodable} undecodable" in rec.output, rec.output
    assert "recorder: recording" in rec.output and "messages on" in rec.output

    r = read_recording(out)  # strict: the file is complete
    assert r.complete and r.statistics is not None
    own_diag = wire.Keys(swarm).diag("recorder")
    got = [m for m in r.messages() if m.topic != own_diag]
    assert [(m.topic, m.payload) for m in got] == traffic  # every payload, as sent, in order
    # log times non-decreasing; publish_time = the payload's t, else log_time
    assert all(a.log_time <= b.log_time for a, b in zip(got, got[1:]))
    for m in got:
        t = sim_time(m.payload)
        assert m.publish_time == (t if t is not None else m.log_time)
    # one msgpack channel per key, no schema, sequence = running count per channel
    topics = {c.topic for c in r.channels.values()}
    assert topics == {k for k, _ in traffic} | {own_diag}
    assert all(c.message_encoding == "msgpack" and c.schema_id == 0 for c in r.channels.values())
    seqs: dict[str, list[int]] = {}
    for ch, m in r.raw_messages():
        seqs.setdefault(ch.topic, []).append(m.sequence)
    assert all(v == list(range(1, len(v) + 1)) for v in seqs.values())
    assert r.statistics.message_count == sum(len(v) for v in seqs.values())
    # the scenario (and the rest) in the metadata record
    assert r.scenario == scenario
    assert r.load_scenario() == load_scenario(EX1)
    assert r.swarm == swarm and r.mode == "lockstep" and r.zenswarm_version == __version__
    assert r.metadata[METADATA_NAME]["scenario_json"]


@pytest.mark.swarm
def test_oversize_payloads_are_counted_per_key_not_recorded(tmp_path: Path) -> None:
    """A payload over the decoders' size bound is not written (a flood once filled 1.76 GB with
    them): the recorder counts it per key, and the counts are in the file's metadata."""
    swarm = swarm_name()
    keys = wire.Keys(swarm)
    scenario = scenario_to_dict(load_scenario(EX1))
    out = tmp_path / "flood.mcap"
    big = b"\x00" * (wire.MAX_PAYLOAD + 1)  # one byte over: every decoder rejects it unread
    huge = b"\x01" * (3 * wire.MAX_PAYLOAD)
    mission = wire.encode(wire.Mission(t=0, seq=1, scenario={**scenario, "pad": "x" * (2 * wire.MAX_PAYLOAD)}))
    assert wire.MAX_PAYLOAD < len(mission) <= wire.MAX_MISSION_PAYLOAD  # over 64 KiB, fine on the mission key
    good = [wire.encode(wire.Clock(t=k * 10_000_000, seq=k + 1)) for k in range(50)]
    with router() as ep, processes() as procs, open_session(client_config([ep]), handle_signals=False) as s:
        rec = start_recorder(procs, ep, swarm, out, "--scenario", EX1, "--diag-interval", "0.2")
        wait_alive(s, swarm)
        pub_state, pub_cmd = publisher(s, keys.state(1)), publisher(s, keys.cmd(2))
        pub_clock, pub_mission = publisher(s, keys.clock), publisher(s, keys.mission)
        for k in range(50):
            pub_clock.put(good[k])
            if k % 2 == 0:
                pub_state.put(big)  # 25
            if k % 10 == 0:
                pub_cmd.put(huge)  # 5
        pub_mission.put(mission)
        pub_mission.put(mission + b"\x00" * wire.MAX_MISSION_PAYLOAD)  # over the mission's own bound
        wait_recorded(s, swarm, 51)
        time.sleep(0.3)
        assert rec.stop() == 0, rec.output
    assert "31 oversize payloads" in rec.output and "not recorded" in rec.output, rec.output

    r = read_recording(out)
    msgs = [m for m in r.messages() if m.topic != keys.diag("recorder")]
    assert [m.payload for m in msgs if m.topic == keys.clock] == good
    assert [m.payload for m in msgs if m.topic == keys.mission] == [mission]
    assert {m.topic for m in msgs} == {keys.clock, keys.mission}  # no oversize payload in the file
    assert max(len(m.payload) for m in r.messages()) <= wire.MAX_MISSION_PAYLOAD
    assert r.dropped_oversize == {
        keys.state(1): {"count": 25, "bytes": 25 * len(big), "largest": len(big), "limit": wire.MAX_PAYLOAD},
        keys.cmd(2): {"count": 5, "bytes": 5 * len(huge), "largest": len(huge), "limit": wire.MAX_PAYLOAD},
        keys.mission: {
            "count": 1,
            "bytes": len(mission) + wire.MAX_MISSION_PAYLOAD,
            "largest": len(mission) + wire.MAX_MISSION_PAYLOAD,
            "limit": wire.MAX_MISSION_PAYLOAD,
        },
    }
    assert r.info["payload_limit_bytes"] == str(wire.MAX_PAYLOAD)
    note = r.dropped_note()
    assert note is not None and "did not record 31 payloads" in note and f"{keys.state(1)}: 25" in note
    # the recorder's own diag counters say it too
    last = [wire.decode("diag", m.payload) for m in r.messages() if m.topic == keys.diag("recorder")][-1]
    assert last.counters["dropped_oversize"] == 31
    assert r.scenario == scenario  # the first metadata record is not overridden by the counts


def test_oversize_counts_survive_a_truncated_file(tmp_path: Path) -> None:
    """In a file without summary the counts are found while the messages are read."""
    swarm = swarm_name()
    keys = wire.Keys(swarm)
    path = tmp_path / "sink.mcap"
    sink = McapSink(path, keys, chunk_size=4096, metadata=build_metadata(swarm, "lockstep", scenario_to_dict(load_scenario(EX1)), "test"))
    sink.start()
    for k in range(200):
        sink.put(1_700_000_000_000_000_000 + k, keys.clock, wire.encode(wire.Clock(t=k, seq=k + 1)))
        if k % 20 == 0:
            sink.put(1_700_000_000_000_000_000 + k, keys.ref(3), b"\x02" * (wire.MAX_PAYLOAD + 7))
    sink.put_oversize(1_700_000_000_000_001_000, keys.ref(3), 10**9)  # as the callback queues it: size only
    sink.close()
    assert sink.error is None and sink.stats.dropped_oversize == 11 and sink.stats.messages == 200
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 40])  # the summary and footer are gone
    r = read_recording(cut, strict=False)
    assert not r.complete
    assert len(list(r.messages())) == 200
    assert r.dropped_oversize == {
        keys.ref(3): {"count": 11, "bytes": 10 * (wire.MAX_PAYLOAD + 7) + 10**9, "largest": 10**9, "limit": wire.MAX_PAYLOAD}
    }
    notes = r.notes()
    assert any("incomplete" in n and "truncated" in n for n in notes) and any("did not record 11 payloads" in n for n in notes)


# --------------------------------------------------------------------------- (b) replay


@pytest.mark.swarm
def test_record_replay_record_gives_the_same_payloads(tmp_path: Path) -> None:
    a, b = swarm_name(), swarm_name()
    scenario = scenario_to_dict(load_scenario(EX1))
    traffic = synthetic_traffic(a, 150, scenario)
    first, second = tmp_path / "first.mcap", tmp_path / "second.mcap"
    with router() as ep, processes() as procs, open_session(client_config([ep]), handle_signals=False) as s:
        rec1 = start_recorder(procs, ep, a, first, "--scenario", EX1, "--diag-interval", "0")
        rec2 = start_recorder(procs, ep, b, second, "--diag-interval", "0")
        wait_alive(s, a)
        wait_alive(s, b)
        pubs = {key: publisher(s, key) for key in dict.fromkeys(k for k, _ in traffic)}
        t0 = time.monotonic()
        for j, (key, payload) in enumerate(traffic):
            pubs[key].put(payload)
            if j % 100 == 99:
                time.sleep(0.05)  # about 1 s of traffic with gaps, to check the timing
        span_pub = time.monotonic() - t0
        time.sleep(0.5)
        assert rec1.stop() == 0, rec1.output
        replay = Proc("replay", first, "--swarm", b, "--connect", ep, "--clock", "wall")  # receive-time pacing
        procs.append(replay)
        assert replay.popen.wait(timeout=60) == 0, replay.output
        assert "replay: end of recording" in replay.output, replay.output
        time.sleep(0.5)
        assert rec2.stop() == 0, rec2.output
    one = list(read_recording(first).messages())
    two = list(read_recording(second).messages())
    assert [(m.topic, m.payload) for m in one] == traffic
    prefix_a, prefix_b = f"swarm/{a}/", f"swarm/{b}/"
    assert [(m.topic, m.payload) for m in two] == [(prefix_b + k[len(prefix_a) :], p) for k, p in traffic]
    assert [m.publish_time for m in two] == [
        m.publish_time if sim_time(m.payload) is not None else n.log_time for m, n in zip(one, two)
    ]
    # original timing: the replayed span matches the recorded one
    span1 = (one[-1].log_time - one[0].log_time) / 1e9
    span2 = (two[-1].log_time - two[0].log_time) / 1e9
    assert span1 > 0.5 * span_pub
    assert abs(span2 - span1) < 0.25 * span1 + 0.05, (span1, span2)


@pytest.mark.swarm
def test_replay_filters_topics_and_window(tmp_path: Path) -> None:
    a, b = swarm_name(), swarm_name()
    path = tmp_path / "fake.mcap"
    expected = fake_recording(path, a, 300, scenario_to_dict(load_scenario(EX1)))  # 300 us of log time
    out = tmp_path / "filtered.mcap"
    with router() as ep, processes() as procs, open_session(client_config([ep]), handle_signals=False) as s:
        rec = start_recorder(procs, ep, b, out, "--diag-interval", "0")
        wait_alive(s, b)
        replay = Proc("replay", path, "--swarm", b, "--connect", ep, "--topic", f"swarm/{a}/uav/2/**", "--start", "1.0", "--rate", "0")
        procs.append(replay)
        assert replay.popen.wait(timeout=60) == 0, replay.output
        time.sleep(0.3)
        assert rec.stop() == 0, rec.output
    got = [(m.topic, m.payload) for m in read_recording(out).messages()]
    lt0 = expected[0][1]
    want = [
        (k.replace(f"swarm/{a}/", f"swarm/{b}/"), p)
        for k, lt, _, p in expected
        if k.endswith("/uav/2/state") and lt - lt0 >= 100_000
    ]
    assert got == want and len(want) == 67


@pytest.mark.swarm
def test_replay_rejects_a_window_or_filter_that_does_not_fit_the_recording(tmp_path: Path) -> None:
    """--start beyond the recording, --end before --start, a negative time and a key filter that
    matches nothing: exit 2 naming the flag and the recording's span, and nothing published."""
    swarm = swarm_name()
    keys = wire.Keys(swarm)
    path = tmp_path / "span.mcap"
    sink = McapSink(path, keys, metadata=build_metadata(swarm, "lockstep", None, "test"))
    sink.start()
    for k in range(300):  # 2.99 s of log time
        sink.put(1_700_000_000_000_000_000 + k * 10_000_000, keys.clock, wire.encode(wire.Clock(t=k * 10_000_000, seq=k + 1)))
    sink.close()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-40])  # without summary: the span is found by reading
    listen = tmp_path / "seen.mcap"
    with router() as ep, processes() as procs, open_session(client_config([ep]), handle_signals=False) as s:
        rec = start_recorder(procs, ep, swarm, listen, "--diag-interval", "0")
        wait_alive(s, swarm)
        for f in (path, cut):
            for flags, flag, words in (
                (["--start", "1000"], "--start", ["1000 s is beyond the end of the recording", "it spans 0 to 2.990 s of sim time"]),
                (["--start", "5", "--end", "2"], "--end", ["2 s is before --start 5 s"]),
                (["--start", "-5"], "--start", ["must be a number of sim seconds >= 0", "got -5"]),
                (["--end", "nan"], "--end", ["must be a number of sim seconds >= 0"]),
                (["--topic", f"swarm/{swarm}/uav/*/state"], "--topic", ["matches none of the keys recorded", keys.clock]),
            ):
                cli = subprocess.run(
                    [sys.executable, "-m", "zenswarm", "replay", str(f), "--connect", ep, "--rate", "0", *flags],
                    cwd=REPO, capture_output=True, text=True, timeout=60,
                )  # fmt: skip
                assert cli.returncode == 2, (flags, cli.stdout, cli.stderr)
                assert cli.stderr.startswith(f"zenswarm: error: {flag}: "), cli.stderr
                assert all(w in cli.stderr for w in words), (flags, cli.stderr)
                assert "Traceback" not in cli.stderr
        # a window that fits still plays
        ok = subprocess.run(
            [sys.executable, "-m", "zenswarm", "replay", str(path), "--connect", ep, "--rate", "0", "--start", "2.5", "--end", "99"],
            cwd=REPO, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert ok.returncode == 0 and "50 messages published" in ok.stderr, ok.stderr
        time.sleep(0.3)
        assert rec.stop() == 0, rec.output
    got = [m for m in read_recording(listen).messages() if m.topic == keys.clock]
    assert len(got) == 50  # only the good window reached the bus


# --------------------------------------------------------------------------- (c) SIGKILL


@pytest.mark.swarm
def test_sigkill_file_reads_up_to_one_second_before_and_recovers(tmp_path: Path) -> None:
    swarm = swarm_name()
    out, fixed = tmp_path / "killed.mcap", tmp_path / "fixed.mcap"
    keys = wire.Keys(swarm)
    sent: list[bytes] = []
    with router() as ep, processes() as procs, open_session(client_config([ep]), handle_signals=False) as s:
        rec = start_recorder(procs, ep, swarm, out, "--scenario", EX1)
        wait_alive(s, swarm)
        pub = publisher(s, keys.state(1))
        t0 = time.monotonic()
        k = 0
        while time.monotonic() - t0 < 2.5:  # steady ~1000 msg/s
            k += 1
            p = wire.encode(wire.State(t=k * 1_000_000, seq=k, q=[k, 0, 0], v=[0, 0, 0], rpy=[0, 0, 0], w=[0, 0, 0]))
            pub.put(p)
            sent.append(p)
            time.sleep(0.001)
        kill_ns = time.time_ns()
        rec.popen.send_signal(signal.SIGKILL)
        rec.popen.wait(timeout=10)
    with pytest.raises(RecordingError) as ei:
        read_recording(out)  # strict
    assert str(out) in str(ei.value) and "incomplete" in str(ei.value)
    r = read_recording(out, strict=False)
    got = [m for m in r.messages() if m.topic == keys.state(1)]
    assert r.problems and not r.complete
    assert len(got) > 1000
    assert [m.payload for m in got] == sent[: len(got)]  # a prefix of what was sent, nothing altered
    lag_s = (kill_ns - got[-1].log_time) / 1e9
    assert lag_s <= 1.0, f"the file ends {lag_s:.3f} s before the kill"
    assert r.scenario == scenario_to_dict(load_scenario(EX1))  # the metadata came first

    cli = subprocess.run(
        [sys.executable, "-m", "zenswarm", "recover", str(out), "--out", str(fixed)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert cli.returncode == 0, cli.stderr
    assert "truncated" in cli.stderr
    assert "(truncated: not closed cleanly)" in cli.stdout and "cannot be known" in cli.stdout, cli.stdout
    assert file_is_complete(fixed)
    r2 = read_recording(fixed)  # strict: complete, with summary
    assert r2.statistics is not None and r2.statistics.message_count >= len(got)
    got2 = [m for m in r2.messages() if m.topic == keys.state(1)]
    assert got2 == got
    assert r2.scenario == r.scenario and r2.swarm == swarm


# --------------------------------------------------------------------------- (d) damage


def test_missing_and_foreign_files_name_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.mcap"
    with pytest.raises(RecordingError, match="nope.mcap: no such file"):
        read_recording(missing)
    foreign = tmp_path / "foreign.mcap"
    foreign.write_bytes(b"PK\x03\x04 definitely a zip file" * 10)
    with pytest.raises(RecordingError, match="foreign.mcap: not an MCAP file"):
        read_recording(foreign, strict=False)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="empty.mcap: not an MCAP file"):
        read_recording(empty)
    with pytest.raises(RecordingError, match="foreign.mcap: not an MCAP file"):
        recover(foreign, tmp_path / "out.mcap")


@pytest.mark.slow
def test_truncated_file_error_and_recover(tmp_path: Path) -> None:
    swarm = swarm_name()
    scenario = scenario_to_dict(load_scenario(EX1))
    whole = tmp_path / "whole.mcap"
    expected = fake_recording(whole, swarm, 3000, scenario)
    assert list(read_recording(whole).messages()) == expected
    data = whole.read_bytes()
    damaged = 0
    for cut in (len(data) // 2, len(data) * 9 // 10, len(data) * 9 // 10 + 5, len(data) - 3):
        trunc = tmp_path / f"trunc{cut}.mcap"
        trunc.write_bytes(data[:cut])
        with pytest.raises(RecordingError) as ei:
            read_recording(trunc)
        assert str(trunc) in str(ei.value) and "incomplete" in str(ei.value)
        r = read_recording(trunc, strict=False)
        got = list(r.messages())
        assert got == expected[: len(got)], "a truncated file yields a prefix, unaltered"
        if cut < len(data) - 1000:
            assert 0 < len(got) < len(expected)
        assert r.problems and r.scenario == scenario
        fixed = tmp_path / f"fixed{cut}.mcap"
        st = recover(trunc, fixed)
        assert st.messages == len(got) and not st.source_complete and st.problems
        # what can be known: the unread tail, the last good time; not how many were never written
        assert not st.intact and st.tail_unknown and st.lost_known == 0 and not st.sequence_gaps
        assert st.last_log_time == got[-1][1]
        assert any("cannot be known" in x for x in st.losses())
        if cut < len(data) - 1000 and r.damage_offset is None:
            assert st.discarded_bytes == 0  # the cut fell on a record boundary: nothing damaged
        elif cut < len(data) - 1000:  # cut inside a record of the messages (not in the summary)
            damaged += 1
            assert 0 < st.discarded_bytes == cut - r.damage_offset
            assert any(f"{st.discarded_bytes} bytes of the cut tail could not be read" in x for x in st.losses())
        r2 = read_recording(fixed)
        assert list(r2.messages()) == got
        assert r2.scenario == scenario and r2.statistics is not None and r2.statistics.message_count == len(got)
    assert damaged >= 1, "no cut fell inside a record: the damaged-tail case went untested"


@pytest.mark.swarm
def test_corrupted_chunk_error_and_recover(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    swarm = swarm_name()
    scenario = scenario_to_dict(load_scenario(EX1))
    whole = tmp_path / "whole.mcap"
    expected = fake_recording(whole, swarm, 3000, scenario)
    with open(whole, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) > 10
    bad = chunks[len(chunks) // 2]
    data = bytearray(whole.read_bytes())
    mid = bad.chunk_start_offset + bad.chunk_length // 2
    for j in range(8):
        data[mid + j] ^= 0x5A  # flip bytes in the middle of a chunk's data
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(bytes(data))

    r = read_recording(broken)  # the summary is intact: opening works
    before = [m for m in expected if m[1] < bad.message_start_time]
    got: list = []
    with pytest.raises(RecordingError) as ei:
        for m in r.messages():
            got.append(m)
    assert str(broken) in str(ei.value) and f"offset {bad.chunk_start_offset}" in str(ei.value)
    assert got == before, "strict read yields everything before the damage"

    fixed = tmp_path / "fixed.mcap"
    st = recover(broken, fixed)
    assert st.source_complete and any("corrupted" in p for p in st.problems)
    rec = list(read_recording(fixed).messages())
    lost = [m for m in expected if bad.message_start_time <= m[1] <= bad.message_end_time]
    assert rec[: len(before)] == before  # what precedes the bad chunk
    assert rec == [m for m in expected if m not in lost]  # and, framing intact, what follows it
    assert 0 < len(lost) < 600
    # the loss is known exactly: the per-key sequence gaps and the skipped chunk's message indexes
    assert not st.intact and not st.tail_unknown and st.discarded_bytes == 0
    assert st.lost_known == len(lost)
    assert st.sequence_gaps == {k: sum(1 for m in lost if m[0] == k) for k in {m[0] for m in lost}}
    assert [(c["offset"], c["messages"]) for c in st.skipped_chunks] == [(bad.chunk_start_offset, len(lost))]

    cli = subprocess.run(
        [sys.executable, "-m", "zenswarm", "recover", str(broken), "--out", str(tmp_path / "fixed2.mcap")],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert cli.returncode == 0, cli.stderr
    assert "(complete but damaged)" in cli.stdout and "(complete)" not in cli.stdout, cli.stdout
    assert f"recover: lost: {len(lost)} messages known lost (per-key sequence gaps: " in cli.stdout, cli.stdout
    cli = subprocess.run(
        [sys.executable, "-m", "zenswarm", "recover", str(whole), "--out", str(tmp_path / "fixed3.mcap")],
        cwd=REPO, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert cli.returncode == 0 and "(complete, intact: nothing damaged)" in cli.stdout and "lost" not in cli.stdout, cli.stdout


def test_corrupted_summary_is_reported(tmp_path: Path) -> None:
    whole = tmp_path / "whole.mcap"
    expected = fake_recording(whole, swarm_name(), 500, scenario_to_dict(load_scenario(EX1)))
    data = bytearray(whole.read_bytes())
    data[-60] ^= 0xFF  # inside the summary section
    broken = tmp_path / "badsummary.mcap"
    broken.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="badsummary.mcap: incomplete recording: summary section fails its CRC"):
        read_recording(broken)
    fixed = tmp_path / "fixed.mcap"
    assert recover(broken, fixed).messages == len(expected)
    assert list(read_recording(fixed).messages()) == expected


# --------------------------------------------------------------------------- (e) verify


def _tamper(src: Path, dst: Path, topic: str, tick: int, dt_ns: int) -> float:
    """Copy ``src`` to ``dst`` with the thrust of the cmd of ``tick`` on ``topic`` nudged by one ulp.
    Returns the new thrust."""
    from mcap.writer import Writer

    r = read_recording(src)
    new_thrust = None
    with open(dst, "wb") as f:
        w = Writer(f)
        w.start()
        for m in r.metadata_records:
            w.add_metadata(m.name, dict(m.metadata))
        ids: dict[int, int] = {}
        for ch, msg in r.raw_messages():
            if ch.id not in ids:
                ids[ch.id] = w.register_channel(ch.topic, ch.message_encoding, 0, dict(ch.metadata))
            data = msg.data
            if ch.topic == topic:
                o = msgpack.unpackb(data)
                if o["t"] == tick * dt_ns:
                    o["thrust"] = new_thrust = float(np.nextafter(o["thrust"], np.inf))
                    data = msgpack.packb(o, use_bin_type=True)
            w.add_message(ids[ch.id], msg.log_time, data, msg.publish_time, msg.sequence)
        w.finish()
    assert new_thrust is not None
    return new_thrust


def record_flight(tmp_path: Path, scen_path: Path, swarm: str) -> Path:
    """Fly ``scen_path`` with ``zenswarm up`` (lockstep) while ``zenswarm record`` records it.

    The recorder joins a router of ours and `zenswarm up` links its own router to it: the
    recorder is subscribed before the swarm exists, so it sees the first tick. The scenario comes
    from the leader's mission queryable (no --scenario)."""
    out = tmp_path / f"{swarm}.mcap"
    with router() as ep, processes() as procs, open_session(client_config([ep]), handle_signals=False) as s:
        rec = start_recorder(procs, ep, swarm, out)
        wait_alive(s, swarm)
        up = Proc(
            "up", scen_path, "--swarm", swarm, "--listen", tcp_endpoint(free_port()), "--router-connect", ep,
            "--out", tmp_path / f"up-{swarm}", "--quiet", "--quiet-children",
        )  # fmt: skip
        procs.append(up)
        assert up.popen.wait(timeout=120) in (0, 1), up.output  # a few seconds are too short for the goal: 1
        assert rec.stop() == 0, rec.output
    assert "received from the leader's mission" in rec.output, rec.output
    return out


def verify_cli(path: Path, agent: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "zenswarm", "replay", "--verify", str(path), "--agent", agent],
        cwd=REPO, capture_output=True, text=True, timeout=120,
    )  # fmt: skip


@pytest.mark.swarm
def test_replay_verify_lockstep_recording_and_tampered_copy(tmp_path: Path) -> None:
    swarm = swarm_name()
    scen_path = short_scenario(tmp_path, 3.0)
    sc = load_scenario(scen_path)
    out = record_flight(tmp_path, scen_path, swarm)
    r = read_recording(out)
    assert r.load_scenario() == sc and r.mode == "lockstep"
    n_ticks = sc.timing.n_ticks

    cli = verify_cli(out, "2")
    assert cli.returncode == 0, cli.stdout + cli.stderr
    assert f"agent 2: verified {n_ticks} ticks" in cli.stdout
    for i in (1, 3):
        res = verify_agent(out, i)
        assert res.ok and res.ticks == n_ticks, res

    tampered = tmp_path / "tampered.mcap"
    dt_ns = wire.t_ns(sc.timing.dt)
    new = _tamper(out, tampered, wire.Keys(swarm).cmd(2), 137, dt_ns)
    cli = verify_cli(tampered, "2")
    assert cli.returncode == 1, cli.stdout + cli.stderr
    assert "agent 2: first difference at tick 137, cmd.thrust: recorded" in cli.stdout, cli.stdout
    res = verify_agent(tampered, 2)
    assert not res.ok and res.ticks == 137
    d = res.difference
    assert d.tick == 137 and d.field == "cmd.thrust" and d.recorded == new
    assert struct.pack("<d", d.recomputed) != struct.pack("<d", new)
    assert verify_agent(tampered, 1).ok  # the others are untouched


@pytest.mark.swarm
def test_replay_verify_replays_link_faults(tmp_path: Path) -> None:
    """With the scenario's [faults] (loss, delay, jitter) the agents' inputs go through their
    receive boxes; verify rebuilds the same boxes and still reproduces every bit."""
    swarm = swarm_name()
    scen_path = short_scenario(tmp_path, 1.5)
    with open(scen_path, "a") as f:
        f.write('\n[faults]\nloss = 0.2\ndelay = "15ms"\njitter = "10ms"\n')
    sc = load_scenario(scen_path)
    out = record_flight(tmp_path, scen_path, swarm)
    cli = subprocess.run(
        [sys.executable, "-m", "zenswarm", "verify", str(out)], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert cli.returncode == 0, cli.stdout + cli.stderr
    for i in range(1, sc.n + 1):
        assert f"agent {i}: verified {sc.timing.n_ticks} ticks" in cli.stdout
    assert "link faults replayed" in cli.stderr


def test_sim_time_extraction() -> None:
    assert sim_time(wire.encode(wire.Clock(t=123, seq=1))) == 123
    assert sim_time(msgpack.packb({"t": 5})) == 5
    for bad in (b"", b"\xc1", msgpack.packb([1, 2]), msgpack.packb({"t": -1}), msgpack.packb({"t": 1.5}), msgpack.packb({"x": 1})):
        assert sim_time(bad) is None


# --------------------------------------------------------------------------- (f) the recorder dies mid-flight


@pytest.mark.swarm
def test_recorder_killed_mid_flight_does_not_abort_the_flight(tmp_path: Path) -> None:
    """`zenswarm up --record F --kill recorder@1.5s --report`: the flight flies to its time limit
    (the plant is not stalled), the exit status is the mission's (0/1, never 3), the loss is said
    and is in results.json, the recording reads up to the kill, and the report says it is partial."""
    from swarmtest import read_results, scenario_variant, unique_swarm, zenswarm

    scen = scenario_variant(tmp_path, time_limit_s=4.0, settle_time_s=1.0)
    out, rec = tmp_path / "up", tmp_path / "flight.mcap"
    swarm = unique_swarm("rk")
    cp = zenswarm(
        "up", str(scen), "--swarm", swarm, "--record", str(rec), "--kill", "recorder@1.5s", "--out", str(out),
        "--report", "--quiet-children", timeout=240,
    )  # fmt: skip
    res = read_results(out)
    assert cp.returncode in (0, 1) and cp.returncode == (0 if res["success"] else 1), cp.stdout
    assert "recording lost: the recorder died (killed by SIGKILL) at sim time" in cp.stdout, cp.stdout
    loss = res["recording_loss"]
    assert loss["how"] == "killed by SIGKILL" and 1.5 <= loss["died_at_sim_time_s"] < 4.0, loss
    assert res["sim_time_s"] == pytest.approx(4.0)  # flown to the end: nothing waited for the recorder
    assert res["process_deaths"] == [] and res["processes"]["plant"] == 0 and res["processes"]["recorder"] == -9
    assert "report: warning: the recorder died at sim time" in cp.stdout and "the report is partial" in cp.stdout
    assert "report: warning: the report covers sim time 0 to" in cp.stdout, cp.stdout
    assert (out / "report" / "results.json").exists()

    r = read_recording(rec, strict=False)  # an MCAP cut by the kill, readable up to it
    assert not r.complete
    states = [m for m in r.messages() if m.topic == wire.Keys(swarm).state(1)]
    assert states and r.scenario is not None
    last_t = states[-1].publish_time / 1e9
    # up to the last flush before the kill: chunks are flushed every 0.25 s of wall time, which is
    # about 1 s of sim time in lockstep on this machine, so only "something, and nothing after it"
    assert 0.0 < last_t <= loss["died_at_sim_time_s"] + 0.01, (last_t, loss)
    fixed = tmp_path / "fixed.mcap"
    assert recover(rec, fixed).messages > 0 and file_is_complete(fixed)


@pytest.mark.swarm
def test_kill_recorder_without_record_is_bad_input(tmp_path: Path) -> None:
    from swarmtest import scenario_variant, zenswarm

    scen = scenario_variant(tmp_path, time_limit_s=1.0)
    cp = zenswarm("up", str(scen), "--kill", "recorder@1s", "--out", str(tmp_path / "up"), timeout=60)
    assert cp.returncode == 2 and "zenswarm: error: --kill: recorder@1s: recorder runs only with --record" in cp.stdout, cp.stdout
    assert not (tmp_path / "up" / "results.json").exists()


@pytest.mark.slow
def test_a_flood_of_oversize_payloads_does_not_hold_back_the_flush(tmp_path: Path) -> None:
    """While the writer works through a long run of oversize payloads, the samples before them are
    still flushed every flush interval, and the counts reach the file while the flood goes on."""
    swarm = swarm_name()
    keys = wire.Keys(swarm)
    path = tmp_path / "flood.mcap"
    sink = McapSink(path, keys, flush_interval_s=0.02, metadata=build_metadata(swarm, "lockstep", None, "test"))
    good = wire.encode(wire.Clock(t=0, seq=1))
    sink.put(1_700_000_000_000_000_000, keys.clock, good)
    n = 400_000
    for _ in range(n):  # queued before the writer starts: it never finds the queue empty
        sink.put_oversize(1_700_000_000_000_000_001, keys.state(1), wire.MAX_PAYLOAD + 1)
    sink.start()
    try:
        time.sleep(0.15)
        backlog = sink.backlog
        r = read_recording(path, strict=False)
        got = [m.payload for m in r.messages()]
        dropped = r.dropped_oversize
    finally:
        sink.close()
    assert backlog > 0, "the writer finished the flood before the check: raise n"
    assert got == [good], "the sample before the flood is not in the file yet"
    assert 0 < dropped[keys.state(1)]["count"] < n
    assert read_recording(path).dropped_oversize[keys.state(1)]["count"] == n

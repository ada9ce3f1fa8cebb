"""Flight report and Foxglove export from an MCAP recording (bridge/reports/report.py, bridge/views/foxglove.py).

The recording is built here, not by the recorder: paper example 1 flown for 3 s by the in-process
simulator, each tick's samples encoded as the swarm's wire messages on their keys with t = k dt
(what a lockstep swarm publishes), written with the mcap Writer the way the recorder writes them
(one channel per key, message encoding msgpack, no schema, log_time = receive wall time,
publish_time = sim time) plus the ``zenswarm`` metadata record.
"""

from __future__ import annotations

import argparse
import json
import struct
import tomllib
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from zenswarm.bridge.reports import report
from zenswarm.bridge.views import foxglove as fx
from zenswarm.bus import wire
from zenswarm.compose.cli import main as cli_main
from zenswarm.compose.sim import simulate
from zenswarm.errors import RecordingError
from zenswarm.judge.metrics import FLIGHT_FIELDS, compute_results
from zenswarm.scenario.config import scenario_from_dict, scenario_to_dict

import foxglove_check

EX1 = Path(__file__).resolve().parents[1] / "compose" / "scenarios" / "paper_example1.toml"
SWARM = "demo"
WALL0 = 1_700_000_000_000_000_000  # receive wall time of the first sample, ns


@pytest.fixture(scope="module")
def flight():
    doc = tomllib.loads(EX1.read_text())
    doc["timing"]["time_limit_s"] = 3.0
    doc["timing"]["settle_time_s"] = 1.0  # so max_formation_error_m is a number, not null
    sc = scenario_from_dict(doc)
    return sc, simulate(sc)


def _samples(sc, series, plant=True):
    """(key, t_ns, payload) of a lockstep flight, in publication order per tick; ``plant``: the
    states carry the plant model's records, as the plant process sends them."""
    keys = wire.Keys(SWARM)
    n = sc.n
    out = [(keys.mission, 0, wire.encode(wire.Mission(0, 0, scenario_to_dict(sc))))]
    dt_ns = wire.t_ns(sc.timing.dt)
    zero = np.zeros(3)
    for k in range(len(series.t)):
        t = k * dt_ns
        assert t == wire.t_ns(float(series.t[k]))
        out.append((keys.clock, t, wire.encode(wire.Clock(t, k))))
        for i in range(n):  # with what the plant model records, as the plant process sends it (issue 43)
            extra = {name: a[k, i].ravel().tolist() for name, a in series.plant.items()} if plant else {}
            out.append((keys.state(i + 1), t, wire.encode(wire.State(t, k, series.q[k, i], series.v[k, i], series.rpy[k, i], zero,
                                                                     extra=extra))))
        out.append((keys.leader_ref, t, wire.encode(wire.Ref(t, k, series.q0[k], series.v0[k]))))
        for i in range(n):
            out.append((keys.ref(i + 1), t, wire.encode(wire.Ref(t, k, series.qref[k, i], series.vref[k, i]))))
            out.append(
                (
                    keys.cmd(i + 1),
                    t,
                    wire.encode(wire.Cmd(t, k, float(series.thrust[k, i]), series.rpy_cmd[k, i], series.u[k, i], series.d_hat[k, i])),
                )
            )
    t_end = (len(series.t) - 1) * dt_ns
    procs = ["plant", "leader"] + [wire.agent(i + 1) for i in range(n)]
    for j, p in enumerate(procs):
        counters = {"decoded": 300 * (j + 1), "rejected": 0, "input_timeouts": 0.0, "loop_ticks": len(series.t)}
        if p == "agent:2":
            counters.update({"rejected": 2, "rejected.nonfinite": 2, "dropped.agent:1": 3})
        out.append((keys.diag(p), t_end, wire.encode(wire.Diag(t_end, 1, p, counters, {"note": "synthetic"}))))
    # a garbage payload on a real key: the report's decoder must count it, the export skip it
    out.append((keys.ref(2), t_end, b"\xc1garbage"))
    return out


def write_recording(
    path: Path, sc, series, *, metadata: bool = True, chunk_size: int = 1 << 20, extra_metadata: dict | None = None,
    plant: bool = True,
) -> int:
    """Write a recording of ``series`` as the recorder does; returns the number of messages.
    extra_metadata: more values for the ``zenswarm`` record. plant: False writes the states
    without the plant model's records (as before issue 43)."""
    samples = _samples(sc, series, plant)
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size)
        w.start(profile="", library="test_report")
        if metadata:
            w.add_metadata(
                "zenswarm",
                {"scenario_json": json.dumps(scenario_to_dict(sc)), "swarm": SWARM, "mode": "lockstep", **(extra_metadata or {})},
            )
        channels: dict[str, int] = {}
        for n, (key, t, payload) in enumerate(samples):
            cid = channels.get(key)
            if cid is None:
                cid = channels[key] = w.register_channel(key, "msgpack", 0)
            w.add_message(cid, log_time=WALL0 + 37_000 * n, data=payload, publish_time=t, sequence=n)
        w.finish()
    return len(samples)


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def recording(flight, tmp_path_factory):
    sc, sim = flight
    p = tmp_path_factory.mktemp("rec") / "flight.mcap"
    n = write_recording(p, sc, sim.series)
    return p, n


@pytest.mark.slow
def test_report_writes_every_figure_and_the_runs_results(flight, recording, tmp_path, capsys):
    sc, sim = flight
    path, _ = recording
    out = tmp_path / "report"
    assert cli_main(["report", str(path), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    printed = captured.out.split()
    assert "warning" not in captured.err  # a complete, intact recording
    for name in report.FIGURES:
        f = out / name
        assert str(f) in printed
        assert f.stat().st_size > 20_000, f"{name} is suspiciously small"
        w, h = _png_size(f)
        assert w >= 800 and h >= 400, (name, w, h)
    res = json.loads((out / "results.json").read_text())
    assert str(out / "results.json") in printed
    expected = compute_results(sim.series, sc)
    for k in FLIGHT_FIELDS:
        assert res[k] == expected[k], k
        assert res[k] == sim.results[k], k
    assert res["schema_version"] == 2 and res["wall_time_s"] is None
    assert res["max_formation_error_m"] is not None
    assert res["mode"] == "lockstep" and res["swarm"] == SWARM
    # bus statistics: the garbage payload is counted against its key, diag counters are kept
    assert res["decoder_rejects"]["rejected"] == 1
    assert res["diagnostics"]["agent:2"]["dropped.agent:1"] == 3
    assert res["message_counts"][f"swarm/{SWARM}/uav/2/ref"] == len(sim.series.t) + 1
    assert not (out / "effective_graph.png").exists()  # no radio, queue or trace: no such figure


@pytest.mark.slow
def test_report_plots_the_effective_graph_of_a_radio_run(flight, recording, tmp_path):
    """A recording whose run had --link-range and --link-capacity (the recorder's fault flags):
    the report's fault plan has them (the fault-free recording's has none: no figure, see above),
    effective_graph.png is drawn, from the same per-tick graph as results.json's effective_graph
    (its summary is recomputed here from graph_series)."""
    from zenswarm.bridge.args import add_fault_args, link_faults
    from zenswarm.link.swarm import effective_graph, graph_series

    sc, sim = flight
    words = ["--link-range", "0.25m", "--link-capacity", "20kB/s", "--link-jitter", "5ms"]
    p = tmp_path / "radio.mcap"
    write_recording(p, sc, sim.series, extra_metadata={"fault_args": json.dumps(words)})
    rec = report.load_recording(p)
    recorded = report.recorded_fault_plan(rec)  # what report_recording passes to report_from_series
    assert recorded is not None and report.network_plan(sc, recorded) is recorded
    assert report.network_plan(sc, report.recorded_fault_plan(report.load_recording(recording[0]))) is None
    f = report.plot_effective_graph(sim.series, sc, recorded, tmp_path / "effective_graph.png")
    assert f.stat().st_size > 20_000
    w, h = _png_size(f)
    assert w >= 800 and h >= 600, (w, h)
    ap = argparse.ArgumentParser()
    add_fault_args(ap)
    plan = link_faults(ap.parse_args(words)).plan(sc)
    A = np.asarray(sc.graph.adjacency, dtype=float)
    nbrs = [[int(j) for j in np.flatnonzero(A[i])] for i in range(sc.n)]
    pinned = [float(b) > 0 for b in sc.graph.pinning]
    gs = graph_series(plan, nbrs, pinned, sim.series.q, sim.series.q0, sc.timing.dt)
    eg = effective_graph(plan, nbrs, pinned, sim.series.q, sim.series.q0, sc.timing.dt)
    assert eg["link_up_fraction"] == {ls.name: float(np.mean(ls.up)) for ls in gs.links}
    assert eg["max_components"] == int(gs.components.max())
    assert 0.0 < eg["spanning_tree_fraction"] == float(np.mean(gs.tree)) < 1.0  # 0.25 m cuts some links, not all
    ups = np.concatenate([ls.up[1:] for ls in gs.links])
    delays = np.concatenate([ls.delay_s[1:][ls.up[1:]] for ls in gs.links])
    assert 0 < ups.sum() < ups.size  # the figure's delivery ratios are neither all 0 nor all 1
    assert delays.min() >= 0.0 and delays.max() > 0.0  # queue wait + serialization + jitter


@pytest.mark.slow
def test_flight_from_recording_equals_the_simulated_series(flight, recording):
    sc, sim = flight
    fl = report.flight_from_recording(report.load_recording(recording[0]))
    for f in ("t", "q0", "v0", "qref", "vref", "q", "v", "rpy", "u", "thrust", "d_hat", "rpy_cmd"):
        np.testing.assert_array_equal(getattr(fl.series, f), getattr(sim.series, f), err_msg=f)


@pytest.mark.slow
def test_report_from_series(flight, tmp_path, capsys):
    sc, sim = flight
    run = tmp_path / "run"
    run.mkdir()
    sim.series.save(str(run / "timeseries.npz"))
    scen = tmp_path / "scenario.toml"
    scen.write_text(_toml(scenario_to_dict(sc)))
    out = tmp_path / "plots"
    assert cli_main(["report", "--series", str(run / "timeseries.npz"), "--scenario", str(scen), "--out", str(out)]) == 0
    printed = capsys.readouterr().out.split()
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted(n for n in report.FIGURES if n != "links.png")
    assert printed == [str(out / n) for n in report.FIGURES if n != "links.png"]


def _toml(d: dict) -> str:
    """Minimal TOML writer for a scenario_to_dict() document (tables, arrays of tables)."""

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        return repr(float(v)) if isinstance(v, float) else str(v)

    lines = []
    for sec, body in d.items():
        if isinstance(body, list):
            for item in body:
                lines.append(f"[[{sec}]]")
                lines += [f"{k} = {val(v)}" for k, v in item.items()]
        else:
            lines.append(f"[{sec}]")
            lines += [f"{k} = {val(v)}" for k, v in body.items()]
    return "\n".join(lines) + "\n"


@pytest.mark.slow
def test_export_foxglove_validates_against_its_schemas(flight, recording, tmp_path, capsys):
    """Recorded topics: JSON, each valid against its JSON Schema; /scene and /tf: protobuf with
    Foxglove's official descriptors (the SDK's, byte for byte), each message decoded with them;
    /metrics: JSON valid against its schema, its figures those of the flight."""
    sc, sim = flight
    path, n_written = recording
    out = tmp_path / "fox.mcap"
    assert cli_main(["export", "--foxglove", str(path), "--out", str(out)]) == 0
    assert str(out) in capsys.readouterr().out.split()

    validators: dict[int, object] = {}
    per_topic: dict[str, int] = {}
    scene_ids: set[str] = set()
    last_state = last_tf = last_metrics = None
    with open(out, "rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        assert summary is not None and summary.chunk_indexes, "a complete, indexed file"
        for ch in summary.channels.values():
            schema = summary.schemas[ch.schema_id]
            if ch.topic in (fx.SCENE_TOPIC, fx.TF_TOPIC):
                assert ch.message_encoding == "protobuf", ch.topic
                foxglove_check.check_official(schema.name, schema.encoding, schema.data)
            else:
                assert ch.message_encoding == "json", ch.topic
                assert ch.schema_id != 0 and schema.encoding == "jsonschema", ch.topic
        meta = {m.name: m.metadata for m in r.iter_metadata()}
        assert json.loads(meta["zenswarm"]["scenario_json"]) == scenario_to_dict(sc)
        for schema, ch, msg in r.iter_messages(log_time_order=True):
            per_topic[ch.topic] = per_topic.get(ch.topic, 0) + 1
            if ch.message_encoding == "protobuf":
                obj = foxglove_check.decode(schema.name, schema.data, msg.data)
                if ch.topic == fx.SCENE_TOPIC:
                    assert schema.name == "foxglove.SceneUpdate"
                    scene_ids |= {e["id"] for e in obj["entities"]}
                else:
                    assert schema.name == "foxglove.FrameTransforms"
                    last_tf = (msg, obj)
                continue
            v = validators.get(schema.id)
            if v is None:
                s = json.loads(schema.data)
                jsonschema.validators.validator_for(s).check_schema(s)
                v = validators[schema.id] = jsonschema.validators.validator_for(s)(s)
            obj = json.loads(msg.data)
            v.validate(obj)
            if ch.topic == f"swarm/{SWARM}/uav/1/state":
                assert schema.name == "zenswarm.State"
                last_state = (msg, obj)
            elif ch.topic == fx.METRICS_TOPIC:
                assert schema.name == "zenswarm.Metrics"
                last_metrics = (msg, obj)
    # every decodable recorded message is there (only the garbage payload is skipped)
    n_scene = per_topic.pop(fx.SCENE_TOPIC)
    assert per_topic.pop(fx.TF_TOPIC) == per_topic.pop(fx.METRICS_TOPIC) == n_scene
    assert sum(per_topic.values()) == n_written - 1
    assert n_scene == len(range(0, len(sim.series.t), 5))  # 20 Hz of a 100 Hz control loop
    assert {"leader", "trails", "links", "goal", "start", "obstacle/1", "obstacle/2", "d0_band/1", "d0_band/2",
            "uav/1", "uav/2", "uav/3"} <= scene_ids
    # JSON carries the wire fields exactly; log time = base + sim time
    msg, obj = last_state
    k = len(sim.series.t) - 1
    assert obj["t"] == k * 10_000_000 and obj["k"] == "state" and obj["v"] == wire.SCHEMA_VERSION
    assert obj["q"] == sim.series.q[k, 0].tolist()
    assert msg.log_time == WALL0 + obj["t"]
    # the last frame (tick 295): its transforms and figures are the flight's
    kf = (len(sim.series.t) - 1) // 5 * 5
    msg, tf = last_tf
    assert msg.log_time == WALL0 + kf * 10_000_000
    uav3 = next(x for x in tf["transforms"] if x["child_frame_id"] == "uav3")
    assert [uav3["translation"][a] for a in "xyz"] == sim.series.q[kf, 2].tolist()
    msg, m = last_metrics
    h = np.asarray(sc.offsets).reshape(-1, 3)
    fe = np.linalg.norm(sim.series.q[kf] - sim.series.q0[kf] - h, axis=1)
    assert m["t"] == pytest.approx(kf * sc.timing.dt)
    assert [u["formation_error_m"] for u in m["uavs"]] == pytest.approx(fe.tolist())
    assert m["max_tracking_error_m"] == pytest.approx(float(np.max(np.linalg.norm(sim.series.qref[kf] - sim.series.q[kf], axis=1))))
    assert m["failsafe_uavs"] == 0 and m["links"] == []


def test_wire_schemas_reject_what_the_decoder_rejects():
    s = fx.wire_json_schema("state")
    v = jsonschema.Draft202012Validator(s)
    good = {"v": 1, "k": "state", "t": 0, "seq": 0, "q": [0, 0, 0.4], "vel": [0.0] * 3, "rpy": [0.0] * 3, "w": [0.0] * 3}
    v.validate(good)
    for bad in ({**good, "q": [0, 0]}, {**good, "t": -1}, {**good, "extra": 1}, {**good, "k": "ref"}):
        assert not v.is_valid(bad), bad


@pytest.mark.slow
def test_no_metadata_is_a_recording_error(flight, tmp_path):
    sc, sim = flight
    p = tmp_path / "bare.mcap"
    write_recording(p, sc, sim.series.truncated(5), metadata=False)
    with pytest.raises(RecordingError, match="bare.mcap.*zenswarm"):
        report.report_recording(p, tmp_path / "out")
    with pytest.raises(RecordingError, match="bare.mcap"):
        fx.export_foxglove(p, tmp_path / "x.mcap")
    assert cli_main(["report", str(p), "--out", str(tmp_path / "out")]) == 2
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(RecordingError, match="junk.mcap"):
        report.load_recording(junk)
    with pytest.raises(RecordingError, match="missing.mcap"):
        report.load_recording(tmp_path / "missing.mcap")


@pytest.mark.slow
def test_truncated_recording_reports_what_it_holds(flight, tmp_path):
    sc, sim = flight
    p = tmp_path / "cut.mcap"
    # the states without the plant's records: the file is then cut where the last tick it holds is whole
    write_recording(p, sc, sim.series, chunk_size=16 * 1024, plant=False)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    rec = report.load_recording(p)
    assert rec.truncated and "truncated" in rec.truncated
    fl = report.flight_from_recording(rec)
    T = len(fl.series.t)
    assert 0 < T < len(sim.series.t)
    np.testing.assert_array_equal(fl.series.q, sim.series.q[:T])
    res = report.results_from_flight(fl)
    assert res["sim_time_s"] == pytest.approx(T * sc.timing.dt)
    files = report.plot_links(fl, tmp_path / "links.png"), report.plot_clearance(fl.series, sc, tmp_path / "c.png")
    assert all(f.stat().st_size > 20_000 for f in files)


@pytest.mark.swarm
def test_report_cli_warns_on_a_truncated_recording(flight, tmp_path):
    """`zenswarm report` on a file cut short (the recorder was killed): exit 0, figures from what
    was read, and a warning on stderr that says so and which sim time the report covers; payloads
    the recorder did not record (oversize) are named too."""
    import subprocess
    import sys

    sc, sim = flight
    p = tmp_path / "cut.mcap"
    dropped = {f"swarm/{SWARM}/uav/1/state": {"count": 4, "bytes": 400000, "largest": 100000, "limit": 65536}}
    write_recording(
        p, sc, sim.series, chunk_size=16 * 1024,
        extra_metadata={"dropped_oversize_json": json.dumps(dropped), "payload_limit_bytes": "65536"},
    )  # fmt: skip
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    out = tmp_path / "report"
    cli = subprocess.run(
        [sys.executable, "-m", "zenswarm", "report", str(p), "--out", str(out)],
        cwd=EX1.parents[2], capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert cli.returncode == 0, cli.stderr
    err = cli.stderr
    assert f"report: warning: {p}: the recording is incomplete (" in err and "truncated" in err, err
    assert "only what could be read from it is covered" in err
    T = len(report.flight_from_recording(report.load_recording(p)).series.t)
    assert 0 < T < len(sim.series.t)
    assert f"the report covers sim time 0 to {T * sc.timing.dt:.2f} s of the {sc.timing.time_limit_s:g} s time limit" in err, err
    assert "did not record 4 payloads (400000 bytes)" in err and f"swarm/{SWARM}/uav/1/state: 4" in err, err
    assert "Traceback" not in err
    assert all((out / f).exists() for f in report.FIGURES)


@pytest.mark.parametrize(
    "fault_args, why, words_bad",
    [
        ("not json", "fault_args unusable", True),
        (json.dumps(["--no-such-flag", "1"]), "fault_args unusable", True),  # argparse would have exited
        (json.dumps(["--seed", "x"]), "fault_args unusable", True),  # a flag's type refuses it
        (json.dumps(["--link-loss", "1.5"]), "--link-loss", False),  # the words parse; the plan refuses the value
    ],
)
def test_a_recordings_unusable_fault_flags_are_a_recording_error_naming_it(fault_args, why, words_bad, tmp_path):
    """The fault flags a recording carries (metadata fault_args), read once for the report, the
    replay's verify and its seed (zenswarm.bridge.args.recorded_link_faults): unusable words are a
    RecordingError naming the file and what is wrong, never argparse's exit."""
    from zenswarm.bridge.args import recorded_fault_plan, recorded_link_faults
    from zenswarm.scenario.config import load_scenario

    sc = load_scenario(EX1)
    src = tmp_path / "run.mcap"
    with pytest.raises(RecordingError, match=why) as e:
        recorded_fault_plan(fault_args, sc, src)
    assert str(src) in str(e.value)
    if words_bad:
        with pytest.raises(RecordingError, match=why):
            recorded_link_faults(fault_args, src)
    else:
        assert recorded_link_faults(fault_args, src).link_loss == "1.5"


def test_a_recordings_fault_flags_give_the_plan_and_seed_they_were_flown_with(tmp_path):
    """Usable words: the same plan as the flags given to zenswarm up, and the recorded --seed."""
    from zenswarm.bridge.args import add_fault_args, link_faults, recorded_fault_plan, recorded_link_faults
    from zenswarm.scenario.config import load_scenario

    sc = load_scenario(EX1)
    words = ["--link-loss", "0.2", "--link-delay", "50ms", "--partition", "agent:2@1s-2s", "--seed", "7"]
    ap = argparse.ArgumentParser()
    add_fault_args(ap)
    assert recorded_fault_plan(json.dumps(words), sc, tmp_path / "r.mcap") == link_faults(ap.parse_args(words)).plan(sc)
    assert recorded_link_faults(json.dumps(words), tmp_path / "r.mcap").seed == 7
    assert recorded_link_faults("[]", tmp_path / "r.mcap").seed is None
    assert recorded_fault_plan("[]", sc, tmp_path / "r.mcap") is None

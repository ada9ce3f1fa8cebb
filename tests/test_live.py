"""The live view (bridge/live.py, `zenswarm up --live`): a Foxglove WebSocket client, headless.

A short lockstep flight of paper example 1 with ``--live PORT``: a client speaking the Foxglove
WebSocket protocol under its first name only (subprotocol ``foxglove.websocket.v1``, which the
foxglove-sdk server itself refuses: bridge/live.py's relay accepts it) connects, checks the advertised channels and schemas (/scene and /tf
with Foxglove's official protobuf descriptors, the SDK's; /metrics with its JSON Schema),
subscribes to them, and decodes what it receives with those schemas. The flight itself equals
the in-process simulator bit for bit, as without --live.
"""

from __future__ import annotations

import asyncio
import base64
import json
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import websockets

from zenswarm.bus import free_port

import foxglove_check
from swarmtest import ROOT, processes_mentioning, scenario_variant, start_zenswarm, stop_swarm, unique_swarm
from test_swarm import _assert_equal_to_sim

WS_V1 = "foxglove.websocket.v1"
"""The subprotocol the flight's client offers, alone: the protocol's name in its specification
(ws-protocol's docs/spec.md), which independent clients speak."""

TOPICS = {"/scene": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransforms", "/metrics": "zenswarm.Metrics"}


async def watch(
    url: str, deadline: float, on_subscribed: Callable[[], None] | None = None
) -> tuple[dict[int, dict], dict[str, list[tuple[int, bytes]]]]:
    """Connect offering only ``foxglove.websocket.v1`` (retrying until the server listens), take
    the advertisements, subscribe to TOPICS (then call ``on_subscribed``, once), and collect
    messages until the server closes the connection or ``deadline`` (monotonic s)."""
    while True:
        try:
            ws = await websockets.connect(url, subprotocols=[WS_V1], max_size=None)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)
    channels: dict[int, dict] = {}
    got: dict[str, list[tuple[int, bytes]]] = {t: [] for t in TOPICS}
    subs: dict[int, str] = {}
    async with ws:
        assert ws.subprotocol == WS_V1, ws.subprotocol  # the server selected the name offered
        while time.monotonic() < deadline:  # until the server closes, at the end of the flight
            try:
                raw = await asyncio.wait_for(ws.recv(), timeout=max(0.05, deadline - time.monotonic()))
            except (TimeoutError, websockets.ConnectionClosed):
                break
            if isinstance(raw, str):
                op = json.loads(raw)
                if op["op"] == "advertise":
                    new = []
                    for ch in op["channels"]:
                        channels[ch["id"]] = ch
                        if ch["topic"] in TOPICS:
                            sid = len(subs) + 1
                            subs[sid] = ch["topic"]
                            new.append({"id": sid, "channelId": ch["id"]})
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    if on_subscribed is not None and set(subs.values()) == set(TOPICS):
                        on_subscribed()
                        on_subscribed = None
                continue
            assert raw[0] == 0x01, f"opcode {raw[0]}: expected message data"
            sid, stamp = struct.unpack_from("<IQ", raw, 1)
            got[subs[sid]].append((stamp, bytes(raw[13:])))
    return channels, got


def check_channels(channels: dict[int, dict]) -> dict[str, dict]:
    by_topic = {ch["topic"]: ch for ch in channels.values()}
    assert set(TOPICS) <= set(by_topic), sorted(by_topic)
    for topic, name in TOPICS.items():
        ch = by_topic[topic]
        assert ch["schemaName"] == name, (topic, ch["schemaName"])
        if topic == "/metrics":
            assert ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema"
            jsonschema.Draft202012Validator.check_schema(json.loads(ch["schema"]))
        else:
            assert ch["encoding"] == "protobuf"
            foxglove_check.check_official(name, ch["schemaEncoding"], base64.b64decode(ch["schema"]))
    return by_topic


@pytest.mark.swarm
def test_live_view_serves_the_flight_to_a_foxglove_client(tmp_path: Path) -> None:
    scenario = scenario_variant(tmp_path, time_limit_s=2.0)
    out, swarm, port, live = tmp_path / "out", unique_swarm("live"), free_port(), free_port()
    proc = start_zenswarm(
        "up", str(scenario), "--out", str(out), "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}",
        "--progress-every", "5", "--live", str(live),
    )
    try:
        channels, got = asyncio.run(watch(f"ws://127.0.0.1:{live}", time.monotonic() + 120.0))
        text, _ = proc.communicate(timeout=180)
    finally:
        stop_swarm([proc], swarm, port)
    assert proc.returncode in (0, 1), text[-3000:]  # 1: a 2 s flight does not reach the goal (nor does the simulator's)
    assert f"ws://127.0.0.1:{live}" in text and "Foxglove" in text
    by_topic = check_channels(channels)
    for topic in TOPICS:
        assert got[topic], f"no message on {topic}"
    # the messages, decoded with the advertised (official) schemas
    metrics = jsonschema.Draft202012Validator(json.loads(by_topic["/metrics"]["schema"]))
    t_last, bases = -1.0, []
    for stamp, data in got["/metrics"]:
        m = json.loads(data)
        metrics.validate(m)
        assert 0.0 <= m["t"] <= 2.0 and m["t"] >= t_last and len(m["uavs"]) == 3
        assert m["min_clearance_m"] is not None and m["min_clearance_m"] > 0
        t_last = m["t"]
        bases.append(stamp - m["t"] * 1e9)
    assert max(bases) - min(bases) < 1e3, "stamped base + sim time"
    ids: set[str] = set()
    children: set[str] = set()
    for topic in ("/scene", "/tf"):
        ch = by_topic[topic]
        for _, data in got[topic]:
            obj = foxglove_check.decode(ch["schemaName"], base64.b64decode(ch["schema"]), data)
            if topic == "/scene":
                ids |= {e["id"] for e in obj["entities"]}
                assert all(e["frame_id"] == "world" for e in obj["entities"])
            else:
                frames = {x["child_frame_id"]: x for x in obj["transforms"]}
                assert {"uav1", "uav2", "uav3"} <= set(frames)  # the leader's: once its first reference came
                assert all(np.isfinite([x["translation"][a] for a in "xyz"]).all() for x in frames.values())
                children |= set(frames)
    assert "leader" in children
    assert {"obstacle/1", "d0_band/1", "goal", "start", "leader", "uav/1", "uav/3", "links", "trails"} <= ids
    # the same flight as without --live: the in-process simulator's, bit for bit
    _assert_equal_to_sim(scenario, out)
    assert not processes_mentioning(f"ws://127.0.0.1:{live}")


def test_live_view_accepts_both_names_of_the_protocol() -> None:
    """In this process, no flight: the relay in front of the SDK's server selects the name the
    client offers (``foxglove.sdk.v1`` when both are), relays the server's first messages, and
    refuses a client offering neither (HTTP 400, as the SDK does)."""
    from zenswarm.bridge.live import LiveView
    from zenswarm.scenario.config import load_scenario

    view = LiveView(load_scenario(ROOT / "compose" / "scenarios" / "paper_example1.toml"), "names", 0)

    advertised: set[str] = set()

    async def handshake(offer: list[str]) -> tuple[str | None, list[str]]:
        async with websockets.connect(view.url, subprotocols=offer, open_timeout=10) as ws:
            ops = [json.loads(await asyncio.wait_for(ws.recv(), 10)) for _ in range(2)]
            advertised.update(ch["topic"] for op in ops if op["op"] == "advertise" for ch in op["channels"])
            return ws.subprotocol, [op["op"] for op in ops]

    try:
        first = ["serverInfo", "advertise"]
        assert asyncio.run(handshake([WS_V1])) == (WS_V1, first)
        assert asyncio.run(handshake(["foxglove.sdk.v1"])) == ("foxglove.sdk.v1", first)
        assert asyncio.run(handshake([WS_V1, "foxglove.sdk.v1"])) == ("foxglove.sdk.v1", first)
        with pytest.raises(websockets.InvalidStatus) as e:
            asyncio.run(handshake(["not.foxglove"]))
        assert e.value.response.status_code == 400
    finally:
        view.close()
    with pytest.raises(OSError):  # closed: nothing listens any more
        socket.create_connection(("127.0.0.1", view.port), timeout=2).close()
    assert advertised == set(TOPICS)
    assert _layout_topics() <= advertised, "docs/foxglove_layout.json shows a topic the live view does not advertise"


LAYOUT = ROOT / "docs" / "foxglove_layout.json"


def _layout_topics() -> set[str]:
    """The topics docs/foxglove_layout.json refers to (3D panel topics, plot paths, raw message paths)."""
    config = json.loads(LAYOUT.read_text())["configById"]
    topics = set()
    for panel in config.values():
        topics |= set(panel.get("topics", {}))
        paths = [p["value"] for p in panel.get("paths", [])] + ([panel["topicPath"]] if "topicPath" in panel else [])
        topics |= {p.split(".")[0] for p in paths}
    return topics


def test_layout_file_refers_only_to_what_the_live_view_and_export_publish() -> None:
    """docs/foxglove_layout.json, in the format the Foxglove app exports and imports (Layout ->
    Import from file): every panel of the tree configured and every configured panel placed; its
    topics published (the handshake test checks they are advertised); every /metrics field a plot
    reads is in the metrics' JSON Schema; the 3D panel follows the scene's frame."""
    from zenswarm.bridge.scene import METRICS_SCHEMA, WORLD

    layout = json.loads(LAYOUT.read_text())
    config = layout["configById"]

    def leaves(node: object) -> list[str]:
        if isinstance(node, str):
            return [node]
        assert isinstance(node, dict) and node["direction"] in ("row", "column") and 0 < node["splitPercentage"] < 100, node
        return leaves(node["first"]) + leaves(node["second"])

    placed = leaves(layout["layout"])
    assert sorted(placed) == sorted(config), (placed, sorted(config))
    assert _layout_topics() == set(TOPICS)
    props = METRICS_SCHEMA["properties"]
    for panel_id, panel in config.items():
        for p in panel.get("paths", []):
            topic, *fields = p["value"].split(".")
            assert topic == "/metrics" and len(fields) in (1, 2), (panel_id, p["value"])
            head = fields[0].removesuffix("[:]")
            assert head in props, (panel_id, p["value"])
            if len(fields) == 2:  # an array's items: uavs[:].formation_error_m
                assert fields[0].endswith("[:]") and fields[1] in props[head]["items"]["properties"], (panel_id, p["value"])
        if panel_id.startswith("3D!"):
            assert panel["followTf"] == WORLD and set(panel["topics"]) == {"/scene", "/tf"}


def test_live_port_in_use_or_invalid_is_exit_2_before_the_flight(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """In this process: the port is bound before anything starts, so nothing does."""
    from zenswarm.compose.cli import main as cli_main

    scenario = ROOT / "compose" / "scenarios" / "paper_example1.toml"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        taken = s.getsockname()[1]
        assert cli_main(["up", str(scenario), "--out", str(tmp_path / "o"), "--live", str(taken)]) == 2
    err = capsys.readouterr().err
    assert "--live" in err and str(taken) in err and "in use" in err, err
    assert not (tmp_path / "o").exists(), "nothing started, nothing written"
    with pytest.raises(SystemExit) as e:
        cli_main(["up", str(scenario), "--live", "70000"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--live" in err and "70000" in err, err

"""The live view (bridge/views/live.py, `zenswarm up --live`): Foxglove WebSocket clients, headless.

A short lockstep flight of paper example 1 with ``--live PORT``: a client speaking the Foxglove
WebSocket protocol under its first name only (subprotocol ``foxglove.websocket.v1``, which the
foxglove-sdk's own server refuses; the live view's server, bridge/views/live.py's, accepts both names)
connects, checks the advertised channels and schemas (/scene and /tf with Foxglove's official
protobuf descriptors, the SDK's; /metrics with its JSON Schema), subscribes to them, and decodes
what it receives with those schemas. The flight itself equals the in-process simulator bit for
bit, as without --live. Without a flight: the handshake under each name, the one listening port,
the bytes against the export's, subscriptions of two clients, a slow client.
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


def test_live_frames_wait_for_every_uavs_first_state() -> None:
    """In this process, no flight: the first states of a tick reach the supervisor one by one
    (on a loaded host, UAV 1's tick 0 well before UAV 2's); a frame built between them must not
    show a swarm of one (a /tf without uav2, uav3). The view waits for every UAV's first state,
    but not for ever: a UAV still missing more than STALE_S of sim time after the first state is
    left out and the others are shown."""
    from zenswarm.bridge.views.scene import LatestFrames, poses
    from zenswarm.bus import wire
    from zenswarm.scenario.config import load_scenario

    sc = load_scenario(ROOT / "compose" / "scenarios" / "paper_example1.toml")
    keys, dt = wire.Keys("first"), sc.timing.dt
    lf = LatestFrames(sc, "first")
    zero = np.zeros(3)

    def put(k: int, i: int) -> None:
        lf.feed(keys.state(i), wire.encode(wire.State(wire.t_ns(k * dt), k, [float(i), 0.0, 1.0], zero, zero, zero)))

    def frames_of(got: tuple | None) -> set[str]:
        assert got is not None
        return {p.child for p in poses(got[0])}

    put(0, 1)
    assert lf.frame() is None, "UAV 1 alone at tick 0: UAV 2's and 3's first states are on the way"
    put(1, 1)
    put(0, 2)
    assert lf.frame() is None
    put(0, 3)
    assert frames_of(lf.frame()) == {"uav1", "uav2", "uav3"}
    # a UAV that never comes does not hold the view back for ever
    lf = LatestFrames(sc, "first")
    k_stale = int(LatestFrames.STALE_S / dt) + 1
    for k in range(k_stale + 1):
        put(k, 1)
        put(k, 2)
        if k < k_stale:
            assert lf.frame() is None, k
    assert frames_of(lf.frame()) == {"uav1", "uav2"}


def test_live_view_accepts_both_names_of_the_protocol() -> None:
    """In this process, no flight: the live view's server selects the name the client offers
    (``foxglove.sdk.v1`` when both are), sends its first messages, and refuses a client offering
    neither (HTTP 400, as the SDK's server does)."""
    from zenswarm.bridge.views.live import LiveView
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
    from zenswarm.bridge.views.scene import METRICS_SCHEMA, WORLD

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


# ----------------------------------------------------------------------------- the server, without a flight

EX1 = ROOT / "compose" / "scenarios" / "paper_example1.toml"


class Client:
    """A Foxglove WebSocket client for the tests below: the server's hello (``info``, the
    advertised channels ``by_topic``), then every message read kept: ``data`` (subscription id,
    timestamp, payload) and ``statuses``."""

    def __init__(self, ws: websockets.ClientConnection) -> None:
        self.ws = ws
        self.info: dict = {}
        self.by_topic: dict[str, dict] = {}
        self.data: list[tuple[int, int, bytes]] = []
        self.statuses: list[dict] = []

    @classmethod
    async def open(cls, url: str, offer: tuple[str, ...] = (WS_V1,), **kw: object) -> Client:
        c = cls(await websockets.connect(url, subprotocols=list(offer), open_timeout=10, max_size=None, **kw))  # type: ignore[arg-type]
        c.info = json.loads(await asyncio.wait_for(c.ws.recv(), 10))
        advertise = json.loads(await asyncio.wait_for(c.ws.recv(), 10))
        assert (c.info["op"], advertise["op"]) == ("serverInfo", "advertise"), (c.info, advertise)
        c.by_topic = {ch["topic"]: ch for ch in advertise["channels"]}
        return c

    async def send(self, op: str, **fields: object) -> None:
        await self.ws.send(json.dumps({"op": op, **fields}))

    async def subscribe(self, subs: dict[int, str]) -> None:
        await self.send("subscribe", subscriptions=[{"id": sid, "channelId": self.by_topic[t]["id"]} for sid, t in subs.items()])

    async def read(self, timeout: float = 10.0) -> None:
        raw = await asyncio.wait_for(self.ws.recv(), timeout)
        if isinstance(raw, str):
            msg = json.loads(raw)
            assert msg["op"] == "status", msg
            self.statuses.append(msg)
        else:
            assert raw[0] == 0x01, f"opcode {raw[0]}: expected message data"
            sid, stamp = struct.unpack_from("<IQ", raw, 1)
            self.data.append((sid, stamp, bytes(raw[13:])))

    async def until(self, done: Callable[[], bool], timeout: float = 10.0) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            await self.read(max(0.01, deadline - time.monotonic()))

    async def barrier(self) -> dict:
        """Everything sent before has been handled by the server: it answers in order, here an
        op it does not support with an error status (which it sends before any data queued)."""
        n = len(self.statuses)
        await self.send("zenswarm.test.barrier")
        await self.until(lambda: any("barrier" in s["message"] for s in self.statuses[n:]))
        return self.statuses[-1]

    def got(self, sid: int) -> list[tuple[int, bytes]]:
        return [(stamp, payload) for s, stamp, payload in self.data if s == sid]


def feed_tick(view, k: int) -> int:
    """The wire messages of tick ``k`` (every UAV's state and reference, the leader's), then a
    frame published; returns its stamp (ns)."""
    from zenswarm.bus import wire

    t, keys = k * 10_000_000, view.keys
    for i in range(1, view.sc.n + 1):
        q, v = [float(i), 0.01 * k, 1.0], [1.0, 0.0, 0.0]
        view.feed(keys.state(i), wire.encode(wire.State(t, k, q, v, [0.0, 0.0, 0.01 * k], [0.0, 0.0, 0.0])))
        view.feed(keys.ref(i), wire.encode(wire.Ref(t, k, q, v)))
    view.feed(keys.leader_ref, wire.encode(wire.Ref(t, k, [0.0, 0.01 * k, 1.0], [1.0, 0.0, 0.0])))
    assert view.publish()
    return view.base_ns + t


@pytest.fixture
def view():
    from zenswarm.bridge.views.live import LiveView
    from zenswarm.scenario.config import load_scenario

    v = LiveView(load_scenario(EX1), "server", 0)
    try:
        yield v
    finally:
        v.close()


def test_the_live_view_listens_on_one_port_only() -> None:
    """A process serving the live view (a LiveView, as in `up --live` and `replay --live`)
    listens on exactly one socket: the port it prints, on 127.0.0.1, where the Origin check is.
    (Before, the foxglove-sdk's server listened on a second, free, loopback port behind the relay,
    reachable by any local process without that check.)"""
    import subprocess
    import sys

    psutil = pytest.importorskip("psutil", reason="psutil (a dependency of rerun-sdk, zenswarm[rerun]) lists the sockets")
    code = (
        "import sys\n"
        "from zenswarm.bridge.views.live import LiveView\n"
        "from zenswarm.scenario.config import load_scenario\n"
        "view = LiveView(load_scenario(sys.argv[1]), 'ports', 0)\n"
        "print(view.port, flush=True)\n"
        "sys.stdin.readline()\n"
        "view.close()\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(EX1)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdin is not None
        port = int(proc.stdout.readline())

        async def serving() -> str:  # it serves there, a client connected while the sockets are listed
            c = await Client.open(f"ws://127.0.0.1:{port}")
            async with c.ws:
                await c.subscribe({1: "/scene"})
                await c.barrier()
                return str(c.info["name"])

        assert asyncio.run(serving()) == "zenswarm ports"
        socks = psutil.Process(proc.pid).net_connections("inet")
        listening = sorted((c.laddr.ip, c.laddr.port) for c in socks if c.status == psutil.CONN_LISTEN)
        assert listening == [("127.0.0.1", port)], f"listening: {listening}, the live view's port: {port}"
        assert not [c for c in socks if c.type == socket.SOCK_DGRAM], socks
        proc.stdin.write("\n")
        proc.stdin.flush()
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_live_view_sends_what_the_export_writes(view, tmp_path: Path) -> None:
    """The channels the live view advertises and the messages it sends are those ``zenswarm
    export --foxglove`` writes (SceneChannels on the foxglove-sdk's MCAP writer), byte for byte:
    topics, encodings, schema names and schemas, each message's payload and log time."""
    import foxglove
    from mcap.reader import make_reader

    from zenswarm.bridge.views.foxglove_scene import SceneChannels

    made = []
    frame = view.latest.frame

    def spy():
        got = frame()
        made.append(got)
        return got

    view.latest.frame = spy

    async def run() -> Client:
        c = await Client.open(view.url)
        async with c.ws:
            await c.subscribe({1: "/scene", 2: "/tf", 3: "/metrics"})
            await c.barrier()
            for k in (1, 2, 3):
                feed_tick(view, k)
            await c.until(lambda: len(c.data) == 9)
        return c

    c = asyncio.run(run())
    ctx = foxglove.Context()
    with foxglove.open_mcap(tmp_path / "same.mcap", context=ctx):
        channels = SceneChannels(view.sc, ctx)
        for f, diag in made:
            channels.put(f, view.base_ns + f.t_ns, diag)
    with open(tmp_path / "same.mcap", "rb") as fh:
        reader = make_reader(fh)
        written: dict[str, list[tuple[int, bytes]]] = {}
        schemas = {}
        for schema, channel, msg in reader.iter_messages():
            written.setdefault(channel.topic, []).append((msg.log_time, bytes(msg.data)))
            schemas[channel.topic] = (channel.message_encoding, schema.name, schema.encoding, bytes(schema.data))
    assert set(written) == set(c.by_topic) == set(TOPICS)
    for sid, topic in ((1, "/scene"), (2, "/tf"), (3, "/metrics")):
        ch = c.by_topic[topic]
        text = ch["schema"]
        data = base64.b64decode(text) if ch["schemaEncoding"] == "protobuf" else text.encode()
        assert (ch["encoding"], ch["schemaName"], ch["schemaEncoding"], data) == schemas[topic], topic
        assert c.got(sid) == written[topic], topic
    assert len(written["/scene"]) == 3


def test_subscribe_unsubscribe_and_two_clients(view) -> None:
    """Two clients at once, each with subscription ids of its own, get their own streams (the same
    payloads); after an unsubscribe no more data comes for that id, and the id may be used again;
    wrong subscriptions and unknown ops are answered with an error status, the connection stays;
    a client leaving unsubscribes it."""
    server = view.server
    scene_id = None

    async def run() -> None:
        nonlocal scene_id
        a = await Client.open(view.url, (WS_V1,))
        b = await Client.open(view.url, ("foxglove.sdk.v1",))
        assert a.ws.subprotocol == WS_V1 and b.ws.subprotocol == "foxglove.sdk.v1"
        assert a.info["capabilities"] == [] and a.info["name"] == "zenswarm server" and a.info["sessionId"] == b.info["sessionId"]
        scene_id, tf_id = a.by_topic["/scene"]["id"], a.by_topic["/tf"]["id"]
        assert not server.subscribed(scene_id)
        async with a.ws, b.ws:
            await a.subscribe({7: "/scene", 8: "/tf"})
            await b.subscribe({1: "/scene", 2: "/metrics"})
            await a.barrier()
            await b.barrier()
            assert server.subscribed(scene_id)
            s1 = feed_tick(view, 1)
            await a.until(lambda: len(a.data) == 2)
            await b.until(lambda: len(b.data) == 2)
            assert [(sid, stamp) for sid, stamp, _ in a.data] == [(7, s1), (8, s1)]
            assert [(sid, stamp) for sid, stamp, _ in b.data] == [(1, s1), (2, s1)]
            assert a.got(7) == b.got(1)  # the same /scene message

            # wrong subscriptions and ops: an error status each, nothing changes
            n = len(a.statuses)
            await a.subscribe({8: "/metrics"})  # id in use
            await a.send("subscribe", subscriptions=[{"id": 9, "channelId": tf_id}])  # channel subscribed already
            await a.send("subscribe", subscriptions=[{"id": 9, "channelId": 999}])  # no such channel
            await a.send("subscribe", subscriptions=[{"id": -1, "channelId": tf_id}])
            await a.send("getParameters", parameterNames=[])  # a capability the server does not offer
            await a.ws.send("not json")
            await a.ws.send(b"\x01\x00\x00\x00\x00")  # client message data: no clientPublish
            await a.send("unsubscribe", subscriptionIds=[99])  # never subscribed: ignored
            await a.barrier()
            levels = [(s["level"], s["message"]) for s in a.statuses[n:]]
            assert len(levels) == 8 and all(level == 2 for level, _ in levels), levels
            assert "in use" in levels[0][1] and "already" in levels[1][1] and "999" in levels[2][1], levels
            assert "getParameters" in levels[4][1] and "JSON" in levels[5][1] and "binary" in levels[6][1], levels

            await a.send("unsubscribe", subscriptionIds=[7])
            await a.barrier()
            s2 = feed_tick(view, 2)
            await a.until(lambda: len(a.got(8)) == 2)  # /tf of tick 2: sent after its /scene would have been
            await b.until(lambda: len(b.data) == 4)
            assert [stamp for stamp, _ in a.got(7)] == [s1], "data for an unsubscribed id"
            assert [(sid, stamp) for sid, stamp, _ in b.data[2:]] == [(1, s2), (2, s2)]

            await a.subscribe({7: "/scene"})  # the id again, after its unsubscribe
            await a.barrier()
            s3 = feed_tick(view, 3)
            await a.until(lambda: len(a.got(8)) == 3)
            assert [stamp for stamp, _ in a.got(7)] == [s1, s3]
            await b.until(lambda: len(b.data) == 6)
            assert a.got(7)[-1] == b.got(1)[-1]
        await asyncio.sleep(0)

    asyncio.run(run())
    deadline = time.monotonic() + 10
    while server.stats() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert server.stats() == [] and not server.subscribed(scene_id), "the clients left: no one subscribed"
    assert feed_tick(view, 4)  # publishing to no one


def test_a_slow_client_does_not_hold_up_publishing(view) -> None:
    """A client that stops reading: publishing returns at once whatever it does, its queue is
    bounded (the oldest dropped), and another client still gets the newest message; when it goes
    away (reset), the server forgets it."""
    from zenswarm.bridge.views.live import BACKLOG

    server = view.server
    scene = view.channels[0]
    payload = bytes(64 * 1024)
    n = 300

    async def run() -> tuple[float, Client]:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect(("127.0.0.1", view.port))
        slow = await Client.open(view.url, sock=sock, max_queue=1)
        fast = await Client.open(view.url)
        await slow.subscribe({1: "/scene"})
        await fast.subscribe({1: "/scene"})
        await slow.barrier()
        await fast.barrier()
        slow.ws.transport.pause_reading()  # it reads nothing more
        t0 = time.perf_counter()
        for i in range(1, n + 1):
            server.publish(scene.id, i, payload)
        took = time.perf_counter() - t0
        await fast.until(lambda: bool(fast.data) and fast.data[-1][1] == n, timeout=60)
        stamps = [stamp for _, stamp, _ in fast.data]
        assert stamps == sorted(stamps) and all(p == payload for _, _, p in fast.data)
        stats = server.stats()
        assert len(stats) == 2 and all(s["queued"] <= BACKLOG for s in stats), stats
        stuck = [s for s in stats if s["dropped"] > 0 and s["sent"] < n]
        assert stuck, stats  # the slow one: most of its messages dropped, not queued
        slow.ws.transport.abort()
        await fast.ws.close()
        return took, fast

    took, fast = asyncio.run(run())
    assert took < 2.0, f"{n} messages published in {took:.2f} s"
    deadline = time.monotonic() + 10
    while server.stats() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert server.stats() == []

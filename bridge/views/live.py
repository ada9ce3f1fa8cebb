"""The live views: a flying (or replayed) swarm served to a viewer while it flies.

``--live [PORT]``: the Foxglove app, over its WebSocket protocol, served by
:class:`FoxgloveServer` (this module's, on the ``websockets`` package) under both names of the
protocol (subprotocols ``foxglove.sdk.v1`` and ``foxglove.websocket.v1``). ``--live
rerun[:PORT]``: Rerun's own web viewer and gRPC server
(:class:`zenswarm.bridge.views.rerun_scene.RerunLiveView`, extra ``zenswarm[rerun]``). :func:`open_view`
makes either from a :class:`LiveTarget`.

Both keep the newest messages of the swarm (:class:`zenswarm.bridge.views.scene.LatestFrames`, fed
per message: cheap enough for the supervisor's bus loop) and, at most ``hz`` times per wall
second (``maybe_publish``), make a :class:`zenswarm.bridge.views.scene.Frame` of one tick and log it:
here on ``/scene``, ``/tf`` and ``/metrics``, encoded by the code ``zenswarm export --foxglove``
writes files with (:mod:`zenswarm.bridge.views.foxglove_scene`: Foxglove's official message types of
the ``foxglove-sdk`` package, protobuf; the metrics as JSON), the same bytes and schemas. Foxglove
frames are stamped ``base + sim time``, base the wall time the server started, so the app's plots
run in sim time; Rerun's are on its ``sim_time`` timeline.

It runs where the swarm's messages already arrive and never in a swarm process: in the
supervisor of ``zenswarm up --live`` (fed from its bus loop; the flight's processes do not know
it exists, so a lockstep flight is the same bit for bit), or beside a replay (``zenswarm replay
--live``: a Zenoh session of its own, subscribed to the replayed swarm, see :class:`BusViewer`).
The servers listen on 127.0.0.1 only: anyone who reaches them sees the flight.

Why a server of our own, not the foxglove-sdk's (``foxglove.start_server``): the SDK's server
(every release on PyPI, 0.5.0 to 0.30.3, tried) accepts a client only if it offers
``foxglove.sdk.v1``, the protocol's current name, and answers HTTP 400 to one offering only
``foxglove.websocket.v1``, its first name (the same messages, renamed by Foxglove), while other
clients of the protocol (older Lichtblick releases, roslibjs-foxglove, ws-protocol's clients,
tests written against the specification) offer only the old name; and it cannot check who
connects, so a browser page of any site could watch the flight. A relay in front of it, on a
free loopback port of its own, left that port open to every local process. The live view needs
only the publishing side of the protocol (``serverInfo``, ``advertise``, ``subscribe``,
``unsubscribe``, binary ``messageData``): :class:`FoxgloveServer` speaks it on the one port the
user asked for, with the ``Origin`` check (:data:`ALLOWED_ORIGINS`) in front of every client.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import concurrent.futures
import json
import os
import re
import struct
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from zenswarm.bridge.views.scene import PacedView
from zenswarm.errors import ScenarioError

__all__ = [
    "DEFAULT_PORT",
    "LIVE_HZ",
    "SUBPROTOCOLS",
    "ALLOWED_ORIGINS",
    "live_port",
    "live_target",
    "LiveTarget",
    "LIVE_HELP",
    "LiveView",
    "open_view",
    "ChannelInfo",
    "scene_channels",
    "FoxgloveServer",
    "BusViewer",
    "open_in_app",
]

DEFAULT_PORT = 8765
"""``--live`` without a port: the Foxglove app's default WebSocket port."""

LIVE_HZ = 10.0
"""Frames per wall second at most (the newest state at each; a lockstep flight computes faster
than real time, so its frames are further apart in sim time)."""

HOST = "127.0.0.1"

SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
"""The names of the protocol the live view accepts, the preferred first: a client offering both
(the Foxglove app) gets ``foxglove.sdk.v1``; one offering only the old name gets that."""

ALLOWED_ORIGINS: tuple[Any, ...] = (
    None,  # no Origin header: not a browser (the desktop apps' native clients, scripts, tests)
    "null",  # a page from a file, a sandboxed frame
    "file://",
    re.compile(r"https?://(localhost|127\.0\.0\.1|\[::1\])(:\d+)?"),  # a viewer served from this machine
    re.compile(r"https://([a-z0-9-]+\.)*foxglove\.dev"),  # the Foxglove web app
)
"""``Origin`` headers the live view accepts (:class:`FoxgloveServer`; values or full-match
patterns). A web page can open a WebSocket to 127.0.0.1 from any site the user visits (WebSockets
are not bound by the same-origin policy): one from another site is refused with HTTP 403."""

def live_port(text: str) -> int:
    """argparse type of a TCP port 1..65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a TCP port number (1..65535)") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port}: a TCP port is 1..65535")
    return port


@dataclass(frozen=True)
class LiveTarget:
    """What ``--live`` asks for: ``viewer`` ``foxglove`` (the Foxglove WebSocket server on
    ``port``) or ``rerun`` (Rerun's web viewer on ``port``, its gRPC server beside it)."""

    viewer: str
    port: int


RERUN_WEB_PORT = 9090
"""``--live rerun`` without a port: the Rerun web viewer's default HTTP port."""

LIVE_HELP = (
    f"PORT (default {DEFAULT_PORT}): serve the flight to the Foxglove app over its WebSocket protocol on "
    f"ws://127.0.0.1:PORT; rerun[:PORT]: serve Rerun's web viewer on http://127.0.0.1:PORT (default {RERUN_WEB_PORT}) "
    "and its gRPC data server (for the native viewer too), URL printed (needs zenswarm[rerun]). "
    "Both show the 3D scene, attitudes, errors, clearance, failsafe and links (docs/live.md); loopback only"
)


def live_target(text: str) -> LiveTarget:
    """argparse type of ``--live [PORT | rerun | rerun:PORT]``."""
    if text == "rerun":
        return LiveTarget("rerun", RERUN_WEB_PORT)
    if text.startswith("rerun:"):
        return LiveTarget("rerun", live_port(text[len("rerun:") :]))
    if not text.strip().isdigit():
        raise argparse.ArgumentTypeError(f"{text!r}: expected a TCP port (Foxglove), rerun or rerun:PORT")
    return LiveTarget("foxglove", live_port(text))


FOXGLOVE_DEFAULT = LiveTarget("foxglove", DEFAULT_PORT)
"""``--live`` alone: the Foxglove view on its default port."""


def open_in_app(url: str) -> str:
    """How to open ``url`` in the Foxglove app (the line the commands print)."""
    return f"live view on {url}: in the Foxglove app, Open connection -> Foxglove WebSocket -> {url} (layout: docs/foxglove_layout.json)"


class LiveView(PacedView):
    """A Foxglove WebSocket server showing scenario ``sc`` flown by swarm ``swarm``. Binds at
    construction: a port in use raises :class:`ScenarioError` naming ``flag`` (exit 2, before
    the flight). ``port`` 0: any free port (see :attr:`port`)."""

    viewer = "foxglove"

    def __init__(self, sc: Any, swarm: str, port: int, *, flag: str = "--live", hz: float = LIVE_HZ, trail_s: float = 10.0) -> None:
        from zenswarm.bridge.views.foxglove_scene import frame_transforms, scene_update
        from zenswarm.bridge.views.scene import metrics, palette

        super().__init__(sc, swarm, hz, trail_s)
        self._encoders = (scene_update, frame_transforms, metrics)
        self.colors = palette(sc.n)
        self.channels = scene_channels()
        try:
            self.server = FoxgloveServer(HOST, port, f"zenswarm {swarm}", self.channels)
        except OSError as e:  # "address already in use"
            reason = os.strerror(e.errno) if e.errno else str(e)
            raise ScenarioError(flag, f"cannot serve the live view on {HOST}:{port}: {reason}") from None
        self.port: int = self.server.port
        self.url = f"ws://{HOST}:{self.port}"
        self.base_ns = time.time_ns()

    def how_to_open(self) -> str:
        """The line the commands print: where the view is and how to open it."""
        return open_in_app(self.url)

    def publish(self) -> bool:
        """Send a frame of the newest messages to the clients subscribed to its channels (False:
        no state yet, or none newer than the last frame). Never waits for a client: the frame is
        encoded here (a channel nobody is subscribed to is not), queued and sent by the server's
        thread."""
        got = self.latest.frame()
        if got is None:
            return False
        f, diag = got
        stamp = self.base_ns + f.t_ns
        scene_update, frame_transforms, metrics = self._encoders
        scene, tf, met = self.channels
        server = self.server
        if server.subscribed(scene.id):
            server.publish(scene.id, stamp, scene_update(f, self.sc, stamp, self.colors).encode())
        if server.subscribed(tf.id):
            server.publish(tf.id, stamp, frame_transforms(f, stamp).encode())
        if server.subscribed(met.id):  # as SceneChannels.put writes it (zenswarm export --foxglove)
            server.publish(met.id, stamp, json.dumps(metrics(f, self.sc, diag), separators=(",", ":"), allow_nan=False).encode())
        self.frames += 1
        return True

    def close(self) -> None:
        """Stop the server (clients are disconnected)."""
        self.server.close()


@dataclass(frozen=True)
class ChannelInfo:
    """A channel the server advertises: ``id``, ``topic``, message ``encoding``, and its schema
    (``schema_name``, ``schema_encoding``, ``schema``: the bytes, e.g. a protobuf
    FileDescriptorSet or a JSON Schema's text)."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: bytes

    def advertised(self) -> dict[str, Any]:
        """This channel in an ``advertise`` message: a binary schema (protobuf, flatbuffer) as
        base64, a text one (JSON Schema) as it is."""
        binary = self.schema_encoding in ("protobuf", "flatbuffer")
        return {
            "id": self.id,
            "topic": self.topic,
            "encoding": self.encoding,
            "schemaName": self.schema_name,
            "schema": base64.b64encode(self.schema).decode("ascii") if binary else self.schema.decode("utf-8"),
            "schemaEncoding": self.schema_encoding,
        }


def scene_channels() -> tuple[ChannelInfo, ChannelInfo, ChannelInfo]:
    """``/scene``, ``/tf`` and ``/metrics`` as ``zenswarm export --foxglove`` writes them
    (:class:`zenswarm.bridge.views.foxglove_scene.SceneChannels`): Foxglove's official protobuf schemas
    of ``foxglove.SceneUpdate`` and ``foxglove.FrameTransforms`` from the foxglove-sdk (the
    FileDescriptorSets its message types carry), and the metrics' JSON Schema serialised as the
    SDK's ``Channel`` does."""
    from foxglove import messages as fm

    from zenswarm.bridge.views.scene import METRICS_SCHEMA, METRICS_TOPIC, SCENE_TOPIC, TF_TOPIC

    scene, tf = fm.SceneUpdate.get_schema(), fm.FrameTransforms.get_schema()
    return (
        ChannelInfo(1, SCENE_TOPIC, "protobuf", scene.name, scene.encoding, bytes(scene.data)),
        ChannelInfo(2, TF_TOPIC, "protobuf", tf.name, tf.encoding, bytes(tf.data)),
        ChannelInfo(3, METRICS_TOPIC, "json", str(METRICS_SCHEMA["title"]), "jsonschema", json.dumps(METRICS_SCHEMA).encode()),
    )


MESSAGE_DATA = 0x01
"""Opcode of a binary ``messageData`` frame: uint32 LE subscription id, uint64 LE timestamp (ns), payload."""

_MESSAGE_DATA_HEADER = struct.Struct("<BIQ")

STATUS_INFO, STATUS_WARNING, STATUS_ERROR = 0, 1, 2
"""Levels of a ``status`` message."""

BACKLOG = 64
"""Messages queued per client at most (about 2 s of frames at :data:`LIVE_HZ`, three channels):
a client that reads slower than frames come loses the oldest (counted as ``dropped``)."""

STATUS_BACKLOG = 16
"""``status`` answers queued per client at most (a client sending garbage and not reading)."""

MAX_CLIENT_MESSAGE = 1 << 20
"""The largest message a client may send, bytes (it sends only subscribe/unsubscribe): larger closes it (1009)."""


def _uint32(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and 0 <= x < 1 << 32


class _Client:
    """One connection's subscriptions (``subs``: subscription id -> channel id, ``by_channel``:
    the reverse) and its outgoing queues, drained in order by :meth:`run` (status answers first,
    then message data; at most :data:`BACKLOG` messages, the oldest dropped)."""

    def __init__(self, ws: Any, backlog: int) -> None:
        self.ws = ws
        self.subs: dict[int, int] = {}
        self.by_channel: dict[int, int] = {}
        self.control: deque[str] = deque(maxlen=STATUS_BACKLOG)
        self.data: deque[tuple[int, bytes]] = deque()
        self.backlog = backlog
        self.sent = 0
        self.dropped = 0
        self.wake = asyncio.Event()

    def put(self, sid: int, frame: bytes) -> None:
        if len(self.data) >= self.backlog:
            self.data.popleft()
            self.dropped += 1
        self.data.append((sid, frame))
        self.wake.set()

    def status(self, level: int, message: str) -> None:
        self.control.append(json.dumps({"op": "status", "level": level, "message": message}))
        self.wake.set()

    def forget(self, sid: int) -> None:
        """Unsubscribed: nothing queued for ``sid`` is sent any more."""
        self.data = deque(item for item in self.data if item[0] != sid)

    async def run(self) -> None:
        from websockets import ConnectionClosed

        try:
            while True:
                await self.wake.wait()
                self.wake.clear()
                while self.control or self.data:
                    if self.control:
                        await self.ws.send(self.control.popleft())
                    else:
                        await self.ws.send(self.data.popleft()[1])
                        self.sent += 1
        except ConnectionClosed:
            pass


class FoxgloveServer:
    """The server side of the Foxglove WebSocket protocol, publish only, on the ``websockets``
    package: on ``host``:``port`` (0: any free port, see :attr:`port`), under both names of the
    protocol (:data:`SUBPROTOCOLS`; a client offering neither: HTTP 400), refusing a browser page
    from a site not in :data:`ALLOWED_ORIGINS` (HTTP 403).

    Each client is sent ``serverInfo`` (no capability: it may only subscribe) and one
    ``advertise`` of ``channels``; it may ``subscribe`` (ids of its choosing, one per channel) and
    ``unsubscribe``; anything else is answered with an error ``status``. :meth:`publish`, from any
    thread, queues a message for the clients subscribed to its channel and returns at once: each
    client has a queue of :data:`BACKLOG` messages, drained by a task of its own, so a slow client
    loses its oldest messages and slows no one else. Runs an event loop in a daemon thread; binds
    at construction (``OSError`` if it cannot); :meth:`close` disconnects every client and stops."""

    def __init__(self, host: str, port: int, name: str, channels: Sequence[ChannelInfo], *, backlog: int = BACKLOG) -> None:
        import websockets
        from websockets.asyncio.server import serve

        self.channels = {c.id: c for c in channels}
        self.backlog = backlog
        self._clients: set[_Client] = set()
        self._subscribers = dict.fromkeys(self.channels, 0)  # clients subscribed, per channel
        self._closed = False
        info = {
            "op": "serverInfo",
            "name": name,
            "capabilities": [],
            "supportedEncodings": [],
            "metadata": {"server": f"zenswarm.bridge.live (websockets {websockets.__version__})"},
            "sessionId": str(time.time_ns()),
        }
        self._hello = (json.dumps(info), json.dumps({"op": "advertise", "channels": [c.advertised() for c in channels]}))
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="live-server", daemon=True)
        self._thread.start()

        async def start() -> Any:
            return await serve(self._handle, host, port, subprotocols=list(SUBPROTOCOLS), compression=None,  # type: ignore[arg-type]
                               max_size=MAX_CLIENT_MESSAGE, origins=list(ALLOWED_ORIGINS), close_timeout=2.0)

        try:
            self._server = asyncio.run_coroutine_threadsafe(start(), self._loop).result(timeout=10.0)
        except BaseException:
            self._stop_loop()
            raise
        self.port: int = self._server.sockets[0].getsockname()[1]

    # ------------------------------------------------------------------ publishing (any thread)

    def subscribed(self, channel_id: int) -> bool:
        """Whether some client is subscribed to ``channel_id`` now (a message on a channel nobody
        is subscribed to need not be made)."""
        return self._subscribers.get(channel_id, 0) > 0

    def publish(self, channel_id: int, log_time_ns: int, payload: bytes) -> None:
        """Send ``payload`` on ``channel_id``, stamped ``log_time_ns``, to every client subscribed
        to it. Returns at once, from any thread (a no-op once closed)."""
        if self._closed:
            return
        try:
            self._loop.call_soon_threadsafe(self._fan_out, channel_id, log_time_ns, payload)
        except RuntimeError:  # the loop closed meanwhile
            pass

    def _fan_out(self, channel_id: int, log_time_ns: int, payload: bytes) -> None:
        for c in self._clients:
            sid = c.by_channel.get(channel_id)
            if sid is not None:
                c.put(sid, _MESSAGE_DATA_HEADER.pack(MESSAGE_DATA, sid, log_time_ns) + payload)

    def stats(self) -> list[dict[str, int]]:
        """Per connected client: its subscriptions, messages queued, sent and dropped."""
        async def snapshot() -> list[dict[str, int]]:
            return [{"subscriptions": len(c.subs), "queued": len(c.data), "sent": c.sent, "dropped": c.dropped} for c in self._clients]

        return asyncio.run_coroutine_threadsafe(snapshot(), self._loop).result(timeout=10.0)

    # ------------------------------------------------------------------ a client (the loop's thread)

    async def _handle(self, ws: Any) -> None:
        from websockets import ConnectionClosed

        client = _Client(ws, self.backlog)
        sender: asyncio.Future[None] | None = None
        try:
            for text in self._hello:
                await ws.send(text)
            self._clients.add(client)
            sender = asyncio.ensure_future(client.run())
            async for message in ws:
                if isinstance(message, str):
                    self._on_text(client, message)
                else:
                    client.status(STATUS_ERROR, "binary messages are not supported: this server only publishes")
        except ConnectionClosed:
            pass
        finally:
            self._clients.discard(client)
            for channel_id in client.by_channel:
                self._subscribers[channel_id] -= 1
            client.by_channel.clear()
            if sender is not None:
                sender.cancel()

    def _on_text(self, client: _Client, text: str) -> None:
        try:
            msg = json.loads(text)
        except ValueError as e:
            client.status(STATUS_ERROR, f"invalid message: not JSON ({e})")
            return
        op = msg.get("op") if isinstance(msg, dict) else None
        if op == "subscribe":
            self._subscribe(client, msg.get("subscriptions"))
        elif op == "unsubscribe":
            self._unsubscribe(client, msg.get("subscriptionIds"))
        else:
            what = f"op {str(op)[:64]!r}" if op is not None else "a message without an op"
            client.status(STATUS_ERROR, f"unsupported: {what} (this server only publishes: subscribe, unsubscribe)")

    def _subscribe(self, client: _Client, subs: Any) -> None:
        if not isinstance(subs, list):
            client.status(STATUS_ERROR, "invalid subscribe: subscriptions must be a list")
            return
        for s in subs:
            sid: Any = s.get("id") if isinstance(s, dict) else None
            cid: Any = s.get("channelId") if isinstance(s, dict) else None
            if not (_uint32(sid) and _uint32(cid)):
                client.status(STATUS_ERROR, "invalid subscribe: each subscription needs an id and a channelId (uint32)")
            elif cid not in self.channels:
                client.status(STATUS_ERROR, f"unknown channel id {cid}")
            elif sid in client.subs:
                client.status(STATUS_ERROR, f"subscription id {sid} is in use (channel {client.subs[sid]})")
            elif cid in client.by_channel:
                client.status(STATUS_ERROR, f"channel {cid} is subscribed already (subscription {client.by_channel[cid]})")
            else:
                client.subs[sid] = cid
                client.by_channel[cid] = sid
                self._subscribers[cid] += 1

    def _unsubscribe(self, client: _Client, ids: Any) -> None:
        if not isinstance(ids, list):
            client.status(STATUS_ERROR, "invalid unsubscribe: subscriptionIds must be a list")
            return
        for sid in ids:
            cid = client.subs.pop(sid, None) if _uint32(sid) else None
            if cid is None:
                continue  # not subscribed (any more): nothing to do
            del client.by_channel[cid]
            self._subscribers[cid] -= 1
            client.forget(sid)

    # ------------------------------------------------------------------ stopping

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5.0)
        if not self._thread.is_alive():
            self._loop.close()

    def close(self) -> None:
        """Disconnect every client and stop listening (again: nothing)."""
        if self._closed:
            return
        self._closed = True

        async def stop() -> None:
            self._server.close()
            await self._server.wait_closed()

        try:
            asyncio.run_coroutine_threadsafe(stop(), self._loop).result(timeout=10.0)
        except (concurrent.futures.TimeoutError, TimeoutError):
            pass
        finally:
            self._stop_loop()


class BusViewer:
    """A :class:`LiveView` fed from a Zenoh session of its own (``zenswarm replay --live``): a
    client of ``connect`` subscribed to ``swarm/<swarm>/**``, drained by a thread that publishes
    frames at the view's rate. :meth:`close` stops it."""

    def __init__(self, view: LiveView, connect: list[str]) -> None:
        import zenoh

        from zenswarm import bus

        self.view = view
        self._cm = bus.open_session(bus.client_config(connect), handle_signals=False)
        session = self._cm.__enter__()
        self._sub = session.declare_subscriber(view.keys.all, zenoh.handlers.FifoChannel(1_000_000))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            while (s := self._sub.try_recv()) is not None:
                self.view.feed(str(s.key_expr), s.payload.to_bytes())
            self.view.maybe_publish(time.monotonic())
            self._stop.wait(0.02)

    def close(self) -> None:
        """Publish the last frame, stop the thread, the subscriber, the session and the server."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.view.publish()
        try:
            self._sub.undeclare()
        finally:
            self._cm.__exit__(None, None, None)
            self.view.close()


def open_view(target: LiveTarget, sc: Any, swarm: str, *, flag: str = "--live") -> Any:
    """The live view ``target`` asks for: a Foxglove :class:`LiveView`, or Rerun's web viewer and
    gRPC server (:class:`zenswarm.bridge.views.rerun_scene.RerunLiveView`). Bound or started now: a
    port in use, or Rerun not installed, raises :class:`ScenarioError` naming ``flag``."""
    if target.viewer == "rerun":
        from zenswarm.bridge.views.rerun_scene import RerunLiveView, require_rerun

        require_rerun(flag)
        return RerunLiveView(sc, swarm, target.port, flag=flag)
    return LiveView(sc, swarm, target.port, flag=flag)


def replay_viewer(path: Path, swarm: str | None, target: LiveTarget, connect: list[str]) -> BusViewer:
    """``zenswarm replay FILE --live [PORT|rerun]``: the live view of the swarm the replay
    publishes (``swarm``, or the recorded one), scenario from the recording's metadata."""
    from zenswarm.bridge.reports.flight import load_recording

    rec = load_recording(path)
    view = open_view(target, rec.scenario, swarm or rec.swarm)
    print(view.how_to_open(), flush=True)
    return BusViewer(view, connect)

"""The live views: a flying (or replayed) swarm served to a viewer while it flies.

``--live [PORT]``: the Foxglove app, over its WebSocket protocol, by the ``foxglove-sdk``
package's server, under both names of the protocol (subprotocols ``foxglove.sdk.v1`` and
``foxglove.websocket.v1``, see :class:`SubprotocolRelay`). ``--live rerun[:PORT]``: Rerun's own
web viewer and gRPC server (:class:`zenswarm.bridge.rerun_scene.RerunLiveView`, extra
``zenswarm[rerun]``). :func:`open_view` makes either from a :class:`LiveTarget`.

Both keep the newest messages of the swarm (:class:`zenswarm.bridge.scene.LatestFrames`, fed
per message: cheap enough for the supervisor's bus loop) and, at most ``hz`` times per wall
second (``maybe_publish``), make a :class:`zenswarm.bridge.scene.Frame` of one tick and log it:
here on ``/scene``, ``/tf`` and ``/metrics`` with the scene code ``zenswarm export --foxglove``
writes files with (:class:`zenswarm.bridge.foxglove_scene.SceneChannels`). Foxglove frames are
stamped ``base + sim time``, base the wall time the server started, so the app's plots run in
sim time; Rerun's are on its ``sim_time`` timeline.

It runs where the swarm's messages already arrive and never in a swarm process: in the
supervisor of ``zenswarm up --live`` (fed from its bus loop; the flight's processes do not know
it exists, so a lockstep flight is the same bit for bit), or beside a replay (``zenswarm replay
--live``: a Zenoh session of its own, subscribed to the replayed swarm, see :class:`BusViewer`).
The servers listen on 127.0.0.1 only: anyone who reaches them sees the flight.

Why a relay: the SDK's server (every foxglove-sdk release on PyPI, 0.5.0 to 0.30.3, tried) accepts
a client only if it offers ``foxglove.sdk.v1``, the protocol's current name, and answers HTTP 400 to
one offering only ``foxglove.websocket.v1``, its first name (the same messages, renamed by
Foxglove); no option of ``start_server`` changes that. The Foxglove app offers both, but other
clients of the protocol (older Lichtblick releases, roslibjs-foxglove, ws-protocol's clients, tests
written against the specification) offer only the old name. So the SDK's server listens on a
free loopback port of its own and :class:`SubprotocolRelay`, built on the maintained
``websockets`` package, listens on the port the user asked for, accepts either name and passes
every WebSocket message both ways unchanged to a connection of its own to the SDK's server.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import os
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from zenswarm.bridge.scene import PacedView
from zenswarm.errors import ScenarioError

__all__ = [
    "DEFAULT_PORT",
    "LIVE_HZ",
    "SUBPROTOCOLS",
    "live_port",
    "live_target",
    "LiveTarget",
    "LIVE_HELP",
    "LiveView",
    "open_view",
    "SubprotocolRelay",
    "BusViewer",
    "open_in_app",
]

DEFAULT_PORT = 8765
"""``--live`` without a port: the Foxglove app's default WebSocket port."""

LIVE_HZ = 10.0
"""Frames per wall second at most (the newest state at each; a lockstep flight computes faster
than real time, so its frames are further apart in sim time)."""

HOST = "127.0.0.1"

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
"""The only subprotocol the foxglove-sdk server accepts."""

SUBPROTOCOLS = (SDK_SUBPROTOCOL, "foxglove.websocket.v1")

ALLOWED_ORIGINS: tuple[Any, ...] = (
    None,  # no Origin header: not a browser (the desktop apps' native clients, scripts, tests)
    "null",  # a page from a file, a sandboxed frame
    "file://",
    re.compile(r"https?://(localhost|127\.0\.0\.1|\[::1\])(:\d+)?"),  # a viewer served from this machine
    re.compile(r"https://([a-z0-9-]+\.)*foxglove\.dev"),  # the Foxglove web app
)
"""``Origin`` headers the relay accepts (:class:`SubprotocolRelay`; values or full-match patterns).
A web page can open a WebSocket to 127.0.0.1 from any site the user visits (WebSockets are not
bound by the same-origin policy): one from another site is refused with HTTP 403."""
"""The names of the protocol the live view accepts, the preferred first: a client offering both
(the Foxglove app) gets ``foxglove.sdk.v1``; one offering only the old name gets that."""


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
        import foxglove

        from zenswarm.bridge.foxglove_scene import SceneChannels

        super().__init__(sc, swarm, hz, trail_s)
        self.context = foxglove.Context()  # the server's own: no other channel of this process on it
        # the channels first: a client that connects at once is advertised all three in one go
        # (a channel created after the server started can race a client's subscription to it)
        self.channels = SceneChannels(sc, self.context, trail_s)
        # the SDK's server on a free loopback port; clients come through the relay (module docstring)
        self.server = foxglove.start_server(name=f"zenswarm {swarm}", host=HOST, port=0, context=self.context)
        try:
            self.relay = SubprotocolRelay(HOST, port, f"ws://{HOST}:{self.server.port}")
        except OSError as e:  # "address already in use"
            self.server.stop()
            reason = os.strerror(e.errno) if e.errno else str(e)
            raise ScenarioError(flag, f"cannot serve the live view on {HOST}:{port}: {reason}") from None
        self.port: int = self.relay.port
        self.url = f"ws://{HOST}:{self.port}"
        self.base_ns = time.time_ns()

    def how_to_open(self) -> str:
        """The line the commands print: where the view is and how to open it."""
        return open_in_app(self.url)

    def publish(self) -> bool:
        """Log a frame of the newest messages (False: no state yet, or none newer than the last frame)."""
        got = self.latest.frame()
        if got is None:
            return False
        f, diag = got
        self.channels.put(f, self.base_ns + f.t_ns, diag)
        self.frames += 1
        return True

    def close(self) -> None:
        """Stop the relay and the server (clients are disconnected)."""
        try:
            self.relay.close()
        finally:
            self.server.stop()


async def _pipe(src: Any, dst: Any) -> None:
    """Send every message of WebSocket ``src`` to ``dst``, unchanged, until either closes."""
    import websockets

    try:
        async for message in src:
            await dst.send(message)
    except websockets.ConnectionClosed:
        pass


class SubprotocolRelay:
    """A WebSocket server (the ``websockets`` package's) on ``host``:``port`` (0: any free port,
    see :attr:`port`) accepting the subprotocols :data:`SUBPROTOCOLS`; each client it accepts
    gets a connection of its own to ``upstream`` (the foxglove-sdk server, subprotocol
    ``foxglove.sdk.v1``) and every message passes both ways unchanged, text and binary alike:
    the protocol is the same under both names. A slow client slows its upstream connection, so
    the SDK's per-client backlog drops the oldest messages as it does for a direct client. A
    browser page from a site not in :data:`ALLOWED_ORIGINS` is refused (HTTP 403). Runs
    an event loop in a daemon thread; binds at construction (``OSError`` if it cannot);
    :meth:`close` disconnects every client and stops it."""

    def __init__(self, host: str, port: int, upstream: str) -> None:
        from websockets.asyncio.server import serve

        self.upstream = upstream
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="live-relay", daemon=True)
        self._thread.start()

        async def start() -> Any:
            return await serve(self._handle, host, port, subprotocols=list(SUBPROTOCOLS), compression=None, max_size=None,  # type: ignore[arg-type]
                               origins=list(ALLOWED_ORIGINS))

        try:
            self._server = asyncio.run_coroutine_threadsafe(start(), self._loop).result(timeout=10.0)
        except BaseException:
            self._stop_loop()
            raise
        self.port: int = self._server.sockets[0].getsockname()[1]

    async def _handle(self, client: Any) -> None:
        from websockets import WebSocketException
        from websockets.asyncio.client import connect

        try:
            async with connect(self.upstream, subprotocols=[SDK_SUBPROTOCOL], compression=None, max_size=None) as up:  # type: ignore[list-item]
                tasks = [asyncio.ensure_future(_pipe(client, up)), asyncio.ensure_future(_pipe(up, client))]
                _, pending = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                for t in pending:
                    t.cancel()
        except (OSError, WebSocketException, TimeoutError):
            pass  # the SDK's server stopped: the client is closed as this returns

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5.0)
        if not self._thread.is_alive():
            self._loop.close()

    def close(self) -> None:
        """Disconnect every client and stop listening."""
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
    gRPC server (:class:`zenswarm.bridge.rerun_scene.RerunLiveView`). Bound or started now: a
    port in use, or Rerun not installed, raises :class:`ScenarioError` naming ``flag``."""
    if target.viewer == "rerun":
        from zenswarm.bridge.rerun_scene import RerunLiveView, require_rerun

        require_rerun(flag)
        return RerunLiveView(sc, swarm, target.port, flag=flag)
    return LiveView(sc, swarm, target.port, flag=flag)


def replay_viewer(path: Path, swarm: str | None, target: LiveTarget, connect: list[str]) -> BusViewer:
    """``zenswarm replay FILE --live [PORT|rerun]``: the live view of the swarm the replay
    publishes (``swarm``, or the recorded one), scenario from the recording's metadata."""
    from zenswarm.bridge.report import load_recording

    rec = load_recording(path)
    view = open_view(target, rec.scenario, swarm or rec.swarm)
    print(view.how_to_open(), flush=True)
    return BusViewer(view, connect)

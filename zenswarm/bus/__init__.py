"""Thin Zenoh helpers: configs, sessions that always close, liveliness (eclipse-zenoh 1.10.x).

This is where messages cross the network; payloads are built and checked by :mod:`zenswarm.bus.wire`,
the keys they travel on are :mod:`zenswarm.bus.keys`.

Topology: one router per swarm (``mode: router``, possibly inside a Python process, see
``python -m zenswarm.compose.router``) and every swarm process a client of it. Multicast scouting and
gossip are off everywhere, so a session only ever talks to the endpoints it was given: two
swarms on different router ports never see each other, even with the same swarm name.

Exiting cleanly (observed with eclipse-zenoh 1.10.2; ``tests/test_bus.py`` checks the safe pattern):

* A subscriber declared with a plain Python callable runs it on a *non-daemon* Python thread
  (``pyo3-closure``) that ends only when the subscriber is undeclared or the session closed.
  The interpreter joins non-daemon threads *before* ``atexit`` hooks run, so a process that
  reaches the end of its main module with such a session open hangs forever, and
  ``atexit.register(session.close)`` does not help. :func:`open_session` closes on every exit
  path of its ``with`` block and also registers the close with ``threading._register_atexit``
  (runs before the join) for sessions that escape it.
* Subscribers with a channel handler (``FifoChannel``/``RingChannel``), liveliness tokens,
  publishers and ``Callback(f, indirect=False)`` create no Python thread and do not hang.
* SIGTERM's default action kills the process without any cleanup (the router then drops its
  tokens at once, as for SIGKILL). :func:`open_session` installs SIGTERM/SIGINT handlers that
  raise :class:`Shutdown` (a ``SystemExit``) in the main thread, so the ``with`` block unwinds
  and the session is closed. A blocking ``recv()`` on a zenoh channel checks for signals every
  100 ms, so it is interrupted too; a closed session wakes a blocked ``recv()`` with ``ZError``.
* Publishers, channel subscribers and liveliness tokens are undeclared when their Python object
  is garbage-collected: keep references. Callback subscribers live until the session closes.
* Sessions do not survive ``fork``: open them in the process that uses them.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from types import FrameType
from typing import Any, Final, Protocol, cast

import zenoh

from zenswarm.bus.keys import InvalidKeyError, Keys, validate_process
from zenswarm.errors import ScenarioError, ZenswarmError

__all__ = [
    "DEFAULT_CONNECT_TIMEOUT_S",
    "TX_QUEUE_BATCHES",
    "ZENOH_RUNTIME_DEFAULT",
    "use_swarm_runtime",
    "zenoh_threads",
    "ZENOH_RUNTIME_ROUTER",
    "BusError",
    "Shutdown",
    "free_port",
    "free_udp_block",
    "tcp_endpoint",
    "check_endpoint_syntax",
    "apply_settings",
    "router_config",
    "client_config",
    "close_at_exit",
    "Undeclarable",
    "undeclare",
    "direct_callback",
    "open_session",
    "declare_alive",
    "AliveWatcher",
    "wait_matching",
    "serve_router",
]

ZENOH_RUNTIME_DEFAULT: Final = (
    "(rx: (handover: app), tx: (handover: app), net: (handover: app), acc: (handover: app), app: (worker_threads: 1))"
)
"""zenoh's thread layout in the swarm's plant, leader and agent processes (see :func:`use_swarm_runtime`)."""


def use_swarm_runtime() -> None:
    """Run this process's zenoh on one thread, unless ``ZENOH_RUNTIME`` is already set.

    By default zenoh runs five tokio runtimes (``app``, ``acc``, ``tx``, ``rx``, ``net``; ``rx``
    with two worker threads), so one message crosses several threads in each process: read by
    an ``rx`` thread, queued to a ``tx`` thread, and so on, each hand-over a thread wake-up.
    :data:`ZENOH_RUNTIME_DEFAULT` hands every runtime over to one ``app`` runtime with a single
    worker thread. On the 2-core machine that, with :func:`direct_callback` (and the router's
    ``tx`` apart), took the lockstep swarm from 2.54 to 1.39 ms per tick on paper example 1 (3
    UAVs) and from 13.15 to 6.77 ms on gen16 (BENCHMARKS.md, "What made the swarm faster": the
    ablation's "+ supervisor queue" row against "as committed").

    zenoh reads the variable once, when it creates its runtimes (the first session of the
    process), so call this before opening one; child processes inherit it. The supervisor's
    router does not use it: a router blocked on one slow receiver (congestion control ``BLOCK``)
    must not stop forwarding everything else, which one worker thread would
    (:data:`ZENOH_RUNTIME_ROUTER`). Set
    ``ZENOH_RUNTIME`` yourself (RON syntax, zenoh's ``zenoh-runtime`` crate) to override it.
    """
    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME_DEFAULT)


ZENOH_RUNTIME_ROUTER: Final = (
    "(rx: (handover: app), net: (handover: app), acc: (handover: app), app: (worker_threads: 1), tx: (worker_threads: 1))"
)
"""zenoh's thread layout in the supervisor (the router): one ``app`` thread, and ``tx`` on its own.

A router forwarding a ``BLOCK`` message into a full queue waits, inside the task that read it,
until the sending task of that queue has drained it. With ``tx`` handed over to the single ``app``
thread too, that sending task could never run: the wait would end only when zenoh closes the link
(seconds later), and one slow receiver would stall the whole swarm. Measured: with everything on
one thread, a flood of 64 KiB garbage messages froze example 1 every time (4 of 4 runs); with
``tx`` apart, it flew (0 of 4 froze, ``tests/test_garbage.py``), and at nearly the same speed."""

DEFAULT_CONNECT_TIMEOUT_S: Final = 5.0
"""How long a client keeps trying to reach its router before ``zenoh.open`` fails, s."""


TX_QUEUE_BATCHES: Final = 16
"""Batches (64 kB each) in a client session's sending queue for data, zenoh's maximum (its
default is 2). zenoh allocates them only when they are needed.

A lockstep tick runs on zenoh's only thread (:func:`direct_callback`, :data:`ZENOH_RUNTIME_DEFAULT`)
and puts there; zenoh's sending task runs on that same thread, once the reading task finds the
socket empty. A process that has fallen behind a flood of input (a replay at ``--rate 0`` into a
live agent on a loaded machine) can tick hundreds of times before that happens, and each tick
queues its messages. With 2 batches an agent's queue was full at tick 354 of such a backlog: the
put then waited for a sending task that could not run, until zenoh closed the link 5 s later
(``block/wait_before_close``) and the rest was lost (seen in CI, ``tests/test_replay.py``). With
16 batches it holds about 2,800 ticks of an agent's output (a ref and a cmd, ~185 bytes each on
the wire). Lockstep speed unchanged (BENCHMARKS.md, "The sending queue of a client")."""


class BusError(ZenswarmError):
    """A Zenoh session could not be configured or opened."""


class Shutdown(SystemExit):
    """Raised in the main thread by the signal handlers of :func:`open_session`.

    A ``SystemExit`` with exit status 0 (a requested, clean stop); ``signum`` is the signal.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(0)
        self.signum = signum


# --------------------------------------------------------------------------- configuration


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago (bind to port 0, read it, close)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def udp_ports_in_use(ports: Sequence[int], host: str = "127.0.0.1") -> list[int]:
    """Those of ``ports`` that cannot be bound on ``host`` for UDP now (in use, or outside
    1..65535), in the given order. Each is bound once and closed."""
    busy = []
    for p in ports:
        if not 0 < int(p) <= 65535:
            busy.append(int(p))
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind((host, int(p)))
            except OSError:
                busy.append(int(p))
    return busy


def free_udp_block(n: int, host: str = "127.0.0.1", also: Sequence[int] = ()) -> int:
    """A UDP port p on ``host`` with p .. p+n-1 free a moment ago (all bound once, then closed),
    and p+d .. p+d+n-1 too for each offset d in ``also`` (e.g. 40: the simulated vehicles' send
    ports with PX4 SITL's direction)."""
    top = max([0, *also]) + n
    offsets = sorted({d + k for d in (0, *also) for k in range(n)})  # the blocks may overlap (n > d)
    for _ in range(200):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s0:
            s0.bind((host, 0))
            base = int(s0.getsockname()[1])
        if base + top >= 65535:
            continue
        socks = []
        try:
            for off in offsets:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind((host, base + off))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise BusError(f"no block of {n} free UDP ports on {host}")


def tcp_endpoint(port: int, host: str = "127.0.0.1") -> str:
    """Zenoh locator ``tcp/<host>:<port>``."""
    return f"tcp/{host}:{port}"


_IP_PROTOCOLS: Final = ("tcp", "udp", "tls", "quic", "ws")
_OTHER_PROTOCOLS: Final = ("unixsock-stream", "unixpipe", "vsock", "serial")


def check_endpoint_syntax(endpoints: Sequence[str], flag: str, *, listen: bool = False) -> list[str]:
    """Check zenoh endpoints given on the command line before anything starts; returns them.

    Each must be ``<protocol>/<address>[?<metadata>][#<config>]`` with a protocol zenoh knows;
    for ``tcp``, ``udp``, ``tls``, ``quic`` and ``ws`` the address is ``<host>:<port>`` with a
    port in 1..65535 (0, any free port, only where ``listen``). zenoh itself parses only the
    outline and would fail later, in each process. Raises :class:`ScenarioError` naming
    ``flag`` and the endpoint. (Whether the host resolves and answers is not checked here.)
    """
    out = []
    for e in endpoints:
        ep = str(e)
        proto, sep, rest = ep.partition("/")
        addr = rest.split("#", 1)[0].split("?", 1)[0]
        example = "e.g. tcp/127.0.0.1:7447"
        if not sep or not addr:
            raise ScenarioError(flag, f"{ep!r} is not a zenoh endpoint: expected <protocol>/<address>, {example}")
        if proto not in _IP_PROTOCOLS + _OTHER_PROTOCOLS:
            raise ScenarioError(flag, f"{ep!r}: unknown protocol {proto!r} (expected one of {', '.join(_IP_PROTOCOLS)}, ...), {example}")
        if proto in _IP_PROTOCOLS:
            host, colon, port = addr.rpartition(":")
            lo = 0 if listen else 1
            if not colon or not host.strip("[]") or not port.isdigit() or not lo <= int(port) <= 65535:
                raise ScenarioError(flag, f"{ep!r}: expected {proto}/<host>:<port> with a port in {lo}..65535, {example}")
        try:
            zenoh.Config().insert_json5("connect/endpoints", json.dumps([ep]))
        except (zenoh.ZError, TypeError, ValueError) as x:  # zenoh's errors; json.dumps' too
            raise ScenarioError(flag, f"{ep!r} is not a zenoh endpoint: {str(x).split(' at ', 1)[0]}") from None
        out.append(ep)
    return out


def apply_settings(conf: zenoh.Config, settings: Mapping[str, Any]) -> zenoh.Config:
    """Insert ``{"path/in/config": json_value}`` into ``conf`` and return it.

    The one hook for everything beyond the basics, e.g. user/password auth
    (``transport/auth/usrpwd/user``, ``.../password``), TLS (``transport/link/tls/...`` with
    ``tls/`` endpoints), ``access_control``, or tuning (``transport/unicast/lowlatency``).
    """
    for path, value in settings.items():
        try:
            conf.insert_json5(path, json.dumps(value))
        except (zenoh.ZError, TypeError, ValueError) as e:  # zenoh's errors; json.dumps' (not JSON)
            raise BusError(f"config {path!r} = {value!r}: {e}") from None
    return conf


def _base_config(mode: str) -> zenoh.Config:
    conf = zenoh.Config()
    return apply_settings(
        conf,
        {
            "mode": mode,
            # Talk only to the endpoints we are given: no multicast discovery, no gossip.
            "scouting/multicast/enabled": False,
            "scouting/gossip/enabled": False,
        },
    )


def router_config(
    listen: Sequence[str],
    *,
    connect: Sequence[str] = (),
    settings: Mapping[str, Any] | None = None,
) -> zenoh.Config:
    """Config of a swarm router listening on ``listen`` (e.g. ``["tcp/127.0.0.1:7447"]``).

    connect: other routers to link to (none by default); settings: see :func:`apply_settings`.
    """
    if not listen:
        raise BusError("a router needs at least one listen endpoint")
    conf = _base_config("router")
    apply_settings(conf, {"listen/endpoints": list(listen), "connect/endpoints": list(connect)})
    return apply_settings(conf, settings or {})


def client_config(
    connect: Sequence[str],
    *,
    connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
    settings: Mapping[str, Any] | None = None,
) -> zenoh.Config:
    """Config of a swarm process: a client of the router(s) at ``connect``, with a sending queue
    of :data:`TX_QUEUE_BATCHES` batches.

    ``zenoh.open`` keeps retrying for ``connect_timeout_s`` seconds (so a process may start
    before its router), then fails; 0 fails at once. settings: see :func:`apply_settings`.
    """
    if not connect:
        raise BusError("a client needs at least one connect endpoint")
    conf = _base_config("client")
    apply_settings(
        conf,
        {
            "connect/endpoints": list(connect),
            "connect/timeout_ms": max(0, round(connect_timeout_s * 1000)),
            "listen/endpoints": [],
            "transport/link/tx/queue/size/data": TX_QUEUE_BATCHES,
        },
    )
    return apply_settings(conf, settings or {})


# --------------------------------------------------------------------------- sessions


class Undeclarable(Protocol):
    """A zenoh entity that can be undeclared: subscriber, publisher, queryable, liveliness token,
    transport-events listener."""

    def undeclare(self) -> None: ...


def undeclare(entity: Undeclarable) -> None:
    """``entity.undeclare()``: zenoh's type stubs (1.10.2) leave ``undeclare`` unannotated, so
    typed code calls it through this protocol."""
    entity.undeclare()


class _Closable(Protocol):
    def close(self) -> None: ...


def _close(session: _Closable) -> None:
    """``session.close()``, typed (zenoh's stubs leave ``Session.close`` unannotated)."""
    session.close()


def close_at_exit(session: zenoh.Session) -> None:
    """Close ``session`` when the interpreter shuts down, *before* it joins non-daemon threads
    (zenoh's Python-callback threads), which ``atexit`` would be too late for."""
    register = getattr(threading, "_register_atexit", None)  # CPython >= 3.9, private
    try:
        if register is not None:
            register(session.close)
        else:  # pragma: no cover - other interpreters
            import atexit

            atexit.register(session.close)
    except RuntimeError:  # interpreter already shutting down
        pass


_SignalHandler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None
"""What :func:`signal.signal` returns and takes: a handler, ``SIG_DFL``/``SIG_IGN``, or None."""


@contextlib.contextmanager
def open_session(conf: zenoh.Config, *, handle_signals: bool = True) -> Iterator[zenoh.Session]:
    """Open a session and close it on every exit path::

        with open_session(client_config([endpoint])) as session:
            ...

    handle_signals: in the main thread, SIGTERM and SIGINT raise :class:`Shutdown` for the
    duration of the block (the previous handlers are restored afterwards); a second signal
    while unwinding is ignored. Pass False in a process that manages signals itself (or in
    tests that open sessions inside pytest). Raises :class:`BusError` if the session cannot
    be opened (e.g. the router is not reachable within the client's connect timeout).
    """
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        raise BusError(f"cannot open zenoh session: {e}") from None
    close_at_exit(session)
    previous: dict[signal.Signals, _SignalHandler] = {}
    quiet = False  # set once a signal fired or the block is left: further signals are ignored

    def _handler(signum: int, frame: FrameType | None) -> None:
        nonlocal quiet
        if not quiet:
            quiet = True
            raise Shutdown(signum)

    if handle_signals and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, _handler)
    try:
        yield session
    finally:
        quiet = True
        try:
            _close(session)
        finally:
            for sig, h in previous.items():
                signal.signal(sig, h)


def zenoh_threads() -> str:
    """Names of this process's zenoh threads, sorted and comma-separated (e.g. ``"app-0"``), as
    Linux names them; ``""`` where /proc is not readable. For diagnostics."""
    names = []
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return ""
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                name = f.read().strip()
        except OSError:  # a thread that ended since the listing: not one of them any more
            continue
        if name.split("-")[0] in ("app", "acc", "tx", "rx", "net"):
            names.append(name)
    return ",".join(sorted(names))


# --------------------------------------------------------------------------- callbacks


_PINNED: set[int] = set()
_PIN_LOCK = threading.Lock()


def _pin_thread_state() -> None:
    """Keep the calling native thread's Python thread state for the life of the process.

    zenoh runs a ``Callback(f, indirect=False)`` on its own (tokio) threads, which have no Python
    thread state: every call creates one and destroys it again (``PyGILState_Ensure`` /
    ``Release``; in CPython 3.11 that includes mapping and unmapping a 16 KiB frame stack). One
    extra ``PyGILState_Ensure`` that is never released keeps the state, so later calls only take
    the GIL. Called with the GIL held; those threads are few (one with :func:`use_swarm_runtime`).
    """
    tid = threading.get_ident()
    with _PIN_LOCK:
        if tid not in _PINNED:
            _PINNED.add(tid)
            ctypes.pythonapi.PyGILState_Ensure()


def direct_callback(fn: Callable[[zenoh.Sample], None]) -> zenoh.handlers.Callback[zenoh.Sample]:
    """A subscriber handler that runs ``fn(sample)`` on zenoh's receiving thread.

    The default for a plain Python callable is a dedicated Python thread per subscriber that
    zenoh hands each sample to: one thread wake-up and one GIL hand-over per message, and with
    several subscribers, several threads contending for the GIL. Here the thread that read the
    sample from the socket runs ``fn`` itself (its Python thread state kept, see
    :func:`_pin_thread_state`). ``fn`` must be quick and must not block: while it runs, this
    session receives nothing else. Other threads may put meanwhile: zenoh-python releases the
    GIL while a ``put`` waits (``py.allow_threads``), so a put from the main loop that waits for
    queue space lets this callback finish, and the one zenoh thread then makes room
    (``tests/test_bus.py::test_a_blocked_put_does_not_hold_the_gil``). A put from inside ``fn``
    that finds the queue full waits for the thread it runs on (see :func:`use_swarm_runtime`).
    BENCHMARKS.md, "What made the swarm faster".
    """

    def run(sample: zenoh.Sample) -> None:
        if threading.get_ident() not in _PINNED:
            _pin_thread_state()
        fn(sample)

    return zenoh.handlers.Callback(run, indirect=False)


# --------------------------------------------------------------------------- liveliness


def declare_alive(session: zenoh.Session, keys: Keys, process: str) -> zenoh.LivelinessToken:
    """Declare the liveliness token ``swarm/<name>/alive/<process>``.

    Keep the returned token referenced: it is undeclared when garbage-collected, when the
    session closes, and (by the router, within milliseconds on loopback) when the process dies.
    """
    return session.liveliness().declare_token(keys.alive(process))


class AliveWatcher:
    """Track which processes of a swarm hold a liveliness token (the supervisor's view).

    On creation the tokens already present are reported (history), then every join and leave.
    ``on_change(process, alive)`` is called on zenoh's callback thread: keep it short and never
    close the session from it. Tokens whose key is not ``alive/<valid process>`` are ignored
    (counted in ``ignored``). Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        on_change: Callable[[str, bool], None] | None = None,
        *,
        history: bool = True,
    ) -> None:
        self._keys = keys
        self._on_change = on_change
        self._cond = threading.Condition()
        self._alive: set[str] = set()
        self.events: list[tuple[float, str, bool]] = []
        """(time.monotonic() s, process, alive) of every change, in arrival order."""
        self.ignored = 0
        self._sub = session.liveliness().declare_subscriber(keys.alive_all, self._on_sample, history=history)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        try:
            kind, _, process = self._keys.parse(str(sample.key_expr))
        except InvalidKeyError:
            kind, process = "", None
        if kind != "alive" or process is None:
            with self._cond:
                self.ignored += 1
            return
        with self._cond:
            if alive:
                self._alive.add(process)
            else:
                self._alive.discard(process)
            self.events.append((time.monotonic(), process, alive))
            self._cond.notify_all()
        if self._on_change is not None:
            self._on_change(process, alive)

    @property
    def alive(self) -> frozenset[str]:
        """Processes holding a token now."""
        with self._cond:
            return frozenset(self._alive)

    def wait_for(self, process: str, alive: bool = True, timeout: float = 5.0) -> bool:
        """Block until ``process`` is (alive=True) or is not (False) holding a token, at most
        ``timeout`` s. Returns whether that happened."""
        validate_process(process)
        with self._cond:
            return self._cond.wait_for(lambda: (process in self._alive) == alive, timeout=timeout)

    def close(self) -> None:
        """Undeclare the liveliness subscriber (idempotent; a closed session already did)."""
        with contextlib.suppress(Exception):
            undeclare(self._sub)

    def __enter__(self) -> AliveWatcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_matching(publisher: zenoh.Publisher, timeout: float = 5.0, poll_s: float = 0.001) -> bool:
    """Wait up to ``timeout`` s until some subscriber matches ``publisher`` (through the router).

    Publications made before a subscription has reached the router are lost; use this before
    the first put when it matters. Note ``Publisher.matching_status`` is a ``MatchingStatus``
    (always truthy) in 1.10.2: its ``.matching`` is the bool.
    """
    deadline = time.monotonic() + timeout
    while True:
        # zenoh 1.10.2's stub types matching_status as bool; it is a MatchingStatus (see above)
        if cast(zenoh.MatchingStatus, publisher.matching_status).matching:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)


# --------------------------------------------------------------------------- router process


def serve_router(listen: Sequence[str], connect: Sequence[str] = (), settings: Mapping[str, Any] | None = None) -> None:
    """Run a swarm router listening on ``listen`` (linked to the routers ``connect``, with extra
    config ``settings`` {path: value}) until SIGTERM/SIGINT, which raise :class:`Shutdown`.
    Prints one line ``ready <zid> <endpoints...>`` once listening; :class:`BusError` if it cannot
    start. The command is ``python -m zenswarm.compose.router``."""
    with open_session(router_config(list(listen), connect=list(connect), settings=settings or {})) as session:
        print("ready", session.zid(), *listen, flush=True)
        while True:  # bounded by a signal: Shutdown ends it
            signal.pause()

"""Bus helpers against a real Zenoh router on loopback, with real client processes.

Every test uses its own free ports and swarm name and reaps every process it starts.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import textwrap
import threading
import time
import uuid
from collections.abc import Iterator

import pytest
import zenoh

from zenswarm.bus import (
    TX_QUEUE_BATCHES,
    ZENOH_RUNTIME_DEFAULT,
    ZENOH_RUNTIME_ROUTER,
    AliveWatcher,
    BusError,
    client_config,
    free_port,
    open_session,
    router_config,
    tcp_endpoint,
    use_swarm_runtime,
    wait_matching,
    wire,
)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# --------------------------------------------------------------------------- helpers


class Child:
    """A Python subprocess running ``code`` with ``args``; stdout+stderr read line by line."""

    def __init__(self, code: str, *args: object, env: dict[str, str] | None = None) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", textwrap.dedent(code), *map(str, args)],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def expect(self, prefix: str, timeout: float = 5.0) -> str:
        """Next line starting with ``prefix`` (other lines are kept in ``seen``)."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                line = self.lines.get(timeout=max(0.0, left))
            except queue.Empty:
                raise AssertionError(f"no {prefix!r} line within {timeout} s; output so far: {self.seen}") from None
            self.seen.append(line)
            if line.startswith(prefix):
                return line

    def wait(self, timeout: float) -> int:
        return self.proc.wait(timeout=timeout)

    def reap(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=10)


@contextlib.contextmanager
def children() -> Iterator[list[Child]]:
    """Collects children and kills and waits for all of them on exit, whatever happens."""
    started: list[Child] = []
    try:
        yield started
    finally:
        for c in started:
            c.reap()


@contextlib.contextmanager
def router() -> Iterator[str]:
    """An in-process router on a free loopback port; yields its endpoint."""
    ep = tcp_endpoint(free_port())
    with open_session(router_config([ep]), handle_signals=False):
        yield ep


def swarm_name() -> str:
    return "t" + uuid.uuid4().hex[:10]


SUB = """
import json, sys
import zenoh
from zenswarm.bus import wire
from zenswarm.bus import client_config, open_session
ep, swarm, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
keys = wire.Keys(swarm)
dec = wire.Decoder()
got = []
with open_session(client_config([ep])) as session:
    sub = session.declare_subscriber(keys.all, zenoh.handlers.FifoChannel(1024))
    print("ready", flush=True)
    while len(got) + dec.rejected < n:  # bounded by the parent's timeout
        sample = sub.recv()
        key = str(sample.key_expr)
        kind, uav, _ = keys.parse(key)
        msg = dec.decode(key, wire.message_kind(kind), sample.payload.to_bytes())
        if msg is not None:
            got.append([key, uav, msg.seq, msg.q.tolist()])
print("result", json.dumps({"got": got, "counters": dec.counters(), "rejects": dec.rejects}), flush=True)
"""

PUB = """
import json, sys, time
import zenoh
from zenswarm.bus import wire
from zenswarm.bus import client_config, open_session, wait_matching
ep, swarm, uav, first, count, garbage = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]), sys.argv[6] == "1"
keys = wire.Keys(swarm)
with open_session(client_config([ep])) as session:
    pub = session.declare_publisher(keys.state(uav), congestion_control=zenoh.CongestionControl.BLOCK)
    matched = wait_matching(pub, timeout=0.5 if first < 0 else 5.0)
    for k in range(max(first, 0), max(first, 0) + count):
        q = [float(k), 0.1, -0.0]
        pub.put(wire.encode(wire.State(t=wire.t_ns(k * 0.01), seq=k, q=q, v=q, rpy=[0, 0, 0], w=[0, 0, 0])))
    if garbage:
        pub.put(b"\\xc1 not msgpack")
print("done", json.dumps({"matched": matched}), flush=True)
"""

TOKEN = """
import sys, time
from zenswarm.bus import wire
from zenswarm.bus import client_config, declare_alive, open_session
ep, swarm, process = sys.argv[1], sys.argv[2], sys.argv[3]
keys = wire.Keys(swarm)
with open_session(client_config([ep])) as session:
    session.declare_subscriber(keys.all, lambda sample: None)  # a Python-callback thread, the hang risk
    token = declare_alive(session, keys, process)
    print("ready", flush=True)
    time.sleep(30)
"""


# --------------------------------------------------------------------------- configs and keys


def test_every_key_is_a_valid_zenoh_key() -> None:
    keys = wire.Keys("demo")
    concrete = [keys.clock, keys.mission, keys.leader_ref, keys.state(1), keys.ref(2), keys.cmd(30)]
    concrete += [keys.diag(p) for p in ("plant", "leader", "agent:2", "recorder", "bridge", "supervisor")]
    concrete += [keys.alive(p) for p in ("plant", "agent:12")]
    everything = zenoh.KeyExpr(keys.all)
    for k in concrete:
        assert str(zenoh.KeyExpr(k)) == k  # ':' is legal in a chunk and the keys are canonical
        assert everything.includes(zenoh.KeyExpr(k))
    assert zenoh.KeyExpr(keys.alive_all).includes(zenoh.KeyExpr(keys.alive("agent:2")))
    assert not zenoh.KeyExpr(keys.alive_all).intersects(zenoh.KeyExpr(keys.state(1)))
    assert not zenoh.KeyExpr(wire.Keys("demo2").all).intersects(zenoh.KeyExpr(keys.state(1)))


def test_configs() -> None:
    r = router_config(["tcp/127.0.0.1:1"], settings={"transport/unicast/lowlatency": False})
    assert json.loads(r.get_json("mode")) == "router"
    assert json.loads(r.get_json("listen/endpoints")) == ["tcp/127.0.0.1:1"]
    c = client_config(["tcp/127.0.0.1:2"], connect_timeout_s=1.5)
    assert json.loads(c.get_json("mode")) == "client"
    assert json.loads(c.get_json("connect/endpoints")) == ["tcp/127.0.0.1:2"]
    assert json.loads(c.get_json("connect/timeout_ms")) == 1500
    # a lockstep process that ticks through a backlog queues its output until zenoh's only
    # thread gets round to sending it: the room of 16 batches, not zenoh's 2 (TX_QUEUE_BATCHES)
    assert json.loads(c.get_json("transport/link/tx/queue/size/data")) == TX_QUEUE_BATCHES == 16
    for conf in (r, c):
        assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
        assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    with pytest.raises(BusError):
        router_config([])
    with pytest.raises(BusError):
        client_config([])
    with pytest.raises(BusError, match="no/such/key"):
        client_config(["tcp/127.0.0.1:2"], settings={"no/such/key": 1})


@pytest.mark.swarm
def test_client_fails_fast_without_router_and_waits_for_a_late_one() -> None:
    ep = tcp_endpoint(free_port())
    t0 = time.monotonic()
    with pytest.raises(BusError):
        with open_session(client_config([ep], connect_timeout_s=0.2), handle_signals=False):
            pass
    assert time.monotonic() - t0 < 3.0

    stop = threading.Event()

    def late_router() -> None:
        time.sleep(0.4)
        with open_session(router_config([ep]), handle_signals=False):
            stop.wait(10)

    th = threading.Thread(target=late_router)
    th.start()
    try:
        with open_session(client_config([ep], connect_timeout_s=5.0), handle_signals=False) as s:
            assert len(s.info.routers_zid()) == 1
    finally:
        stop.set()
        th.join(10)


# --------------------------------------------------------------------------- pub/sub across processes


@pytest.mark.swarm
def test_two_client_processes_exchange_messages() -> None:
    swarm = swarm_name()
    n = 40
    with router() as ep, children() as kids:
        sub = Child(SUB, ep, swarm, n + 1)
        kids.append(sub)
        sub.expect("ready")
        pub = Child(PUB, ep, swarm, 2, 0, n, 1)
        kids.append(pub)
        assert json.loads(pub.expect("done", 10).split(" ", 1)[1]) == {"matched": True}
        res = json.loads(sub.expect("result", 10).split(" ", 1)[1])
        assert sub.wait(5) == 0 and pub.wait(5) == 0
    key = wire.Keys(swarm).state(2)
    assert res["got"] == [[key, 2, k, [float(k), 0.1, -0.0]] for k in range(n)]
    assert res["counters"] == {"decoded": n, "rejected": 1, "rejected.malformed": 1}
    assert res["rejects"] == {key: 1}


@pytest.mark.swarm
def test_two_routers_with_the_same_swarm_name_are_isolated() -> None:
    swarm = swarm_name()
    with router() as ep_a, router() as ep_b, children() as kids:
        sub = Child(SUB, ep_a, swarm, 1)
        # On router B nobody subscribes: its publisher never matches, and what it sends is lost.
        pub_b = Child(PUB, ep_b, swarm, 1, -1, 20, 0)
        kids += [sub, pub_b]
        sub.expect("ready")
        assert json.loads(pub_b.expect("done", 10).split(" ", 1)[1]) == {"matched": False}
        pub_a = Child(PUB, ep_a, swarm, 7, 999, 1, 0)
        kids.append(pub_a)
        assert json.loads(pub_a.expect("done", 10).split(" ", 1)[1]) == {"matched": True}
        res = json.loads(sub.expect("result", 10).split(" ", 1)[1])
    assert res["got"] == [[wire.Keys(swarm).state(7), 7, 999, [999.0, 0.1, -0.0]]]


# --------------------------------------------------------------------------- liveliness and exit


@pytest.mark.swarm
def test_liveliness_token_of_killed_process_goes_within_2s() -> None:
    swarm = swarm_name()
    keys = wire.Keys(swarm)
    with router() as ep, children() as kids:
        holder = Child(TOKEN, ep, swarm, "agent:3")
        kids.append(holder)
        holder.expect("ready")
        with open_session(client_config([ep]), handle_signals=False) as session, AliveWatcher(session, keys) as watch:
            assert watch.wait_for("agent:3", alive=True, timeout=5.0)  # reported from history
            holder.proc.send_signal(signal.SIGKILL)
            t0 = time.monotonic()
            assert watch.wait_for("agent:3", alive=False, timeout=2.0)
            gone_after = time.monotonic() - t0
            assert watch.alive == frozenset()
            assert [(p, a) for _, p, a in watch.events] == [("agent:3", True), ("agent:3", False)]
    assert gone_after < 2.0


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
@pytest.mark.swarm
def test_signal_closes_session_and_exits_cleanly(sig: signal.Signals) -> None:
    """A process in open_session with a Python-callback subscriber exits 0 on SIGTERM/SIGINT
    (default SIGTERM would kill it, and falling off the end would hang)."""
    swarm = swarm_name()
    keys = wire.Keys(swarm)
    with router() as ep, children() as kids:
        with open_session(client_config([ep]), handle_signals=False) as session, AliveWatcher(session, keys) as watch:
            holder = Child(TOKEN, ep, swarm, "leader")
            kids.append(holder)
            holder.expect("ready")
            assert watch.wait_for("leader", alive=True, timeout=5.0)
            holder.proc.send_signal(sig)
            assert holder.wait(timeout=5.0) == 0
            assert watch.wait_for("leader", alive=False, timeout=2.0)


@pytest.mark.swarm
def test_blocked_recv_and_forgotten_close_do_not_hang() -> None:
    blocked = """
    import sys, zenoh
    from zenswarm.bus import client_config, open_session
    with open_session(client_config([sys.argv[1]])) as session:
        sub = session.declare_subscriber("nothing/here", zenoh.handlers.FifoChannel(8))
        print("ready", flush=True)
        sub.recv()  # nothing ever comes; SIGTERM must still end the process
    """
    forgotten = """
    import sys, zenoh
    from zenswarm.bus import client_config, close_at_exit
    session = zenoh.open(client_config([sys.argv[1]]))
    close_at_exit(session)
    session.declare_subscriber("nothing/here", lambda s: None)
    print("ready", flush=True)
    # falls off the end without closing: close_at_exit runs before the thread join
    """
    with router() as ep, children() as kids:
        a, b = Child(blocked, ep), Child(forgotten, ep)
        kids += [a, b]
        a.expect("ready")
        b.expect("ready")
        assert b.wait(timeout=5.0) == 0
        a.proc.send_signal(signal.SIGTERM)
        assert a.wait(timeout=5.0) == 0


# --------------------------------------------------------------------------- one zenoh thread


ONE_THREAD = """
import json, os, sys, threading, time
from zenswarm import bus
bus.use_swarm_runtime()
import zenoh
got, where = [], set()
done = threading.Event()
def on_sample(sample):
    got.append(int(sample.payload.to_bytes()))
    where.add((threading.get_ident(), threading.current_thread() is threading.main_thread()))
    if len(got) == int(sys.argv[2]):
        done.set()
with bus.open_session(bus.client_config([sys.argv[1]]), handle_signals=False) as s:
    sub = s.declare_subscriber("onethread/data", bus.direct_callback(on_sample))
    print("ready", flush=True)
    done.wait(10)
    names = sorted(open(f).read().strip() for f in
                   [f"/proc/self/task/{t}/comm" for t in os.listdir("/proc/self/task")])
    print("result " + json.dumps({"env": os.environ.get("ZENOH_RUNTIME"), "got": got, "threads": names,
          "callback_threads": sorted(w[1] for w in where), "pinned": len(bus._PINNED)}), flush=True)
"""


@pytest.mark.swarm
def test_swarm_runtime_runs_zenoh_and_callbacks_on_one_thread() -> None:
    """A swarm process (bus.use_swarm_runtime + bus.direct_callback): zenoh has a single thread
    (no rx/tx/net/acc threads), every sample reaches the callback on it, in order, and that
    thread's Python state is created once (pinned), not per sample."""
    n = 200
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    with router() as ep, children() as kids:
        c = Child(ONE_THREAD, ep, n, env=env)
        kids.append(c)
        c.expect("ready", 10)
        with open_session(client_config([ep]), handle_signals=False) as s:
            pub = s.declare_publisher("onethread/data", congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_matching(pub, 5.0)
            for k in range(n):
                pub.put(str(k).encode())
            res = json.loads(c.expect("result", 15).split(" ", 1)[1])
        assert c.wait(10) == 0
    assert res["env"] == ZENOH_RUNTIME_DEFAULT
    assert res["got"] == list(range(n))
    # every runtime handed over to app: no rx/tx/net/acc thread (tokio may add a blocking-pool
    # thread to app, named app-<n> too)
    runtimes = {t.split("-")[0] for t in res["threads"] if t.split("-")[0] in ("app", "rx", "tx", "net", "acc")}
    assert runtimes == {"app"}, res["threads"]
    assert res["callback_threads"] == [False]  # never the main thread, always zenoh's one
    assert res["pinned"] == 1


BLOCKED_PUT = """
import json, sys, threading, time
from zenswarm import bus
bus.use_swarm_runtime()
import zenoh
started = threading.Event()
busy = {}
def on_trigger(sample):  # holds zenoh's only thread, and wants the GIL, for 1 s
    started.set()
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.0:
        pass
    busy["s"] = time.monotonic() - t0
with bus.open_session(bus.client_config([sys.argv[1]]), handle_signals=False) as s:
    sub = s.declare_subscriber("blocked/trigger", bus.direct_callback(on_trigger))
    pub = s.declare_publisher("blocked/data", congestion_control=zenoh.CongestionControl.BLOCK)
    print("ready", flush=True)
    print("matched" if bus.wait_matching(pub, 10) else "unmatched", flush=True)
    started.wait(10)
    t0 = time.monotonic()
    longest = 0.0
    for _ in range(int(sys.argv[2])):
        t1 = time.monotonic()
        pub.put(bytes(200_000))
        longest = max(longest, time.monotonic() - t1)
    print("result " + json.dumps({"puts_s": time.monotonic() - t0, "longest_put_s": longest,
                                  "callback_s": busy.get("s")}), flush=True)
"""


@pytest.mark.swarm
def test_a_blocked_put_does_not_hold_the_gil() -> None:
    """Realtime loops put from the main thread while zenoh's only thread runs subscriber
    callbacks (bus.direct_callback). A put that waits for queue space must release the GIL:
    otherwise a callback waiting for the GIL on the thread that would make room deadlocks the
    process. The callback busies zenoh's thread for 1 s while the main thread puts 60 MB with
    BLOCK: the queue fills, a put waits, the callback finishes, and everything is sent."""
    n = 300
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    got = [0]
    all_in = threading.Event()

    def on_data(sample: zenoh.Sample) -> None:
        got[0] += 1
        if got[0] == n:
            all_in.set()

    with router() as ep, children() as kids:
        c = Child(BLOCKED_PUT, ep, n, env=env)
        kids.append(c)
        c.expect("ready", 10)
        with open_session(client_config([ep]), handle_signals=False) as s:
            sub = s.declare_subscriber("blocked/data", on_data)
            c.expect("matched", 15)  # the child's publisher knows of this subscriber
            s.put("blocked/trigger", b"go")
            res = json.loads(c.expect("result", 30).split(" ", 1)[1])
            all_in.wait(10)
            sub.undeclare()
        assert c.wait(10) == 0
    assert res["callback_s"] is not None and res["callback_s"] >= 1.0
    # a put did wait for queue space while the callback ran (the case under test), and only that long
    assert 0.3 < res["longest_put_s"] < 10, res
    assert got[0] == n, f"received {got[0]} of {n}"


@pytest.mark.swarm
def test_use_swarm_runtime_keeps_what_the_user_set(monkeypatch: pytest.MonkeyPatch) -> None:
    # setenv first, so that monkeypatch restores the variable as it was (use_swarm_runtime sets
    # os.environ itself, which monkeypatch would not undo: a later `zenswarm up` in this process
    # would then take it for the user's choice)
    monkeypatch.setenv("ZENOH_RUNTIME", "")
    monkeypatch.delenv("ZENOH_RUNTIME")
    use_swarm_runtime()
    assert os.environ["ZENOH_RUNTIME"] == ZENOH_RUNTIME_DEFAULT
    monkeypatch.setenv("ZENOH_RUNTIME", "(app: (worker_threads: 3))")
    use_swarm_runtime()
    assert os.environ["ZENOH_RUNTIME"] == "(app: (worker_threads: 3))"
    # the router keeps its sending runtime apart (see ZENOH_RUNTIME_ROUTER's docstring)
    assert "tx: (handover" not in ZENOH_RUNTIME_ROUTER and "tx: (handover: app)" in ZENOH_RUNTIME_DEFAULT


def test_router_command_serves_until_sigterm_and_refuses_a_bad_setting() -> None:
    """``python -m zenswarm.compose.router``: ``ready <zid> <endpoint>`` once listening, a client
    can join, SIGTERM ends it with status 0; a bad ``--set`` is exit status 1 naming it."""
    ep = tcp_endpoint(free_port())
    cmd = [sys.executable, "-m", "zenswarm.compose.router", "--listen", ep, "--set", "adminspace/enabled=true"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert p.stdout is not None
        line = p.stdout.readline().split()
        assert line[0] == "ready" and line[-1] == ep, line
        with open_session(client_config([ep], connect_timeout_s=5.0), handle_signals=False) as s:
            assert s.zid() is not None
        p.send_signal(signal.SIGTERM)
        assert p.wait(timeout=10) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    bad = subprocess.run([*cmd[:-2], "--set", "adminspace/enabled"], capture_output=True, text=True, timeout=30)
    assert bad.returncode == 1 and "--set 'adminspace/enabled': expected PATH=JSON" in bad.stderr, bad.stderr


def test_free_udp_block_takes_overlapping_blocks() -> None:
    """More vehicles than the send offset (64 > 40): the two blocks overlap, and every port of
    their union is free. (Each port was bound twice before, which always failed: a 64-UAV
    flight could not start, even with the simulated plant.)"""
    import socket

    from zenswarm.bus import free_udp_block

    base = free_udp_block(64, also=(40,))
    socks = []
    try:
        for p in range(base, base + 104):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            socks.append(s)
            s.bind(("127.0.0.1", p))
    finally:
        for s in socks:
            s.close()

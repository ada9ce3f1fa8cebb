"""One-way latency of the swarm bus: put -> subscriber delivery, client -> router -> client.

A router (``python -m zenswarm.compose.router``) and, per variant, one subscriber and one publisher
process, all on loopback. The publisher stamps each ~100-byte payload with
``time.monotonic_ns()`` (CLOCK_MONOTONIC is system-wide on Linux, so stamps compare across
processes); the subscriber subtracts it from its own clock when the sample reaches Python.
Messages are paced (default 1 ms apart) so the figure is latency, not queueing.

Variants: handler (Python ``callback`` on zenoh's helper thread, ``direct`` =
``Callback(f, indirect=False)`` on zenoh's network thread, ``fifo`` = ``FifoChannel`` drained
by the main thread with ``recv()``) x sender (``session.put`` vs a declared ``publisher``)
x express (batching bypass) on or off.

    python bench/bus_latency.py                      # all 12 variants, 2000 messages each
    python bench/bus_latency.py --rounds 3           # interleaved repeats, pooled figures
    python bench/bus_latency.py -n 500 --handlers fifo --senders publisher --express-modes off
    python bench/bus_latency.py --lowlatency         # transport/unicast/lowlatency everywhere
    python bench/bus_latency.py --congestion block   # puts wait instead of dropping on a full queue

Not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import statistics
import struct
import subprocess
import sys
import threading
import time
from typing import Any

import zenoh

from zenswarm.bus import Shutdown, client_config, free_port, open_session, tcp_endpoint, wait_matching

KEY = "bench/latency/data"
STAMP = struct.Struct("<qq")  # send time (monotonic ns), sequence number


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    return json.loads(args.settings) if args.settings else {}


def run_sub(args: argparse.Namespace) -> None:
    """Subscriber role: collect (receive - send) in ns for warmup + n messages, print JSON."""
    total = args.warmup + args.n
    lat: list[int] = []
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        sent, _seq = STAMP.unpack_from(sample.payload.to_bytes())
        lat.append(now - sent)
        if len(lat) >= total:
            done.set()

    conf = client_config([args.endpoint], settings=_settings(args))
    with open_session(conf) as session:
        if args.handler == "callback":
            session.declare_subscriber(KEY, on_sample)
        elif args.handler == "direct":
            session.declare_subscriber(KEY, zenoh.handlers.Callback(on_sample, indirect=False))
        else:
            sub = session.declare_subscriber(KEY, zenoh.handlers.FifoChannel(4096))
        print("ready", flush=True)
        try:
            if args.handler == "fifo":
                deadline = time.monotonic() + args.timeout
                while len(lat) < total and time.monotonic() < deadline:
                    on_sample(sub.recv())  # interrupted by SIGTERM (Shutdown) if messages stop
            else:
                done.wait(timeout=args.timeout)
        except Shutdown:
            pass  # the parent gave up waiting: report what arrived
        got = list(lat)
    us = [round(x / 1000, 1) for x in got[args.warmup :]]
    print(json.dumps({"received": len(got), "lat_us": us}), flush=True)


def _stats(us: list[float]) -> dict[str, float]:
    if not us:
        return {"median_us": float("nan"), "p99_us": float("nan"), "max_us": float("nan")}
    us = sorted(us)
    return {"median_us": statistics.median(us), "p99_us": us[min(len(us) - 1, int(0.99 * len(us)))], "max_us": us[-1]}


def run_pub(args: argparse.Namespace) -> None:
    """Publisher role: wait for the subscriber to match, send paced stamped payloads, print
    the median cost of one put call in us."""
    pad = b"\0" * max(0, args.size - STAMP.size)
    conf = client_config([args.endpoint], settings=_settings(args))
    cost: list[int] = []
    with open_session(conf) as session:
        cc = zenoh.CongestionControl.BLOCK if args.congestion == "block" else zenoh.CongestionControl.DROP
        pub = session.declare_publisher(KEY, express=args.express_flag, congestion_control=cc)
        if not wait_matching(pub, timeout=5.0):
            print(json.dumps({"error": "no matching subscriber"}), flush=True)
            return
        time.sleep(0.05)
        period = args.interval_ms / 1000.0
        nxt = time.monotonic()
        for seq in range(args.warmup + args.n):
            payload = STAMP.pack(time.monotonic_ns(), seq) + pad
            t0 = time.perf_counter_ns()
            if args.sender == "publisher":
                pub.put(payload)
            else:
                session.put(KEY, payload, express=args.express_flag, congestion_control=cc)
            cost.append(time.perf_counter_ns() - t0)
            nxt += period
            delay = nxt - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        time.sleep(0.2)  # let the tail drain before closing
    c = sorted(cost[args.warmup :])
    print(json.dumps({"put_median_us": statistics.median(c) / 1000, "put_p99_us": c[int(0.99 * len(c))] / 1000}))


def _spawn(argv: list[str]) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, os.path.abspath(__file__), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _stop(p: subprocess.Popen[str]) -> None:
    if p.poll() is None:
        p.terminate()
        try:
            p.wait(timeout=3)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _one(args: argparse.Namespace, common: list[str], handler: str, sender: str, express: bool) -> tuple[dict, dict]:
    sub = _spawn(["--role", "sub", "--handler", handler, *common])
    pub = None
    try:
        assert sub.stdout is not None
        if not sub.stdout.readline().startswith("ready"):
            raise RuntimeError(sub.stderr.read() if sub.stderr else "subscriber failed")
        pub = _spawn(["--role", "pub", "--sender", sender, *(["--express"] if express else []), *common])
        pout, _ = pub.communicate(timeout=args.timeout + 30)
        try:
            sout, _ = sub.communicate(timeout=3)
        except subprocess.TimeoutExpired:  # some messages were lost: stop it, keep its partial report
            sub.terminate()
            sout, _ = sub.communicate(timeout=5)
        return json.loads(sout.strip().splitlines()[-1]), json.loads(pout.strip().splitlines()[-1])
    finally:
        _stop(sub)
        if pub is not None:
            _stop(pub)


def run_all(args: argparse.Namespace) -> None:
    """Start a router, run every variant ``rounds`` times in shuffled order, print pooled figures."""
    port = free_port()
    ep = tcp_endpoint(port)
    router_argv = [sys.executable, "-m", "zenswarm.compose.router", "--listen", ep]
    settings = _settings(args)
    if args.lowlatency:
        settings.update({"transport/unicast/lowlatency": True, "transport/unicast/qos/enabled": False})
    for path, value in settings.items():
        router_argv += ["--set", f"{path}={json.dumps(value)}"]
    router = subprocess.Popen(router_argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    common = ["--endpoint", ep, "-n", str(args.n), "--warmup", str(args.warmup), "--size", str(args.size)]
    common += ["--interval-ms", str(args.interval_ms), "--timeout", str(args.timeout), "--congestion", args.congestion]
    if settings:
        common += ["--settings", json.dumps(settings)]
    variants = list(itertools.product(args.handlers, args.senders, args.express_modes))
    pooled: dict[tuple, dict[str, Any]] = {v: {"lat": [], "put": [], "sent": 0, "received": 0} for v in variants}
    rng = random.Random(args.seed)
    try:
        assert router.stdout is not None
        line = router.stdout.readline()
        if not line.startswith("ready"):
            raise SystemExit(f"router did not start: {line!r} {router.stderr.read() if router.stderr else ''}")
        print(
            f"router {ep} {settings or ''}; congestion {args.congestion}; {args.n} msgs of {args.size} B every "
            f"{args.interval_ms} ms "
            f"per variant and round; {args.rounds} round(s)",
            flush=True,
        )
        for r in range(args.rounds):
            order = variants[:]
            rng.shuffle(order)
            for v in order:
                s, p = _one(args, common, *v)
                acc = pooled[v]
                acc["lat"] += s["lat_us"]
                acc["received"] += s["received"]
                acc["sent"] += args.n + args.warmup
                acc["put"].append(p.get("put_median_us", float("nan")))
                st = _stats(s["lat_us"])
                print(f"  round {r} {v[0]:8} {v[1]:9} express={str(v[2]):5} median {st['median_us']:7.1f} us  "
                      f"p99 {st['p99_us']:8.1f} us  lost {args.n + args.warmup - s['received']}", flush=True)
    finally:
        _stop(router)
    print(f"{'handler':9} {'sender':10} {'express':7} {'lost':>5} {'median_us':>9} {'p99_us':>8} {'max_us':>8} {'put_us':>7}")
    rows = []
    for v in variants:
        acc = pooled[v]
        st = _stats(acc["lat"])
        put = statistics.median(acc["put"]) if acc["put"] else float("nan")
        lost = acc["sent"] - acc["received"]
        rows.append({"handler": v[0], "sender": v[1], "express": v[2], "lost": lost, **st, "put_median_us": put})
        print(f"{v[0]:9} {v[1]:10} {str(v[2]):7} {lost:5d} {st['median_us']:9.1f} {st['p99_us']:8.1f} "
              f"{st['max_us']:8.1f} {put:7.2f}")
    if args.json:
        print(json.dumps(rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--role", choices=["all", "sub", "pub"], default="all")
    ap.add_argument("--endpoint", default="")
    ap.add_argument("-n", type=int, default=2000, help="measured messages per variant")
    ap.add_argument("--warmup", type=int, default=200, help="messages sent first and not measured")
    ap.add_argument("--size", type=int, default=100, help="payload bytes")
    ap.add_argument("--interval-ms", type=float, default=1.0, help="pacing between puts, ms")
    ap.add_argument("--timeout", type=float, default=30.0, help="per-variant deadline, s")
    ap.add_argument("--handler", choices=["callback", "direct", "fifo"], default="callback")
    ap.add_argument("--sender", choices=["put", "publisher"], default="publisher")
    ap.add_argument("--express", dest="express_flag", action="store_true", help="(pub role) express puts")
    ap.add_argument("--handlers", nargs="+", default=["callback", "direct", "fifo"])
    ap.add_argument("--senders", nargs="+", default=["put", "publisher"])
    ap.add_argument("--express-modes", nargs="+", type=lambda s: s == "on", default=[False, True],
                    help="on/off (default: both)")
    ap.add_argument("--settings", default="", help="JSON {config path: value} for the router and the clients")
    ap.add_argument("--congestion", choices=["drop", "block"], default="drop",
                    help="congestion control of the puts (zenoh's default is drop)")
    ap.add_argument("--rounds", type=int, default=1, help="repeat every variant, in shuffled order")
    ap.add_argument("--seed", type=int, default=0, help="seed of the shuffling")
    ap.add_argument("--lowlatency", action="store_true",
                    help="router and clients with transport/unicast/lowlatency (and qos off)")
    ap.add_argument("--json", action="store_true", help="also print all rows as JSON")
    args = ap.parse_args()
    if args.role == "sub":
        run_sub(args)
    elif args.role == "pub":
        run_pub(args)
    else:
        run_all(args)


if __name__ == "__main__":
    main()

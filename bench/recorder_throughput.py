"""Recorder throughput: does ``zenswarm record`` keep every sample at 50,000 messages/s?

Runs a Zenoh router in this process, the recorder as a separate OS process (exactly as
``zenswarm record`` runs), and publishes a paced mix of swarm messages (state, ref, cmd of 10
UAVs, leader ref, clock, diag) on loopback for ``--seconds`` at ``--rate`` messages/s. Then it
stops the recorder with SIGTERM, reads the file back and checks that every published message is
in it exactly once, in publication order per key. Prints the figures; exit 1 if any was lost.

    python bench/recorder_throughput.py [--rate 50000] [--seconds 5]

Not a test (timing figures belong in bench/).
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import NamedTuple

import msgpack
import numpy as np
import zenoh

from zenswarm import bus
from zenswarm.bridge.recording.mcapio import Recording, read_recording
from zenswarm.bus import wire


def _payloads(n_uav: int) -> list[tuple[str, wire.Message]]:
    """One round of (key kind, template) pairs; seq/t are patched per message."""
    keys = wire.Keys("bench")
    v = np.array([0.1, -0.2, 0.3])
    out: list[tuple[str, wire.Message]] = []
    for i in range(1, n_uav + 1):
        out.append((keys.state(i), wire.State(t=0, seq=0, q=v, v=v, rpy=v, w=v)))
        out.append((keys.ref(i), wire.Ref(t=0, seq=0, q=v, v=v)))
        out.append((keys.cmd(i), wire.Cmd(t=0, seq=0, thrust=0.3, rpy=v, u=v, d_hat=v)))
    out.append((keys.leader_ref, wire.Ref(t=0, seq=0, q=v, v=v)))
    out.append((keys.clock, wire.Clock(t=0, seq=0)))
    out.append((keys.diag("plant"), wire.Diag(t=0, seq=0, process="plant", counters={"x": 1}, info={})))
    return out


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rate", type=float, default=50_000.0, help="messages per second (default 50000)")
    ap.add_argument("--seconds", type=float, default=5.0, help="how long to publish (default 5)")
    ap.add_argument("--uavs", type=int, default=10)
    ap.add_argument("--out", type=Path, help="recording path (default: a temporary file)")
    return ap.parse_args()


def start_recorder(ep: str, out: Path) -> subprocess.Popen[str]:
    """``zenswarm record`` of swarm ``bench`` from the router at ``ep`` into ``out``, a process of its own."""
    return subprocess.Popen(
        [sys.executable, "-m", "zenswarm", "record", "--swarm", "bench", "--connect", ep, "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def stop_recorder(rec: subprocess.Popen[str]) -> str:
    """SIGTERM (the recorder then writes the file's end), killed after 120 s; its output."""
    if rec.poll() is None:
        rec.send_signal(signal.SIGTERM)
    try:
        rec.wait(120)
    except subprocess.TimeoutExpired:
        rec.kill()
        rec.wait()
    return rec.stdout.read() if rec.stdout else ""


def encode_all(pubs: dict[str, zenoh.Publisher], templates: list[tuple[str, wire.Message]],
               n_total: int) -> list[tuple[zenoh.Publisher, bytes]]:
    """The whole run encoded beforehand (the publisher's loop must cost as little as possible):
    the templates in turn, ``t`` = 1 us per message, ``seq`` counting per key from 1."""
    seqs = {k: 0 for k, _ in templates}
    wire_maps = [msgpack.unpackb(wire.encode(m)) for _, m in templates]  # the messages as sent
    msgs: list[tuple[zenoh.Publisher, bytes]] = []
    for j in range(n_total):
        k, _ = templates[j % len(templates)]
        seqs[k] += 1
        d = dict(wire_maps[j % len(templates)])
        d["t"], d["seq"] = j * 1000, seqs[k]
        msgs.append((pubs[k], msgpack.packb(d, use_bin_type=True)))
    return msgs


def publish_paced(msgs: list[tuple[zenoh.Publisher, bytes]], rate: float) -> float:
    """Put every message at ``rate`` messages/s, in bursts every millisecond; the seconds it took."""
    n_total = len(msgs)
    burst = max(1, int(rate / 1000))
    t0 = time.perf_counter()
    sent = 0
    while sent < n_total:
        target = t0 + sent / rate
        now = time.perf_counter()
        if now < target:
            time.sleep(target - now)
        for pub, payload in msgs[sent : sent + burst]:
            pub.put(payload)
        sent += min(burst, n_total - sent)
    return time.perf_counter() - t0


def wait_recorded(s: zenoh.Session, keys: wire.Keys, n_total: int, timeout_s: float = 120.0) -> tuple[bool, float]:
    """Wait until the recorder says it has written everything (its diag counters; its own diag
    messages are recorded too: diag number s follows s - 1 of them); (in time, seconds waited)."""
    drained = threading.Event()

    def on_diag(sample: zenoh.Sample) -> None:
        d = wire.decode("diag", sample.payload.to_bytes())
        if d.counters["recorded"] >= n_total + d.seq - 1:
            drained.set()

    diag_sub = s.declare_subscriber(keys.diag("recorder"), on_diag)
    t_drain = time.perf_counter()
    ok = drained.wait(timeout_s)
    drain_s = time.perf_counter() - t_drain
    diag_sub.undeclare()
    return ok, drain_s


class Timings(NamedTuple):
    encode_s: float  # encoding the whole run beforehand
    publish_s: float  # publishing it
    drain_s: float  # from the last publication until the recorder had written everything


def publish(ep: str, keys: wire.Keys, templates: list[tuple[str, wire.Message]], n_total: int, rate: float) -> Timings | None:
    """Once the recorder is up: ``n_total`` messages published at ``rate`` and waited for until
    recorded. None if the recorder did not come up."""
    with bus.open_session(bus.client_config([ep]), handle_signals=False) as s:
        with bus.AliveWatcher(s, keys) as w:
            if not w.wait_for("recorder", timeout=30):
                print("recorder did not come up", file=sys.stderr)
                return None
        pubs = {
            k: s.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
            for k, _ in templates
        }
        for p in pubs.values():
            bus.wait_matching(p, 5.0)
        t_enc = time.perf_counter()
        msgs = encode_all(pubs, templates, n_total)
        t_enc = time.perf_counter() - t_enc
        pub_s = publish_paced(msgs, rate)
        ok, drain_s = wait_recorded(s, keys, n_total)
        if not ok:
            print("recorder did not catch up within 120 s", file=sys.stderr)
    return Timings(t_enc, pub_s, drain_s)


def read_back(out: Path, keys: wire.Keys) -> tuple[Recording, int, bool]:
    """The recording, how many of the published messages it holds (the recorder's own diag left
    out) and whether each key's are in publication order (seq 1, 2, ...)."""
    r = read_recording(out)
    got: dict[str, list[int]] = {}
    count = 0
    for m in r.messages():
        if m.topic == keys.diag("recorder"):
            continue
        count += 1
        got.setdefault(m.topic, []).append(msgpack.unpackb(m.payload)["seq"])
    return r, count, all(v == list(range(1, len(v) + 1)) for v in got.values())


def main() -> int:
    args = parse_args()
    tmp = tempfile.TemporaryDirectory(prefix="zenswarm-bench-")
    out = args.out or Path(tmp.name) / "bench.mcap"
    ep = bus.tcp_endpoint(bus.free_port())
    keys = wire.Keys("bench")
    templates = _payloads(args.uavs)
    n_total = int(args.rate * args.seconds)
    with bus.open_session(bus.router_config([ep]), handle_signals=False):
        rec = start_recorder(ep, out)
        try:
            tm = publish(ep, keys, templates, n_total, args.rate)
            if tm is None:
                return 2
        finally:
            log = stop_recorder(rec)
    r, count, in_order = read_back(out, keys)
    lost = n_total - count
    size = os.path.getsize(out)
    print(log.strip())
    print(
        f"published {n_total} messages on {len(templates)} keys in {tm.publish_s:.2f} s "
        f"= {n_total / tm.publish_s:,.0f} msg/s (target {args.rate:,.0f}); encoding took {tm.encode_s:.1f} s beforehand"
    )
    print(f"the recorder had written everything {tm.drain_s:.2f} s after the last publication")
    print(
        f"recorded {count} messages ({'none lost' if lost == 0 else f'{lost} LOST'}), per-key order "
        f"{'intact' if in_order else 'BROKEN'}; file {size / 1e6:.1f} MB, complete={r.complete}"
    )
    return 0 if lost == 0 and in_order else 1


if __name__ == "__main__":
    sys.exit(main())

"""The supervisor's collector keeps flat memory however long the flight (issue 16): the samples it
decodes after the flight wait raw in a :class:`zenswarm.process.collector.Spool` (an anonymous file), not
in a list, and the series it builds from them is the one it built before, to the bit.

Pure tests (no process): a spool round trip across blocks, a collector fed the same samples with
a tiny spool block and an unbounded one, against the samples applied one by one, and the memory
the collector holds while 20 000 samples arrive.
"""

from __future__ import annotations

import random
import tracemalloc
from pathlib import Path

import numpy as np

from zenswarm.bus import wire
from zenswarm.judge.metrics import TimeSeries
from zenswarm.process.collector import Collector, Spool
from zenswarm.scenario.config import load_scenario

from swarmtest import SCENARIOS

EX1 = SCENARIOS / "paper_example1.toml"


def test_spool_returns_every_record_in_order_across_blocks(tmp_path: Path) -> None:
    rng = random.Random(1)
    sp = Spool(tmp_path, block_bytes=100)  # records straddle the file's blocks
    sent: list[tuple[str, bytes]] = []
    got: list[tuple[str, bytes]] = []
    for _round in range(3):
        for _j in range(257):
            rec = (f"k/{rng.randrange(5)}", bytes(rng.randrange(256) for _ in range(rng.randrange(0, 90))))
            sp.append(*rec)
            sent.append(rec)
        assert sp.records == 257 and sp.file_bytes > 0  # most of it went to the file
        got.extend(sp.take())
        assert sp.records == 0 and sp.file_bytes == 0  # taken: the file is emptied
    assert got == sent
    assert list(sp.take()) == []
    sp.close()
    assert list(tmp_path.iterdir()) == []  # anonymous: nothing left in the directory


def _samples(sc, keys: wire.Keys, n_ticks: int, seed: int) -> list[tuple[str, bytes]]:
    """A flight's worth of wire samples, shuffled a little, some (key, tick) sent twice with
    other values (a restarted process: the later one must win, as before)."""
    rng = np.random.default_rng(seed)
    dt_ns = wire.t_ns(sc.timing.dt)
    out: list[tuple[str, bytes]] = []
    for k in range(n_ticks):
        t = k * dt_ns
        out.append((keys.clock, wire.encode(wire.Clock(t=t, seq=k))))
        out.append((keys.leader_ref, wire.encode(wire.Ref(t=t, seq=k, q=rng.normal(size=3), v=rng.normal(size=3)))))
        for i in range(1, sc.n + 1):
            for _ in range(2 if rng.random() < 0.05 else 1):
                r = [rng.normal(size=3) for _ in range(4)]
                out.append((keys.state(i), wire.encode(wire.State(t=t, seq=k, q=r[0], v=r[1], rpy=r[2], w=r[3]))))
                out.append((keys.ref(i), wire.encode(wire.Ref(t=t, seq=k, q=r[1], v=r[2]))))
                out.append((keys.cmd(i), wire.encode(wire.Cmd(t=t, seq=k, thrust=float(rng.normal()), rpy=r[3], u=r[0], d_hat=r[2]))))
    out.append((keys.state(1), b"\xc1garbage"))  # counted by the decoder, not in the series
    return out


def _same(a: TimeSeries, b: TimeSeries) -> None:
    for f in TimeSeries.FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.shape == y.shape and x.tobytes() == y.tobytes(), f


def test_series_through_the_spool_is_the_samples_applied_in_order(tmp_path: Path) -> None:
    sc = load_scenario(EX1)
    keys = wire.Keys("spool")
    samples = _samples(sc, keys, 120, seed=3)
    ref = Collector(sc, keys)
    for key, payload in samples:  # the reference: every sample decoded as it arrives
        ref._apply(key, payload)
    small = Collector(sc, keys, spool_dir=tmp_path, spool_block_bytes=512)
    half = len(samples) // 2
    for j, (key, payload) in enumerate(samples):
        small.on_sample(key, payload)
        if j == half:  # an early decision reads the series mid-flight
            ref_half = Collector(sc, keys)
            for key_, payload_ in samples[: half + 1]:
                ref_half._apply(key_, payload_)
            _same(small.series(60, fill=True), ref_half.series(60, fill=True))
    assert small.spooled > 0
    for upto, fill in ((None, False), (100, True), (0, True)):
        _same(small.series(upto, fill=fill), ref.series(upto, fill=fill))
    assert small.complete_ticks(120) == ref.complete_ticks(120) == 120
    assert small.counts == ref.counts and small.decoder.counters() == ref.decoder.counters()
    assert small.sim_t_ns == ref.sim_t_ns and small.goal_tick == ref.goal_tick
    small.close()


def test_collector_memory_does_not_grow_with_the_samples(tmp_path: Path) -> None:
    """20 000 samples (about 3 MB of payloads): the collector holds at most its spool's block,
    not the samples (it held them all in a list, 40 MB a minute with 8 UAVs at 100 Hz)."""
    sc = load_scenario(EX1)
    keys = wire.Keys("flat")
    payload = wire.encode(wire.State(t=0, seq=0, q=np.ones(3), v=np.ones(3), rpy=np.ones(3), w=np.ones(3)))
    col = Collector(sc, keys, spool_dir=tmp_path)
    key = keys.state(1)
    blobs = [bytes(payload[:-1]) + bytes([j % 200]) for j in range(64)]  # distinct objects, as from the bus
    tracemalloc.start()
    try:
        col.on_sample(key, blobs[0])
        base = tracemalloc.get_traced_memory()[0]
        for j in range(20_000):
            col.on_sample(key, bytes(blobs[j % 64]))
        held = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert col.spooled == 20_001 and len(payload) * 20_000 > 2.5e6
    assert held < 1.5 * (1 << 20), held  # one spool block (1 MiB) and change
    ts = col.series(1)
    assert ts.q[0, 0].tolist() == [1.0, 1.0, 1.0]
    col.close()

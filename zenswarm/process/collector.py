"""The flight's time series assembled from the swarm bus: what ``zenswarm up`` judges and what a
report of a recording reads.

:class:`Collector` takes every sample of the swarm's key space (its sender checked as the
processes' input guard does), decodes the clock, the leader's reference and diagnostics at once
and the rest after the flight, and fills a :class:`zenswarm.judge.metrics.TimeSeries` indexed by tick
(the same one the in-process simulator writes), so ``results.json`` is computed by the same code
for both.

Memory stays flat however long the flight: the samples decoded after the flight wait, raw and in
arrival order, in a :class:`Spool` (an anonymous temporary file, written in 1 MiB blocks, read
back block by block), not in a list; the per-UAV series (``(T, N, 3)`` arrays sized by the
scenario's tick count) are allocated only when first needed (the end of the flight, or an early
decision). The leader's series, the clock and the diagnostics, which progress and the live verdict
read, stay in memory as before. The samples are applied in the same order as before, so the
series (``results.json``, ``timeseries.npz``) is the same to the bit.
"""

from __future__ import annotations

import math
import struct
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from zenswarm.bus import wire
from zenswarm.errors import ZenswarmError
from zenswarm.judge.metrics import TimeSeries, fill_forward
from zenswarm.process.runtime import expected_senders, sample_sender
from zenswarm.scenario.config import Scenario

__all__ = ["Collector", "Spool"]

SPOOL_BLOCK_BYTES = 1 << 20
"""A :class:`Spool` writes its buffer to its file once it holds this many bytes (and reads back
in blocks of this size)."""


class Spool:
    """Raw samples (key, payload), kept in arrival order in an anonymous temporary file, so that
    memory does not grow with the flight.

    Records are ``<u32 key id><u32 payload length><payload>``, buffered in memory up to
    :data:`SPOOL_BLOCK_BYTES` and then appended to the file. :meth:`take` yields every record
    appended since the previous :meth:`take`, in order, reading the file block by block, and then
    empties the file (its disk space is freed). The file is created in ``directory`` (default: the
    system's temporary directory) without a name (``tempfile.TemporaryFile``): nothing is left
    behind, even when the process is killed. Disk use: the raw samples not yet taken (about
    18 MB per minute for 8 UAVs at 100 Hz: states, refs and commands).
    """

    _HEAD = struct.Struct("<II")

    def __init__(self, directory: str | Path | None = None, block_bytes: int = SPOOL_BLOCK_BYTES) -> None:
        self.directory = None if directory is None else str(directory)
        self.block_bytes = int(block_bytes)
        self._file: IO[bytes] | None = None
        self._buf = bytearray()
        self._ids: dict[str, int] = {}
        self._keys: list[str] = []
        self.records = 0  # records waiting (appended, not yet taken)
        self.file_bytes = 0  # bytes in the file, not yet taken

    def append(self, key: str, payload: bytes) -> None:
        """Keep one sample (cheap: no decoding; a write to the file once per block)."""
        kid = self._ids.get(key)
        if kid is None:
            kid = self._ids[key] = len(self._keys)
            self._keys.append(key)
        buf = self._buf
        buf += self._HEAD.pack(kid, len(payload))
        buf += payload
        self.records += 1
        if len(buf) >= self.block_bytes:
            self._write()

    def _write(self) -> None:
        if not self._buf:
            return
        if self._file is None:
            if self.directory is not None:
                Path(self.directory).mkdir(parents=True, exist_ok=True)
            self._file = tempfile.TemporaryFile(dir=self.directory, prefix=".zenswarm-collector-")
        self._file.seek(0, 2)
        self._file.write(self._buf)
        self.file_bytes += len(self._buf)
        self._buf = bytearray()

    def take(self) -> Iterator[tuple[str, bytes]]:
        """Every sample appended since the last take, in arrival order; consume it whole (the file
        is emptied at the end). Memory: one block at a time."""
        head, keys = self._HEAD, self._keys
        hn = head.size
        if self._file is not None and self.file_bytes:
            f = self._file
            f.flush()
            f.seek(0)
            carry = b""
            while True:
                block = f.read(self.block_bytes)
                if not block:
                    break
                data = carry + block if carry else block
                pos, end = 0, len(data)
                while pos + hn <= end:
                    kid, n = head.unpack_from(data, pos)
                    if pos + hn + n > end:
                        break
                    yield keys[kid], data[pos + hn : pos + hn + n]
                    pos += hn + n
                carry = data[pos:]
            if carry:
                raise RuntimeError(f"collector spool: {len(carry)} bytes of a truncated record")
            f.seek(0)
            f.truncate()
            self.file_bytes = 0
        buf, self._buf = bytes(self._buf), bytearray()
        pos = 0
        while pos < len(buf):
            kid, n = head.unpack_from(buf, pos)
            yield keys[kid], buf[pos + hn : pos + hn + n]
            pos += hn + n
        self.records = 0

    def close(self) -> None:
        """Drop what is waiting and close the file."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self._buf = bytearray()
        self.records = self.file_bytes = 0


class Collector:
    """Assembles the flight's time series from the bus (callback on the supervisor's session). It is
    what the end-of-flight watch reads (:class:`zenswarm.judge.watch.LiveRecord`)."""

    def __init__(
        self, scenario: Scenario, keys: wire.Keys, spool_dir: str | Path | None = None, spool_block_bytes: int = SPOOL_BLOCK_BYTES
    ) -> None:
        """``spool_dir``: where the :class:`Spool`'s anonymous file goes (the supervisor's output
        directory; default: the system's temporary directory); ``spool_block_bytes``: its block."""
        self.sc = scenario
        self.keys = keys
        self.T = scenario.timing.n_ticks
        self.t = np.arange(self.T) * scenario.timing.dt
        self.q0 = np.full((self.T, 3), np.nan)  # the leader's series (decoded as it arrives)
        self.v0 = np.full((self.T, 3), np.nan)
        self._ts: TimeSeries | None = None  # the whole series, allocated when first needed
        self.dt_ns = wire.t_ns(scenario.timing.dt)
        self.decoder = wire.Decoder()
        self.lock = threading.Lock()
        self.sim_t_ns = -1
        self.ignored_clocks = 0  # decodable clocks beyond the mission's end (garbage), not taken
        self.leader_q: np.ndarray | None = None
        self.leader_ticks = 0  # leader refs of ticks 0 .. leader_ticks - 1 may have arrived
        self.goal_tick: int | None = None
        self._goal = np.asarray(scenario.leader.goal, dtype=float)
        self._goal_tol = scenario.timing.goal_tolerance_m
        self.diag: dict[str, dict[str, Any]] = {}
        # the plant's failsafe as its diagnostics said it, each change once: (sim time ns, summary
        # such as "2:hover"; "none" when every UAV is back to nominal), see failsafe_intervals()
        self.failsafe_log: list[tuple[int, str]] = []
        self.counts: dict[str, int] = {}
        self._eager = {keys.clock, keys.leader_ref}
        self._spool = Spool(spool_dir, spool_block_bytes)  # samples decoded later, raw, in arrival order
        # for the live verdict: each UAV's newest state and ref message, decoded only when asked
        self._live_keys = {k: (kind, i) for i in range(1, scenario.n + 1) for kind, k in (("state", keys.state(i)), ("ref", keys.ref(i)))}
        self._last: dict[tuple[str, int], bytes] = {}
        self.got_state = np.zeros((self.T, scenario.n), dtype=bool)  # a state message of (tick, UAV) arrived
        # Who may publish what (open and secure swarms; in a secure one the router also admits
        # each key, and alive/<process>/<zid>, from its process's credentials only): as the
        # processes' input guard, the first session that holds the key's sender token is pinned;
        # another session (also one with the same credentials) is taken only once the pinned
        # one's token is gone (a restarted process).
        self.holders: dict[str, set[str]] = {}  # process -> sessions holding alive/<process>/<zid>
        self.pins: dict[str, str] = {}  # key -> the session whose messages are taken
        self.foreign = 0  # samples ignored: not from their key's process
        self.foreign_by_key: dict[str, int] = {}
        self._senders: dict[str, tuple[str, ...]] = {}
        self._rec_shapes = _declared_records(scenario)  # the plant model's signals: name -> shape per UAV

    def token(self, process: str, zid: str, alive: bool) -> None:
        """``alive/<process>/<zid>`` appeared (alive) or went away."""
        with self.lock:
            h = self.holders.setdefault(process, set())
            if alive:
                h.add(zid)
            else:
                h.discard(zid)

    def sender_ok(self, key: str, zid: str) -> bool:
        """May this sample (from session ``zid``, "" when anonymous) enter the series? Counts it
        when not. Before any token of the key's process is known, everything is taken."""
        if zid and self.pins.get(key) == zid:  # the usual case, without the lock
            return True
        senders = self._senders.get(key)
        if senders is None:
            senders = self._senders[key] = expected_senders(self.keys, key)
        with self.lock:
            holders = set().union(*(self.holders.get(p, ()) for p in senders))
            pin = self.pins.get(key)
            if zid == pin or (not holders and pin is None):
                return True
            if zid in holders and (pin is None or pin not in holders):  # first, or a restart
                self.pins[key] = zid
                return True
            self.foreign += 1
            self.foreign_by_key[key] = self.foreign_by_key.get(key, 0) + 1
            return False

    def poll(self, sub: Any, tap: Callable[[str, bytes], None] | None = None) -> int:
        """Take every sample queued on ``sub`` (a subscriber with a channel handler); returns
        how many. Called from the supervisor's own loop, so the swarm's messages cost the
        supervisor no Python thread wake-up each (they wait in zenoh's channel between polls).
        ``tap`` (the live view's feed) also gets each sample taken, as (key, payload)."""
        n = 0
        while (s := sub.try_recv()) is not None:
            key = str(s.key_expr)
            if self.sender_ok(key, sample_sender(s)):
                payload = s.payload.to_bytes()
                self.on_sample(key, payload)
                if tap is not None:
                    tap(key, payload)
            n += 1
        return n

    def on_sample(self, key: str, payload: bytes) -> None:
        """Take one sample (its sender checked). The clock, the leader's ref and diagnostics
        (what progress needs) are decoded at once; the rest is queued and decoded by
        :meth:`series`, after the flight (the swarm's processes share this machine's cores)."""
        if key in self._eager or "/diag/" in key:
            self._apply(key, payload)
        else:
            self._spool.append(key, payload)
            live = self._live_keys.get(key)
            if live is not None:
                self._last[live] = payload

    def clock_ticks(self) -> int:
        """The ticks the plant's clock has reached: 0 .. k - 1, k = sim time // dt (0 before its first clock)."""
        return int(max(self.sim_t_ns, 0) // self.dt_ns)

    def last_tick_flown(self) -> int:
        """Lockstep, every process ended with status 0: the plant ran every tick of the time limit
        (its loop ends only there, or when it is stopped), so the last tick flown is T - 1, whatever
        this clock says yet: the plant's final clocks travel with the last ticks' messages, and a
        clock seen only up to an earlier tick judged the ticks after it missing. A plant stopped
        early says so in its final diagnostics (``finished`` false): then the last tick of the clock seen."""
        if (self.diag.get("plant") or {}).get("finished") is False:
            return min(self.T, self.clock_ticks() + 1) - 1
        return self.T - 1

    def facts(self) -> dict[str, Any]:
        """What ``results.json`` says of the bus beside the verdict: ``failsafe`` (the UAVs the plant
        or the bridge held, :meth:`failsafe_intervals`), each process's last ``diagnostics``, the
        decoder's rejects and the ``foreign_samples`` (per key: not from their key's process, not in the series)."""
        return {
            "failsafe": self.failsafe_intervals(),
            "diagnostics": self.diag,
            "decoder_rejects": self.decoder.counters(),
            "foreign_samples": dict(sorted(self.foreign_by_key.items())),
        }

    def complete_ticks(self, upto: int) -> int:
        """How many ticks from 0, up to ``upto``, have every UAV's state (the rest were cut off
        when the run was stopped)."""
        self._drain()
        missing = np.flatnonzero(~self.got_state[:upto].all(axis=1))
        return int(missing[0]) if len(missing) else min(upto, self.T)

    def tick_complete(self, k: int) -> bool:
        """Every message of tick k arrived: each UAV's state, ref and cmd, and the leader's ref
        (with :meth:`complete_ticks`, in lockstep: every tick before it too)."""
        if not 0 <= k < self.T:
            return k < 0
        if self.complete_ticks(k + 1) < k + 1:
            return False
        with self.lock:
            ts = self.ts
            return bool(np.isfinite(self.q0[k]).all() and np.isfinite(ts.qref[k]).all() and np.isfinite(ts.thrust[k]).all())

    def outputs_of_tick(self, kind: str, k: int) -> np.ndarray:
        """(N,) bool: each UAV's ``ref`` or ``cmd`` message of tick k arrived."""
        self._drain()
        with self.lock:
            ts = self.ts
            if kind == "ref":
                return np.asarray(~np.isnan(ts.qref[k]).any(axis=1))
            return np.asarray(~np.isnan(ts.thrust[k]))

    def latest(self, kind: str) -> dict[int, tuple[int, np.ndarray]]:
        """UAV number -> (tick, q (3,)) of its newest ``state`` or ``ref`` message, decoded now:
        what the live verdict needs, without decoding the whole flight."""
        out: dict[int, tuple[int, np.ndarray]] = {}
        for (k, i), payload in list(self._last.items()):
            if k != kind:
                continue
            try:  # not through self.decoder: its counters are the flight's, counted once in series()
                msg = wire.decode(kind, payload)
            except Exception:  # noqa: BLE001 - garbage: the series' decoder counts it
                continue
            if not isinstance(msg, (wire.State, wire.Ref)):
                continue
            out[i] = ((msg.t + self.dt_ns // 2) // self.dt_ns, np.asarray(msg.q, dtype=float))
        return out

    @property
    def ts(self) -> TimeSeries:
        """The whole series (t, the leader's and the UAVs' fields, NaN where nothing arrived),
        allocated on first use; the samples still in the spool are not in it (see :meth:`series`)."""
        if self._ts is None:
            ts = TimeSeries.allocate(self.T, self.sc.n)
            ts.t, ts.q0, ts.v0 = self.t, self.q0, self.v0
            self._ts = ts
        return self._ts

    @property
    def spooled(self) -> int:
        """Samples waiting in the spool (received, not yet decoded)."""
        return self._spool.records

    def close(self) -> None:
        """Drop the samples still in the spool and free its file."""
        self._spool.close()

    def failsafe_intervals(self) -> list[dict[str, Any]]:
        """The plant's failsafe as its diagnostics told it (:attr:`failsafe_log`): one entry per
        UAV and interval it was out of nominal mode, ``{"uav": i (1-based), "modes": ["hover",
        "land"...] in order, "from_s": sim time s, "to_s": sim time s or None (still held at the
        end)}``, in order of start. A UAV there was flown by the plant, not by its agent: that
        agent's commands were stale (frozen, dead or cut off)."""
        open_: dict[int, dict[str, Any]] = {}
        done: list[dict[str, Any]] = []
        for t_ns, summary in self.failsafe_log:
            modes = {}
            for part in summary.split(","):
                uav, sep, mode = part.partition(":")
                if sep and uav.strip().isdigit():
                    modes[int(uav)] = mode.strip()
            for i in [i for i in open_ if i not in modes]:
                done.append({**open_.pop(i), "to_s": t_ns / 1e9})
            for i, mode in modes.items():
                cur = open_.setdefault(i, {"uav": i, "modes": [], "from_s": t_ns / 1e9, "to_s": None})
                if not cur["modes"] or cur["modes"][-1] != mode:
                    cur["modes"].append(mode)
        return sorted(done + list(open_.values()), key=lambda e: (e["from_s"], e["uav"]))

    def _drain(self) -> None:
        if not self._spool.records:
            return
        _ = self.ts  # the series the spooled samples go into
        for key, payload in self._spool.take():
            self._apply(key, payload)

    def _apply(self, key: str, payload: bytes) -> None:
        try:
            kind, idx, proc = self.keys.parse(key)
        except ZenswarmError:
            return
        self.counts[kind] = self.counts.get(kind, 0) + 1
        msg = self.decoder.decode(key, "ref" if kind == "leader_ref" else kind, payload)
        if msg is None:
            return
        if isinstance(msg, wire.Diag):
            fs = msg.info.get("failsafe")
            last = self.failsafe_log[-1][1] if self.failsafe_log else "none"
            if msg.process in ("plant", "bridge") and isinstance(fs, str) and last != fs:  # the bridge: a lost vehicle
                self.failsafe_log.append((int(msg.t), fs))
            self.diag[msg.process] = {**msg.counters, **{k: v for k, v in msg.info.items() if isinstance(v, (int, float, bool, str))}}
            return
        if isinstance(msg, wire.Mission):
            return
        k = (msg.t + self.dt_ns // 2) // self.dt_ns
        with self.lock:
            if isinstance(msg, wire.Clock):
                if 0 <= k <= self.T:  # a clock past the mission's end is garbage: progress must not jump
                    self.sim_t_ns = max(self.sim_t_ns, msg.t)
                else:
                    self.ignored_clocks += 1
                return
            if not 0 <= k < self.T:
                return
            if kind == "leader_ref" and isinstance(msg, wire.Ref):
                self.q0[k] = msg.q
                self.v0[k] = msg.v
                self.leader_q = msg.q
                self.leader_ticks = max(self.leader_ticks, int(k) + 1)
                if self.goal_tick is None and float(np.linalg.norm(msg.q - self._goal)) <= self._goal_tol:
                    self.goal_tick = int(k)
                return
            ts = self.ts
            if isinstance(msg, wire.Ref) and idx is not None:
                ts.qref[k, idx - 1] = msg.q
                ts.vref[k, idx - 1] = msg.v
            elif isinstance(msg, wire.State) and idx is not None:
                self.got_state[k, idx - 1] = True
                ts.q[k, idx - 1] = msg.q
                ts.v[k, idx - 1] = msg.v
                ts.rpy[k, idx - 1] = msg.rpy
                if msg.extra:
                    self._put_records(ts, k, idx - 1, msg.extra)
            elif isinstance(msg, wire.Cmd) and idx is not None:
                ts.u[k, idx - 1] = msg.u
                ts.thrust[k, idx - 1] = msg.thrust
                ts.d_hat[k, idx - 1] = msg.d_hat
                ts.rpy_cmd[k, idx - 1] = msg.rpy

    def _put_records(self, ts: TimeSeries, k: int, i: int, extra: dict[str, tuple[float, ...]]) -> None:
        """A state message's plant records (:attr:`zenswarm.bus.wire.State.extra`) into
        ``ts.plant``: each series allocated when its first value comes, (T, N, *shape) with the
        plant model's declared shape (flat when the model cannot be resolved here, e.g. a
        recording read where its plug-in is not installed, or the size does not match)."""
        for name, vals in extra.items():
            a = ts.plant.get(name)
            if a is None:
                shape = self._rec_shapes.get(name)
                if shape is None or int(np.prod(shape)) != len(vals):
                    shape = (len(vals),)
                a = ts.plant[name] = np.full((self.T, self.sc.n, *shape), np.nan)
            shape = a.shape[2:]
            if math.prod(shape) == len(vals):  # (a scalar signal's a[k, i] is not a view: assign through a)
                a[k, i] = np.reshape(np.array(vals, dtype=float), shape)

    def series(self, upto_tick: int | None = None, fill: bool = False) -> TimeSeries:
        """The collected series up to ``upto_tick``; ``fill`` forward-fills gaps (realtime)."""
        self._drain()
        with self.lock:
            T = self.T if upto_tick is None else max(0, min(self.T, upto_tick))
            ts = self.ts.truncated(T)
            ts = TimeSeries.from_arrays({f: np.array(a) for f, a in ts.arrays().items()})
        # realtime: a tick a process skipped holds its previous value (latest value wins);
        # ticks before every process produced its first value are dropped
        return fill_forward(ts) if fill else ts


def _declared_records(scenario: Scenario) -> dict[str, tuple[int, ...]]:
    """The shapes per UAV of the signals the scenario's plant model records
    (:func:`zenswarm.scenario.plugins.plant_records`); {} when the model cannot be resolved here
    (its values are then kept flat)."""
    from zenswarm.scenario.plugins import plant_records

    try:
        return {name: sig.shape for name, sig in plant_records(scenario).items()}
    except Exception:  # noqa: BLE001 - a plug-in not installed here, or anything its import raised: keep the values flat
        return {}

"""What every swarm process shares: its Zenoh session, an inbox of decoded inputs, lockstep waits,
diagnostics, liveliness, and a clean exit on SIGINT/SIGTERM.

The process shells (``agents/process.py``, ``leader/process.py``, ``plant/process.py``) are thin:
decode -> pure step -> encode. This module is the glue they share; messages cross the network in
:mod:`zenswarm.bus` (sessions) and :mod:`zenswarm.wire` (keys and payloads).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import zenoh

from . import bus, security, wire
from .config import Scenario, load_scenario, scenario_from_dict
from .errors import ScenarioError, ZenswarmError

__all__ = ["Inbox", "SwarmProcess", "add_common_args", "LoopStats"]

# Lockstep: a missing input is waited for this long (wall clock) before it counts as a drop.
DEFAULT_LOCKSTEP_TIMEOUT_S = 5.0

# Zenoh runs Python callbacks on its own threads; with the default 5 ms GIL switch interval a
# callback thread can keep the main loop waiting for the GIL for milliseconds per message.
SWITCH_INTERVAL_S = 0.0002


class Inbox:
    """Decoded messages by key: the latest one, and (for lockstep) one per tick index.

    Filled from Zenoh callbacks (other threads); read by the process loop. ``wait`` blocks until
    every (key, tick) needed is present or a deadline passes.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.latest: dict[str, Any] = {}
        self.latest_rx: dict[str, float] = {}
        self._by_tick: dict[str, dict[int, Any]] = defaultdict(dict)

    def put(self, key: str, tick: int, msg: Any) -> None:
        with self._cond:
            self.latest[key] = msg
            self.latest_rx[key] = time.monotonic()
            self._by_tick[key][tick] = msg
            self._cond.notify_all()

    def get(self, key: str, tick: int) -> Any | None:
        with self._cond:
            return self._by_tick[key].get(tick)

    def wait(self, needs: list[tuple[str, int]], timeout_s: float, stop: threading.Event | None = None) -> list[tuple[str, int]]:
        """Wait until every (key, tick) in ``needs`` has arrived; return the ones still missing."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                missing = [(k, t) for (k, t) in needs if t not in self._by_tick[k]]
                if not missing:
                    return []
                left = deadline - time.monotonic()
                if left <= 0 or (stop is not None and stop.is_set()):
                    return missing
                self._cond.wait(min(left, 0.2))

    def forget_before(self, tick: int) -> None:
        """Drop per-tick entries older than ``tick`` (bounded memory)."""
        with self._cond:
            for d in self._by_tick.values():
                for t in [t for t in d if t < tick]:
                    del d[t]

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()


class LoopStats:
    """Realtime loop timing: period jitter and missed deadlines."""

    def __init__(self, period_s: float) -> None:
        self.period = period_s
        self.ticks = 0
        self.missed = 0
        self.max_jitter_s = 0.0
        self._sum_jitter = 0.0

    def record(self, lateness_s: float) -> None:
        self.ticks += 1
        j = abs(lateness_s)
        self._sum_jitter += j
        self.max_jitter_s = max(self.max_jitter_s, j)
        if lateness_s > self.period:
            self.missed += 1

    def as_dict(self) -> dict[str, float]:
        return {
            "loop_ticks": self.ticks,
            "missed_deadlines": self.missed,
            "jitter_max_ms": 1e3 * self.max_jitter_s,
            "jitter_mean_ms": 1e3 * self._sum_jitter / self.ticks if self.ticks else 0.0,
        }


def add_common_args(p: argparse.ArgumentParser) -> None:
    """The flags every swarm process takes."""
    p.add_argument("--scenario", type=Path, help="scenario TOML; if omitted, fetched from the leader's mission key")
    p.add_argument("--swarm", default="default", help="swarm name: the key prefix swarm/<name> (default: default)")
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh router endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--realtime", action="store_true", help="run on the wall clock (latest value wins) instead of lockstep")
    security.add_security_args(p)
    from .linkfaults import add_fault_args

    add_fault_args(p)
    p.add_argument(
        "--lockstep-timeout",
        type=float,
        default=DEFAULT_LOCKSTEP_TIMEOUT_S,
        metavar="S",
        help=f"lockstep: wall seconds to wait for an input before it counts as a drop (default {DEFAULT_LOCKSTEP_TIMEOUT_S})",
    )


class SwarmProcess:
    """A process of the swarm: session, keys, decoder, inbox, diagnostics, liveliness, stop flag.

    Use as a context manager; the session is always closed (a session left open with Python
    callbacks hangs interpreter exit).
    """

    def __init__(self, name: str, args: argparse.Namespace) -> None:
        self.name = name
        self.args = args
        self.keys = wire.Keys(args.swarm)
        self.decoder = wire.Decoder()
        self.inbox = Inbox()
        self.stop = threading.Event()
        self.session: zenoh.Session | None = None
        self._subs: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._token = None
        self.counters: dict[str, float] = defaultdict(float)
        self._diag_seq = 0
        self.scenario: Scenario | None = None
        self.on_input: Callable[[str, int, Any], None] | None = None  # (key, tick, msg) of every accepted message
        self.subscribed: list[str] = []  # every key this process subscribed to (contract tests)
        self.extra_counters: Callable[[], dict[str, float]] | None = None
        self._delay_line: Any = None
        self._dl_lock = threading.Lock()
        self._links: dict[str, tuple[str, str, str]] = {}
        self._alive: dict[str, bool] = {}
        self._alive_subs: list[Any] = []

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> "SwarmProcess":
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        connect = self.args.connect or ["tcp/127.0.0.1:7447"]
        conf = bus.client_config(connect, settings=security.client_fragments_from_args(self.name, self.args))
        self._session_cm = bus.open_session(conf, handle_signals=False)
        self.session = self._session_cm.__enter__()
        self.scenario = self._load_scenario()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.stop.set()
        self.inbox.wake()

    def close(self) -> None:
        s, self.session = self.session, None
        if s is None:
            return
        try:
            if self._token is not None:
                self._token.undeclare()
        except Exception:  # noqa: BLE001 - best effort on shutdown
            pass
        for sub in self._subs + self._alive_subs:
            try:
                sub.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self._session_cm.__exit__(None, None, None)

    def _load_scenario(self) -> Scenario:
        sc = self._fetch_scenario()
        seed = getattr(self.args, "seed", None)
        return sc if seed is None else replace(sc, seed=int(seed))

    def _fetch_scenario(self) -> Scenario:
        if self.args.scenario is not None:
            return load_scenario(self.args.scenario)
        # Fetch the mission from the leader (late joiners, other hosts).
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not self.stop.is_set():
            for reply in self.session.get(self.keys.mission, timeout=2.0):
                ok = getattr(reply, "ok", None)
                if ok is None:
                    continue
                msg = wire.decode("mission", ok.payload.to_bytes())
                return scenario_from_dict(msg.scenario)
            time.sleep(0.2)
        raise ScenarioError("--scenario", "not given, and no leader answered on the mission key within 30 s")

    # ------------------------------------------------------------------ bus
    def subscribe(self, key: str, kind: str, on_msg: Callable[[str, Any], None] | None = None) -> None:
        """Subscribe to ``key``; decoded messages go to the inbox keyed by their tick."""
        dt_ns = wire.t_ns(self.scenario.timing.dt)
        decoder = self.decoder
        inbox = self.inbox

        def cb(sample: zenoh.Sample) -> None:
            msg = decoder.decode(key, kind, sample.payload.to_bytes())
            if msg is None:
                return
            tick = (msg.t + dt_ns // 2) // dt_ns
            dl = self._delay_line
            if dl is not None and key in self._links:
                with self._dl_lock:
                    dl.offer(time.monotonic(), self._links[key], key, tick, msg)
                return
            inbox.put(key, tick, msg)
            if on_msg is not None:
                on_msg(key, msg)
            hook = self.on_input
            if hook is not None:
                hook(key, tick, msg)

        self._subs.append(self.session.declare_subscriber(key, cb))
        self.subscribed.append(key)

    def publisher(self, key: str) -> Any:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, express=True, reliability=zenoh.Reliability.RELIABLE
            )
            self._pubs[key] = pub
        return pub

    def publish(self, key: str, msg: Any) -> None:
        self.publisher(key).put(wire.encode(msg))

    def announce(self) -> None:
        """Declare this process's liveliness token: all its subscriptions are in place."""
        self._token = self.session.liveliness().declare_token(self.keys.alive(self.name))

    def wait_for_alive(self, names: list[str], timeout_s: float = 60.0) -> list[str]:
        """Block until every named process has announced itself; return those still missing."""
        deadline = time.monotonic() + timeout_s
        want = {self.keys.alive(n): n for n in names}
        while not self.stop.is_set():
            seen = set()
            for reply in self.session.liveliness().get(self.keys.alive_all, timeout=1.0):
                ok = getattr(reply, "ok", None)
                if ok is not None:
                    seen.add(str(ok.key_expr))
            missing = [n for k, n in want.items() if k not in seen]
            if not missing or time.monotonic() > deadline:
                return missing
            time.sleep(0.02)
        return list(want.values())

    # ------------------------------------------------------------------ liveliness of senders
    def watch_alive(self, names: list[str], on_change: Callable[[], None] | None = None) -> None:
        """Track the liveliness tokens of ``names`` (one subscriber each, with history)."""
        for name in names:
            self._alive.setdefault(name, True)  # assume alive until told otherwise

            def cb(sample: Any, name: str = name) -> None:
                self._alive[name] = sample.kind == zenoh.SampleKind.PUT
                if on_change is not None:
                    on_change()

            self._alive_subs.append(self.session.liveliness().declare_subscriber(self.keys.alive(name), cb, history=True))

    def linger_until_gone(self, name: str, timeout_s: float = 30.0) -> None:
        """Lockstep end: stay (token held) until ``name`` is gone, so a receiver still on its last
        tick never mistakes our normal exit for a crash and stops waiting for what we sent."""
        if name not in self._alive:
            self.watch_alive([name])
        deadline = time.monotonic() + timeout_s
        while self._alive.get(name, False) and not self.stop.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)

    def is_alive(self, name: str) -> bool:
        """False once ``name``'s liveliness token is gone (True for names not watched)."""
        return self._alive.get(name, True)

    # ------------------------------------------------------------------ realtime link faults
    def use_delay_line(self, state: Any, links: dict[str, tuple[str, str, str]]) -> None:
        """Realtime link faults on these keys: decided on receipt, released after their delay."""
        from .linkfaults import DelayLine

        self._links = dict(links)
        self._delay_line = DelayLine(state, self.scenario.timing.dt)

    def release_delayed(self) -> None:
        """Hand over the delayed messages whose time has come (call from the process loop)."""
        dl = self._delay_line
        if dl is None:
            return
        with self._dl_lock:
            dl.release(time.monotonic(), self.inbox.put)

    def publish_diag(self, t_ns: int, info: dict[str, Any] | None = None) -> None:
        counters = dict(self.counters)
        counters.update(self.decoder.counters())
        if self.extra_counters is not None:
            counters.update(self.extra_counters())
        if self._delay_line is not None:
            counters.update(self._delay_line.dropped)
        self._diag_seq += 1
        self.publish(
            self.keys.diag(self.name),
            wire.Diag(
                t=t_ns,
                seq=self._diag_seq,
                process=self.name,
                counters=counters,
                info={"subscriptions": ",".join(sorted(self.subscribed)), **(info or {})},
            ),
        )

    def log(self, text: str) -> None:
        print(text, flush=True)


def run_process(fn: Callable[[SwarmProcess], int], name: str, args: argparse.Namespace) -> int:
    """Run ``fn`` inside a :class:`SwarmProcess`; map errors to exit codes and always close."""
    try:
        with SwarmProcess(name, args) as proc:
            return fn(proc)
    except ZenswarmError as e:  # bad scenario, credentials, unreachable router: say what, exit 2
        print(f"{name}: error: {e}", file=sys.stderr, flush=True)
        return 2


class Lockstep:
    """Event-driven lockstep loop: tick k runs as soon as its inputs are there.

    ``ready(k)`` says whether tick k's inputs have all arrived; ``step(k, forced)`` runs the tick
    (``forced`` = some input timed out and the tick runs with held values). ``prepare(k)`` runs
    before each readiness check (e.g. to publish what others need from us first).
    ``can_force(k)`` says whether a timed-out tick may run anyway (False when the missing input
    is the clock itself).

    Ticks run inside the Zenoh callback that delivered the last missing input (call
    :meth:`poke` from every subscriber callback), so no thread hand-off sits on the critical
    path; a lock serialises callbacks of different subscribers. :meth:`run` (main thread)
    waits for the end and forces timed-out ticks.
    """

    def __init__(
        self,
        n_ticks: int,
        ready: Callable[[int], bool],
        step: Callable[[int, bool], None],
        timeout_s: float,
        stop: threading.Event,
        prepare: Callable[[int], None] | None = None,
        can_force: Callable[[int], bool] | None = None,
        on_msg: Callable[[str, int, Any], None] | None = None,
    ) -> None:
        self.n = n_ticks
        self.k = 0
        self._ready = ready
        self._step = step
        self._prepare = prepare
        self._can_force = can_force or (lambda k: True)
        self._on_msg = on_msg
        self.timeout = timeout_s
        self.stop = stop
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.error: BaseException | None = None
        self.forced = 0
        self._wait_since: float | None = None
        self.step_s = 0.0  # wall time spent inside step(), s
        self.wait_s = 0.0  # wall time between the end of a tick and the start of the next, s
        self._t_end: float | None = None

    def poke(self, key: str | None = None, tick: int = 0, msg: Any = None) -> None:
        """Take a message (``on_msg``, under the lock) and advance as far as the inputs allow.

        Safe to call from any thread; ``poke()`` without a message just re-checks readiness
        (e.g. after a sender's liveliness changed)."""
        with self.lock:
            if key is not None and self._on_msg is not None:
                try:
                    self._on_msg(key, tick, msg)
                except BaseException as e:  # noqa: BLE001 - surfaced by run()
                    self.error = e
                    self.done.set()
                    return
            self._advance(False)

    def _advance(self, force: bool) -> None:
        if self.done.is_set():
            return
        try:
            while self.k < self.n and not self.stop.is_set():
                k = self.k
                if self._prepare is not None:
                    self._prepare(k)
                ok = self._ready(k)
                if not ok and not force:
                    if self._wait_since is None:
                        self._wait_since = time.monotonic()
                    return
                t0 = time.perf_counter()
                if self._t_end is not None:
                    self.wait_s += t0 - self._t_end
                self._step(k, not ok)
                self._t_end = time.perf_counter()
                self.step_s += self._t_end - t0
                if not ok:
                    self.forced += 1
                force = False
                self._wait_since = None
                self.k = k + 1
            self.done.set()
        except BaseException as e:  # noqa: BLE001 - surfaced by run() in the main thread
            self.error = e
            self.done.set()

    def timing(self) -> dict[str, float]:
        """Mean step and wait times per tick, ms (for diagnostics)."""
        n = max(self.k, 1)
        return {"step_ms_mean": 1e3 * self.step_s / n, "wait_ms_mean": 1e3 * self.wait_s / n, "forced_ticks": self.forced}

    def run(self) -> int:
        """Block until every tick ran (or stop); returns the number of ticks run."""
        self.poke()
        while not self.done.is_set() and not self.stop.is_set():
            self.done.wait(0.05)
            with self.lock:
                ws = self._wait_since
                if ws is not None and time.monotonic() - ws > self.timeout and self._can_force(self.k):
                    self._advance(True)
        if self.error is not None:
            raise self.error
        return self.k

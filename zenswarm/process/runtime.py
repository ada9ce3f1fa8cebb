"""What every swarm process shares: its Zenoh session, an inbox of decoded inputs, lockstep waits,
diagnostics, liveliness, and a clean exit on SIGINT/SIGTERM (:class:`SwarmProcess`, :func:`run_process`).

The process shells (``agents/process.py``, ``leader/process.py``, ``plant/process.py``) are thin:
decode -> pure step -> encode. This module is the glue they share; messages cross the network in
:mod:`zenswarm.bus` (sessions), :mod:`zenswarm.bus.keys` (the key space) and
:mod:`zenswarm.bus.wire` (payloads). Its parts, one concept a module, are importable from here as
before: the options (:mod:`zenswarm.process.options`), the input guard
(:mod:`zenswarm.process.guard`: malformed input and sender identity), the inbox
(:mod:`zenswarm.process.inbox`), the realtime clock (:mod:`zenswarm.process.clocks`), the lockstep
loop (:mod:`zenswarm.process.lockstep`) and the garbage-collector policy
(:mod:`zenswarm.process.gcpolicy`).
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import zenoh

from zenswarm import bus
from zenswarm.bus import wire
from zenswarm.errors import EXIT_PLUGIN_FAILED, PluginFailure, ScenarioError, ZenswarmError
from zenswarm.process import rtsched, security
from zenswarm.process.clocks import LoopStats, WallClock, sleep_until
from zenswarm.process.gcpolicy import (
    GC_ENV,
    GC_FORCE_LIMIT,
    GC_MIN_SLACK_S,
    GC_OLDER_LIMIT,
    GC_YOUNG_LIMIT,
    GcPolicy,
    gc_policy,
    gc_safe_point,
    gc_startup_done,
)
from zenswarm.process.guard import (
    GUARD_MARGIN_TICKS,
    GUARD_REASONS,
    MAX_ABS_VALUE,
    InputGuard,
    _KeyedDecoder,
    expected_senders,
    sample_sender,
)
from zenswarm.process.inbox import Inbox
from zenswarm.process.lockstep import CLOCK_EVERY_TICKS, LEADER_AHEAD_TICKS, Lockstep, kill_self, kill_self_line
from zenswarm.process.options import DEFAULT_LOCKSTEP_TIMEOUT_S, DEFAULT_ROUTER_LOST_TIMEOUT_S, ProcessOptions
from zenswarm.scenario.config import Scenario, load_scenario, scenario_from_dict

__all__ = ["Inbox", "SwarmProcess", "ProcessOptions", "run_process", "LoopStats", "WallClock", "sleep_until",
           "InputGuard", "GUARD_REASONS", "sample_sender", "expected_senders", "GcPolicy", "gc_policy",
           "gc_startup_done", "gc_safe_point", "GC_ENV", "GC_YOUNG_LIMIT", "GC_OLDER_LIMIT", "GC_FORCE_LIMIT",
           "GC_MIN_SLACK_S", "MAX_ABS_VALUE", "GUARD_MARGIN_TICKS", "CLOCK_EVERY_TICKS", "LEADER_AHEAD_TICKS", "Lockstep",
           "kill_self", "kill_self_line", "DEFAULT_LOCKSTEP_TIMEOUT_S", "DEFAULT_ROUTER_LOST_TIMEOUT_S", "EXIT_ROUTER_LOST",
           "PLUGIN_FAILURE_MARK", "report_plugin_failure"]

EXIT_ROUTER_LOST = 3
"""Exit status of a process that gave up on its router (``--router-lost-timeout``)."""

# Zenoh runs Python callbacks on its own threads; with the default 5 ms GIL switch interval a
# callback thread can keep the main loop waiting for the GIL for milliseconds per message.
SWITCH_INTERVAL_S = 0.0002


class SwarmProcess:
    """A process of the swarm: session, keys, decoder, inbox, diagnostics, liveliness, stop flag.

    Use as a context manager; the session is always closed (a session left open with Python
    callbacks hangs interpreter exit).
    """

    def __init__(self, name: str, options: ProcessOptions | Any) -> None:
        self.name = name
        self.options = ProcessOptions.of(options)
        self.args = options  # what it was started with: an edge's own settings (bridge/vehicles/settings.py)
        self.keys = wire.Keys(self.options.swarm)
        self.decoder = _KeyedDecoder()
        self.inbox = Inbox()
        self.stop = threading.Event()
        self.session: zenoh.Session | None = None
        self._subs: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._token: zenoh.LivelinessToken | None = None
        self.counters: dict[str, float] = defaultdict(float)
        self._diag_seq = 0
        self._scenario: Scenario | None = None
        self._on_input: Callable[[str, int, Any], None] | None = None
        self._lockstep: Lockstep | None = None
        self.subscribed: list[str] = []  # every key this process subscribed to (contract tests)
        self.extra_counters: Callable[[], dict[str, float]] | None = None
        self._delay_line: Any = None
        self._dl_lock = threading.Lock()
        self._links: dict[str, tuple[str, str, str]] = {}
        self._alive: dict[str, bool] = {}
        self._alive_subs: list[Any] = []
        # input hardening (see the module docstring): sender pinning, open or secure swarm (the
        # secure router admits alive/<process>/<zid> from the process's own credentials only)
        self.check_sender = True
        self._guard: InputGuard | None = None
        self._watched_senders: set[str] = set()
        self._zid_token: zenoh.LivelinessToken | None = None
        self._source_info: dict[str, Any] = {}
        self._transport_listener: bus.Undeclarable | None = None
        self._link_lost = False
        self._lost_since: float | None = None  # monotonic s when zenoh closed the link to the router
        self.router_gone = False  # gave up on the router (--router-lost-timeout): exit EXIT_ROUTER_LOST
        self.on_reconnect: Callable[[], None] | None = None  # called (zenoh's thread) when the link to the router is back

    @property
    def scenario(self) -> Scenario:
        """The scenario of this run: loaded (or fetched from the leader) on entering the ``with``
        block; :class:`ScenarioError` before that."""
        sc = self._scenario
        if sc is None:
            raise ScenarioError("--scenario", f"{self.name}: not loaded yet (use the process as a context manager)")
        return sc

    @scenario.setter
    def scenario(self, sc: Scenario) -> None:
        self._scenario = sc

    def _zenoh(self) -> zenoh.Session:
        """The open session (inside the ``with`` block); :class:`zenswarm.bus.BusError` outside it."""
        s = self.session
        if s is None:
            raise bus.BusError(f"{self.name}: no open zenoh session (use the process as a context manager)")
        return s

    @property
    def on_input(self) -> Callable[[str, int, Any], None] | None:
        """Called with (key, tick, msg) of every accepted message. Assigning a
        :meth:`Lockstep.poke` also tells the input guard the process's current tick."""
        return self._on_input

    @on_input.setter
    def on_input(self, hook: Callable[[str, int, Any], None] | None) -> None:
        self._on_input = hook
        owner = getattr(hook, "__self__", None)
        if isinstance(owner, Lockstep):
            self._lockstep = owner

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> SwarmProcess:
        gc_policy()  # a bad ZENSWARM_GC: exit 2 before any work
        self._check_rt_priority()  # a bad or forbidden --rt-priority: exit 2 before any work
        self._check_kill_at_tick()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)
        bus.use_swarm_runtime()  # before the first session: zenoh reads it once per process
        given = self.options.scenario is not None
        if given:  # a missing or bad file, a bad plug-in: exit 2 naming it, before the router is asked
            self.scenario = self._load_scenario()
        connect = list(self.options.connect) or ["tcp/127.0.0.1:7447"]
        conf = bus.client_config(connect, settings=security.client_fragments(
                self.name,
                security.ClientSecurity(self.options.keys, self.options.tls),
                connect=self.options.connect,
                swarm=self.options.swarm,
            ))
        self._session_cm = bus.open_session(conf, handle_signals=False)
        self.session = session = self._session_cm.__enter__()
        try:
            self._transport_listener = session.info.declare_transport_events_listener(self._on_transport)
        except Exception:  # noqa: BLE001 - diagnostics only
            self._transport_listener = None
        if not given:  # fetched from the leader over the session
            self.scenario = self._load_scenario()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _check_kill_at_tick(self) -> None:
        """``--kill-at-tick K``: a tick >= 0, lockstep only (realtime processes do not run tick by tick)."""
        k = self.options.kill_at_tick
        if k is None:
            return
        if self.options.realtime:
            raise ScenarioError("--kill-at-tick", f"{self.name}: lockstep only (a realtime process is killed from outside)")
        if int(k) < 0:
            raise ScenarioError("--kill-at-tick", f"{self.name}: a tick >= 0, got {k}")

    def _check_rt_priority(self) -> None:
        """``--rt-priority``: an integer 1-99, realtime only, and permitted to this user; what
        :meth:`announce` applies once start-up is over (:mod:`zenswarm.process.rtsched`)."""
        rtsched.set_requested(rtsched.validate(self.options.rt_priority, realtime=self.options.realtime))

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.stop.set()
        self.inbox.wake()

    def close(self) -> None:
        s, self.session = self.session, None
        if s is None:
            return
        for tok in (self._token, self._zid_token, self._transport_listener):
            try:
                if tok is not None:
                    bus.undeclare(tok)
            except Exception:  # noqa: BLE001 - best effort on shutdown
                pass
        for sub in self._subs + self._alive_subs:
            try:
                bus.undeclare(sub)
            except Exception:  # noqa: BLE001
                pass
        self._session_cm.__exit__(None, None, None)

    def _load_scenario(self) -> Scenario:
        from zenswarm.scenario.plugins import check_selection, select

        sc = self._fetch_scenario()
        seed = self.options.seed
        sc = sc if seed is None else replace(sc, seed=int(seed))
        sc = select(sc, self.options.controller, self.options.planner, self.options.plant_model)
        check_selection(sc)  # a bad plug-in name or parameter: exit 2 before any work
        return sc

    def _fetch_scenario(self) -> Scenario:
        given = self.options.scenario
        if isinstance(given, Scenario):  # parsed by the front door (zenswarm.process.settings)
            return given
        if given is not None:
            return load_scenario(given)
        # Fetch the mission from the leader (late joiners, other hosts). A reply that does not
        # decode or is not a valid scenario is counted (decoder / rejected.value) and skipped.
        deadline = time.monotonic() + 30.0
        key = self.keys.mission
        while time.monotonic() < deadline and not self.stop.is_set():
            for reply in self._zenoh().get(key, timeout=2.0):
                ok = getattr(reply, "ok", None)
                if ok is None:
                    continue
                try:
                    payload = ok.payload.to_bytes()
                except Exception as e:  # noqa: BLE001
                    self.decoder.reject(key, "malformed", f"unreadable reply: {e}")
                    continue
                msg = self.decoder.decode(key, "mission", payload)
                if not isinstance(msg, wire.Mission):  # None: rejected (counted)
                    continue
                try:
                    return scenario_from_dict(msg.scenario)
                except ZenswarmError as e:
                    self.decoder.reject(key, "value", f"not a valid scenario: {e}")
            time.sleep(0.2)
        raise ScenarioError("--scenario", "not given, and no leader answered on the mission key within 30 s")

    # ------------------------------------------------------------------ bus
    @property
    def guard(self) -> InputGuard:
        """The input guard of this process (created on first use, from the scenario and flags)."""
        g = self._guard
        if g is None:
            sc = self.scenario
            dt = sc.timing.dt
            timeout = self.options.lockstep_timeout
            realtime = self.options.realtime
            g = self._guard = InputGuard(
                dt_ns=wire.t_ns(dt),
                n_ticks=sc.timing.n_ticks,
                horizon_ticks=self._fault_horizon_ticks(),
                growth_period_s=dt if realtime else min(dt, timeout),
                paced=realtime,
                check_sender=self.check_sender,
                now_tick=self._now_tick,
                prefix=self.keys.prefix + "/",
            )
        return g

    def _fault_horizon_ticks(self) -> int:
        """Largest link-fault delay of the run, in ticks (+1), 0 without faults."""
        try:
            plan = self.options.fault_plan(self.scenario)
        except Exception:  # noqa: BLE001 - bad flags are reported by the process itself
            return 0
        if plan is None:
            return 0
        from zenswarm.link import delivery_tick

        worst = plan.worst_delay_s()
        return delivery_tick(0, worst, self.scenario.timing.dt) + 1 if worst > 0 else 0

    def _now_tick(self) -> int | None:
        """Lockstep: the tick this process is at, once it ran one (None before, and in realtime)."""
        ls = self._lockstep
        if ls is None or not ls.started:
            return None
        return ls.k

    def handle_sample(self, key: str, kind: str, sample: Any, senders: tuple[str, ...] = (),
                      on_msg: Callable[[str, Any], None] | None = None) -> Any | None:
        """One received sample of ``key``: decode, guard, then hand it on (delay line or inbox,
        ``on_msg``, :attr:`on_input`). Returns the accepted message, or None if it was rejected
        (counted). Never raises for a bad sample (exceptions of the hand-on callbacks propagate)."""
        try:
            payload = sample.payload.to_bytes()
        except Exception as e:  # noqa: BLE001 - not a readable zenoh sample
            self.decoder.reject(key, "malformed", f"unreadable sample: {type(e).__name__}")
            return None
        msg = self.decoder.decode(key, kind, payload)
        if msg is None:
            return None
        dt_ns = self.guard.dt_ns
        tick = (msg.t + dt_ns // 2) // dt_ns
        if self.guard.check(key, senders, tick, msg, sample_sender(sample)) is not None:
            return None
        dl = self._delay_line
        if dl is not None and key in self._links:
            with self._dl_lock:
                dl.offer(time.monotonic(), self._links[key], key, tick, msg)
            return msg
        self.inbox.put(key, tick, msg)
        if on_msg is not None:
            on_msg(key, msg)
        hook = self._on_input
        if hook is not None:
            hook(key, tick, msg)
        return msg

    def subscribe(self, key: str, kind: str, on_msg: Callable[[str, Any], None] | None = None) -> None:
        """Subscribe to ``key``; decoded messages that pass the input guard go to the inbox keyed
        by their tick (see :meth:`handle_sample`)."""
        senders = expected_senders(self.keys, key)
        self.guard  # noqa: B018 - create it before the first sample
        if self.check_sender:
            self._watch_sender_tokens(senders)
        handle = self.handle_sample

        def cb(sample: zenoh.Sample) -> None:
            handle(key, kind, sample, senders, on_msg)

        # On zenoh's receiving thread (bus.direct_callback). Lockstep ticks, and their puts, run
        # there; in realtime the callback only files the message and the main loop puts. A put
        # releases the GIL while it waits for queue space, so a main-loop put never keeps this
        # callback from running (tests/test_bus.py checks it).
        self._subs.append(self._zenoh().declare_subscriber(key, bus.direct_callback(cb)))
        self.subscribed.append(key)

    def _watch_sender_tokens(self, names: tuple[str, ...]) -> None:
        """Follow ``alive/<name>/<zid>`` of each sender name (which sessions are that process)."""
        guard = self.guard
        for name in names:
            if name in self._watched_senders:
                continue
            self._watched_senders.add(name)
            prefix = self.keys.alive(name) + "/"

            def cb(sample: Any, name: str = name, prefix: str = prefix) -> None:
                key = str(sample.key_expr)
                if key.startswith(prefix):
                    guard.token(name, key[len(prefix):], sample.kind == zenoh.SampleKind.PUT)

            self._alive_subs.append(self._zenoh().liveliness().declare_subscriber(prefix + "*", cb, history=True))

    def _on_transport(self, event: Any) -> None:
        """Our link to the router went away or came back (zenoh clients reconnect by themselves)."""
        try:
            up = event.kind == zenoh.SampleKind.PUT
        except Exception:  # noqa: BLE001
            return
        if not up:
            self._link_lost = True
            since = self._lost_since = time.monotonic()
            self.counters["router_link_lost"] += 1
            wait = self.options.router_lost_timeout
            self.log(f"{self.name}: link to the router lost; zenoh keeps trying to reconnect for {wait:g} s (--router-lost-timeout)")
            t = threading.Timer(wait, self._router_lost_for_good, args=(since,))
            t.daemon = True
            t.start()
        elif self._link_lost:
            self._link_lost = False
            self._lost_since = None
            self.counters["router_reconnects"] += 1
            if self._guard is not None:
                self._guard.discontinuity()
            self.log(f"{self.name}: reconnected to the router (messages sent meanwhile are lost)")
            hook = self.on_reconnect
            if hook is not None:
                hook()

    def _router_lost_for_good(self, since: float) -> None:
        """The router did not come back within ``--router-lost-timeout`` of the link loss at
        ``since``: stop the process (its loop ends, it exits with :data:`EXIT_ROUTER_LOST`)."""
        if not self._link_lost or self._lost_since != since or self.stop.is_set():
            return
        self.router_gone = True
        self.counters["router_lost"] += 1
        self.log(f"{self.name}: error: the router has been unreachable for {self.options.router_lost_timeout:g} s "
                 f"(--router-lost-timeout); giving up, exit {EXIT_ROUTER_LOST}")
        self.stop.set()
        self.inbox.wake()

    def publisher(self, key: str) -> Any:
        pub = self._pubs.get(key)
        if pub is None:
            # BLOCK: lockstep traffic must not be dropped. No express (one batch per message): it
            # costs a write, and a wake-up of zenoh's thread, per put: 16 puts of a State cost 42 µs
            # wall / 64 µs CPU each with express, 2.7 / 13.5 µs without; realtime at 16 UAVs missed
            # 0.73-0.76 % of deadlines with express, 0.09-0.42 % without, p99 25 ms against 9-14 ms
            # (BENCHMARKS.md, "Scheduling of the lockstep tick"). The lockstep gain when express was
            # first turned off (up to 36 %, with zenoh's default threads) is in git history:
            # `git show 3ff7b8f:BENCHMARKS.md`.
            pub = self._zenoh().declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.BLOCK,
                express=False,
                reliability=zenoh.Reliability.RELIABLE,
            )
            self._pubs[key] = pub
        return pub

    def publish(self, key: str, msg: Any) -> None:
        """Encode and put ``msg`` on ``key``, stamped with this publisher's id (``SourceInfo``),
        so receivers can tell which session sent it."""
        self.put(key, wire.encode(msg))

    def put(self, key: str, payload: bytes) -> None:
        """Put an encoded message (:func:`zenswarm.bus.wire.encode`, or its hot paths such as
        :func:`zenswarm.bus.wire.encode_state`) on ``key``, stamped like :meth:`publish`."""
        pub = self._pubs.get(key)
        if pub is None:
            pub = self.publisher(key)
        si = self._source_info.get(key)
        if si is None:
            si = self._source_info[key] = zenoh.SourceInfo(pub.id, 0)
        pub.put(payload, source_info=si)

    def announce(self) -> None:
        """Declare this process's liveliness token: all its subscriptions are in place. Also
        ``alive/<process>/<zid>``: which session is this process (the receivers pin to it)."""
        session = self._zenoh()
        if self.check_sender and self._zid_token is None:
            self._zid_token = session.liveliness().declare_token(f"{self.keys.alive(self.name)}/{session.zid()}")
        self._token = session.liveliness().declare_token(self.keys.alive(self.name))
        if self.options.realtime:
            gc_startup_done()  # subscribed and announced: start-up is over (see GcPolicy; realtime only)
            rtsched.apply_after_startup(self.log)  # --rt-priority: the loops under SCHED_FIFO from now on

    def wait_for_alive(self, names: list[str], timeout_s: float = 60.0) -> list[str]:
        """Block until every named process has announced itself; return those still missing."""
        deadline = time.monotonic() + timeout_s
        want = {self.keys.alive(n): n for n in names}
        while not self.stop.is_set():
            seen = set()
            for reply in self._zenoh().liveliness().get(self.keys.alive_all, timeout=1.0):
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

            self._alive_subs.append(self._zenoh().liveliness().declare_subscriber(self.keys.alive(name), cb, history=True))

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
        from zenswarm.link import DelayLine

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
        counters = self.diag_counters()
        self._diag_seq += 1
        self.publish(
            self.keys.diag(self.name),
            wire.Diag(
                t=t_ns,
                seq=self._diag_seq,
                process=self.name,
                counters=counters,
                info={
                    "subscriptions": ",".join(sorted(self.subscribed)),
                    "zenoh_threads": bus.zenoh_threads(),
                    **self._reject_info(),
                    **(info or {}),
                },
            ),
        )

    def _reject_info(self) -> dict[str, str]:
        """The last rejected input, for the humans reading diagnostics."""
        out = {}
        if self.decoder.last_error:
            out["last_decode_error"] = self.decoder.last_error[:200]
        if self._guard is not None and self._guard.last_reject:
            out["last_reject"] = self._guard.last_reject[:200]
        return out

    def diag_counters(self) -> dict[str, float]:
        """Every counter of this process: its own, the decoder's (``decoded``, ``rejected``,
        ``rejected.<reason>``), the input guard's (``accepted``, ``rejected.<reason>``), rejects
        per key (``rejected@<key>.<reason>``), link faults and the process's extra counters."""
        counters = dict(self.counters)
        counters.update(self.decoder.counters())
        plen = len(self.keys.prefix) + 1
        for (key, reason), n in list(self.decoder.by_key.items()):
            counters[f"rejected@{key[plen:] if key.startswith(self.keys.prefix) else key}.{reason}"] = n
        if self._guard is not None:
            for name, n in self._guard.counters().items():  # out_of_range is a decoder reason too: add up
                counters[name] = counters.get(name, 0) + n
            counters["rejected"] = self.decoder.rejected + self._guard.rejected
            counters["accepted"] = self._guard.accepted
        counters.update(gc_policy().counters())
        counters.update(rtsched.counters())
        if self.extra_counters is not None:
            counters.update(self.extra_counters())
        if self._delay_line is not None:
            counters.update(self._delay_line.dropped)
        return counters

    def log(self, text: str) -> None:
        print(text, flush=True)


PLUGIN_FAILURE_MARK = "zenswarm-plugin-failure "
"""The line a swarm process prints (``MARK`` + JSON of :meth:`zenswarm.errors.PluginFailure.to_dict`)
before it exits with :data:`zenswarm.errors.EXIT_PLUGIN_FAILED`: how its supervisor learns
which plug-in failed, where and when."""


PLUGIN_FAILURE_LINGER_S = 30.0
"""Wall seconds a process whose plug-in failed stays up at most (its token held), until the plant
is gone or it is stopped: what it published last reaches its receivers, and they never mistake
it for a crash."""


def report_plugin_failure(proc: SwarmProcess | None, e: PluginFailure) -> None:
    """Say that a plug-in failed: a line for humans, the machine-readable line
    (:data:`PLUGIN_FAILURE_MARK`) for the supervisor, and a diagnostic on the bus (best effort);
    then linger (:data:`PLUGIN_FAILURE_LINGER_S`) until the flight is over."""
    import json

    print(f"{e.process}: plugin_error: {e}", file=sys.stderr, flush=True)
    print(PLUGIN_FAILURE_MARK + json.dumps(e.to_dict(), sort_keys=True), file=sys.stderr, flush=True)
    if proc is not None and proc.session is not None:
        try:
            dt_ns = wire.t_ns(proc.scenario.timing.dt) if proc.scenario is not None else 0
            proc.publish_diag(e.tick * dt_ns, {"plugin_failure": json.dumps(e.to_dict(), sort_keys=True)})
        except Exception:  # noqa: BLE001 - the line above is what counts
            pass
        if proc.name != "plant":
            proc.linger_until_gone("plant", PLUGIN_FAILURE_LINGER_S)


def run_process(fn: Callable[[SwarmProcess], int], name: str, options: ProcessOptions | Any) -> int:
    """Run ``fn`` inside a :class:`SwarmProcess` started with ``options`` (or any object with
    their attribute names, see :meth:`ProcessOptions.of`); map errors to exit codes (2: bad
    scenario, credentials, unreachable router; 4: a plug-in failed, :func:`report_plugin_failure`)
    and always close."""
    try:
        with SwarmProcess(name, options) as proc:
            try:
                rc = fn(proc)
            except PluginFailure as e:
                report_plugin_failure(proc, e)
                return EXIT_PLUGIN_FAILED
            return EXIT_ROUTER_LOST if proc.router_gone else rc
    except ZenswarmError as e:  # bad scenario, credentials, unreachable router: say what, exit 2
        print(f"{name}: error: {e}", file=sys.stderr, flush=True)
        return 2

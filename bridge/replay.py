"""Replay a recording onto Zenoh, and verify an agent against a recording.

``zenswarm replay FILE [--swarm NAME] [--connect EP] [--rate R] [--loop] [--topics KEYEXPR]
[--start S] [--end S]`` republishes the recorded payloads, byte for byte, with their original
timing (log-time deltas divided by the rate), optionally under another swarm name.

``zenswarm replay --verify FILE --agent I`` (also ``zenswarm verify FILE [--agent I|all]``)
rebuilds agent I's controller from the recorded scenario, feeds it agent I's recorded inputs
tick by tick exactly as :mod:`zenswarm.agents.process` does, and compares what it computes with what the
agent published: bit for bit. The tool for "why did UAV 2 do that".
"""

from __future__ import annotations

import argparse
import bisect
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm import wire
from zenswarm.bridge import live
from zenswarm.bridge.mcapio import Recording, read_recording
from zenswarm.errors import RecordingError, ScenarioError
from zenswarm.runtime import sleep_until

__all__ = [
    "ReplayStats",
    "check_window",
    "replay",
    "Difference",
    "VerifyResult",
    "verify_agent",
    "rewrite_topic",
    "add_parsers",
]

PROGRESS_EVERY_S = 1.0


# --------------------------------------------------------------------------- replay


@dataclass
class ReplayStats:
    published: int = 0
    skipped: int = 0
    loops: int = 0
    span_s: float = 0.0
    wall_s: float = 0.0
    max_lag_s: float = 0.0
    stopped_by: str = ""
    problems: list[str] = field(default_factory=list)


def _original_swarm(rec: Recording, first_topic: str | None) -> str | None:
    if rec.swarm:
        return rec.swarm
    if first_topic and first_topic.startswith("swarm/"):
        parts = first_topic.split("/")
        if len(parts) > 2:
            return parts[1]
    return None


def rewrite_topic(topic: str, orig: str | None, new: str | None) -> str:
    """``swarm/<orig>/rest`` -> ``swarm/<new>/rest`` (unchanged if not under ``swarm/<orig>/``)."""
    if not new or not orig or new == orig:
        return topic
    prefix = f"swarm/{orig}/"
    if topic.startswith(prefix):
        return f"swarm/{new}/" + topic[len(prefix) :]
    return topic


def _topic_filter(expr: str | None) -> Callable[[str], bool] | None:
    if not expr:
        return None
    import zenoh

    try:
        ke = zenoh.KeyExpr(expr)
    except Exception as e:  # noqa: BLE001 - zenoh raises ZError
        raise ScenarioError("--topics", f"invalid key expression {expr!r}: {e}") from None
    cache: dict[str, bool] = {}

    def match(topic: str) -> bool:
        r = cache.get(topic)
        if r is None:
            try:
                r = ke.intersects(zenoh.KeyExpr(topic))
            except Exception:  # noqa: BLE001 - a topic that is not a valid key
                r = False
            cache[topic] = r
        return r

    return match


def _span_and_topics(rec: Recording, path: str | Path) -> tuple[float | None, list[str]]:
    """The recording's span in seconds (last minus first log time; None if it holds no message)
    and its recorded topics: from the summary of a complete file, else by reading it once."""
    st = rec.statistics
    if rec.complete and st is not None:
        span = (st.message_end_time - st.message_start_time) / 1e9 if st.message_count else None
        return span, rec.topics()
    first: int | None = None
    last = 0
    topics: set[str] = set()
    for m in read_recording(path, strict=False).messages():
        if first is None:
            first = m.log_time
        last = m.log_time
        topics.add(m.topic)
    return (None if first is None else (last - first) / 1e9), sorted(topics)


def _check_window_flags(start_s: float | None, end_s: float | None) -> None:
    """``--start``/``--end`` on their own: finite, >= 0, end not before start (ScenarioError)."""
    import math

    for flag, v in (("--start", start_s), ("--end", end_s)):
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise ScenarioError(flag, f"must be a number of seconds >= 0 after the first recorded message, got {v:g}")
    if start_s is not None and end_s is not None and end_s < start_s:
        raise ScenarioError("--end", f"{end_s:g} s is before --start {start_s:g} s")


def check_window(
    rec: Recording, path: str | Path, start_s: float | None, end_s: float | None, topics: str | None
) -> float | None:
    """Bad ``--start``/``--end``/``--topics`` for this recording raise :class:`ScenarioError`
    naming the flag and the recording's actual span (exit 2 from the CLI, before anything is
    published): a negative or non-finite time, ``--end`` before ``--start``, ``--start`` beyond
    the last message, a key expression that matches none of the recorded keys. Returns the span (s)."""
    _check_window_flags(start_s, end_s)
    match = _topic_filter(topics)
    if start_s is None and end_s is None and match is None:
        return None
    span, recorded = _span_and_topics(rec, path)
    where = "it holds no message" if span is None else f"it spans 0 to {span:.3f} s from its first message"
    if start_s is not None and (span is None or start_s > span):
        raise ScenarioError("--start", f"{start_s:g} s is beyond the end of the recording {path}: {where}")
    if match is not None and not any(match(t) for t in recorded):
        shown = ", ".join(recorded[:8]) + (f", ... ({len(recorded)} keys)" if len(recorded) > 8 else "")
        raise ScenarioError(
            "--topics", f"{topics!r} matches none of the keys recorded in {path} ({shown or 'none'}); nothing to replay"
        )
    return span


class _Player:
    """One replay's publishing side: a publisher per (rewritten) key, declared at first use,
    pacing at ``rate`` (0 = as fast as possible), progress lines; counts in ``stats``.
    Times: ``time.monotonic()`` s; log times ns."""

    def __init__(
        self,
        session: Any,
        rec: Recording,
        *,
        swarm: str | None,
        rate: float,
        match: Callable[[str], bool] | None,
        stop: threading.Event,
        stats: ReplayStats,
        progress: Callable[[str], None] | None,
        wait_subscribers_s: float,
        wall0: float,
    ) -> None:
        self.session = session
        self.rec = rec
        self.swarm = swarm
        self.rate = rate
        self.match = match
        self.stop = stop
        self.stats = stats
        self.progress = progress
        self.wait_subscribers_s = wait_subscribers_s
        self.wall0 = wall0
        self.total_s: float | None = None  # the recording's span, s (complete files), for progress
        if rec.statistics is not None and rec.statistics.message_count:
            self.total_s = (rec.statistics.message_end_time - rec.statistics.message_start_time) / 1e9
        self.pubs: dict[str, Any] = {}
        self.rewritten: dict[str, str] = {}
        self.waited = False
        self.last_progress = time.monotonic()

    def play_once(self, path: str | Path, t_lo: int | None, t_hi: int | None) -> bool:
        """Publish the recording once, within [t_lo, t_hi] ns from its first message; False if
        it holds no message."""
        stats = self.stats
        file_t0: int | None = None
        play_t0: int | None = None
        wall_t0 = 0.0
        orig: str | None = None
        for m in read_recording(path, strict=False).messages():
            if self.stop.is_set():
                break
            if file_t0 is None:
                file_t0 = m.log_time
                orig = _original_swarm(self.rec, m.topic)
            rel = m.log_time - file_t0
            if t_lo is not None and rel < t_lo:
                continue
            if t_hi is not None and rel > t_hi:
                break
            if self.match is not None and not self.match(m.topic):
                stats.skipped += 1
                continue
            pub = self._publisher(m.topic, orig)
            if play_t0 is None:
                play_t0 = m.log_time
                wall_t0 = time.monotonic()
            if self.rate > 0:
                self._wait_until(wall_t0 + (m.log_time - play_t0) / 1e9 / self.rate)
            pub.put(m.payload)
            stats.published += 1
            stats.span_s = max(stats.span_s, (m.log_time - play_t0) / 1e9)
            self._report(rel)
        return file_t0 is not None

    def _publisher(self, topic: str, orig: str | None) -> Any:
        """The publisher of ``topic`` under the replay's swarm; before the first put, waits for a
        subscriber to match (puts before that would be lost)."""
        import zenoh

        from zenswarm import bus

        key = self.rewritten.get(topic)
        if key is None:
            key = self.rewritten[topic] = rewrite_topic(topic, orig, self.swarm)
        pub = self.pubs.get(key)
        if pub is None:
            pub = self.pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
            )
            if not self.waited:
                self.waited = True
                if not bus.wait_matching(pub, timeout=self.wait_subscribers_s) and self.progress:
                    self.progress(f"replay: no subscriber on {key} after {self.wait_subscribers_s:g} s; publishing anyway")
        return pub

    def _wait_until(self, target: float) -> None:
        """Sleep until ``target`` (or a stop); note how late it was."""
        sleep_until(target, self.stop, slice_s=0.1)
        lag = time.monotonic() - target
        if lag > self.stats.max_lag_s:
            self.stats.max_lag_s = lag

    def _report(self, rel: int) -> None:
        """A progress line every PROGRESS_EVERY_S (``rel``: ns since the first message)."""
        now = time.monotonic()
        if self.progress is not None and now - self.last_progress >= PROGRESS_EVERY_S:
            self.last_progress = now
            stats = self.stats
            of = f"/{self.total_s:.1f}" if self.total_s is not None else ""
            self.progress(
                f"replay: loop {stats.loops}  t={rel / 1e9:.1f}{of} s  {stats.published} published  "
                f"{stats.published / max(now - self.wall0, 1e-9):.0f} msg/s"
            )


def replay(
    path: str | Path,
    *,
    connect: list[str],
    swarm: str | None = None,
    rate: float = 1.0,
    loop: bool = False,
    topics: str | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    wait_subscribers_s: float = 2.0,
    linger_s: float = 0.5,
    stop: threading.Event | None = None,
    progress: Callable[[str], None] | None = None,
) -> ReplayStats:
    """Republish the recorded payloads of ``path`` onto Zenoh (client of ``connect``).

    rate: playback speed (2 = twice as fast; 0 = as fast as possible). start_s/end_s: window in
    seconds from the first recorded message. topics: zenoh key expression matched against the
    recorded topics. swarm: replay under ``swarm/<swarm>/`` instead of the recorded prefix.
    loop: start over at the end until ``stop`` is set. Before the first put, waits up to
    ``wait_subscribers_s`` for a subscriber to match (puts before that would be lost). A window
    or filter that does not fit the recording raises :class:`ScenarioError` first
    (:func:`check_window`).
    """
    from zenswarm import bus

    if rate < 0:
        raise ScenarioError("--rate", f"must be >= 0, got {rate}")
    if swarm is not None:
        wire.validate_swarm_name(swarm)
    match = _topic_filter(topics)
    stop = stop or threading.Event()
    stats = ReplayStats()
    rec = read_recording(path, strict=False)
    check_window(rec, path, start_s, end_s, topics)
    stats.problems += rec.problems
    t_lo = None if start_s is None else round(start_s * 1e9)
    t_hi = None if end_s is None else round(end_s * 1e9)
    wall0 = time.monotonic()
    with bus.open_session(bus.client_config(connect), handle_signals=False) as session:
        player = _Player(
            session, rec, swarm=swarm, rate=rate, match=match, stop=stop, stats=stats, progress=progress,
            wait_subscribers_s=wait_subscribers_s, wall0=wall0,
        )
        while not stop.is_set():
            stats.loops += 1
            if not player.play_once(path, t_lo, t_hi):
                stats.stopped_by = "empty recording"
                break
            if not loop:
                stats.stopped_by = "end of recording" if not stop.is_set() else "interrupted"
                break
        else:
            stats.stopped_by = "interrupted"
        if linger_s > 0 and not stop.is_set():
            time.sleep(linger_s)  # let the last batches leave before the session closes
    stats.wall_s = time.monotonic() - wall0
    return stats


def _run_replay(args: argparse.Namespace) -> int:
    if args.verify:
        return _run_verify(args)
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)

    def progress(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    connect = args.connect or ["tcp/127.0.0.1:7447"]
    viewer = live.replay_viewer(args.file, args.swarm, args.live, connect) if args.live is not None else None  # port in use: exit 2 now
    st = replay(
        args.file,
        connect=connect,
        swarm=args.swarm,
        rate=args.rate,
        loop=args.loop,
        topics=args.topics,
        start_s=args.start,
        end_s=args.end,
        wait_subscribers_s=args.wait_subscribers,
        stop=stop,
        progress=progress,
    )
    if viewer is not None:
        viewer.close()
    for p in st.problems:
        progress(f"replay: warning: {args.file}: {p}")
    progress(
        f"replay: {st.stopped_by}: {st.published} messages published ({st.skipped} filtered out) in "
        f"{st.loops} loop(s), {st.wall_s:.2f} s wall, max lag {1e3 * st.max_lag_s:.1f} ms"
    )
    return 0


# --------------------------------------------------------------------------- verify


@dataclass
class Difference:
    """First mismatch between the recording and the recomputation."""

    tick: int
    field: str
    recorded: Any
    recomputed: Any

    def __str__(self) -> str:
        return f"tick {self.tick}, {self.field}: recorded {_fmt(self.recorded)} vs recomputed {_fmt(self.recomputed)}"


@dataclass
class VerifyResult:
    agent: int
    ticks: int = 0
    mode: str | None = None
    difference: Difference | None = None
    notes: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.difference is None


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        return f"{x!r} (0x{struct.unpack('<Q', struct.pack('<d', x))[0]:016x})"
    return str(x)


def _same(a: float, b: float) -> bool:
    """Bit-for-bit equality of two float64 values."""
    return struct.pack("<d", a) == struct.pack("<d", b)


def _compare_vec(tick: int, name: str, rec: np.ndarray, new: np.ndarray) -> Difference | None:
    r = np.asarray(rec, dtype=np.float64).reshape(-1)
    n = np.asarray(new, dtype=np.float64).reshape(-1)
    for j in range(len(r)):
        if not _same(float(r[j]), float(n[j])):
            return Difference(tick, f"{name}[{j}]", float(r[j]), float(n[j]))
    return None


def _compare_cmd(tick: int, rec: wire.Cmd, cmd: Any) -> Difference | None:
    if not _same(rec.thrust, float(cmd.thrust)):
        return Difference(tick, "cmd.thrust", rec.thrust, float(cmd.thrust))
    for name in ("rpy", "u", "d_hat"):
        d = _compare_vec(tick, f"cmd.{name}", getattr(rec, name), getattr(cmd, name))
        if d is not None:
            return d
    return None


def _compare_ref(tick: int, rec: wire.Ref, shared: Any) -> Difference | None:
    """ref.q, ref.v and each extra shared quantity (:attr:`zenswarm.wire.Ref.extra`), bit for bit."""
    d = _compare_vec(tick, "ref.q", rec.q, shared.q) or _compare_vec(tick, "ref.v", rec.v, shared.v)
    if d is not None:
        return d
    extra = dict(shared.extra)
    if sorted(extra) != sorted(rec.extra):
        return Difference(tick, "ref.extra", sorted(rec.extra), sorted(extra))
    for name, x in extra.items():
        d = _compare_vec(tick, f"ref.extra.{name}", np.asarray(rec.extra[name]), np.asarray(x))
        if d is not None:
            return d
    return None


def _swarm_of(rec: Recording) -> str:
    if rec.swarm:
        return rec.swarm
    for t in rec.topics():
        s = _original_swarm(rec, t)
        if s:
            return s
    for m in rec.messages():
        s = _original_swarm(rec, m.topic)
        if s:
            return s
    raise RecordingError(f"{rec.path}: cannot tell the swarm name (no metadata and no swarm/<name>/ topics)")


def _recorded_seed(rec: Recording, sc: Any) -> Any:
    """The scenario with the run's ``--seed`` (recorded with the fault flags) applied: the
    controllers' random streams (:func:`zenswarm.plugins.plugin_rng`) derive from it."""
    import json
    from dataclasses import replace

    from zenswarm.bridge.args import add_fault_args

    p = argparse.ArgumentParser(add_help=False)
    add_fault_args(p)
    seed = p.parse_args(json.loads(rec.info.get("fault_args", "[]"))).seed
    return sc if seed is None else replace(sc, seed=int(seed))


def _fault_plan(rec: Recording, sc: Any) -> Any:
    """The link-fault plan of the recorded run: the scenario's ``[faults]`` table plus the fault
    flags the recorder was given (metadata ``fault_args``). None when no fault was active."""
    import json

    from zenswarm.bridge.args import add_fault_args, link_faults

    p = argparse.ArgumentParser(add_help=False)
    add_fault_args(p)
    words = json.loads(rec.info.get("fault_args", "[]"))
    return link_faults(p.parse_args(words)).plan(sc)


def verify_agent(path: str | Path, agent: int, *, strict: bool = False) -> VerifyResult:
    """Re-run agent ``agent``'s controller on its recorded inputs and compare its outputs.

    Lockstep (and unknown-mode) recordings are replayed as :mod:`zenswarm.agents.process` runs lockstep.
    The agent (re)starts where it published a reference with ``seq == 1`` (normally tick 0; a
    restarted process starts its sequence numbers again): it resets the generator and ESO from
    the state of that tick, and that recorded reference must equal the reset. Then for each tick
    k up to the last recorded command: own state of tick k, neighbours' refs and, if pinned, the
    leader's ref of tick k, holding the newest earlier value when one is missing from the
    recording (as the agent does after a timeout). With link faults (the scenario's ``[faults]``
    table and the recorder's fault flags) every input goes through the same
    :class:`zenswarm.linkfaults.Box` the agent uses, so the same messages are lost or delayed.
    The tick of a message is ``(t + dt_ns // 2) // dt_ns`` as in
    :meth:`zenswarm.runtime.SwarmProcess.subscribe`. A restarted agent's first tick is fed no
    inputs of that tick (they were sent before it subscribed): an approximation.
    Realtime recordings: the agent ticked on each new state with the latest inputs; the inputs
    are taken as the newest recorded before the command's receive time (an approximation: a
    difference may come from it; link faults are not replayed there).

    Compares, bit for bit, cmd(k) (thrust, rpy, u, d_hat) and ref(k + 1) (q, v), and stops at the
    first difference. strict: refuse a damaged file (default: verify what is readable and list
    the damage in ``problems``).
    """
    rec = read_recording(path, strict=strict)
    sc = _recorded_seed(rec, rec.load_scenario())
    if not 1 <= agent <= sc.n:
        raise ScenarioError("--agent", f"agent {agent} out of range 1..{sc.n} for scenario {sc.name}")
    v = _Verifier(rec, sc, agent)
    v.res.problems += rec.problems
    dropped = rec.dropped_note()
    if dropped is not None:
        v.res.notes.append(dropped)
    if v.decoder.rejected:
        v.res.notes.append(f"{v.decoder.rejected} recorded payloads of agent {agent}'s keys were rejected by the decoder")
    v.find_starts()
    try:
        if rec.mode == "realtime":
            v.verify_realtime()
        else:
            v.verify_lockstep(_fault_plan(rec, sc))
    except _Differs as e:
        v.res.difference = e.difference
    return v.res


class _Differs(Exception):
    """The first difference: ends the verification."""

    def __init__(self, difference: Difference) -> None:
        super().__init__(str(difference))
        self.difference = difference


class _Verifier:
    """Agent ``agent``'s recorded messages, and its controller plug-in (the recorded scenario's
    ``[agents] controller``) fed with them tick by tick (as the agent process feeds it, through
    :func:`zenswarm.agents.api.prepare` and :func:`zenswarm.agents.api.finish`)."""

    def __init__(self, rec: Recording, sc: Any, agent: int) -> None:
        from zenswarm.agents.core import AgentRow
        from zenswarm.params import QuadParams

        self.sc = sc
        self.res = VerifyResult(agent=agent, mode=rec.mode)
        self.keys = keys = wire.Keys(_swarm_of(rec))
        self.me = wire.agent(agent)
        params = QuadParams.from_vehicle(sc.vehicle)
        self.row = AgentRow.from_scenario(sc, agent - 1, params.mass, params.g)
        self.quad = params
        self.ctrl = self._new_controller()
        self.dt_ns = wire.t_ns(sc.timing.dt)
        self.state_key, self.ref_key, self.cmd_key = keys.state(agent), keys.ref(agent), keys.cmd(agent)
        self.nbr_keys = [keys.ref(j + 1) for j in self.row.neighbours]
        self.input_keys = self.nbr_keys + ([keys.leader_ref] if self.row.pinned else [])
        self.sender = {self.state_key: "plant", keys.leader_ref: "leader"}
        self.sender.update({keys.ref(j + 1): wire.agent(j + 1) for j in self.row.neighbours})
        self.decoder = wire.Decoder()
        self._read(rec)

    def _read(self, rec: Recording) -> None:
        """Decode the agent's keys: the newest message per (key, tick), each key's timeline and
        the agent's start references (seq 1: a (re)start of the agent process)."""
        wanted = {self.state_key: "state", self.ref_key: "ref", self.cmd_key: "cmd"}
        wanted.update({k: "ref" for k in self.input_keys})
        self.by_tick: dict[str, dict[int, Any]] = {k: {} for k in wanted}
        self.timeline: dict[str, list[tuple[int, int, Any]]] = {k: [] for k in wanted}  # (log_time, tick, msg)
        self.start_refs: dict[int, wire.Ref] = {}
        dt_ns = self.dt_ns
        for m in rec.messages(topics=wanted.__contains__):
            msg = self.decoder.decode(m.topic, wanted[m.topic], m.payload)
            if msg is None:
                continue
            k = (msg.t + dt_ns // 2) // dt_ns
            if m.topic == self.ref_key and isinstance(msg, wire.Ref) and msg.seq == 1:
                self.start_refs[k] = msg
            else:
                self.by_tick[m.topic][k] = msg  # the latest wins, as in the inbox
            self.timeline[m.topic].append((m.log_time, k, msg))
        self.cmds = self.by_tick[self.cmd_key]
        if not self.cmds:
            raise RecordingError(f"{rec.path}: no commands of agent {self.res.agent} ({self.cmd_key}) in the recording")
        self.last = max(self.cmds)
        self.refs = self.by_tick[self.ref_key]  # references published after a tick (seq > 1)
        self.states = self.by_tick[self.state_key]

    def find_starts(self) -> None:
        """The ticks where the agent (re)started (its references with seq 1)."""
        self.starts = sorted(self.start_refs)
        if not self.starts:
            self.starts = [min(self.cmds)]
            self.res.notes.append(f"the agent's start reference (seq 1) is not in the recording; starting at tick {self.starts[0]}")
        if len(self.starts) > 1:
            self.res.notes.append(f"the agent (re)started at ticks {self.starts}")

    def state(self, k: int) -> wire.State:
        st = self.states.get(k)
        if st is None:
            raise _Differs(Difference(k, "input state", "<missing from the recording>", "needed to compute the tick"))
        return st

    def _new_controller(self) -> Any:
        from zenswarm.agents.api import make_controller

        return make_controller(self.sc, self.res.agent - 1, self.quad.mass, self.quad.g)

    def compute(self, k: int, st: wire.State, inputs: dict[str, Any], seg_end: int) -> None:
        """Tick k exactly as the agent process ticks (:func:`zenswarm.agents.api.prepare`, then
        :func:`zenswarm.agents.api.finish` with the nominal dt), then compare cmd(k) and ref(k + 1)."""
        from zenswarm.agents.api import finish, prepare

        ctrl = self.ctrl
        nbr = [inputs.get(key) for key in self.nbr_keys]
        cmd = finish(ctrl, st.q, st.v, prepare(ctrl, nbr, inputs.get(self.keys.leader_ref)), self.sc.timing.dt)
        shared = ctrl.share()
        q_ref = shared.q
        rc = self.cmds.get(k)
        if rc is None:
            raise _Differs(Difference(k, "cmd", "<missing from the recording>", f"thrust={float(cmd.thrust)!r}"))
        d = _compare_cmd(k, rc, cmd)
        if d is None:
            rr = self.refs.get(k + 1)
            if rr is None and k == seg_end:
                self.res.notes.append(f"ref of tick {k + 1} (after the last command of a run) is not in the recording")
            elif rr is None:
                d = Difference(k + 1, "ref", "<missing from the recording>", f"q={q_ref.tolist()}")
            else:
                d = _compare_ref(k + 1, rr, shared)
        if d is not None:
            raise _Differs(d)
        self.res.ticks += 1

    def restart(self, k: int, st: wire.State) -> None:
        """(Re)start the controller (a fresh one, as a restarted process builds) from the state of
        tick k; the recorded start reference of tick k, if any, must equal its share()."""
        if self.ctrl.initialised:
            self.ctrl = self._new_controller()
        self.ctrl.reset(st.q, st.v)
        r0 = self.start_refs.get(k)
        d = None if r0 is None else _compare_ref(k, r0, self.ctrl.share())
        if d is not None:
            raise _Differs(d)

    # ------------------------------------------------------------------ realtime
    def verify_realtime(self) -> None:
        """Each recorded command with the inputs newest before its receive time."""
        self.res.notes.append("realtime recording: inputs reconstructed from the recorder's receive times")
        lt_of = {key: [lt for lt, _, _ in self.timeline[key]] for key in self.input_keys}
        started: set[int] = set()
        for lt_cmd, k, _rc in self.timeline[self.cmd_key]:
            st = self.state(k)
            s = max((x for x in self.starts if x <= k), default=None)
            if s is not None and s not in started:
                started.add(s)
                self.restart(s, self.states.get(s, st))
            elif not self.ctrl.initialised:
                self.ctrl.reset(st.q, st.v)
            inputs = {}
            for key in self.input_keys:
                j = bisect.bisect_right(lt_of[key], lt_cmd) - 1
                if j >= 0:
                    inputs[key] = self.timeline[key][j][2]
            self.compute(k, st, inputs, self.last)

    # ------------------------------------------------------------------ lockstep
    def verify_lockstep(self, plan: Any) -> None:
        """Each run of the agent process (from one start to the next), tick by tick."""
        if plan is not None:
            self.res.notes.append("link faults replayed through the agent's receive boxes")
        for idx, s in enumerate(self.starts):
            hi = self.starts[idx + 1] - 1 if idx + 1 < len(self.starts) else self.last
            seg = [k for k in self.cmds if s <= k <= hi]
            if seg:
                inputs = _BoxedInputs(self, plan, s) if plan is not None else _HeldInputs(self, s)
                for k in range(s, max(seg) + 1):
                    st_raw = self.state(k)
                    if k == s:
                        self.restart(k, st_raw)
                    st, got = inputs.at(k, st_raw)
                    self.compute(k, st, got, max(seg))


class _HeldInputs:
    """A run's inputs without link faults: the newest recorded value of each input key, held
    (a new process holds nothing; a rejoining one hears no input of its first tick)."""

    def __init__(self, v: _Verifier, start: int) -> None:
        self.v = v
        self.start = start
        self.held: dict[str, Any] = {}

    def at(self, k: int, st: wire.State) -> tuple[wire.State, dict[str, Any]]:
        if not (k == self.start and self.start > 0):  # the inputs of a rejoin tick were sent before it subscribed
            for key in self.v.input_keys:
                m = self.v.by_tick[key].get(k)
                if m is not None:
                    self.held[key] = m
        return st, self.held


class _BoxedInputs:
    """A run's inputs with link faults: every input through the receive box the agent uses
    (:class:`zenswarm.linkfaults.Box`), fed the recorded messages in order."""

    def __init__(self, v: _Verifier, plan: Any, start: int) -> None:
        from zenswarm.faults import FaultState
        from zenswarm.linkfaults import Box

        fstate = FaultState(plan)
        kinds = {v.state_key: "state", v.keys.leader_ref: "leader"}
        self.v = v
        self.start = start
        self.boxes = {
            key: Box(fstate, v.sender[key], v.me, kinds.get(key, "ref"), v.sc.timing.dt) for key in [v.state_key] + v.input_keys
        }
        self.feed = {key: [(k, msg) for _, k, msg in v.timeline[key] if k >= start] for key in self.boxes}
        self.pos = {key: 0 for key in self.feed}

    def _offer(self, k: int, rejoin: bool) -> None:
        """Offer every recorded message up to tick k (none of a rejoin tick but the state)."""
        for key, box in self.boxes.items():
            lst, i = self.feed[key], self.pos[key]
            while i < len(lst) and lst[i][0] <= k:
                if not (rejoin and key != self.v.state_key and lst[i][0] == k):
                    box.offer(lst[i][0], lst[i][1].seq, lst[i][1])
                i += 1
            self.pos[key] = i

    def at(self, k: int, st_raw: wire.State) -> tuple[wire.State, dict[str, Any]]:
        rejoin = k == self.start and self.start > 0  # the inputs of this tick were sent before it subscribed
        self._offer(k, rejoin)
        for box in self.boxes.values():
            if not box.ready(k) and not rejoin:
                due = box.due(k)
                assert due is not None, "a box that is not ready has a due message"
                box.mark_timeout(due)
        got = {key: box.at(k) for key, box in self.boxes.items()}
        h = got.pop(self.v.state_key)
        return (h.value if h is not None else st_raw), {key: g.value for key, g in got.items() if g is not None}


def _agents_arg(text: str) -> str:
    if text != "all":
        try:
            if int(text) < 1:
                raise ValueError
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a UAV number >= 1 or 'all', got {text!r}") from None
    return text


def _run_verify(args: argparse.Namespace) -> int:
    if args.agent is None:
        if getattr(args, "command", None) == "replay":
            raise ScenarioError("--agent", "replay --verify needs --agent I (a UAV number) or --agent all")
        args.agent = "all"
    if args.agent == "all":
        rec = read_recording(args.file, strict=False)
        agents = list(range(1, rec.load_scenario().n + 1))
    else:
        agents = [int(args.agent)]
    code = 0
    for i in agents:
        r = verify_agent(args.file, i, strict=args.strict)
        for p in r.problems:
            print(f"verify: warning: {args.file}: {p}", file=sys.stderr)
        for n in r.notes:
            print(f"verify: agent {i}: note: {n}", file=sys.stderr)
        if r.ok:
            print(f"agent {i}: verified {r.ticks} ticks")
        else:
            d = r.difference
            assert d is not None
            print(f"agent {i}: first difference at {d} (after {r.ticks} verified ticks)")
            code = 1
    return code


def add_parsers(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="republish a recording onto Zenoh, or verify an agent against it (--verify)",
        description=(
            "Republish the payloads recorded in FILE, byte for byte, with their original timing "
            "(log-time deltas / --rate), optionally under another swarm name and filtered by a key "
            "expression. Progress goes to stderr. A window outside the recording (--start beyond its "
            "last message, --end before --start, a negative time) or a --topics that matches no recorded "
            "key is bad input: exit 2, naming the flag and the recording's span, before anything is "
            "published. With --verify, no Zenoh: rebuild agent I's "
            "controller from the recorded scenario, feed it its recorded inputs tick by tick as in "
            "lockstep, and check its commands and references bit for bit; exit 1 and name the first "
            "difference otherwise."
        ),
    )
    p.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    p.add_argument("--swarm", help="publish under swarm/<NAME>/ instead of the recorded swarm name")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="Zenoh router (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument("--rate", type=float, default=1.0, metavar="R", help="playback speed factor; 0 = as fast as possible (default 1)")
    p.add_argument("--loop", action="store_true", help="start over at the end, until interrupted")
    p.add_argument(
        "--topics",
        metavar="KEYEXPR",
        help="replay only recorded topics that intersect this key expression (exit 2 if it matches none)",
    )
    p.add_argument(
        "--start",
        type=float,
        metavar="S",
        help="start S seconds after the first recorded message (0 <= S <= the recording's span, else exit 2)",
    )
    p.add_argument("--end", type=float, metavar="S", help="stop S seconds after the first recorded message (>= --start)")
    p.add_argument(
        "--wait-subscribers",
        type=float,
        default=2.0,
        metavar="S",
        help="before the first message, wait up to S s for a subscriber to match (default 2)",
    )
    p.add_argument(
        "--live", nargs="?", const=live.DEFAULT_PORT, type=live.live_port, metavar="PORT",
        help=f"also serve the replayed swarm to the Foxglove app on ws://127.0.0.1:PORT (default {live.DEFAULT_PORT}; docs/live.md)",
    )
    p.add_argument("--verify", action="store_true", help="verify agent --agent against the recording instead of publishing")
    p.add_argument("--agent", type=_agents_arg, metavar="I", help="with --verify: UAV number I (1..N) or 'all'")
    p.add_argument("--strict", action="store_true", help="with --verify: refuse a truncated or damaged recording")
    p.set_defaults(func=_run_replay)

    v = sub.add_parser(
        "verify",
        help="check that agents reproduce their recorded commands bit for bit (same as replay --verify)",
        description=(
            "For each agent (or --agent I): rebuild its controller from the recorded scenario, feed it "
            "its recorded inputs tick by tick, and compare its commands and references with the "
            "recorded ones, bit for bit. Exit 0 if all match, 1 at the first difference (named)."
        ),
    )
    v.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    v.add_argument("--agent", type=_agents_arg, default="all", metavar="I", help="UAV number I (1..N) or 'all' (default)")
    v.add_argument("--strict", action="store_true", help="refuse a truncated or damaged recording")
    v.set_defaults(func=_run_verify, verify=True)

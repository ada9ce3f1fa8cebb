"""``zenswarm replay``: a recording published back onto Zenoh.

``zenswarm replay FILE [--swarm NAME] [--connect EP] [--rate R] [--loop] [--topics KEYEXPR]
[--start S] [--end S]`` republishes the recorded payloads, byte for byte, with their original
timing (log-time deltas divided by the rate), optionally under another swarm name. Its parts that
need no Zenoh (filters, pacing, re-stamping, keys) are :mod:`zenswarm.bridge.replay.playback`.

``zenswarm replay --verify FILE --agent I`` runs ``zenswarm verify`` instead
(:mod:`zenswarm.bridge.replay.verify`: agent I's computation run again on its recorded inputs,
bit for bit); :class:`Difference`, :class:`VerifyResult` and :func:`verify_agent` are importable
from here too.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from zenswarm.bridge.recording.info import RecordingInfo, scan
from zenswarm.bridge.recording.mcapio import Recording, read_recording
from zenswarm.bridge.replay import verify
from zenswarm.bridge.replay.playback import Controls, KeyboardControls, Pacer, TopicFilter, original_swarm, restamp, rewrite_topic
from zenswarm.bridge.replay.verify import Difference, VerifyResult, verify_agent
from zenswarm.bridge.views import live
from zenswarm.bus import wire
from zenswarm.errors import ScenarioError
from zenswarm.process.signals import SignalRelay

__all__ = [
    "ReplayStats",
    "replay",
    # verify's (zenswarm.bridge.replay.verify) and playback's (rewrite_topic), importable from here as before
    "Difference",
    "VerifyResult",
    "verify_agent",
    "rewrite_topic",
    "add_parser",
    "add_parsers",
]

PROGRESS_EVERY_S = 1.0
CLOCKS = ("sim", "wall")
WAIT_FOR_TIMEOUT_S = 60.0
"""How long ``--wait-for`` waits for the named processes' liveliness tokens, s."""
END_SLACK_NS = 1_000_000_000
"""Reading stops this much sim time after ``--end`` (later messages may still carry older times)."""


# --------------------------------------------------------------------------- replay


@dataclass
class ReplayStats:
    """What a replay did. ``span_s``: the timestamps played (sim or receive time, by ``clock``),
    s; ``wall_s``: how long playing took, from the first message published (the session and the wait
    for subscribers before it not counted); ``loops``: passes started; ``restamped``: payloads whose
    ``t``/``seq`` were moved on for a loop pass (``not_restamped``: payloads that carry none,
    published as recorded); ``clocks``: clock messages published by ``--clock-rate``."""

    published: int = 0
    skipped: int = 0
    loops: int = 0
    span_s: float = 0.0
    wall_s: float = 0.0
    max_lag_s: float = 0.0
    stopped_by: str = ""
    clock: str = ""
    restamped: int = 0
    not_restamped: int = 0
    clocks: int = 0
    problems: list[str] = field(default_factory=list)


def _finite(flag: str, v: float | None, lo: float, what: str) -> None:
    if v is not None and not (math.isfinite(v) and v >= lo):
        raise ScenarioError(flag, f"must be {what}, got {v:g}")


@dataclass
class _Plan:
    """A replay checked against its recording: the window (ns of sim time), the clock, the
    filter, the tick (ns) and what the scan found."""

    info: RecordingInfo
    rec: Recording
    clock: str
    t_lo: int | None
    t_hi: int | None
    match: TopicFilter
    dt_ns: int | None
    orig: str | None


def _plan(path: str | Path, *, clock: str | None, start_s: float | None, end_s: float | None,
          topics: Sequence[str], exclude: Sequence[str]) -> _Plan:  # fmt: skip
    """Check the options against the recording (ScenarioError naming the flag, before anything
    is published): the window within the recording's sim-time range, every filter matching a
    recorded key, a sim clock only for a recording with sim times."""
    _finite("--start", start_s, 0.0, "a number of sim seconds >= 0")
    _finite("--end", end_s, 0.0, "a number of sim seconds >= 0")
    if start_s is not None and end_s is not None and end_s < start_s:
        raise ScenarioError("--end", f"{end_s:g} s is before --start {start_s:g} s")
    if clock is not None and clock not in CLOCKS:
        raise ScenarioError("--clock", f"expected sim or wall, got {clock!r}")
    info = scan(path)
    rec = read_recording(path, strict=False)
    topics_rec = [c.topic for c in info.channels]
    match = TopicFilter(topics, exclude)
    match.validate(topics_rec, path)
    lo, hi = info.first_sim_ns, info.last_sim_ns
    where = "it holds no message with a sim time" if lo is None or hi is None else (
        f"it spans {lo / 1e9:g} to {hi / 1e9:.3f} s of sim time"
    )
    if start_s is not None and (hi is None or start_s * 1e9 > hi):
        raise ScenarioError("--start", f"{start_s:g} s is beyond the end of the recording {path}: {where}")
    if end_s is not None and (lo is None or end_s * 1e9 < lo):
        raise ScenarioError("--end", f"{end_s:g} s is before the start of the recording {path}: {where}")
    if clock is None:
        clock = "sim" if rec.mode == "lockstep" and lo is not None else "wall"
    if clock == "sim" and lo is None:
        raise ScenarioError("--clock", f"sim: the recording {path} holds no message with a sim time; use --clock wall")
    dt_ns = None
    if info.control_rate_hz:
        dt_ns = wire.t_ns(1.0 / info.control_rate_hz)
    first_topic = topics_rec[0] if topics_rec else None
    return _Plan(
        info, rec, clock, None if start_s is None else round(start_s * 1e9), None if end_s is None else round(end_s * 1e9),
        match, dt_ns, original_swarm(rec, first_topic),
    )  # fmt: skip


class _Player:
    """One replay's publishing side: a publisher per (rewritten) key, declared at first use,
    paced by :class:`zenswarm.bridge.replay.playback.Pacer`, progress lines; counts in ``stats``."""

    def __init__(self, session: Any, plan: _Plan, *, swarm: str | None, pacer: Pacer, stop: threading.Event,
                 stats: ReplayStats, progress: Callable[[str], None] | None, wait_subscribers_s: float,
                 skip_topic: str | None, loop: bool) -> None:  # fmt: skip
        self.session = session
        self.plan = plan
        self.swarm = swarm
        self.pacer = pacer
        self.stop = stop
        self.stats = stats
        self.progress = progress
        self.wait_subscribers_s = wait_subscribers_s
        self.skip_topic = skip_topic  # the recorded clock, replaced by --clock-rate
        self.loop = loop
        self.pubs: dict[str, Any] = {}
        self.rewritten: dict[str, str] = {}
        self.waited = False
        self.wall0 = time.monotonic()
        self.last_progress = self.wall0
        self.position: int | None = None
        """Sim time played (restamped), ns: what ``--clock-rate`` publishes."""
        # what pass 0 saw, for re-stamping the next passes
        self.sim_lo: int | None = None
        self.sim_hi: int | None = None
        self.max_seq = 0
        self.min_step: int | None = None
        self.shift_t = 0
        self.shift_seq = 0
        self.played_lo: int | None = None
        self.played_hi = 0
        info = plan.info
        self.total = (info.sim_s if plan.clock == "sim" else info.wall_s) or 0.0

    def next_pass(self) -> bool:
        """Move the re-stamping on by one pass: sim time by the played span plus one tick, seq
        by the largest seq played plus one. False if there is nothing to move on by."""
        if self.sim_lo is None or self.sim_hi is None:
            return False
        tick = self.plan.dt_ns or self.min_step or 1
        self.shift_t += self.sim_hi - self.sim_lo + tick
        self.shift_seq += self.max_seq + 1
        return True

    def play_once(self, path: str | Path, first_pass: bool) -> bool:
        """Publish the recording's selected messages once; False if none was selected."""
        plan, stats = self.plan, self.stats
        sim_clock = plan.clock == "sim"
        pos: int | None = None  # the recorded sim time reached (the largest so far), ns
        published = False
        for m in read_recording(path, strict=False).messages():
            if self.stop.is_set() or self.pacer.controls.quit:
                break
            sim = m.publish_time if m.publish_time <= wire.MAX_T_NS else None
            if sim is not None:
                if pos is not None and sim > pos and first_pass and (self.min_step is None or sim - pos < self.min_step):
                    self.min_step = sim - pos
                pos = sim if pos is None else max(pos, sim)
            where = self._window(sim if sim is not None else pos, pos)
            if where == "past":
                break
            if where == "out":
                continue
            if not plan.match(m.topic) or m.topic == self.skip_topic:
                stats.skipped += 1
                continue
            payload = self._stamped(m.payload, sim, first_pass)
            pub = self._publisher(m.topic)
            ts = (None if pos is None else pos + self.shift_t) if sim_clock else m.log_time
            if ts is not None:
                if not self.pacer.wait(ts):
                    break
                if self.played_lo is None:
                    self.played_lo = ts
                self.played_hi = max(self.played_hi, ts)
            if pos is not None:
                self.position = pos + self.shift_t
            pub.put(payload)
            published = True
            stats.published += 1
            self._report(pos)
        return published

    def _window(self, at: int | None, pos: int | None) -> str:
        """``"in"`` the --start/--end window, ``"out"`` or ``"past"`` it (nothing more to read);
        ``at``: the message's sim time (its own, else the largest so far ``pos``), ns."""
        plan = self.plan
        if plan.t_lo is not None and (at is None or at < plan.t_lo):
            return "out"
        if plan.t_hi is not None and at is not None and at > plan.t_hi:
            return "past" if pos is not None and pos > plan.t_hi + END_SLACK_NS else "out"
        return "in"

    def _stamped(self, payload: bytes, sim: int | None, first_pass: bool) -> bytes:
        """The payload to publish: as recorded in the first pass (noted for the next ones when
        looping), re-stamped in the next ones."""
        if first_pass:
            if self.loop:
                self._note(payload, sim)
            return payload
        new = restamp(payload, self.shift_t, self.shift_seq)
        if new is None:
            self.stats.not_restamped += 1
            return payload
        self.stats.restamped += 1
        return new

    def _note(self, payload: bytes, sim: int | None) -> None:
        """Pass 0 of a loop: the sim-time range and the largest seq played."""
        if sim is not None:
            self.sim_lo = sim if self.sim_lo is None else min(self.sim_lo, sim)
            self.sim_hi = sim if self.sim_hi is None else max(self.sim_hi, sim)
        try:
            o = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        except Exception:  # noqa: BLE001 - not msgpack: published as is
            return
        if type(o) is dict and type(o.get("seq")) is int and o["seq"] > self.max_seq:
            self.max_seq = o["seq"]

    def _publisher(self, topic: str) -> Any:
        """The publisher of ``topic`` under the replay's swarm; before the first put, waits for a
        subscriber to match (puts before that would be lost)."""
        import zenoh

        from zenswarm import bus

        key = self.rewritten.get(topic)
        if key is None:
            key = self.rewritten[topic] = rewrite_topic(topic, self.plan.orig, self.swarm)
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

    def _report(self, pos: int | None) -> None:
        """A progress line every PROGRESS_EVERY_S."""
        now = time.monotonic()
        if self.progress is None or now - self.last_progress < PROGRESS_EVERY_S:
            return
        self.last_progress = now
        st = self.stats
        if self.plan.clock == "sim" and pos is not None:
            first = self.plan.info.first_sim_ns or 0
            done = (pos - first) / 1e9
            where = f"sim t={pos / 1e9:.2f} s"
        else:
            done = (self.played_hi - (self.played_lo or 0)) / 1e9
            where = f"wall +{done:.2f} s"
        pct = f" ({min(100.0, 100 * done / self.total):.0f} %)" if self.total > 0 else ""
        paused = "  [paused]" if self.pacer.controls.paused else ""
        self.progress(
            f"replay: pass {st.loops}  {where} of {self.total:.2f} s{pct}  {st.published} published  "
            f"{st.published / max(now - self.wall0, 1e-9):.0f} msg/s{paused}"
        )


def _clock_thread(player: _Player, session: Any, key: str, hz: float, dt_ns: int | None, stop: threading.Event,
                  stats: ReplayStats) -> threading.Thread:  # fmt: skip
    """Publish ``clock`` messages on ``key`` at ``hz`` (wall time) while the replay runs: ``t`` =
    the sim time played, rounded down to a tick, ``seq`` counting up; nothing while the sim time
    stands still (paused), since a receiver would reject the repeat as stale."""
    import zenoh

    pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)

    def run() -> None:
        last: int | None = None
        seq = 0
        period = 1.0 / hz
        nxt = time.monotonic()
        while not stop.is_set():
            pos = player.position
            if pos is not None:
                t = pos - pos % dt_ns if dt_ns else pos
                if t != last:
                    last = t
                    seq += 1
                    pub.put(wire.encode(wire.Clock(t=t, seq=seq)))
                    stats.clocks += 1
            nxt += period
            stop.wait(max(0.0, nxt - time.monotonic()))

    th = threading.Thread(target=run, name="replay-clock", daemon=True)
    th.start()
    return th


def _wait_for_processes(session: Any, keys_prefix: str, names: Sequence[str], timeout_s: float,
                        stop: threading.Event, progress: Callable[[str], None] | None) -> None:  # fmt: skip
    """Block until every process in ``names`` holds its ``alive/<name>`` token (it subscribed
    to what it needs), at most ``timeout_s``; ScenarioError naming ``--wait-for`` otherwise."""
    want = {f"{keys_prefix}/alive/{n}": n for n in names}
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        seen = set()
        for reply in session.liveliness().get(f"{keys_prefix}/alive/*", timeout=1.0):
            ok = getattr(reply, "ok", None)
            if ok is not None:
                seen.add(str(ok.key_expr))
        missing = [n for k, n in want.items() if k not in seen]
        if not missing:
            return
        if time.monotonic() > deadline:
            raise ScenarioError("--wait-for", f"{', '.join(missing)} did not appear ({keys_prefix}/alive/...) within {timeout_s:g} s")
        time.sleep(0.05)


def _check_flags(rate: float, clock_rate: float | None, loops: int | None, swarm: str | None, wait_for: Sequence[str]) -> None:
    """The options that need no recording (ScenarioError naming the flag)."""
    _finite("--rate", rate, 0.0, "a finite number >= 0")
    if clock_rate is not None and not (math.isfinite(clock_rate) and clock_rate > 0):
        raise ScenarioError("--clock-rate", f"must be a finite number of Hz > 0, got {clock_rate:g}")
    if loops is not None and loops < 1:
        raise ScenarioError("--loops", f"must be >= 1, got {loops}")
    if swarm is not None:
        wire.validate_swarm_name(swarm)
    for name in wait_for:
        try:
            wire.validate_process(name)
        except wire.InvalidKeyError as e:
            raise ScenarioError("--wait-for", str(e)) from None


def replay(
    path: str | Path,
    *,
    connect: list[str],
    swarm: str | None = None,
    rate: float = 1.0,
    loop: bool = False,
    loops: int | None = None,
    topics: Sequence[str] = (),
    exclude: Sequence[str] = (),
    start_s: float | None = None,
    end_s: float | None = None,
    clock: str | None = None,
    clock_rate: float | None = None,
    controls: Controls | None = None,
    wait_for: Sequence[str] = (),
    wait_for_timeout_s: float = WAIT_FOR_TIMEOUT_S,
    wait_subscribers_s: float = 2.0,
    linger_s: float = 0.5,
    stop: threading.Event | None = None,
    progress: Callable[[str], None] | None = None,
    session: Any = None,
) -> ReplayStats:
    """Republish the recorded payloads of ``path`` onto Zenoh (client of ``connect``, or the
    open ``session``).

    clock: ``"sim"`` paces by the payloads' sim time, ``"wall"`` by receive time; None: sim for a
    lockstep recording, wall otherwise. rate: playback speed (2 = twice as fast; 0 = as fast as
    possible). start_s/end_s: window in sim seconds. topics/exclude: :class:`TopicFilter`
    patterns. swarm: replay under ``swarm/<swarm>/`` instead of the recorded prefix. loop: start
    over at the end until ``stop`` is set (loops: after that many passes); each pass after the
    first moves every payload's ``t`` on by the played sim span plus one tick and its ``seq`` by
    the largest seq played plus one, so live receivers take it as the stream going on.
    clock_rate: publish ``clock`` messages at this rate (Hz, wall) on the swarm's clock key,
    instead of the recorded ones. controls: pause/step/quit (:class:`Controls`). wait_for:
    process names whose liveliness tokens to wait for first. Before the first put, waits up to
    ``wait_subscribers_s`` for a subscriber to match. Options that do not fit the recording
    raise :class:`ScenarioError` first.
    """
    # Over 80 lines only by its 22 keyword arguments and their description; the body is one
    # session's flow (check, plan, open, play, close) and reads better whole.
    from zenswarm import bus

    _check_flags(rate, clock_rate, loops, swarm, wait_for)
    plan = _plan(path, clock=clock, start_s=start_s, end_s=end_s, topics=topics, exclude=exclude)
    if clock_rate is not None and plan.info.first_sim_ns is None:
        raise ScenarioError("--clock-rate", f"the recording {path} holds no sim time to publish")
    stop = stop or threading.Event()
    controls = controls or Controls()
    stats = ReplayStats(clock=plan.clock)
    stats.problems += plan.info.problems
    wall0 = time.monotonic()
    target_swarm = swarm or plan.orig
    prefix = f"swarm/{target_swarm}" if target_swarm else None
    clock_key = f"{prefix}/clock" if prefix else None
    skip = f"swarm/{plan.orig}/clock" if clock_rate is not None and plan.orig else None
    own = session is None
    cm = bus.open_session(bus.client_config(connect), handle_signals=False) if own else contextlib.nullcontext(session)
    repeat = loop or loops is not None
    with cm as sess:
        if wait_for:
            if prefix is None:
                raise ScenarioError("--wait-for", f"the swarm of {path} is unknown: give --swarm")
            _wait_for_processes(sess, prefix, wait_for, wait_for_timeout_s, stop, progress)
        pacer = Pacer(rate, stop, controls)
        player = _Player(
            sess, plan, swarm=swarm, pacer=pacer, stop=stop, stats=stats, progress=progress,
            wait_subscribers_s=wait_subscribers_s, skip_topic=skip, loop=repeat,
        )  # fmt: skip
        clock_stop = threading.Event()
        th = None
        if clock_rate is not None and clock_key is not None:
            th = _clock_thread(player, sess, clock_key, clock_rate, plan.dt_ns, clock_stop, stats)
        try:
            _play_passes(player, path, pacer, stats, stop, controls, repeat, loops)
            # from the first message published: the session's start and the wait for subscribers are not playing time
            stats.wall_s = time.monotonic() - (pacer.started if pacer.started is not None else wall0)
            if linger_s > 0 and not stop.is_set():
                time.sleep(linger_s)  # let the last batches (and clock messages) leave before the session closes
        finally:
            clock_stop.set()
            if th is not None:
                th.join(2.0)
    stats.max_lag_s = pacer.max_lag_s
    stats.span_s = (player.played_hi - (player.played_lo or 0)) / 1e9 if player.played_lo is not None else 0.0
    return stats


def _play_passes(
    player: _Player, path: str | Path, pacer: Pacer, stats: ReplayStats, stop: threading.Event, controls: Controls,
    repeat: bool, loops: int | None,
) -> None:
    """Play the recording once, or pass after pass (``repeat``; at most ``loops`` passes), until its
    end, ``stop`` or quit; ``stats.stopped_by`` says which."""
    while not stop.is_set() and not controls.quit:
        stats.loops += 1
        if not player.play_once(path, stats.loops == 1):
            stopped = stop.is_set() or controls.quit  # before the first message: not an empty window
            stats.stopped_by = "nothing selected in the window" if stats.loops == 1 and not stopped else "interrupted"
            break
        if not repeat or (loops is not None and stats.loops >= loops):
            stats.stopped_by = "end of recording" if not (stop.is_set() or controls.quit) else "interrupted"
            break
        if not player.next_pass():
            stats.stopped_by = "end of recording (no sim time to loop on)"
            break
        pacer.anchor = None  # the next pass starts at once
    else:
        stats.stopped_by = "interrupted"


def _run_replay(args: argparse.Namespace) -> int:
    if args.verify:
        return verify.run_verify(args)
    stop = threading.Event()

    def progress(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    tty = sys.stdin is not None and sys.stdin.isatty()
    if args.start_paused and not tty:
        raise ScenarioError("--start-paused", "stdin is not a terminal: nothing could resume (space) or step (s) the replay")
    # SIGINT/SIGTERM set `stop` through a relay thread, not in the handler: the pacer waits on `stop`
    # in this thread, and a handler run while it held the event's lock would wait for it forever
    SignalRelay(lambda signum: stop.set(), name="replay-signals")  # for the rest of the command
    controls = Controls(paused=args.start_paused)
    controls.on_change = lambda text: progress(f"replay: {text}")
    connect = args.connect or ["tcp/127.0.0.1:7447"]
    viewer = live.replay_viewer(args.file, args.swarm, args.live, connect) if args.live is not None else None  # port in use: exit 2 now
    keyboard = KeyboardControls(controls, sys.stdin.fileno()) if tty else contextlib.nullcontext()
    if tty:
        progress("replay: keys: space = pause/resume, s or right arrow = step, q = quit")
    try:
        with keyboard:
            st = replay(
                args.file, connect=connect, swarm=args.swarm, rate=args.rate, loop=args.loop, loops=args.loops,
                topics=args.topic or (), exclude=args.exclude or (), start_s=args.start, end_s=args.end,
                clock=args.clock, clock_rate=args.clock_rate, controls=controls, wait_for=args.wait_for or (),
                wait_subscribers_s=args.wait_subscribers, stop=stop, progress=progress,
            )  # fmt: skip
    finally:
        if viewer is not None:
            viewer.close()
    for p in st.problems:
        progress(f"replay: warning: {args.file}: {p}")
    extra = f", {st.restamped} re-stamped" if st.restamped or st.not_restamped else ""
    extra += f", {st.clocks} clock messages" if st.clocks else ""
    progress(
        f"replay: {st.stopped_by}: {st.published} messages published ({st.skipped} filtered out{extra}) in "
        f"{st.loops} pass(es), by {st.clock} time, {st.span_s:.3f} s played in {st.wall_s:.2f} s wall, "
        f"max lag {1e3 * st.max_lag_s:.1f} ms"
    )
    return 130 if stop.is_set() else 0  # only SIGINT/SIGTERM set `stop`: interrupted, as every command exits


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``replay`` and ``verify`` (:func:`zenswarm.bridge.replay.verify.add_parser`)."""
    add_parser(sub)
    verify.add_parser(sub)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``replay``."""
    # The flags of one command in the order --help lists them: reads better whole than cut into groups.
    p = sub.add_parser(
        "replay",
        help="republish a recording onto Zenoh (with ros2 bag play's controls), or verify an agent against it (--verify)",
        description=(
            "Republish the payloads recorded in FILE, byte for byte, paced by their sim time (--clock sim, the "
            "default for lockstep recordings) or by their receive time (--clock wall, the default otherwise), "
            "divided by --rate; optionally a window of sim time, a subset of keys, under another swarm name, in "
            "a loop, publishing the swarm clock. On a terminal: space pauses and resumes, s or the right arrow "
            "steps (one tick of sim time while paused), q quits. Progress goes to stderr. Options that do not fit "
            "the recording (a window outside its sim-time range, a filter that matches no recorded key) are bad "
            "input: exit 2 naming the flag (and listing the recorded keys), before anything is published. "
            "With --verify, no Zenoh: rebuild agent I's controller from the recorded scenario, feed it its "
            "recorded inputs tick by tick as in lockstep, and check its commands and references bit for bit; "
            "exit 1 and name the first difference otherwise. See docs/replay.md."
        ),
    )
    p.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    p.add_argument("--swarm", help="publish under swarm/<NAME>/ instead of the recorded swarm name")
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="Zenoh router (repeatable; default tcp/127.0.0.1:7447)")
    p.add_argument(
        "--clock", choices=CLOCKS, default=None,
        help="pace by the payloads' sim time (sim) or by the recorder's receive time (wall); "
        "default: sim for a lockstep recording, wall for a realtime one (from the file's metadata)",
    )  # fmt: skip
    p.add_argument("--rate", type=float, default=1.0, metavar="R", help="playback speed factor; 0 = as fast as possible (default 1)")
    p.add_argument(
        "--start", type=float, metavar="S",
        help="start at sim time S seconds (within the recording's sim-time range, else exit 2)",
    )  # fmt: skip
    p.add_argument("--end", type=float, metavar="S", help="stop after sim time S seconds (>= --start and the recording's start)")
    p.add_argument(
        "--topic", action="append", metavar="PATTERN",
        help="replay only the recorded keys matching PATTERN: a Zenoh key expression (uav/*/ref, swarm/x/**) or a "
        "shell glob (*/state, uav/[13]/ref), against the full key or the key without swarm/<name>/; repeatable "
        "(any may match); a pattern matching no recorded key is exit 2",
    )  # fmt: skip
    p.add_argument("--topics", dest="topic", action="append", help=argparse.SUPPRESS)  # the old spelling
    p.add_argument(
        "--exclude", action="append", metavar="PATTERN",
        help="leave out the recorded keys matching PATTERN (as --topic; repeatable; applied after --topic)",
    )  # fmt: skip
    p.add_argument(
        "--loop", action="store_true",
        help="start over at the end, until interrupted; each new pass moves every payload's t on by the played sim span "
        "plus one tick and its seq by the largest seq played, so live processes accept it as the stream going on",
    )  # fmt: skip
    p.add_argument("--loops", type=int, metavar="N", help="like --loop, but stop after N passes")
    p.add_argument(
        "--start-paused", action="store_true",
        help="start paused (needs a terminal on stdin: space resumes, s or right arrow steps)",
    )  # fmt: skip
    p.add_argument(
        "--clock-rate", type=float, metavar="HZ",
        help="publish clock messages on swarm/<name>/clock at HZ (wall time) with the sim time played, "
        "instead of the recorded clock",
    )  # fmt: skip
    p.add_argument(
        "--wait-for", action="append", metavar="PROCESS",
        help="before publishing, wait for PROCESS (e.g. agent:2) to hold its liveliness token alive/PROCESS, "
        f"i.e. to have subscribed (repeatable; up to {WAIT_FOR_TIMEOUT_S:g} s, else exit 2)",
    )  # fmt: skip
    p.add_argument(
        "--wait-subscribers",
        type=float,
        default=2.0,
        metavar="S",
        help="before the first message, wait up to S s for a subscriber to match (default 2)",
    )
    p.add_argument(
        "--live", nargs="?", const=live.FOXGLOVE_DEFAULT, type=live.live_target, metavar="PORT|rerun[:PORT]",
        help=f"also serve the replayed swarm to a viewer. {live.LIVE_HELP}",
    )
    p.add_argument("--verify", action="store_true", help="verify agent --agent against the recording instead of publishing")
    p.add_argument("--agent", type=verify.agents_arg, metavar="I", help="with --verify: UAV number I (1..N) or 'all'")
    p.add_argument("--strict", action="store_true", help="with --verify: refuse a truncated or damaged recording")
    p.set_defaults(func=_run_replay)

"""The recorder process (``recorder``): every sample of a swarm, written to an MCAP file.

``zenswarm record --swarm NAME --connect EP --out FILE.mcap [--scenario F] [--duration S]``

Subscribes to ``swarm/<name>/**`` and writes each sample as it was received (file layout: see
:mod:`zenswarm.bridge.recording.mcapio`). It declares its liveliness token ``swarm/<name>/alive/recorder`` only
once its subscriber is declared, so a plant that waits for the recorder loses nothing.

Threads and crash safety
------------------------
* The Zenoh callback only stamps the receive wall time and appends ``(log_time, key, payload)``
  to an unbounded ``queue.SimpleQueue``: no decoding, no I/O, no lock held across calls. Nothing
  the swarm's decoders could accept is ever dropped (memory is the bound; the peak backlog is
  reported).
* The writer side, the MCAP sink (:class:`zenswarm.bridge.recording.sink.McapSink`), has a
  thread of its own: it registers the channels, takes the sender's sim time out of each payload,
  counts (not records) the payloads over the decoders' size bound (the callback queues only the
  key and size of those), and closes and flushes a chunk at least every ``--flush-interval``
  (default 0.25 s), so that after a SIGKILL of the recorder the file holds every sample received
  up to a quarter of a second before the kill. See :mod:`zenswarm.bridge.recording.sink`.
* SIGTERM and SIGINT reach the main thread's stop event through a relay thread
  (:class:`zenswarm.process.signals.SignalRelay`), never by setting the event in the signal
  handler: the main thread waits on that event, and a handler run while it held the event's lock
  would wait for it forever (the recorder then never exited).
* A clean stop (SIGTERM, SIGINT, ``--duration``): undeclare the token and the subscriber,
  close the session, let the writer drain the queue, write the end marker (a last ``zenswarm``
  metadata record: ``recorder_end_unix_ns``, ``recorder_stop_reason`` and
  ``recorder_stats_json``, the counters of
  :class:`~zenswarm.bridge.recording.sink.RecorderStats`), then ``Writer.finish()`` writes the
  summary (statistics, channels, chunk/message/metadata indexes) and the footer. ``zenswarm
  info`` shows all three.

Metadata: a ``zenswarm`` record is written right after the header (swarm, mode, version and,
with ``--scenario``, the scenario). Without ``--scenario`` a helper thread asks the leader's
mission queryable once a second until a leader answers, and a second ``zenswarm`` record with
``scenario_json`` is written when it does (readers merge the two).

Every ``--diag-interval`` seconds (default 1) the recorder publishes its counters on
``swarm/<name>/diag/recorder`` (recorded, channels, undecodable, backlog, ...); being in the key
space, they are recorded too. ``bench/recorder_throughput.py`` uses them to know when the
recorder has caught up.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Final

import msgspec

from zenswarm import bus
from zenswarm.bridge.args import add_fault_args, add_plugin_args, add_security_args, link_faults
from zenswarm.bridge.recording.sink import (
    _OVERSIZE,
    DEFAULT_CHUNK_SIZE,
    DEFAULT_FLUSH_INTERVAL_S,
    DROPPED_METADATA_INTERVAL_S,
    MAX_DROPPED_KEYS,
    McapSink,
    RecorderStats,
    build_metadata,
    payload_limit,
    sim_time,
)
from zenswarm.bus import wire
from zenswarm.link import LinkFaults
from zenswarm.process import security
from zenswarm.process.paths import check_output_file
from zenswarm.process.runtime import gc_policy, gc_safe_point, gc_startup_done
from zenswarm.process.signals import SignalRelay
from zenswarm.scenario.config import Scenario

__all__ = [
    "PROCESS_NAME",
    "DEFAULT_FLUSH_INTERVAL_S",
    "DEFAULT_CHUNK_SIZE",
    "DROPPED_METADATA_INTERVAL_S",
    "MAX_DROPPED_KEYS",
    "RecorderStats",
    "McapSink",
    "payload_limit",
    "sim_time",
    "build_metadata",
    "RecorderSettings",
    "recorder_settings",
    "run",
    "run_settings",
    "main",
    "add_parser",
]

PROCESS_NAME: Final = "recorder"
DEFAULT_CONNECT_TIMEOUT_S: Final = 60.0
"""The recorder may start before the swarm's router: keep trying to reach it this long, s."""


class RecorderSettings(msgspec.Struct, frozen=True, kw_only=True):
    """What the recorder is started with: ``zenswarm record``'s flags (:func:`recorder_settings`)
    or, under ``zenswarm up --record``, the flight's (msgpack on its standard input,
    :mod:`zenswarm.compose.commands`). One way in: :func:`run_settings`.

    out: the MCAP file. scenario: stored in the file (its plug-in names applied); None: asked of
    the leader's mission. scenario_source: what the metadata says it came from (``file:PATH``).
    mode: ``lockstep``, ``realtime`` or ``unknown`` (metadata; realtime also sets the GC policy).
    connect: router endpoints (empty: ``tcp/127.0.0.1:7447``); keys, tls: credentials of a
    secured router. faults: the swarm's link faults, not applied, stored for ``replay --verify``.
    Durations in seconds; chunk_size in bytes."""

    out: Path
    swarm: str = "default"
    connect: tuple[str, ...] = ()
    scenario: Scenario | None = None
    scenario_source: str = ""
    duration: float | None = None
    mode: str = "lockstep"
    connect_timeout: float = DEFAULT_CONNECT_TIMEOUT_S
    flush_interval: float = DEFAULT_FLUSH_INTERVAL_S
    chunk_size: int = DEFAULT_CHUNK_SIZE
    compression: str = "zstd"
    keys: Path | None = None
    tls: bool = False
    diag_interval: float = 1.0
    faults: LinkFaults = msgspec.field(default_factory=LinkFaults)


def recorder_settings(args: argparse.Namespace) -> RecorderSettings:
    """``zenswarm record``'s flags (:func:`add_parser`) as :class:`RecorderSettings`: the
    ``--scenario`` file parsed, the plug-in flags applied to it (what ``verify`` rebuilds the
    agents from); a bad file is a ScenarioError naming it (exit 2)."""
    from zenswarm.scenario.config import load_scenario
    from zenswarm.scenario.plugins import select

    scenario = None
    if args.scenario is not None:
        scenario = select(load_scenario(args.scenario), args.controller, args.planner, getattr(args, "plant_model", None))
    return RecorderSettings(
        out=args.out, swarm=args.swarm, connect=tuple(args.connect or ()), scenario=scenario,
        scenario_source=f"file:{args.scenario}" if scenario is not None else "", duration=args.duration,
        mode="realtime" if args.realtime else args.mode, connect_timeout=args.connect_timeout,
        flush_interval=args.flush_interval, chunk_size=args.chunk_size, compression=args.compression,
        keys=args.keys, tls=bool(args.tls), diag_interval=args.diag_interval, faults=link_faults(args),
    )  # fmt: skip


def _fetch_mission(session: Any, keys: wire.Keys, stop: threading.Event, on_scenario: Any, log: Any) -> None:
    """Ask the leader's mission queryable until it answers or ``stop`` is set: at once when the
    leader's liveliness token appears (it declares the queryable before the token), and once a
    second in any case."""
    from zenswarm.scenario.config import scenario_from_dict, scenario_to_dict

    leader_seen = threading.Event()
    watch = None
    try:
        watch = session.liveliness().declare_subscriber(
            keys.alive("leader"), lambda sample: leader_seen.set(), history=True
        )
    except Exception:  # noqa: BLE001 - fall back to polling
        pass
    asked = 0
    try:
        while not stop.is_set():
            asked += 1
            leader_seen.clear()
            try:
                for reply in session.get(keys.mission, timeout=1.0):
                    ok = getattr(reply, "ok", None)
                    if ok is None:
                        continue
                    try:
                        msg = wire.decode("mission", ok.payload.to_bytes())
                        if not isinstance(msg, wire.Mission):  # decode("mission") gives a Mission or raises
                            raise TypeError(f"not a mission: {type(msg).__name__}")
                        sc = scenario_from_dict(msg.scenario)
                    except Exception as e:  # noqa: BLE001 - a bad answer: keep asking
                        log(f"recorder: ignoring an invalid mission answer: {e}")
                        continue
                    on_scenario(scenario_to_dict(sc))
                    log(f"recorder: scenario '{sc.name}' received from the leader's mission")
                    return
            except Exception as e:  # noqa: BLE001 - session closing, router gone: retry until stop
                if stop.is_set():
                    return
                if asked == 1:
                    log(f"recorder: mission query failed ({e}); retrying")
            if asked == 30:
                log("recorder: no leader has answered on the mission key yet; still asking")
            for _ in range(20):  # up to 1 s, sooner if the leader shows up
                if stop.is_set() or leader_seen.wait(0.05):
                    break
    finally:
        if watch is not None:
            try:
                watch.undeclare()
            except Exception:  # noqa: BLE001 - best effort
                pass


class _Stop:
    """The recorder's stop request: an event, and why it was set (the last line of the log).

    SIGINT/SIGTERM reach it through a :class:`zenswarm.process.signals.SignalRelay` (:meth:`install`):
    the main thread waits on ``event`` all the time (``_wait_and_report``), and a handler that set
    the event itself could run while the main thread held the event's lock, and wait for it forever
    (a recorder that never exited after SIGTERM, seen once under load)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.why = "stopped"
        self.relay: SignalRelay | None = None

    def install(self) -> None:
        """SIGINT and SIGTERM set the event (main thread only)."""
        self.relay = SignalRelay(self.on_signal, name="recorder-signals")

    def on_signal(self, signum: int) -> None:
        """A stop signal (called by the relay's thread, never in the signal handler)."""
        self.why = f"received {signal.Signals(signum).name}"
        self.event.set()

    def close(self) -> None:
        """Restore the previous signal handlers."""
        if self.relay is not None:
            self.relay.close()
            self.relay = None


def _undeclare(*entities: Any) -> None:
    """Undeclare Zenoh entities, best effort (on shutdown)."""
    for e in entities:
        try:
            e.undeclare()
        except Exception:  # noqa: BLE001 - best effort on shutdown
            pass


def _subscribe_all(session: Any, keys: wire.Keys, sink: McapSink) -> Any:
    """Subscribe to every key of the swarm; each sample goes to ``sink`` (over-size ones counted only)."""
    put_item = sink.put_item
    now_ns = time.time_ns
    small = wire.MAX_PAYLOAD  # the bound of every key but the mission's (payload_limit)
    mission_key, mission_limit = keys.mission, wire.MAX_MISSION_PAYLOAD

    def on_sample(sample: Any) -> None:  # the whole callback: stamp, copy, enqueue
        payload = sample.payload
        n = len(payload)
        if n > small:  # no decoder reads it: count it without copying it (payload_limit)
            key = str(sample.key_expr)
            if key != mission_key or n > mission_limit:
                put_item((_OVERSIZE, key, n, now_ns()))
                return
            put_item((now_ns(), key, payload.to_bytes()))
            return
        put_item((now_ns(), str(sample.key_expr), payload.to_bytes()))

    return session.declare_subscriber(keys.all, on_sample)


def _wait_and_report(s: RecorderSettings, stop: _Stop, session: Any, keys: wire.Keys, sink: McapSink, out: Path) -> None:
    """Until a stop request, ``--duration`` or a writer failure (``stop.why``), publishing the
    recorder's counters on diag/recorder every ``--diag-interval`` s."""
    deadline = None if s.duration is None else time.monotonic() + s.duration
    diag_pub = session.declare_publisher(keys.diag(PROCESS_NAME)) if s.diag_interval > 0 else None
    diag_seq = 0
    next_diag = time.monotonic() + (s.diag_interval if diag_pub is not None else 1e18)
    if s.mode == "realtime":
        gc_startup_done()  # subscribed, writer running: see zenswarm.process.gcpolicy.GcPolicy (realtime only)
    while not stop.event.is_set():
        gc_safe_point()
        now = time.monotonic()
        left = min(0.2, next_diag - now)
        if deadline is not None:
            left = min(left, deadline - now)
            if left <= 0:
                stop.why = f"duration of {s.duration:g} s reached"
                break
        if left > 0:
            stop.event.wait(left)
        if sink.error is not None:
            stop.why = f"writer failed: {sink.error!r}"
            break
        if diag_pub is not None and time.monotonic() >= next_diag:
            diag_seq += 1
            next_diag += s.diag_interval
            st = sink.stats
            diag = wire.Diag(
                t=st.last_sim_t, seq=diag_seq, process=PROCESS_NAME, counters={**st.counters(sink.backlog), **gc_policy().counters()},
                info={"file": str(out)},
            )
            diag_pub.put(wire.encode(diag))


def run(s: RecorderSettings, exit_hard: bool = True) -> int:
    """Run the recorder until SIGTERM/SIGINT or ``--duration``. Exit code 0 on a clean stop.
    ``exit_hard`` False (in-process): the signal handlers are restored at the end."""
    gc_policy()  # a bad ZENSWARM_GC: exit 2 before any work
    stop = _Stop()
    stop.install()
    try:
        return _run(s, stop)
    finally:
        if not exit_hard:  # in-process: restore the handlers; the command
            stop.close()  # exits at once (main), where a second signal must change nothing


def _run(s: RecorderSettings, stop: _Stop) -> int:
    # One session's life in order (open, subscribe, record, close in one try/finally): reads better
    # whole than with its setup and its end in other functions.
    from zenswarm.scenario.config import scenario_to_dict

    def log(text: str) -> None:
        print(text, flush=True)

    keys = wire.Keys(s.swarm)
    mode = s.mode
    scenario: dict[str, Any] | None = None if s.scenario is None else scenario_to_dict(s.scenario)
    connect = list(s.connect) or ["tcp/127.0.0.1:7447"]
    out: Path = check_output_file(s.out, "--out")  # before joining: exit 2, nothing recorded in vain
    conf = bus.client_config(
        connect,
        connect_timeout_s=s.connect_timeout,
        # retry quickly while the swarm's router is not up yet
        settings={
            "connect/retry": {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2},
            **security.client_fragments(PROCESS_NAME, security.ClientSecurity(keys=s.keys, tls=s.tls), connect=s.connect, swarm=s.swarm),
        },
    )
    try:
        session_cm = bus.open_session(conf, handle_signals=False)
        session = session_cm.__enter__()
    except bus.BusError as e:
        print(f"recorder: error: {e} (router {', '.join(connect)})", file=sys.stderr, flush=True)
        return 3
    sink: McapSink | None = None
    fetcher: threading.Thread | None = None
    source = s.scenario_source if scenario is not None else "pending: asking the leader's mission"
    fault_args = s.faults.argv()
    try:
        sink = McapSink(
            out,
            keys,
            flush_interval_s=s.flush_interval,
            chunk_size=s.chunk_size,
            compression=s.compression,
            metadata=build_metadata(s.swarm, mode, scenario, source, fault_args),
        )
        sink.start()
        sub = _subscribe_all(session, keys, sink)
        token = bus.declare_alive(session, keys, PROCESS_NAME)  # only now: the subscriber is in place
        if scenario is None:
            the_sink = sink

            def on_mission(d: dict[str, Any]) -> None:
                the_sink.set_metadata(build_metadata(s.swarm, mode, d, "mission", fault_args))

            fetcher = threading.Thread(
                target=_fetch_mission,
                args=(session, keys, stop.event, on_mission, log),
                name="mission-fetch",
                daemon=True,
            )
            fetcher.start()
        log(
            f"recorder: recording {keys.all} from {', '.join(connect)} to {out} "
            f"(chunks flushed every {s.flush_interval:g} s; {mode})"
        )
        _wait_and_report(s, stop, session, keys, sink, out)
        stop.event.set()
        _undeclare(token, sub)
        if fetcher is not None:
            fetcher.join(timeout=3.0)
    finally:
        stop.event.set()
        session_cm.__exit__(None, None, None)  # closes the session: no callback runs after this
        if sink is not None:
            sink.stop_reason = stop.why
            sink.close()
    st = sink.stats
    log(f"recorder: {stop.why}; wrote {out}: {st.line()}")
    if sink.error is not None:
        ended = f"; {out}: {sink.salvaged}" if sink.salvaged else ""
        print(f"recorder: error: writing {out} failed: {sink.error!r}{ended}", file=sys.stderr, flush=True)
        return 3
    return 0


def run_settings(s: RecorderSettings, exit_hard: bool = True) -> int:
    """The recorder command with these settings (``zenswarm record``, or ``zenswarm up``'s
    recorder reading them on its standard input): :func:`run`, then the process ends."""
    rc = run(s, exit_hard)
    # The file is complete and closed, the session closed: leave without the interpreter's
    # shutdown, where a zenoh helper thread still unwinding native frames can abort the process
    # ("FATAL: exception not rethrown", seen once under load), which would turn a clean stop
    # into a crash report. Only when run as the `zenswarm record` command, not in-process.
    if exit_hard:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    return rc


def main(args: argparse.Namespace) -> int:
    """``zenswarm record``: its flags as :class:`RecorderSettings`, recorded with them."""
    return run_settings(recorder_settings(args), getattr(args, "exit_hard", True))


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "record",
        help="record every message of a swarm to an MCAP file",
        description=(
            "Subscribe to swarm/<NAME>/** and write every sample, as received, to an MCAP file: one "
            "channel per key, message encoding msgpack, log_time = receive wall time, publish_time = "
            "the sender's sim time, the scenario in a metadata record. Crash-safe: chunks are closed "
            "and flushed to the OS at least every --flush-interval seconds; `zenswarm recover` rewrites "
            "a file cut by a crash. Stops cleanly on SIGINT/SIGTERM or after --duration. A payload over the "
            "decoders' size bound (64 KiB; 1 MiB on the mission key) is not written: it is counted per key, "
            "and the counts are stored in the file's metadata (dropped_oversize_json)."
        ),
    )
    p.add_argument("--swarm", default="default", help="swarm name: records swarm/<name>/** (default: default)")
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh router endpoint (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--out", type=Path, required=True, metavar="FILE.mcap", help="output MCAP file (overwritten)")
    p.add_argument("--scenario", type=Path, help="scenario TOML to store in the file; default: ask the leader's mission")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: run until SIGINT/SIGTERM)")
    p.add_argument(
        "--mode",
        choices=("lockstep", "realtime", "unknown"),
        default="lockstep",
        help="time mode of the swarm, stored in the metadata (default lockstep)",
    )
    p.add_argument("--realtime", action="store_true", help="same as --mode realtime")
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=DEFAULT_CONNECT_TIMEOUT_S,
        metavar="S",
        help=f"keep trying to reach the router this long (default {DEFAULT_CONNECT_TIMEOUT_S:g} s)",
    )
    p.add_argument(
        "--flush-interval",
        type=float,
        default=DEFAULT_FLUSH_INTERVAL_S,
        metavar="S",
        help=f"close the chunk and flush the file at least this often (default {DEFAULT_FLUSH_INTERVAL_S} s)",
    )
    p.add_argument(
        "--chunk-size", type=int, default=DEFAULT_CHUNK_SIZE, metavar="BYTES", help="close a chunk at this size (default 1 MiB)"
    )
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunk compression (default zstd)")
    add_security_args(p)
    p.add_argument(
        "--diag-interval",
        type=float,
        default=1.0,
        metavar="S",
        help="publish the recorder's counters on diag/recorder every S seconds (recorded too; 0 = never; default 1)",
    )
    add_fault_args(p)  # not applied here: stored in the metadata for `replay --verify`
    add_plugin_args(p)  # applied to the scenario stored (what `verify` rebuilds the agents from)
    p.set_defaults(func=main)

"""Subcommands of the flight recorder, wired into ``zenswarm`` by :func:`add_parsers`.

``record`` (:mod:`zenswarm.bridge.recording.recorder`), ``replay`` (:mod:`zenswarm.bridge.replay.replay`),
``verify`` (:mod:`zenswarm.bridge.replay.verify`), ``recover`` (:mod:`zenswarm.bridge.recording.recover`),
``info`` (:mod:`zenswarm.bridge.recording.info`);
``report`` (:mod:`zenswarm.bridge.reports.report`) and ``export``
(:mod:`zenswarm.bridge.views.export`) when those modules are present.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["BRIDGE_COMMANDS", "add_parsers"]


def _run_recover(args: argparse.Namespace) -> int:
    from zenswarm.bridge.recording.recover import recover
    from zenswarm.process.paths import check_output_file

    check_output_file(args.out, "--out")
    st = recover(args.src, args.out)
    span = ""
    if st.first_log_time is not None and st.last_log_time is not None:
        span = f" spanning {(st.last_log_time - st.first_log_time) / 1e9:.3f} s"
    if st.intact:
        state = "complete, intact: nothing damaged"
    elif st.source_complete:
        state = "complete but damaged"
    else:
        state = "truncated: not closed cleanly"
    print(
        f"recover: {args.src} ({state}) -> {args.out}: "
        f"{st.messages} messages on {st.channels} channels{span}, {st.metadata} metadata records"
    )
    for line in st.losses():
        print(f"recover: lost: {line}")
    for p in st.problems:
        print(f"recover: source problem: {p}", file=sys.stderr)
    if args.json:
        print(json.dumps(st.as_dict(), sort_keys=True))
    return 0


def _add_recover(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "recover",
        help="rewrite a truncated or corrupted recording into a complete MCAP file",
        description=(
            "Read SRC leniently (everything written before a crash, skipping chunks that fail their "
            "CRC) and write DST as a complete MCAP file with summary and indexes: same messages, "
            "channels and metadata. Says whether the source was intact, and what is known about what "
            "was lost (`recover: lost:` lines): messages missing by the recorder's per-key sequence "
            "numbers, chunks skipped as corrupted and how many messages their indexes list, the bytes "
            "of a cut or damaged tail, the last good log time; the number of messages a killed "
            "recorder never wrote cannot be known and is not guessed. Lists the damage found on stderr."
        ),
    )
    p.add_argument("src", type=Path, help="damaged recording")
    p.add_argument("--out", type=Path, required=True, metavar="DST", help="output MCAP file (must differ from SRC)")
    p.add_argument("--json", action="store_true", help="also print the statistics as JSON")
    p.set_defaults(func=_run_recover)


#: The subcommands :func:`add_parsers` registers, in its order.
BRIDGE_COMMANDS = ("record", "replay", "verify", "info", "recover", "bridge", "report", "export")


def add_parsers(sub: argparse._SubParsersAction, only: str | None = None) -> None:
    """Register ``record``, ``replay``, ``verify``, ``recover``, ``info``, ``bridge`` (and
    ``report``/``export`` when :mod:`zenswarm.bridge.reports.report` /
    :mod:`zenswarm.bridge.views.export` exist); with ``only`` (one of :data:`BRIDGE_COMMANDS`),
    only the module that registers it is imported and asked."""

    def wanted(*names: str) -> bool:
        return only is None or only in names

    if wanted("record"):
        from zenswarm.bridge.recording import recorder

        recorder.add_parser(sub)
    if wanted("replay"):
        from zenswarm.bridge.replay import replay

        replay.add_parser(sub)
    if wanted("verify"):
        from zenswarm.bridge.replay import verify

        verify.add_parser(sub)
    if wanted("info"):
        from zenswarm.bridge.recording import info

        info.add_parser(sub)
    if wanted("recover"):
        _add_recover(sub)
    if wanted("bridge"):
        _add_bridge(sub)
    for name, modname in (("report", "zenswarm.bridge.reports.report"), ("export", "zenswarm.bridge.views.export")):
        if wanted(name):
            _add_optional(sub, modname)


def _add_bridge(sub: argparse._SubParsersAction) -> None:
    from zenswarm.bridge.vehicles import crazyflie, mavlink

    b = sub.add_parser(
        "bridge",
        help="connect the swarm bus to the outside (MAVLink vehicles, Crazyflies)",
        description="Bridges between the swarm bus and the outside world.",
    )
    bsub = b.add_subparsers(dest="bridge_cmd", metavar="{mavlink,crazyflie}", required=True)
    mavlink.add_mavlink_parser(bsub)
    crazyflie.add_crazyflie_parser(bsub)


def _add_optional(sub: argparse._SubParsersAction, modname: str) -> None:
    """The subcommand of ``modname`` (``report``, ``export``), when that module imports."""
    try:
        mod = __import__(modname, fromlist=["add_parser"])
    except ImportError as e:
        if not (e.name and modname.startswith(e.name)):
            # present but broken (a missing dependency): keep every other command working
            print(f"zenswarm: warning: {modname} not available: {e}", file=sys.stderr)
        return
    register = getattr(mod, "add_parsers", None) or getattr(mod, "add_parser", None)
    if register is not None:
        register(sub)

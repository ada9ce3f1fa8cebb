"""``python -m zenswarm.compose.router --listen tcp/127.0.0.1:7447 [--connect EP] [--set PATH=JSON ...]``:
run a swarm router (:func:`zenswarm.bus.serve_router`) until SIGTERM/SIGINT (exit 0). Prints one
line ``ready <zid> <endpoints...>`` once listening; exit 1 with a message on stderr if it cannot
start (a bad ``--set`` included)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

from zenswarm import bus

__all__ = ["build_parser", "parse_settings", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m zenswarm.compose.router", description="Run a zenswarm Zenoh router.")
    parser.add_argument("--listen", action="append", required=True, help="endpoint, e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--connect", action="append", default=[], help="another router to link to")
    parser.add_argument(
        "--set", action="append", default=[], metavar="PATH=JSON", help="config setting, e.g. adminspace/enabled=true"
    )
    return parser


def parse_settings(items: Sequence[str]) -> dict[str, Any]:
    """``--set PATH=JSON`` words as {path: value}; :class:`zenswarm.bus.BusError` naming the bad one."""
    settings: dict[str, Any] = {}
    for item in items:
        path, sep, value = item.partition("=")
        if not sep:
            raise bus.BusError(f"--set {item!r}: expected PATH=JSON")
        try:
            settings[path] = json.loads(value)
        except json.JSONDecodeError as e:
            raise bus.BusError(f"--set {item!r}: {e}") from None
    return settings


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        bus.serve_router(args.listen, args.connect, parse_settings(args.set))
    except bus.Shutdown:
        return 0
    except bus.BusError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    return 0  # pragma: no cover - serve_router returns only by Shutdown


if __name__ == "__main__":
    sys.exit(main())

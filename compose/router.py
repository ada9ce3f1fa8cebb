"""A swarm's Zenoh router: the one ``zenswarm up``'s supervisor opens in its own process
(:func:`open_router`, a free port taken again if another program bound it first; its session's
channel of every message of the swarm, :func:`swarm_channel`), and
``python -m zenswarm.compose.router --listen tcp/127.0.0.1:7447 [--connect EP] [--set PATH=JSON ...]``:
run a swarm router (:func:`zenswarm.bus.serve_router`) until SIGTERM/SIGINT (exit 0). Prints one
line ``ready <zid> <endpoints...>`` once listening; exit 1 with a message on stderr if it cannot
start (a bad ``--set`` included)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from zenswarm import bus
from zenswarm.bus import wire

__all__ = [
    "COLLECTOR_QUEUE",
    "ROUTER_PORT_TRIES",
    "open_router",
    "swarm_channel",
    "undeclare_all",
    "build_parser",
    "parse_settings",
    "main",
]

COLLECTOR_QUEUE = 4_000_000
"""Capacity of the supervisor's bus queue, in messages (drained every ~50 ms, so it never fills)."""

ROUTER_PORT_TRIES = 5
"""Without ``--listen`` the router's port is a free one, chosen a moment before the router binds
it; another program (a second flight started at the same moment) may take it in between. Then a
new free port, up to this many ports in all."""


def open_router(
    listen: list[str], settings: dict[str, Any], *, router_connect: Sequence[str], given: bool, say: Callable[[str], None]
) -> tuple[Any, zenoh.Session, list[str]]:
    """A router's session in this process (its context manager, entered; the session; the
    endpoints it listens on), with its config ``settings`` (security), linked to the routers
    ``router_connect``. ``given`` false: the port was chosen free a moment ago, and if another
    program bound it since (two flights started at once) the router takes a new free port, up to
    :data:`ROUTER_PORT_TRIES` ports, and says so (``say``). A port ``given`` (``--listen``) is never
    changed: :class:`zenswarm.bus.BusError` naming ``--listen`` (exit 2)."""
    for attempt in range(1, ROUTER_PORT_TRIES + 1):
        cm = bus.open_session(bus.router_config(listen, connect=list(router_connect), settings=settings), handle_signals=False)
        try:
            return cm, cm.__enter__(), listen
        except bus.BusError as e:
            if "Address already in use" not in str(e) or attempt == ROUTER_PORT_TRIES:
                raise
            if given:
                raise bus.BusError(f"--listen {', '.join(listen)}: the port is taken by another program (another flight?); "
                                   "give another port, or leave --listen out for a free one") from None
            port = bus.free_port()
            say(f"the router's port was taken by another program before the router bound it ({', '.join(listen)}); "
                f"taking port {port}")
            listen = [ep.rpartition(":")[0] + f":{port}" for ep in listen]
    raise AssertionError("unreachable")  # the last try returns or raises


def swarm_channel(session: zenoh.Session, keys: wire.Keys) -> Any:
    """A subscriber of ``session`` to the swarm's whole key space (``keys.all``), as a channel of
    :data:`COLLECTOR_QUEUE` messages the supervisor's watch loop drains: no Python callback per
    message (each would wake a thread of this process, on the cores the swarm shares). The capacity
    holds minutes of a large swarm's traffic, so the router never waits on this queue."""
    return session.declare_subscriber(keys.all, zenoh.handlers.FifoChannel(COLLECTOR_QUEUE))


def undeclare_all(subs: Sequence[Any]) -> None:
    """Undeclare each subscriber of ``subs``, best effort (on shutdown: one that fails does not stop the rest)."""
    for s in subs:
        try:
            s.undeclare()
        except Exception:  # noqa: BLE001 - best effort on shutdown
            pass


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

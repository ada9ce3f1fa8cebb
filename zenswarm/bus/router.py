"""A swarm router as a process of its own (:func:`serve_router`, the body of
``python -m zenswarm.compose.router``)."""

from __future__ import annotations

import signal
from collections.abc import Mapping, Sequence
from typing import Any

from zenswarm.bus.config import router_config
from zenswarm.bus.session import open_session

__all__ = ["serve_router"]


def serve_router(listen: Sequence[str], connect: Sequence[str] = (), settings: Mapping[str, Any] | None = None) -> None:
    """Run a swarm router listening on ``listen`` (linked to the routers ``connect``, with extra
    config ``settings`` {path: value}) until SIGTERM/SIGINT, which raise
    :class:`~zenswarm.bus.errors.Shutdown`. Prints one line ``ready <zid> <endpoints...>`` once
    listening; :class:`~zenswarm.bus.errors.BusError` if it cannot start. The command is
    ``python -m zenswarm.compose.router``."""
    with open_session(router_config(list(listen), connect=list(connect), settings=settings or {})) as session:
        print("ready", session.zid(), *listen, flush=True)
        while True:  # bounded by a signal: Shutdown ends it
            signal.pause()

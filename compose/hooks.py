"""What ``zenswarm up``'s supervisor offers the objects its front door (:mod:`zenswarm.compose.up`)
attaches to it, so that it only supervises: taps (:class:`Tap`), fed every message its router's
session takes (the live view), and end hooks, called with the :class:`FlightEnd` once the results
are written (the flight report).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

__all__ = ["Tap", "feeds", "FlightEnd", "EndHook"]


class Tap(Protocol):
    """A view of the flight as it flies (:class:`zenswarm.bridge.views.live.LiveView` is one)."""

    def feed(self, key: str, payload: bytes) -> None:
        """One message of the swarm (its key, its payload), as the supervisor's session took it."""

    def maybe_publish(self, now: float) -> bool:
        """One pass of the supervisor's loop at wall time ``now`` (monotonic s): publish if due."""

    def publish(self) -> bool:
        """The flight's last frame, once its processes are stopped."""


def feeds(taps: Sequence[Tap]) -> Callable[[str, bytes], None] | None:
    """One callable feeding every tap of ``taps`` a message (the collector's ``tap``); None without a tap."""
    if len(taps) <= 1:
        return taps[0].feed if taps else None
    fed = list(taps)

    def feed(key: str, payload: bytes) -> None:
        for t in fed:
            t.feed(key, payload)

    return feed


@dataclass(frozen=True)
class FlightEnd:
    """A supervised flight that ended, its results written: into ``out``; ``code``, the exit
    status so far (before the verdict's 0 or 1); ``results``, results.json's fields; the
    ``recording`` (``--record``) and, if the recorder died, its ``recording_loss``; ``say``, the
    supervisor's console."""

    out: Path
    code: int
    results: dict[str, Any]
    recording: Path | None
    recording_loss: dict[str, Any] | None
    say: Callable[[str], None]


EndHook = Callable[[FlightEnd], None]
"""Called once a flight's results are written (the report with ``--report``)."""

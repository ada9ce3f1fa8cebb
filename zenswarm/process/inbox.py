"""A process's inbox: decoded inputs by (key, tick), and the wait for the ones a tick needs."""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from typing import Any

__all__ = ["Inbox"]


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
        # No lock: a dict lookup is atomic under the GIL, and this one inserts nothing (the
        # lockstep checks call it a few times per message: the lock cost more than the rest).
        d = self._by_tick.get(key)
        return None if d is None else d.get(tick)

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

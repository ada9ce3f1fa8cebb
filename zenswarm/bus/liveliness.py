"""Who is there: a process's liveliness token (:func:`declare_alive`), the supervisor's view of
every process's token (:class:`AliveWatcher`), and whether a publisher has a subscriber yet
(:func:`wait_matching`)."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from typing import cast

import zenoh

from zenswarm.bus.keys import InvalidKeyError, Keys, validate_process
from zenswarm.bus.session import undeclare

__all__ = ["declare_alive", "AliveWatcher", "wait_matching"]


def declare_alive(session: zenoh.Session, keys: Keys, process: str) -> zenoh.LivelinessToken:
    """Declare the liveliness token ``swarm/<name>/alive/<process>``.

    Keep the returned token referenced: it is undeclared when garbage-collected, when the
    session closes, and (by the router, within milliseconds on loopback) when the process dies.
    """
    return session.liveliness().declare_token(keys.alive(process))


class AliveWatcher:
    """Track which processes of a swarm hold a liveliness token (the supervisor's view).

    On creation the tokens already present are reported (history), then every join and leave.
    ``on_change(process, alive)`` is called on zenoh's callback thread: keep it short and never
    close the session from it. Tokens whose key is not ``alive/<valid process>`` are ignored
    (counted in ``ignored``). Use as a context manager or call :meth:`close`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        on_change: Callable[[str, bool], None] | None = None,
        *,
        history: bool = True,
    ) -> None:
        self._keys = keys
        self._on_change = on_change
        self._cond = threading.Condition()
        self._alive: set[str] = set()
        self.events: list[tuple[float, str, bool]] = []
        """(time.monotonic() s, process, alive) of every change, in arrival order."""
        self.ignored = 0
        self._sub = session.liveliness().declare_subscriber(keys.alive_all, self._on_sample, history=history)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        try:
            kind, _, process = self._keys.parse(str(sample.key_expr))
        except InvalidKeyError:
            kind, process = "", None
        if kind != "alive" or process is None:
            with self._cond:
                self.ignored += 1
            return
        with self._cond:
            if alive:
                self._alive.add(process)
            else:
                self._alive.discard(process)
            self.events.append((time.monotonic(), process, alive))
            self._cond.notify_all()
        if self._on_change is not None:
            self._on_change(process, alive)

    @property
    def alive(self) -> frozenset[str]:
        """Processes holding a token now."""
        with self._cond:
            return frozenset(self._alive)

    def wait_for(self, process: str, alive: bool = True, timeout: float = 5.0) -> bool:
        """Block until ``process`` is (alive=True) or is not (False) holding a token, at most
        ``timeout`` s. Returns whether that happened."""
        validate_process(process)
        with self._cond:
            return self._cond.wait_for(lambda: (process in self._alive) == alive, timeout=timeout)

    def close(self) -> None:
        """Undeclare the liveliness subscriber (idempotent; a closed session already did)."""
        with contextlib.suppress(Exception):
            undeclare(self._sub)

    def __enter__(self) -> AliveWatcher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_matching(publisher: zenoh.Publisher, timeout: float = 5.0, poll_s: float = 0.001) -> bool:
    """Wait up to ``timeout`` s until some subscriber matches ``publisher`` (through the router).

    Publications made before a subscription has reached the router are lost; use this before
    the first put when it matters. Note ``Publisher.matching_status`` is a ``MatchingStatus``
    (always truthy) in 1.10.2: its ``.matching`` is the bool.
    """
    deadline = time.monotonic() + timeout
    while True:
        # zenoh 1.10.2's stub types matching_status as bool; it is a MatchingStatus (see above)
        if cast(zenoh.MatchingStatus, publisher.matching_status).matching:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(poll_s)

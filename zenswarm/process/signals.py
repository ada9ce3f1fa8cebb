"""Stop requests from SIGINT/SIGTERM without taking a lock inside the signal handler.

Python runs a signal handler in the main thread, between two bytecodes of whatever the main
thread was doing. A handler that calls ``threading.Event.set()`` takes the event's internal lock
(a plain ``threading.Lock``); if the main thread was itself inside that event's ``wait()`` or
``set()`` at that moment, it already holds the lock, and the handler waits for it forever: the
process hangs on its stop signal (the Python documentation of :mod:`signal`: synchronization
primitives should not be used within signal handlers). A loop that waits on its stop event in
the main thread (``stop.wait(0.2)``) has that window every time round.

:class:`SignalRelay` keeps the handler lock-free: it only writes the signal's number to a pipe.
A daemon thread reads the pipe and calls ``on_signal(signum)`` there, where taking locks is
safe (at worst it waits the few microseconds until the main thread leaves ``wait()``)::

    stop = threading.Event()
    with SignalRelay(lambda signum: stop.set()):
        while not stop.wait(0.2):
            ...
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterable
from types import FrameType
from typing import Any

__all__ = ["SignalRelay"]

_CLOSE = 0
"""The byte :meth:`SignalRelay.close` writes to end the relay thread (no signal has number 0)."""


class SignalRelay:
    """Install handlers for ``signals`` (main thread only) that hand each signal to ``on_signal``,
    called in a thread of its own, never in the handler. :meth:`close` (or leaving the ``with``
    block) restores the previous handlers and ends the thread."""

    def __init__(
        self,
        on_signal: Callable[[int], None],
        signals: Iterable[signal.Signals] = (signal.SIGINT, signal.SIGTERM),
        name: str = "signal-relay",
    ) -> None:
        self._on_signal = on_signal
        self._r, self._w = os.pipe()
        os.set_blocking(self._w, False)  # a handler never blocks (a full pipe drops the signal: one is enough)
        self._thread = threading.Thread(target=self._relay, name=name, daemon=True)
        self._thread.start()
        self._previous: dict[signal.Signals, Any] = {}
        try:
            for sig in signals:
                self._previous[sig] = signal.signal(sig, self._handler)
        except BaseException:
            self.close()
            raise

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        # Runs between two bytecodes of the main thread: no lock, no allocation beyond the byte.
        try:
            os.write(self._w, bytes((signum,)))
        except OSError:  # a full pipe (signals already pending) or closed (after close())
            pass

    def _relay(self) -> None:
        while True:
            try:
                data = os.read(self._r, 64)
            except OSError:
                return
            for signum in data:
                if signum == _CLOSE:
                    return
                try:
                    self._on_signal(signum)
                except Exception:  # noqa: BLE001 - a failing callback must not end the relay
                    pass
            if not data:
                return

    def close(self) -> None:
        """Restore the previous handlers, end the relay thread (signals already received are
        handed on first), close the pipe. Idempotent."""
        for sig, h in self._previous.items():
            signal.signal(sig, h)
        self._previous = {}
        if self._w < 0:
            return
        try:
            os.set_blocking(self._w, True)
            os.write(self._w, bytes((_CLOSE,)))
        except OSError:
            pass
        if self._thread.ident != threading.get_ident():
            self._thread.join(5.0)
        w, self._w = self._w, -1
        os.close(w)
        if not self._thread.is_alive():  # else on_signal is still running: its read end stays open
            os.close(self._r)

    def __enter__(self) -> SignalRelay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

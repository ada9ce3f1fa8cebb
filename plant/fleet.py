"""A fleet of simulated vehicles whose loop runs in a daemon thread: start, stop, context manager.

Shared by the simulated MAVLink vehicles (``plant/mavlink_vehicle.py``) and the simulated
Crazyflies (``plant/crazyflie_vehicle.py``). A subclass sets, in its ``__init__``, ``vehicles``
(each with ``close()``), ``_stop`` (a ``threading.Event``), ``_thread = None`` and ``error = None``,
and implements ``run(stop)``: the loop, returning why it ended.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any, Protocol, Self


class _Closable(Protocol):
    def close(self) -> None: ...


class FleetThread(ABC):
    """The thread around a fleet's loop; ``error`` holds what ended it, if anything raised."""

    thread_name = "fleet"
    vehicles: Sequence[_Closable]
    _stop: threading.Event
    _thread: threading.Thread | None
    error: BaseException | None

    @abstractmethod
    def run(self, stop: threading.Event) -> str:
        """The fleet's loop until ``stop`` is set (or its own end); returns the reason it ended."""

    def start(self) -> Self:
        """Run the loop in a daemon thread."""
        if self._thread is not None:
            raise RuntimeError("fleet already started")

        def target() -> None:
            try:
                self.run(self._stop)
            except BaseException as e:  # noqa: BLE001 - reported through .error
                self.error = e

        self._thread = threading.Thread(target=target, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the loop (waiting at most ``timeout`` s for it) and close every vehicle."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self.close()

    def close(self) -> None:
        for v in self.vehicles:
            v.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

"""What the simulated fleets share: the thread around a fleet's loop (start, stop, context
manager), the flat ground the vehicles stand on, and the command line's run until a signal.

Shared by the simulated MAVLink vehicles (``plant/mavlink/fleet.py``) and the simulated
Crazyflies (``plant/crazyflie/fleet.py``). A subclass of :class:`FleetThread` sets, in its
``__init__``, ``vehicles`` (each with ``close()``), ``_stop`` (a ``threading.Event``),
``_thread = None``, ``error = None``, ``overruns = 0``, ``state`` (the plant's
:class:`~zenswarm.plant.quadrotor.PlantState`) and ``_lock`` (a ``threading.Lock`` its loop holds
while it integrates), and implements ``run(stop, duration_s)``: the loop, returning why it ended,
and ``status()``: one line of facts per vehicle. Positions are the plant's, m ENU. Another thread
reads the vehicles' state with :meth:`FleetThread.snapshot`: ``state`` itself is half-written
while a physics sub-step runs (a vehicle resting on the ground reads a few micrometres below it
between the integration and the ground contact).
"""

from __future__ import annotations

import signal
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any, Protocol, Self

from zenswarm.plant.quadrotor import PlantState


class _Closable(Protocol):
    def close(self) -> None: ...


class FleetThread(ABC):
    """The thread around a fleet's loop; ``error`` holds what ended it, if anything raised."""

    thread_name = "fleet"
    vehicles: Sequence[_Closable]
    _stop: threading.Event
    _thread: threading.Thread | None
    error: BaseException | None
    overruns: int
    state: PlantState
    _lock: threading.Lock

    @abstractmethod
    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> str:
        """The fleet's loop until ``stop`` is set (or ``duration_s`` s passed); returns the reason it ended."""

    @abstractmethod
    def status(self) -> list[dict[str, Any]]:
        """One line of facts per vehicle (for logs and tests)."""

    def snapshot(self) -> PlantState:
        """A copy of the plant's state between two physics chunks (ENU: m, m/s, rad; body rates
        FLU, rad/s); safe to call from any thread while the loop runs."""
        with self._lock:
            return self.state.copy()

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


def ground_contact(st: PlantState, ground_z: float) -> None:
    """Flat ground at ``ground_z`` (m, ENU z): a vehicle below it is put back on it, at rest and
    level (in place; runs every physics sub-step, so the common case returns at once)."""
    if st.q[:, 2].min() >= ground_z:
        return
    below = st.q[:, 2] < ground_z
    st.q[below, 2] = ground_z
    st.v[below] = 0.0
    st.w[below] = 0.0
    st.rpy[below, 0:2] = 0.0
    st.rate_int[below] = 0.0


def run_until_signal(
    fleet: FleetThread,
    name: str,
    ready: str,
    duration: float | None,
    *,
    on_ready: Callable[[], None] | None = None,
    counters: Callable[[], str] | None = None,
) -> int:
    """Run ``fleet`` in the calling thread until SIGTERM/SIGINT (or ``duration`` s), then close it;
    returns the exit status (0). Prints ``NAME: ready: READY``, calls ``on_ready`` (start-up is
    over), applies the requested real-time priority (:func:`zenswarm.process.rtsched.apply_after_startup`,
    its lines prefixed ``NAME:``), and at the end ``NAME: stopped (why); overruns K; [COUNTERS; ]STATUS``
    (``counters()``, then :meth:`FleetThread.status`)."""
    from zenswarm.process import rtsched

    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    try:
        print(f"{name}: ready: {ready}", flush=True)
        if on_ready is not None:
            on_ready()
        rtsched.apply_after_startup(lambda text: print(f"{name}: {text}", flush=True))  # --rt-priority
        why = fleet.run(stop, duration)
        extra = f"{counters()}; " if counters is not None else ""
        print(f"{name}: stopped ({why}); overruns {fleet.overruns}; {extra}{fleet.status()}", flush=True)
    finally:
        fleet.close()
    return 0

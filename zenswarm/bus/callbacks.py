"""Subscriber callbacks on zenoh's own receiving thread (:func:`direct_callback`), that thread's
Python thread state kept for the life of the process."""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable

import zenoh

__all__ = ["direct_callback"]

_PINNED: set[int] = set()
_PIN_LOCK = threading.Lock()


def _pin_thread_state() -> None:
    """Keep the calling native thread's Python thread state for the life of the process.

    zenoh runs a ``Callback(f, indirect=False)`` on its own (tokio) threads, which have no Python
    thread state: every call creates one and destroys it again (``PyGILState_Ensure`` /
    ``Release``; in CPython 3.11 that includes mapping and unmapping a 16 KiB frame stack). One
    extra ``PyGILState_Ensure`` that is never released keeps the state, so later calls only take
    the GIL. Called with the GIL held; those threads are few (one with
    :func:`~zenswarm.bus.runtime.use_swarm_runtime`).
    """
    tid = threading.get_ident()
    with _PIN_LOCK:
        if tid not in _PINNED:
            _PINNED.add(tid)
            ctypes.pythonapi.PyGILState_Ensure()


def direct_callback(fn: Callable[[zenoh.Sample], None]) -> zenoh.handlers.Callback[zenoh.Sample]:
    """A subscriber handler that runs ``fn(sample)`` on zenoh's receiving thread.

    The default for a plain Python callable is a dedicated Python thread per subscriber that
    zenoh hands each sample to: one thread wake-up and one GIL hand-over per message, and with
    several subscribers, several threads contending for the GIL. Here the thread that read the
    sample from the socket runs ``fn`` itself (its Python thread state kept, see
    :func:`_pin_thread_state`). ``fn`` must be quick and must not block: while it runs, this
    session receives nothing else. Other threads may put meanwhile: zenoh-python releases the
    GIL while a ``put`` waits (``py.allow_threads``), so a put from the main loop that waits for
    queue space lets this callback finish, and the one zenoh thread then makes room
    (``tests/test_bus.py::test_a_blocked_put_does_not_hold_the_gil``). A put from inside ``fn``
    that finds the queue full waits for the thread it runs on (see
    :func:`~zenswarm.bus.runtime.use_swarm_runtime`). BENCHMARKS.md, "What made the swarm faster".
    """

    def run(sample: zenoh.Sample) -> None:
        if threading.get_ident() not in _PINNED:
            _pin_thread_state()
        fn(sample)

    return zenoh.handlers.Callback(run, indirect=False)

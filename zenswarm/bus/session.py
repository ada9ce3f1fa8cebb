"""Sessions that always close (eclipse-zenoh 1.10.x), and the undeclaring of what they declared.

Exiting cleanly (observed with eclipse-zenoh 1.10.2; ``tests/test_bus.py`` checks the safe pattern):

* A subscriber declared with a plain Python callable runs it on a *non-daemon* Python thread
  (``pyo3-closure``) that ends only when the subscriber is undeclared or the session closed.
  The interpreter joins non-daemon threads *before* ``atexit`` hooks run, so a process that
  reaches the end of its main module with such a session open hangs forever, and
  ``atexit.register(session.close)`` does not help. :func:`open_session` closes on every exit
  path of its ``with`` block and also registers the close with ``threading._register_atexit``
  (runs before the join) for sessions that escape it.
* Subscribers with a channel handler (``FifoChannel``/``RingChannel``), liveliness tokens,
  publishers and ``Callback(f, indirect=False)`` create no Python thread and do not hang.
* SIGTERM's default action kills the process without any cleanup (the router then drops its
  tokens at once, as for SIGKILL). :func:`open_session` installs SIGTERM/SIGINT handlers that
  raise :class:`~zenswarm.bus.errors.Shutdown` (a ``SystemExit``) in the main thread, so the
  ``with`` block unwinds and the session is closed. A blocking ``recv()`` on a zenoh channel checks
  for signals every 100 ms, so it is interrupted too; a closed session wakes a blocked ``recv()``
  with ``ZError``.
* Publishers, channel subscribers and liveliness tokens are undeclared when their Python object
  is garbage-collected: keep references. Callback subscribers live until the session closes.
* Sessions do not survive ``fork``: open them in the process that uses them.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any, Protocol

import zenoh

from zenswarm.bus.errors import BusError, Shutdown

__all__ = ["Undeclarable", "undeclare", "close_at_exit", "open_session"]


class Undeclarable(Protocol):
    """A zenoh entity that can be undeclared: subscriber, publisher, queryable, liveliness token,
    transport-events listener."""

    def undeclare(self) -> None: ...


def undeclare(entity: Undeclarable) -> None:
    """``entity.undeclare()``: zenoh's type stubs (1.10.2) leave ``undeclare`` unannotated, so
    typed code calls it through this protocol."""
    entity.undeclare()


class _Closable(Protocol):
    def close(self) -> None: ...


def _close(session: _Closable) -> None:
    """``session.close()``, typed (zenoh's stubs leave ``Session.close`` unannotated)."""
    session.close()


def close_at_exit(session: zenoh.Session) -> None:
    """Close ``session`` when the interpreter shuts down, *before* it joins non-daemon threads
    (zenoh's Python-callback threads), which ``atexit`` would be too late for."""
    register = getattr(threading, "_register_atexit", None)  # CPython >= 3.9, private
    try:
        if register is not None:
            register(session.close)
        else:  # pragma: no cover - other interpreters
            import atexit

            atexit.register(session.close)
    except RuntimeError:  # interpreter already shutting down
        pass


_SignalHandler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None
"""What :func:`signal.signal` returns and takes: a handler, ``SIG_DFL``/``SIG_IGN``, or None."""


@contextlib.contextmanager
def open_session(conf: zenoh.Config, *, handle_signals: bool = True) -> Iterator[zenoh.Session]:
    """Open a session and close it on every exit path::

        with open_session(client_config([endpoint])) as session:
            ...

    handle_signals: in the main thread, SIGTERM and SIGINT raise :class:`Shutdown` for the
    duration of the block (the previous handlers are restored afterwards); a second signal
    while unwinding is ignored. Pass False in a process that manages signals itself (or in
    tests that open sessions inside pytest). Raises :class:`BusError` if the session cannot
    be opened (e.g. the router is not reachable within the client's connect timeout).
    """
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as e:
        raise BusError(f"cannot open zenoh session: {e}") from None
    close_at_exit(session)
    previous: dict[signal.Signals, _SignalHandler] = {}
    quiet = False  # set once a signal fired or the block is left: further signals are ignored

    def _handler(signum: int, frame: FrameType | None) -> None:
        nonlocal quiet
        if not quiet:
            quiet = True
            raise Shutdown(signum)

    if handle_signals and threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, _handler)
    try:
        yield session
    finally:
        quiet = True
        try:
            _close(session)
        finally:
            for sig, h in previous.items():
                signal.signal(sig, h)

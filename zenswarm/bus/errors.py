"""The bus's two exceptions: :class:`BusError` (a session could not be configured or opened) and
:class:`Shutdown` (a requested stop, raised by the signal handlers of
:func:`zenswarm.bus.session.open_session`)."""

from __future__ import annotations

from zenswarm.errors import ZenswarmError

__all__ = ["BusError", "Shutdown"]


class BusError(ZenswarmError):
    """A Zenoh session could not be configured or opened."""


class Shutdown(SystemExit):
    """Raised in the main thread by the signal handlers of :func:`~zenswarm.bus.session.open_session`.

    A ``SystemExit`` with exit status 0 (a requested, clean stop); ``signum`` is the signal.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(0)
        self.signum = signum

"""Output paths checked before any work: a run must never fly (or compute) and then fail to write.

Every command that writes calls :func:`check_output_dir` or :func:`check_output_file` on each of
its output flags first (``--out``, ``--record``). Both raise :class:`ScenarioError` whose field is
the flag, so the CLI prints ``zenswarm: error: --out: ...`` and exits with status 2.

Nothing is created: a missing directory is fine when its nearest existing ancestor is a directory
this process can write in (the command creates the rest when it writes), which is probed by
creating and removing a temporary file there. The probe, not the permission bits, decides, so the
check also holds for root (who ignores permission bits) on read-only or pseudo file systems such
as ``/proc``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from zenswarm.errors import ScenarioError

__all__ = ["check_output_dir", "check_output_file"]


def _nearest_existing(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists (``lexists``: a dangling link counts)."""
    p = path
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def _probe_writable(directory: Path, path: Path, flag: str) -> None:
    """Create and remove a temporary file in ``directory``; ScenarioError naming ``flag`` if that fails."""
    try:
        fd, name = tempfile.mkstemp(dir=directory, prefix=".zenswarm-probe-")
    except OSError as e:
        where = "" if directory == path else f" (nothing can be created in {directory})"
        raise ScenarioError(flag, f"{path}: not writable{where}: {e.strerror or e}") from None
    os.close(fd)
    try:
        os.unlink(name)
    except OSError:  # pragma: no cover - we just created it
        pass


def _check_ancestor(path: Path, flag: str) -> Path:
    """The nearest existing ancestor of ``path`` (path itself excluded), which must be a writable
    directory."""
    anc = _nearest_existing(path.parent)
    if not anc.is_dir():
        raise ScenarioError(flag, f"{path}: {anc} is a file, not a directory")
    return anc


def check_output_dir(path: str | os.PathLike[str], flag: str) -> Path:
    """Check that ``path`` is, or can be created as, a directory this process can write in.

    Raises :class:`ScenarioError` (field ``flag``) when ``path`` is a file, when one of its
    ancestors is a file, or when nothing can be written there. Creates nothing. Returns ``path``.
    """
    p = Path(path)
    if os.path.lexists(p):
        if not p.is_dir():
            raise ScenarioError(flag, f"{p} exists and is not a directory (an output directory is needed here)")
        _probe_writable(p, p, flag)
        return p
    _probe_writable(_check_ancestor(p, flag), p, flag)
    return p


def check_output_file(path: str | os.PathLike[str], flag: str) -> Path:
    """Check that ``path`` can be written as a file (an existing file will be replaced).

    Raises :class:`ScenarioError` (field ``flag``) when ``path`` is a directory, when one of its
    ancestors is a file, or when its directory cannot be written in. Creates nothing. Returns
    ``path``.
    """
    p = Path(path)
    if p.is_dir():
        raise ScenarioError(flag, f"{p} is a directory (an output file is needed here)")
    if os.path.lexists(p) and not os.access(p, os.W_OK):
        raise ScenarioError(flag, f"{p}: the file is not writable")
    anc = _check_ancestor(p, flag)
    _probe_writable(anc, p, flag)
    return p


OUTPUT_LOCK = ".zenswarm-up.lock"
"""The file in an output directory that a running flight holds locked (:func:`lock_output_dir`)."""


class OutputLock:
    """An exclusive lock (``flock``) on ``DIR/.zenswarm-up.lock`` held while a flight writes into
    ``DIR``; released by :meth:`release` or when the process ends, however it ends (the kernel
    drops the lock with the descriptor: a SIGKILLed flight leaves no stale lock)."""

    def __init__(self, fd: int, path: Path) -> None:
        self.fd: int | None = fd
        self.path = path

    def release(self) -> None:
        fd, self.fd = self.fd, None
        if fd is not None:
            os.close(fd)


def lock_output_dir(path: str | os.PathLike[str], flag: str) -> OutputLock:
    """Lock the output directory ``path`` (created if missing) for one flight: a second flight
    with the same ``--out`` while the first runs would overwrite its results (two flights at once
    on one machine with the default ``--out``). Raises :class:`ScenarioError` (field ``flag``)
    naming the flight that holds it (its pid), before anything starts."""
    import fcntl

    p = Path(path)
    p.mkdir(parents=True, exist_ok=True)
    lock = p / OUTPUT_LOCK
    fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        try:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        finally:
            os.close(fd)
        raise ScenarioError(
            flag, f"{p} is the output directory of another flight that is running (pid {holder}); give this one its own --out"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return OutputLock(fd, lock)

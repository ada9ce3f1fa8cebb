"""The processes a supervisor starts, as handles it can poll, signal and read.

:class:`Child` is one started role: its name, when it started, its output (the last lines kept,
each line handed to a callback as it comes) and a :class:`Proc`: the OS process behind it. Here a
:class:`LocalProc` (a :class:`subprocess.Popen` on this host); another launcher (a cluster's) gives
its own :class:`Proc` and the supervisor watches both the same way.
"""

from __future__ import annotations

import ctypes
import signal
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

__all__ = ["Proc", "LocalProc", "Child", "start_local", "start_with_settings", "await_exit", "stop_children", "stop_in_order", "pdeathsig",
           "pdeathsig_term"]

LINES_KEPT = 50
"""How many of a child's last output lines are kept (the tail said when it dies)."""


class Proc(Protocol):
    """An OS process a supervisor started (here or on another host)."""

    pid: int

    def poll(self) -> int | None:
        """The exit status once it ended (minus the signal number if a signal ended it), else None."""

    def wait(self, timeout: float | None = None) -> int:
        """Wait for it to end; :class:`subprocess.TimeoutExpired` after ``timeout`` s."""

    def send_signal(self, sig: int) -> None:
        """Send ``sig`` to it (nothing if it has already ended)."""

    def kill(self) -> None:
        """SIGKILL it."""

    def output(self) -> Iterable[str]:
        """Its output (stdout and stderr), line by line, newline stripped, until it ends."""

    def where(self) -> dict[str, Any]:
        """Where it runs, for results.json: ``host`` (name) and ``pid``; a cluster's adds its worker."""


class LocalProc:
    """A :class:`Proc` on this host: a :class:`subprocess.Popen` with its output on a text pipe."""

    def __init__(self, popen: subprocess.Popen) -> None:
        self.popen = popen
        self.pid = popen.pid

    def poll(self) -> int | None:
        return self.popen.poll()

    def wait(self, timeout: float | None = None) -> int:
        return self.popen.wait(timeout=timeout)

    def send_signal(self, sig: int) -> None:
        try:
            self.popen.send_signal(sig)
        except ProcessLookupError:
            pass

    def kill(self) -> None:
        self.popen.kill()

    def where(self) -> dict[str, Any]:
        return {"host": socket.gethostname(), "pid": self.pid}

    def output(self) -> Iterable[str]:
        assert self.popen.stdout is not None
        for raw in self.popen.stdout:
            yield raw.rstrip("\n")


def pdeathsig(sig: int = signal.SIGKILL) -> None:  # runs in the child between fork and exec
    """``PR_SET_PDEATHSIG``: the child gets ``sig`` when the thread that started it ends."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, sig)
    except OSError:
        pass


def pdeathsig_term() -> None:
    """The recorder's: a SIGTERM when the supervisor dies, so it closes its MCAP file (summary
    and footer written: readable as it is) before it exits; the flying roles get a SIGKILL."""
    pdeathsig(signal.SIGTERM)


@dataclass
class Child:
    """One started role: its process, its output's last lines and its exit status once seen."""

    name: str
    proc: Proc
    started: float
    returncode: int | None = None
    reader: threading.Thread | None = None
    lines: list[str] = field(default_factory=list)

    def read(self, on_line: Callable[[Child, str], bool]) -> None:
        """Read the output in a thread of its own until the process ends: each line goes to
        ``on_line``, and is kept (the last :data:`LINES_KEPT`) unless ``on_line`` returns False."""

        def pump() -> None:
            for line in self.proc.output():
                if on_line(self, line):
                    self.lines.append(line)
                    del self.lines[:-LINES_KEPT]

        self.reader = threading.Thread(target=pump, name=f"out-{self.name}", daemon=True)
        self.reader.start()

    def status(self) -> int | None:
        """The exit status seen by the watch, else the process's own (None while it runs)."""
        return self.returncode if self.returncode is not None else self.proc.poll()

    def join_output(self, timeout: float) -> None:
        """Wait (at most ``timeout`` s) for its last lines: the output ends with the process."""
        if self.reader is not None:
            self.reader.join(timeout=timeout)


def start_local(name: str, argv: list[str], env: dict[str, str], stdin: Any, *, term_on_parent_death: bool = False) -> Child:
    """Start ``argv`` on this host in a session of its own (Ctrl-C reaches the supervisor only; it
    stops its children) that dies with the supervisor (SIGKILL, or SIGTERM with
    ``term_on_parent_death``); ``stdin`` as :class:`subprocess.Popen` takes it."""
    p = subprocess.Popen(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=stdin,
        text=True,
        start_new_session=True,
        preexec_fn=pdeathsig_term if term_on_parent_death else pdeathsig,
        env=env,
    )
    return Child(name, LocalProc(p), time.monotonic())


def await_exit(children: Iterable[Child], grace_s: float) -> None:
    """Wait (at most ``grace_s`` in all) for ``children`` to exit by themselves."""
    deadline = time.monotonic() + grace_s
    for c in children:
        try:
            c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass


def stop_children(children: list[Child], grace_s: float, say: Callable[[str], None]) -> None:
    """SIGTERM each of ``children`` still running, wait ``grace_s`` in all, then SIGKILL (said)
    those still there; read their last lines."""
    for c in children:
        if c.proc.poll() is None:
            c.proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for c in children:
        try:
            c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            say(f"{c.name} did not stop within {grace_s:.0f} s; killing it")
            c.proc.kill()
            c.proc.wait()
    for c in children:
        c.join_output(2.0)


def swarm_env(environ: Mapping[str, str], zenoh_runtime: str | None) -> dict[str, str]:
    """The environment a swarm process starts with: ``environ`` with unbuffered output, and
    ``ZENOH_RUNTIME`` set to ``zenoh_runtime`` when given (None: the user's own choice is kept)."""
    env = dict(environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    if zenoh_runtime is not None:
        env["ZENOH_RUNTIME"] = zenoh_runtime
    return env


def start_with_settings(name: str, argv: list[str], settings: bytes, env: dict[str, str], *, term_on_parent_death: bool = False) -> Child:
    """:func:`start_local` with ``settings`` on the child's standard input: a file of its own,
    already gone from the disk (the child holds its own descriptor)."""
    with tempfile.TemporaryFile() as stdin:
        stdin.write(settings)
        stdin.seek(0)
        return start_local(name, argv, env, stdin, term_on_parent_death=term_on_parent_death)


STOPPED_LAST = ("recorder", "bridge", "vehicles")
"""Stopped after the flying roles, in this order: the bridge lands and disarms its vehicles, which
must still run for that; the recorder drains what is still in flight."""


def stop_in_order(children: Mapping[str, Child], leaving: Collection[str], grace_s: float, say: Callable[[str], None]) -> None:
    """SIGTERM a swarm's started roles and wait (then SIGKILL), in order: the flying roles; then
    those ``leaving`` by themselves (a plug-in failed: status 4 after its report), given the grace
    before any signal, so results.json says 4, not the signal that caught them on their way out;
    then the bridge (25 s to land), the vehicles, and the recorder last, after a moment for
    messages in flight, with 60 s to drain its queue and write its summary."""
    rest = [c for c in children.values() if c.name not in STOPPED_LAST]
    going = [c for c in rest if c.name in leaving]
    stop_children([c for c in rest if c not in going], grace_s, say)
    await_exit(going, grace_s)
    stop_children(going, grace_s, say)
    for name, grace in (("bridge", 25.0), ("vehicles", grace_s)):
        if name in children:
            stop_children([children[name]], grace, say)
    rec = children.get("recorder")
    if rec is not None:
        if rec.proc.poll() is None:
            time.sleep(0.3)
        stop_children([rec], 60.0, say)

"""Run ``zenswarm up`` as a child process group and make sure nothing of its swarm outlives it.

Used by the public API (:func:`zenswarm.api.fly`) and ``zenswarm plugins check``. The supervisor
runs in a session of its own; the swarm's processes die with it (``PR_SET_PDEATHSIG``, see
:mod:`zenswarm.compose.supervisor`); on a timeout or an exception (Ctrl-C included) its group is
stopped (SIGTERM: the supervisor stops its swarm and writes what was flown; then SIGKILL), and
any process still carrying ``--swarm NAME`` afterwards is killed and reported. Linux (/proc).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from zenswarm.process.settings import FlightSettings, encode

__all__ = ["UpRun", "up_argv", "run_up", "processes_mentioning", "processes_of", "kill_processes_of", "live_flights", "stop_flight"]


@dataclass(frozen=True)
class UpRun:
    """How a ``zenswarm up`` child ended: its exit status (-N: killed by signal N), its output,
    whether it was stopped for exceeding its wall-time bound, and the command lines of processes
    of its swarm found alive afterwards (killed; empty unless something went wrong)."""

    exit_code: int
    log: str
    timed_out: bool
    leftovers: tuple[str, ...]


def up_argv(o: FlightSettings) -> list[str]:
    """The command line of the ``zenswarm up`` child that flies ``o`` (this interpreter's): it
    reads the settings on its standard input (:func:`run_up`); ``--swarm`` names it in the process
    table."""
    return [sys.executable, "-m", "zenswarm", "up", "--settings", "-", "--swarm", o.swarm]


def processes_mentioning(text: str) -> list[tuple[int, str]]:
    """(pid, command line) of the live processes (not zombies) whose command line, its
    arguments joined by spaces and followed by one, contains ``text``."""
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            cmd = (Path("/proc") / entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            stat = (Path("/proc") / entry / "stat").read_text()
        except OSError:
            continue
        if text in cmd + " " and ") Z " not in stat:
            found.append((int(entry), cmd.strip()))
    return found


def processes_of(swarm: str) -> list[tuple[int, str]]:
    """(pid, command line) of the live processes of ``swarm`` (``--swarm NAME`` on their command
    line; not zombies)."""
    return processes_mentioning(f"--swarm {swarm} ")


def kill_processes_of(swarm: str) -> list[str]:
    """SIGKILL every live process of ``swarm``; returns their command lines."""
    found = processes_of(swarm)
    for pid, _ in found:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return [cmd for _, cmd in found]


_LIVE: dict[int, subprocess.Popen[str]] = {}
_LIVE_LOCK = threading.Lock()


def live_flights() -> list[subprocess.Popen[str]]:
    """The supervisors started by :func:`run_up` in this process that are still running."""
    with _LIVE_LOCK:
        return [p for p in _LIVE.values() if p.poll() is None]


def stop_flight(p: subprocess.Popen[str], grace_s: float = 10.0) -> None:
    """SIGTERM the supervisor's process group (it stops its swarm), SIGKILL it after ``grace_s``."""
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        if p.poll() is not None:
            break
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            break
        try:
            p.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            continue


def run_up(opts: FlightSettings, timeout: float) -> UpRun:
    """Run ``zenswarm up`` (:func:`up_argv`, ``opts`` on its standard input) to its end or for at
    most ``timeout`` wall seconds, in its own process group; whatever happens, nothing of
    ``opts.swarm`` is left running."""
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    with tempfile.TemporaryFile() as settings:  # a file of its own, already gone from the disk
        settings.write(encode(opts))
        settings.seek(0)
        p = subprocess.Popen(
            up_argv(opts), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=settings, text=True,
            start_new_session=True, env=env,
        )
    with _LIVE_LOCK:
        _LIVE[p.pid] = p
    timed_out = False
    try:
        try:
            log, _ = p.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            timed_out = True
            stop_flight(p)
            log, _ = p.communicate()
    finally:
        if p.poll() is None:  # an exception here (KeyboardInterrupt): nothing may outlive us
            stop_flight(p)
        with _LIVE_LOCK:
            _LIVE.pop(p.pid, None)
        leftovers = tuple(_reap(opts.swarm))
    return UpRun(int(p.returncode), log, timed_out, leftovers)


def _reap(swarm: str, settle_s: float = 2.0) -> list[str]:
    """Processes of ``swarm`` still alive a moment after its supervisor ended (they die with it),
    killed; their command lines."""
    deadline = time.monotonic() + settle_s
    while processes_of(swarm) and time.monotonic() < deadline:
        time.sleep(0.05)
    return kill_processes_of(swarm)

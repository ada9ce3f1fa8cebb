"""The worker's side of ``zenswarm up --scheduler`` without a cluster: :class:`RoleHost` as a plain
object in this process, starting real (tiny) processes: output, exit status, signals, the
watchdog that ends the roles when the supervisor stops calling, the credentials' directory, and
the sweep of those a killed worker left (tests/test_cluster_swarm.py runs it as a Dask actor)."""

from __future__ import annotations

import os
import signal
import stat
import sys
import time
from pathlib import Path

import pytest

from zenswarm.compose.cluster import RoleHost, local_address, sweep_stale_keys


def _until(host: RoleHost, pid: int, timeout: float = 20.0) -> tuple[int, list[str]]:
    """Poll ``host`` until ``pid`` ended: (exit status, every line it wrote)."""
    lines: list[str] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = host.poll().get(pid)
        if got is not None:
            lines += got[1]
            if got[0] is not None:
                return got[0], lines
        time.sleep(0.05)
    raise AssertionError(f"{pid} did not end; lines so far {lines}")


def test_a_role_runs_with_its_stdin_env_and_credentials_and_its_output_comes_back(tmp_path: Path) -> None:
    host = RoleHost("unit1")
    try:
        code = ("import os, sys; print(sys.stdin.read()); print(os.environ['ZS_TEST']); "
                "d = os.environ['ZS_KEYS']; print(sorted(os.listdir(d))); sys.exit(7)")  # fmt: skip
        keys = host.keys_root / "agent-2"
        pid = host.start("agent:2", ["-c", code], b"settings bytes", {"ZS_TEST": "yes", "ZS_KEYS": str(keys)},
                         {"credentials.json": b"{}", "key.pem": b"k"})  # fmt: skip
        rc, lines = _until(host, pid)
        assert rc == 7 and lines == ["settings bytes", "yes", "['credentials.json', 'key.pem']"], lines
        assert not keys.exists()  # removed once the role ended
        assert stat.S_IMODE(host.keys_root.stat().st_mode) == 0o700
        assert host.poll() == {}  # an ended role is reported once
    finally:
        host.close()
    assert not host.keys_root.exists()


def test_signals_reach_the_role_and_close_ends_every_role() -> None:
    host = RoleHost("unit2")
    try:
        sleeper = ["-c", "import time; print('up', flush=True); time.sleep(60)"]
        a = host.start("agent:1", sleeper, b"", {}, {})
        b = host.start("agent:2", sleeper, b"", {}, {})
        host.signal(a, signal.SIGKILL)
        assert _until(host, a)[0] == -signal.SIGKILL
        host.signal(a, signal.SIGTERM)  # ended: nothing happens
    finally:
        host.close()
    with pytest.raises(ProcessLookupError):
        os.kill(b, 0)
    with pytest.raises(RuntimeError, match="closed"):
        host.start("agent:3", sleeper, b"", {}, {})


def test_the_watchdog_ends_the_roles_when_the_supervisor_stops_calling() -> None:
    host = RoleHost("unit3", heartbeat_lost_s=1.0)
    pid = host.start("agent:1", ["-c", "import time; time.sleep(60)"], b"", {}, {})
    t0 = time.monotonic()
    while time.monotonic() - t0 < 15:
        try:
            if os.waitpid(pid, os.WNOHANG) != (0, 0):  # ended (a zombie until reaped: here, or by the watchdog's wait)
                break
        except ChildProcessError:  # reaped by the watchdog
            break
        time.sleep(0.1)
    took = time.monotonic() - t0
    assert 0.8 < took < 8, took
    # the watchdog's close() deletes the credentials once it has reaped its roles: a moment after
    # the role ended, which is what the loop above saw
    t1 = time.monotonic()
    while host.keys_root.exists() and time.monotonic() - t1 < 10:
        time.sleep(0.05)
    assert host.closed.is_set() and not host.keys_root.exists()


def test_the_credentials_of_a_killed_worker_are_swept(tmp_path: Path) -> None:
    import subprocess

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True, check=True)
    gone = tmp_path / f"zenswarm-sw1-w{int(dead.stdout)}-abc123"
    alive = tmp_path / f"zenswarm-sw1-w{os.getpid()}-def456"
    other = tmp_path / "zenswarm-not-ours"
    for d in (gone, alive, other):
        (d / "agent-1").mkdir(parents=True)
    assert sweep_stale_keys(tmp_path) == [gone]
    assert not gone.exists() and alive.exists() and other.exists()


def test_local_address() -> None:
    assert local_address("127.0.0.1") and local_address("127.3.0.1")
    assert not local_address("192.0.2.1")  # TEST-NET-1: never an address of this machine

"""Helpers for tests that run real swarm processes: unique names, short scenarios, process checks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tomllib
import uuid
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "compose" / "scenarios"


def unique_swarm(prefix: str = "t") -> str:
    return f"{prefix}{uuid.uuid4().hex[:10]}"


def scenario_variant(tmp: Path, base: str = "paper_example1", **timing: Any) -> Path:
    """Write a copy of a paper scenario with [timing] fields overridden; returns its path."""
    from zenswarm.scenario.generate import to_toml

    d = tomllib.loads((SCENARIOS / f"{base}.toml").read_text())
    d["timing"].update(timing)
    p = tmp / f"{base}_{'_'.join(f'{k}{v}' for k, v in timing.items()) or 'copy'}.toml"
    p.write_text(to_toml(d))
    return p


def processes_mentioning(text: str) -> list[tuple[int, str]]:
    """(pid, cmdline) of live processes whose command line contains ``text`` (not zombies)."""
    from zenswarm.compose.launch import processes_mentioning as found

    return found(text)


def kill_mentioning(text: str) -> None:
    for pid, _ in processes_mentioning(text):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def zenswarm(*args: str, timeout: float = 300.0, **kw: Any) -> subprocess.CompletedProcess:
    """Run ``python -m zenswarm ARGS`` to completion and return it (stdout+stderr as text)."""
    return subprocess.run(
        [sys.executable, "-m", "zenswarm", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=timeout,
        cwd=kw.pop("cwd", ROOT),
        **kw,
    )


def start_zenswarm(*args: str, **kw: Any) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "zenswarm", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        cwd=kw.pop("cwd", ROOT),
        **kw,
    )


def stop_swarm(procs: list, swarm: str, port: int | None = None) -> None:
    """End a test's swarm: kill the given processes (``subprocess.Popen`` or None) if still
    running and every process of ``swarm``; fail if any was left behind or the router port
    stays bound."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.kill()
            p.wait()
    leftovers = processes_mentioning(f"--swarm {swarm}")
    kill_mentioning(f"--swarm {swarm}")
    assert not leftovers, f"processes left behind: {leftovers}"
    if port is not None:
        assert wait_port_free(port), f"router port {port} still bound"


def read_results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


def udp_ports_free(base: int, n: int) -> bool:
    """True when the n UDP ports from ``base`` on 127.0.0.1 can all be bound (nothing holds them)."""
    import socket

    socks = []
    try:
        for k in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            socks.append(s)
            s.bind(("127.0.0.1", base + k))
        return True
    except OSError:
        return False
    finally:
        for s in socks:
            s.close()


def wait_port_free(port: int, timeout: float = 10.0) -> bool:
    """True once nothing listens on 127.0.0.1:port (connections in TIME_WAIT do not count)."""
    from zenswarm.pytest_plugin import port_free

    return port_free(port, timeout)

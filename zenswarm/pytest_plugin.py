"""The pytest plugin of zenswarm: fixtures for users' own flight tests (docs/testing.md).

Installed with zenswarm (entry point ``pytest11``: ``zenswarm``), so any test module may use:

``zenswarm_fly``
    A factory: ``zenswarm_fly(scenario, **kwargs) -> Flight``, :func:`zenswarm.api.fly` with a
    unique swarm name, a free router port and an output directory under the test's ``tmp_path``
    filled in for swarm flights. At teardown it stops any flight still running (its process
    group), then checks that no process of any of the test's swarms is left and that their
    router ports are free: a leftover is killed and fails the test.
``zenswarm_port``
    A TCP port on 127.0.0.1 that was free a moment ago (for a router of your own).
``zenswarm_swarm``
    A unique swarm name (key prefix ``swarm/<name>``); at teardown, any process still running
    with ``--swarm <name>`` is killed and fails the test.

Swarm flights start processes: mark such tests (the project marks them ``swarm``) and keep them
short (``duration=``).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from zenswarm import api
from zenswarm.bus import free_port

__all__ = ["zenswarm_fly", "zenswarm_port", "zenswarm_swarm", "FlyFactory", "port_free"]

PORT_FREE_TIMEOUT_S = 10.0
"""Wall seconds a finished swarm's router port may take to be free again."""


def port_free(port: int, timeout: float = PORT_FREE_TIMEOUT_S) -> bool:
    """True once nothing listens on 127.0.0.1:port (connections in TIME_WAIT do not count)."""
    deadline = time.monotonic() + timeout
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("127.0.0.1", port))
                return True
            except OSError:
                if time.monotonic() > deadline:
                    return False
        time.sleep(0.1)


def _check_swarm(swarm: str) -> list[str]:
    """Problems of a finished swarm: its processes still alive (killed here)."""
    left = api.kill_processes_of(swarm)
    return [f"swarm {swarm}: process left behind and killed: {cmd}" for cmd in left]


class FlyFactory:
    """The ``zenswarm_fly`` fixture: call it like :func:`zenswarm.api.fly`. Swarm flights get a
    unique ``swarm`` and ``out`` = ``tmp_path/flight<k>`` unless given; their router's port is the
    one given, else a free one that the flight's supervisor chooses (:attr:`zenswarm.api.Flight.port`)."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.swarms: list[tuple[str, int | None]] = []  # (swarm, router port: None until known)
        self.flights: list[api.Flight] = []

    def __call__(self, scenario: Any, **kwargs: Any) -> api.Flight:
        swarm = kwargs.get("mode", "sim") == "swarm"
        if swarm:
            kwargs.setdefault("swarm", api.unique_swarm_name("pt"))
            kwargs.setdefault("out", self.tmp_path / f"flight{len(self.swarms) + 1}")
            self.swarms.append((kwargs["swarm"], kwargs.get("port")))
        flight = api.fly(scenario, **kwargs)
        if swarm and flight.port is not None:
            self.swarms[-1] = (kwargs["swarm"], flight.port)
        self.flights.append(flight)
        return flight

    def teardown(self) -> list[str]:
        """Stop what still runs, then the problems found (empty: nothing left behind)."""
        for p in api.live_flights():  # a flight abandoned by another thread of the test
            api.stop_flight(p)
        problems: list[str] = []
        for f in self.flights:
            problems += [f"swarm {f.swarm}: process left behind after the flight and killed: {cmd}" for cmd in f.leftovers]
        for swarm, port in self.swarms:
            problems += _check_swarm(swarm)
            if port is not None and not port_free(port):
                problems.append(f"swarm {swarm}: router port {port} still bound")
        return problems


@pytest.fixture
def zenswarm_fly(tmp_path: Path) -> Iterator[Callable[..., api.Flight]]:
    """Fly scenarios (:func:`zenswarm.api.fly`); nothing is left running after the test."""
    factory = FlyFactory(tmp_path)
    yield factory
    problems = factory.teardown()
    if problems:
        pytest.fail("\n".join(problems), pytrace=False)


@pytest.fixture
def zenswarm_port() -> int:
    """A free TCP port on 127.0.0.1."""
    return free_port()


@pytest.fixture
def zenswarm_swarm() -> Iterator[str]:
    """A unique swarm name; its processes must all be gone at teardown."""
    name = api.unique_swarm_name("pt")
    yield name
    problems = _check_swarm(name)
    if problems:
        pytest.fail("\n".join(problems), pytrace=False)

"""Linux network namespaces for tests: one namespace per "host", joined to the root namespace by a
veth pair with a private /30 out of 10.213.0.0/16 that nothing on this machine uses.

:func:`namespace` (a context manager for a fixture) skips the test, with the reason printed,
only where a namespace cannot be made (no privilege, no ``ip``). Used by tests/test_netsplit.py
(an agent behind a link that is cut) and tests/test_cluster_swarm.py (Dask workers on two "hosts").
"""

from __future__ import annotations

import contextlib
import ipaddress
import random
import re
import shutil
import subprocess
import uuid
from collections.abc import Iterator

import pytest

__all__ = ["Netns", "namespace"]


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def _used_networks() -> list[ipaddress.IPv4Network]:
    out = _ip("-4", "-o", "addr", "show", check=False).stdout + _ip("-4", "route", "show", "table", "all", check=False).stdout
    nets = []
    for m in re.finditer(r"\b(\d+\.\d+\.\d+\.\d+)(/\d+)?", out):
        try:
            nets.append(ipaddress.ip_network(m.group(1) + (m.group(2) or "/32"), strict=False))
        except ValueError:
            pass
    return nets


class Netns:
    """One network namespace with a veth pair to the root namespace and a private /30 out of
    10.213.0.0/16 that nothing on this machine uses. Everything is removed by :meth:`remove`."""

    def __init__(self, default_route: bool = False) -> None:
        self.default_route = default_route  # route everything through the root namespace (reach other namespaces' veths)
        tag = uuid.uuid4().hex[:8]
        self.name = f"zsnet{tag}"
        self.root_if, self.ns_if = f"zr{tag}", f"zn{tag}"
        self.created = False
        self.root_ip = self.ns_ip = ""

    def create(self) -> None:
        r = _ip("netns", "add", self.name, check=False)
        if r.returncode != 0:
            err = r.stderr.strip()
            if any(s in err.lower() for s in ("permission", "operation not permitted", "not supported")):
                pytest.skip(f"cannot create a network namespace here: {err}")
            raise RuntimeError(f"ip netns add {self.name}: {err}")
        self.created = True
        used = _used_networks()
        rng = random.Random()
        for _ in range(200):
            net = ipaddress.ip_network(f"10.213.{rng.randrange(256)}.{4 * rng.randrange(64)}/30")
            if not any(net.overlaps(u) for u in used):
                break
        else:
            raise RuntimeError("no free /30 in 10.213.0.0/16")
        hosts = list(net.hosts())
        self.root_ip, self.ns_ip = str(hosts[0]), str(hosts[1])
        _ip("link", "add", self.root_if, "type", "veth", "peer", "name", self.ns_if, "netns", self.name)
        _ip("addr", "add", f"{self.root_ip}/30", "dev", self.root_if)
        _ip("link", "set", self.root_if, "up")
        _ip("-n", self.name, "addr", "add", f"{self.ns_ip}/30", "dev", self.ns_if)
        _ip("-n", self.name, "link", "set", self.ns_if, "up")
        _ip("-n", self.name, "link", "set", "lo", "up")
        if self.default_route:
            _ip("-n", self.name, "route", "add", "default", "via", self.root_ip)

    def link(self, up: bool) -> None:
        _ip("link", "set", self.root_if, "up" if up else "down")

    def remove(self) -> None:
        _ip("link", "del", self.root_if, check=False)  # removes both ends
        if self.created:
            _ip("netns", "del", self.name, check=False)

    def exists(self) -> bool:
        names = _ip("netns", "list", check=False).stdout.split()
        return self.name in names or _ip("link", "show", self.root_if, check=False).returncode == 0


@contextlib.contextmanager
def namespace(default_route: bool = False) -> Iterator[Netns]:
    """A :class:`Netns`, created (or the test skipped, saying why) and removed afterwards; fails
    the test if anything of it is left behind."""
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) on this machine")
    ns = Netns(default_route)
    try:
        ns.create()
        yield ns
    finally:
        ns.remove()
        assert not ns.exists(), f"namespace {ns.name} or its veth left behind"

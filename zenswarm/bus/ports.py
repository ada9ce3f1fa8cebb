"""Ports and endpoints: free TCP and UDP ports on a host, zenoh locators, and the check of the
endpoints given on the command line (before anything starts)."""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence
from typing import Final

import zenoh

from zenswarm.bus.errors import BusError
from zenswarm.errors import ScenarioError

__all__ = ["free_port", "udp_ports_in_use", "free_udp_block", "tcp_endpoint", "check_endpoint_syntax"]


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free on ``host`` a moment ago (bind to port 0, read it, close)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def udp_ports_in_use(ports: Sequence[int], host: str = "127.0.0.1") -> list[int]:
    """Those of ``ports`` that cannot be bound on ``host`` for UDP now (in use, or outside
    1..65535), in the given order. Each is bound once and closed."""
    busy = []
    for p in ports:
        if not 0 < int(p) <= 65535:
            busy.append(int(p))
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind((host, int(p)))
            except OSError:
                busy.append(int(p))
    return busy


def free_udp_block(n: int, host: str = "127.0.0.1", also: Sequence[int] = ()) -> int:
    """A UDP port p on ``host`` with p .. p+n-1 free a moment ago (all bound once, then closed),
    and p+d .. p+d+n-1 too for each offset d in ``also`` (e.g. 40: the simulated vehicles' send
    ports with PX4 SITL's direction)."""
    top = max([0, *also]) + n
    offsets = sorted({d + k for d in (0, *also) for k in range(n)})  # the blocks may overlap (n > d)
    for _ in range(200):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s0:
            s0.bind((host, 0))
            base = int(s0.getsockname()[1])
        if base + top >= 65535:
            continue
        socks = []
        try:
            for off in offsets:
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(s)
                s.bind((host, base + off))
            return base
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise BusError(f"no block of {n} free UDP ports on {host}")


def tcp_endpoint(port: int, host: str = "127.0.0.1") -> str:
    """Zenoh locator ``tcp/<host>:<port>``."""
    return f"tcp/{host}:{port}"


_IP_PROTOCOLS: Final = ("tcp", "udp", "tls", "quic", "ws")
_OTHER_PROTOCOLS: Final = ("unixsock-stream", "unixpipe", "vsock", "serial")


def check_endpoint_syntax(endpoints: Sequence[str], flag: str, *, listen: bool = False) -> list[str]:
    """Check zenoh endpoints given on the command line before anything starts; returns them.

    Each must be ``<protocol>/<address>[?<metadata>][#<config>]`` with a protocol zenoh knows;
    for ``tcp``, ``udp``, ``tls``, ``quic`` and ``ws`` the address is ``<host>:<port>`` with a
    port in 1..65535 (0, any free port, only where ``listen``). zenoh itself parses only the
    outline and would fail later, in each process. Raises :class:`ScenarioError` naming
    ``flag`` and the endpoint. (Whether the host resolves and answers is not checked here.)
    """
    out = []
    for e in endpoints:
        ep = str(e)
        proto, sep, rest = ep.partition("/")
        addr = rest.split("#", 1)[0].split("?", 1)[0]
        example = "e.g. tcp/127.0.0.1:7447"
        if not sep or not addr:
            raise ScenarioError(flag, f"{ep!r} is not a zenoh endpoint: expected <protocol>/<address>, {example}")
        if proto not in _IP_PROTOCOLS + _OTHER_PROTOCOLS:
            raise ScenarioError(flag, f"{ep!r}: unknown protocol {proto!r} (expected one of {', '.join(_IP_PROTOCOLS)}, ...), {example}")
        if proto in _IP_PROTOCOLS:
            host, colon, port = addr.rpartition(":")
            lo = 0 if listen else 1
            if not colon or not host.strip("[]") or not port.isdigit() or not lo <= int(port) <= 65535:
                raise ScenarioError(flag, f"{ep!r}: expected {proto}/<host>:<port> with a port in {lo}..65535, {example}")
        try:
            zenoh.Config().insert_json5("connect/endpoints", json.dumps([ep]))
        except (zenoh.ZError, TypeError, ValueError) as x:  # zenoh's errors; json.dumps' too
            raise ScenarioError(flag, f"{ep!r} is not a zenoh endpoint: {str(x).split(' at ', 1)[0]}") from None
        out.append(ep)
    return out

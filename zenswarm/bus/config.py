"""zenoh configuration: a swarm router's and a swarm client's, and the hook for any other setting.

Topology: one router per swarm (``mode: router``, possibly inside a Python process, see
``python -m zenswarm.compose.router``) and every swarm process a client of it. Multicast scouting and
gossip are off everywhere, so a session only ever talks to the endpoints it was given: two
swarms on different router ports never see each other, even with the same swarm name.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any, Final

import zenoh

from zenswarm.bus.errors import BusError
from zenswarm.bus.ports import check_endpoint_syntax

__all__ = ["DEFAULT_CONNECT_TIMEOUT_S", "TX_QUEUE_BATCHES", "apply_settings", "router_config", "client_config"]

DEFAULT_CONNECT_TIMEOUT_S: Final = 5.0
"""How long a client keeps trying to reach its router before ``zenoh.open`` fails, s."""


TX_QUEUE_BATCHES: Final = 16
"""Batches (64 kB each) in a client session's sending queue for data, zenoh's maximum (its
default is 2). zenoh allocates them only when they are needed.

A lockstep tick runs on zenoh's only thread (:func:`~zenswarm.bus.callbacks.direct_callback`,
:data:`~zenswarm.bus.runtime.ZENOH_RUNTIME_DEFAULT`) and puts there; zenoh's sending task runs on
that same thread, once the reading task finds the socket empty. A process that has fallen behind a
flood of input (a replay at ``--rate 0`` into a live agent on a loaded machine) can tick hundreds
of times before that happens, and each tick queues its messages. With 2 batches an agent's queue
was full at tick 354 of such a backlog: the put then waited for a sending task that could not run,
until zenoh closed the link 5 s later (``block/wait_before_close``) and the rest was lost (seen in
CI, ``tests/test_replay.py``). With 16 batches it holds about 2,800 ticks of an agent's output (a
ref and a cmd, ~185 bytes each on the wire). Lockstep speed unchanged (BENCHMARKS.md, "The
sending queue of a client")."""


def apply_settings(conf: zenoh.Config, settings: Mapping[str, Any]) -> zenoh.Config:
    """Insert ``{"path/in/config": json_value}`` into ``conf`` and return it.

    The one hook for everything beyond the basics, e.g. user/password auth
    (``transport/auth/usrpwd/user``, ``.../password``), TLS (``transport/link/tls/...`` with
    ``tls/`` endpoints), ``access_control``, or tuning (``transport/unicast/lowlatency``).
    """
    for path, value in settings.items():
        try:
            conf.insert_json5(path, json.dumps(value))
        except (zenoh.ZError, TypeError, ValueError) as e:  # zenoh's errors; json.dumps' (not JSON)
            raise BusError(f"config {path!r} = {value!r}: {e}") from None
    return conf


def _base_config(mode: str) -> zenoh.Config:
    conf = zenoh.Config()
    return apply_settings(
        conf,
        {
            "mode": mode,
            # Talk only to the endpoints we are given: no multicast discovery, no gossip.
            "scouting/multicast/enabled": False,
            "scouting/gossip/enabled": False,
        },
    )


def router_config(
    listen: Sequence[str],
    *,
    connect: Sequence[str] = (),
    settings: Mapping[str, Any] | None = None,
) -> zenoh.Config:
    """Config of a swarm router listening on ``listen`` (e.g. ``["tcp/127.0.0.1:7447"]``).

    connect: other routers to link to (none by default); settings: see :func:`apply_settings`.
    """
    if not listen:
        raise BusError("a router needs at least one listen endpoint")
    conf = _base_config("router")
    apply_settings(conf, {"listen/endpoints": list(listen), "connect/endpoints": list(connect)})
    return apply_settings(conf, settings or {})


def client_config(
    connect: Sequence[str],
    *,
    connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
    settings: Mapping[str, Any] | None = None,
) -> zenoh.Config:
    """Config of a swarm process: a client of the router(s) at ``connect``, with a sending queue
    of :data:`TX_QUEUE_BATCHES` batches.

    ``zenoh.open`` keeps retrying for ``connect_timeout_s`` seconds (so a process may start
    before its router), then fails; 0 fails at once. settings: see :func:`apply_settings`.
    """
    if not connect:
        raise BusError("a client needs at least one connect endpoint")
    check_endpoint_syntax(connect, "--connect")  # what every command calls them: exit 2 naming the endpoint
    conf = _base_config("client")
    apply_settings(
        conf,
        {
            "connect/endpoints": list(connect),
            "connect/timeout_ms": max(0, round(connect_timeout_s * 1000)),
            "listen/endpoints": [],
            "transport/link/tx/queue/size/data": TX_QUEUE_BATCHES,
        },
    )
    return apply_settings(conf, settings or {})

"""The swarm bus: where messages cross the network (Zenoh, eclipse-zenoh 1.10.x), one idea a module.

What travels, and on which keys (pure: no zenoh):

* :mod:`~zenswarm.bus.keys`: the key space of one swarm (:class:`~zenswarm.bus.keys.Keys`), swarm
  and process names.
* :mod:`~zenswarm.bus.fields`: the field types of the messages, their checks and bounds.
* :mod:`~zenswarm.bus.wire`: the messages and their msgpack codec (re-exports ``keys`` and
  ``fields``).
* :mod:`~zenswarm.bus.mocap`: the external positioning feed's message.

How it travels (zenoh), every public name re-exported here (``bus.open_session``, ...):

* :mod:`~zenswarm.bus.runtime`: zenoh's thread layout, :data:`ZENOH_RUNTIME_DEFAULT` for the
  swarm's processes (:func:`use_swarm_runtime`, before the first session) and
  :data:`ZENOH_RUNTIME_ROUTER` for the router; :func:`zenoh_threads`.
* :mod:`~zenswarm.bus.errors`: :class:`BusError` and :class:`Shutdown`.
* :mod:`~zenswarm.bus.ports`: free ports (:func:`free_port`, :func:`free_udp_block`,
  :func:`udp_ports_in_use`) and endpoints (:func:`tcp_endpoint`, :func:`check_endpoint_syntax`).
* :mod:`~zenswarm.bus.config`: a router's and a client's configuration (:func:`router_config`,
  :func:`client_config`, :func:`apply_settings`; scouting and gossip off, so a session only talks
  to the endpoints it was given).
* :mod:`~zenswarm.bus.session`: sessions that always close (:func:`open_session`,
  :func:`close_at_exit`; how a process exits cleanly), :func:`undeclare`.
* :mod:`~zenswarm.bus.callbacks`: subscriber callbacks on zenoh's own thread
  (:func:`direct_callback`).
* :mod:`~zenswarm.bus.liveliness`: who is there (:func:`declare_alive`, :class:`AliveWatcher`,
  :func:`wait_matching`).
* :mod:`~zenswarm.bus.router`: a router as a process of its own (:func:`serve_router`).
"""

from __future__ import annotations

from zenswarm.bus.callbacks import _PINNED as _PINNED  # the pinned threads (tests/test_bus.py reads it)
from zenswarm.bus.callbacks import direct_callback
from zenswarm.bus.config import DEFAULT_CONNECT_TIMEOUT_S, TX_QUEUE_BATCHES, apply_settings, client_config, router_config
from zenswarm.bus.errors import BusError, Shutdown
from zenswarm.bus.liveliness import AliveWatcher, declare_alive, wait_matching
from zenswarm.bus.ports import check_endpoint_syntax, free_port, free_udp_block, tcp_endpoint, udp_ports_in_use
from zenswarm.bus.router import serve_router
from zenswarm.bus.runtime import ZENOH_RUNTIME_DEFAULT, ZENOH_RUNTIME_ROUTER, use_swarm_runtime, zenoh_threads
from zenswarm.bus.session import Undeclarable, close_at_exit, open_session, undeclare

__all__ = [
    "DEFAULT_CONNECT_TIMEOUT_S",
    "TX_QUEUE_BATCHES",
    "ZENOH_RUNTIME_DEFAULT",
    "use_swarm_runtime",
    "zenoh_threads",
    "ZENOH_RUNTIME_ROUTER",
    "BusError",
    "Shutdown",
    "free_port",
    "udp_ports_in_use",
    "free_udp_block",
    "tcp_endpoint",
    "check_endpoint_syntax",
    "apply_settings",
    "router_config",
    "client_config",
    "close_at_exit",
    "Undeclarable",
    "undeclare",
    "direct_callback",
    "open_session",
    "declare_alive",
    "AliveWatcher",
    "wait_matching",
    "serve_router",
]

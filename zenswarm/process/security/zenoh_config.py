"""Zenoh configuration for a secured swarm: the router's and each client's fragments, and their endpoints.

A fragment set is ``{zenoh config path: value}`` (:func:`router_security_config`,
:func:`client_security_config`, :func:`client_fragments`), inserted into a ``zenoh.Config`` by
:func:`apply_config`. ``usrpwd``: the router checks a user/password dictionary
(``transport/auth/usrpwd``) on ``tcp/`` or ``tls/`` links; ``tls``: mutual TLS
(``transport/link/tls``) with the swarm's CA, only on ``tls/<host>:<port>`` endpoints
(:func:`tls_endpoint`, :func:`check_endpoints`). The router's also carries the access control of
:mod:`zenswarm.process.security.acl`. Plain Zenoh 1.x configuration, checked against
eclipse-zenoh 1.10.2.
"""

from __future__ import annotations

import ipaddress
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from zenswarm.process.security.acl import acl_rules
from zenswarm.process.security.credentials import load_credentials, process_dir
from zenswarm.process.security.manifest import ROUTER_PROCESS, AuthMode, CredentialsError, Manifest, load_manifest
from zenswarm.scenario.config import Scenario

__all__ = [
    "router_security_config",
    "client_security_config",
    "apply_config",
    "check_endpoints",
    "is_loopback_endpoint",
    "tls_endpoint",
    "ClientSecurity",
    "client_fragments",
]


def _manifest_of(keys: Manifest | str | Path) -> Manifest:
    return keys if isinstance(keys, Manifest) else load_manifest(keys)


def router_security_config(
    keys: Manifest | str | Path,
    scenario: Scenario | str | Path,
    swarm: str | None = None,
    *,
    auth: AuthMode = "usrpwd",
) -> dict[str, Any]:
    """Configuration fragments ``{zenoh config path: value}`` for the swarm's router.

    ``keys`` is the :class:`Manifest` or the directory :func:`generate_credentials` wrote (the
    router host needs ``router/usrpwd.txt``, ``supervisor/`` and ``manifest.json``). ``swarm``
    defaults to the manifest's. ``auth="usrpwd"``: the router requires a user/password from the
    dictionary; ``auth="tls"``: mutual TLS with the swarm's CA, the supervisor's certificate as
    the router's, and only ``tls`` links (listen endpoints must be ``tls/<host>:<port>``, see
    :func:`tls_endpoint`). Both add :func:`acl_rules`. Insert with :func:`apply_config`.
    """
    m = _manifest_of(keys)
    swarm = m.swarm if swarm is None else swarm
    if swarm != m.swarm:
        raise CredentialsError(f"credentials in {m.root} are for swarm {m.swarm!r}, not {swarm!r}")
    frag: dict[str, Any] = {}
    if auth == "usrpwd":
        _need(m.usrpwd_file)
        frag["transport/auth/usrpwd/dictionary_file"] = str(m.usrpwd_file)
    elif auth == "tls":
        r = m.process(ROUTER_PROCESS)
        for f in (r.ca_cert, r.cert, r.key):
            _need(f)
        frag.update(
            {
                "transport/link/protocols": ["tls"],
                "transport/link/tls/root_ca_certificate": str(r.ca_cert),
                "transport/link/tls/listen_certificate": str(r.cert),
                "transport/link/tls/listen_private_key": str(r.key),
                "transport/link/tls/enable_mtls": True,
                # A router that also dials other routers presents the same identity.
                "transport/link/tls/connect_certificate": str(r.cert),
                "transport/link/tls/connect_private_key": str(r.key),
            }
        )
    else:
        raise CredentialsError(f"auth: expected 'usrpwd' or 'tls', got {auth!r}")
    frag["access_control"] = acl_rules(scenario, swarm, auth=auth)
    return frag


def client_security_config(
    process: str,
    keys_dir: str | Path,
    *,
    auth: AuthMode = "usrpwd",
    swarm: str | None = None,
) -> dict[str, Any]:
    """Configuration fragments ``{zenoh config path: value}`` for ``process``'s client session.

    ``keys_dir`` is the tree :func:`generate_credentials` wrote or just that process's directory
    (see :func:`process_dir`). ``auth="usrpwd"``: user and password; ``auth="tls"``: the
    process's certificate and key for mutual TLS, the swarm's CA to check the router, and only
    ``tls`` links (connect endpoints must be ``tls/<host>:<port>``; the host must be one of the
    router certificate's names). ``swarm``, if given, must match the credentials'.
    """
    d = process_dir(process, keys_dir)
    creds = load_credentials(process, keys_dir, swarm)
    if auth == "usrpwd":
        return {
            "transport/auth/usrpwd/user": creds["user"],
            "transport/auth/usrpwd/password": creds["password"],
        }
    if auth == "tls":
        ca, cert, key = d / "ca.pem", d / "cert.pem", d / "key.pem"
        for f in (ca, cert, key):
            _need(f)
        return {
            "transport/link/protocols": ["tls"],
            "transport/link/tls/root_ca_certificate": str(ca),
            "transport/link/tls/connect_certificate": str(cert),
            "transport/link/tls/connect_private_key": str(key),
            "transport/link/tls/enable_mtls": True,
        }
    raise CredentialsError(f"auth: expected 'usrpwd' or 'tls', got {auth!r}")


def _need(path: Path) -> None:
    if not Path(path).is_file():
        raise CredentialsError(f"missing credentials file {path}")


def apply_config(config: Any, fragments: Mapping[str, Any]) -> Any:
    """Insert ``fragments`` (from :func:`router_security_config` / :func:`client_security_config`)
    into a ``zenoh.Config`` with ``insert_json5``; returns the config."""
    for path, value in fragments.items():
        config.insert_json5(path, json.dumps(value))
    return config


def check_endpoints(endpoints: Iterable[str], auth: AuthMode) -> list[str]:
    """Return ``endpoints`` if they suit ``auth`` (``tls`` needs ``tls/...`` endpoints, ``usrpwd``
    ``tcp/...`` or ``tls/...``); else raise CredentialsError naming the endpoint. Zenoh itself
    would only say "Unable to connect"."""
    eps = [str(e) for e in endpoints]
    for e in eps:
        proto = e.partition("/")[0]
        if auth == "tls" and proto != "tls":
            raise CredentialsError(f"endpoint {e!r}: mutual TLS needs a tls/<host>:<port> endpoint")
        if auth == "usrpwd" and proto not in ("tcp", "tls"):
            raise CredentialsError(f"endpoint {e!r}: expected tcp/<host>:<port> (or tls/...)")
    return eps


def is_loopback_endpoint(endpoint: str) -> bool:
    """True for ``tcp/127.0.0.1:7447``, ``tls/localhost:7447``, ``tcp/[::1]:7447``; False for any
    other host, including ``0.0.0.0`` and ``[::]`` (every interface). For "secure by default
    unless the router listens on loopback only"."""
    rest = str(endpoint).partition("/")[2].split("#", 1)[0].split("?", 1)[0]
    host = rest.rsplit(":", 1)[0].strip("[]") if ":" in rest else rest
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class ClientSecurity:
    """How a swarm process joins its router: ``keys`` the credentials written by
    ``zenswarm keys`` (the whole tree or this process's directory; None: an open swarm), ``tls``
    mutual TLS instead of user/password (``--keys DIR``, ``--tls``; parsed at the edges by
    :mod:`zenswarm.bridge.args`)."""

    keys: Path | None = None
    tls: bool = False


def client_fragments(
    process: str, sec: ClientSecurity, *, connect: Iterable[str] = (), swarm: str | None = None
) -> dict[str, Any]:
    """Config fragments for ``process`` joining with ``sec`` through the router endpoints
    ``connect`` (checked against the auth mode) as a process of ``swarm``; ``{}`` without keys
    (an open swarm). :class:`CredentialsError` naming the flag (``--tls``) otherwise."""
    if sec.keys is None:
        if sec.tls:
            raise CredentialsError("--tls needs --keys DIR")
        return {}
    auth: AuthMode = "tls" if sec.tls else "usrpwd"
    endpoints = list(connect)
    if endpoints:
        check_endpoints(endpoints, auth)
    return client_security_config(process, sec.keys, auth=auth, swarm=swarm)


def tls_endpoint(endpoint: str) -> str:
    """``tcp/127.0.0.1:7447`` -> ``tls/127.0.0.1:7447`` (a ``tls/`` endpoint is returned as is)."""
    proto, sep, rest = str(endpoint).partition("/")
    if not sep or proto not in ("tcp", "tls"):
        raise CredentialsError(f"endpoint {endpoint!r}: expected tcp/<host>:<port> or tls/<host>:<port>")
    return f"tls/{rest}"

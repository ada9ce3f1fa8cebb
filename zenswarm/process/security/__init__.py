"""Credentials and access control for an authenticated swarm (``zenswarm keys``, ``up --secure``).

Three pieces, all plain Zenoh 1.x configuration (checked against eclipse-zenoh 1.10.2):

* **who may connect** - either user/password (``transport/auth/usrpwd``: the router holds a
  ``user:password`` dictionary file, each process its own user and password), or mutual TLS
  (``transport/link/tls``: one CA per swarm, the router's certificate for ``127.0.0.1`` /
  ``localhost`` and any extra router host names, one client certificate per process whose common
  name is the process name; ``tls/<host>:<port>`` endpoints only);
* **what each process may do** - ``access_control`` generated from the scenario's graph
  (:func:`acl_rules`): default deny, one subject per process (by user name or by certificate
  common name) and only the key expressions of its role;
* **files** - :func:`generate_credentials` writes everything under one directory, one
  sub-directory per process so that each host gets only what its processes need.

Zenoh user names may not contain ``:`` (the dictionary file splits at the first ``:``), so a
process's user name is ``<p>@<swarm>``, e.g. ``agent-2@demo``.

Use :func:`router_security_config` / :func:`client_security_config` to get the configuration
fragments ({config path: value}) and :func:`apply_config` to insert them into a ``zenoh.Config``.

One concept a module, each importing only those before it:

- :mod:`~zenswarm.process.security.manifest`: the swarm's process names and users, and the
  manifest of a key directory (``OUT/manifest.json``);
- :mod:`~zenswarm.process.security.certificates`: the swarm's CA and its processes' certificates;
- :mod:`~zenswarm.process.security.credentials`: the credential files, generated and written
  (the layout of ``OUT``), and read back by each process;
- :mod:`~zenswarm.process.security.acl`: the router's access control from the scenario's graph;
- :mod:`~zenswarm.process.security.zenoh_config`: the router's and the clients' Zenoh
  configuration fragments, and the endpoints each auth mode accepts.

This package holds every name its modules export (``security.X`` for each of them).
"""

from __future__ import annotations

from zenswarm.process.security.acl import acl_rules
from zenswarm.process.security.credentials import DEFAULT_DAYS as DEFAULT_DAYS
from zenswarm.process.security.credentials import DEFAULT_ROUTER_HOSTS as DEFAULT_ROUTER_HOSTS
from zenswarm.process.security.credentials import generate_credentials, load_credentials, process_dir
from zenswarm.process.security.manifest import (
    MANIFEST_FILE,
    MOCAP_FEEDER,
    ROLES,
    AuthMode,
    CredentialsError,
    Manifest,
    ProcessCredentials,
    feeder_names,
    load_manifest,
    manifest_mismatch,
    process_names,
    process_slug,
    username,
)
from zenswarm.process.security.manifest import MANIFEST_VERSION as MANIFEST_VERSION
from zenswarm.process.security.manifest import ROUTER_PROCESS as ROUTER_PROCESS
from zenswarm.process.security.zenoh_config import (
    ClientSecurity,
    apply_config,
    check_endpoints,
    client_fragments,
    client_security_config,
    is_loopback_endpoint,
    router_security_config,
    tls_endpoint,
)

__all__ = [
    "CredentialsError",
    "Manifest",
    "ProcessCredentials",
    "AuthMode",
    "ROLES",
    "MOCAP_FEEDER",
    "feeder_names",
    "MANIFEST_FILE",
    "process_names",
    "process_slug",
    "username",
    "generate_credentials",
    "load_manifest",
    "manifest_mismatch",
    "load_credentials",
    "process_dir",
    "acl_rules",
    "router_security_config",
    "client_security_config",
    "apply_config",
    "tls_endpoint",
    "check_endpoints",
    "is_loopback_endpoint",
    "ClientSecurity",
    "client_fragments",
]

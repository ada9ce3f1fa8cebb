"""A flight's security, as ``zenswarm up`` sets it up before its router opens: open, or secure
(user/password or mutual TLS, with access control generated from the scenario's graph), and the
credentials' directory the roles join with (the user's ``--keys DIR``, else generated into
``OUT/keys``). Secure is the default whenever the router listens on a non-loopback address.

:func:`router_security` decides in one order: open or secure, the endpoints
(:func:`secure_endpoints`), the credentials (:func:`user_keys` or :func:`run_keys`), then the
router's configuration (:mod:`zenswarm.process.security`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from zenswarm.errors import ScenarioError
from zenswarm.process import security
from zenswarm.process.paths import check_output_dir
from zenswarm.scenario.config import Scenario

__all__ = ["RouterSecurity", "router_security", "secure_endpoints", "user_keys", "run_keys"]


@dataclass(frozen=True)
class RouterSecurity:
    """What the router is opened with: its config ``settings`` (``{}``: an open router), the
    endpoints it listens on (``listen``; ``tls/`` ones with ``--tls``), and the credentials' directory
    the roles join with (None: an open router)."""

    settings: dict[str, Any]
    listen: list[str]
    keys_dir: Path | None


def router_security(
    sc: Scenario,
    listen: list[str],
    out: Path,
    say: Callable[[str], None],
    *,
    swarm: str,
    connect: Sequence[str],
    secure: bool,
    tls: bool,
    insecure: bool,
    keys: Path | None,
) -> RouterSecurity:
    """The router of swarm ``swarm`` (the roles join it on ``connect``): its security for
    ``secure``/``tls``/``keys`` (``--secure``, ``--tls``, ``--keys DIR``; secure by default off
    loopback, unless ``insecure``, ``--insecure``: then a warning is said). An endpoint secure
    mode cannot use, or credentials that do not fit this swarm: an error before anything starts
    (exit 2)."""
    open_net = not all(security.is_loopback_endpoint(e) for e in listen)
    asked = secure or tls or keys is not None
    if not (asked or (open_net and not insecure)):
        if open_net:
            say("WARNING: --insecure on a non-loopback address: anyone who reaches the router can command the swarm")
        return RouterSecurity({}, listen, None)
    auth: security.AuthMode = "tls" if tls else "usrpwd"
    listen = secure_endpoints(listen, connect, auth, asked=asked)
    keys_dir = user_keys(keys, sc, swarm) if keys is not None else run_keys(out / "keys", sc, swarm, say)
    say(f"secure mode: {'mutual TLS' if tls else 'user/password'} authentication, access control from the graph")
    return RouterSecurity(security.router_security_config(keys_dir, sc, swarm, auth=auth), listen, keys_dir)


def secure_endpoints(listen: list[str], connect: Sequence[str], auth: security.AuthMode, *, asked: bool) -> list[str]:
    """The router's ``listen`` endpoints in ``auth`` mode (``tls/`` ones for mutual TLS), checked
    with the roles' ``connect`` before anything starts: the processes would each die on an
    endpoint the mode cannot use. :class:`~zenswarm.process.security.CredentialsError` naming
    it, and whether secure mode was ``asked`` for or is the default off loopback."""
    if auth == "tls":
        listen = [security.tls_endpoint(e) for e in listen]
    try:
        security.check_endpoints([*listen, *connect], auth)
    except security.CredentialsError as e:
        why = "secure mode" if asked else "secure mode (the default when the router is not on loopback only)"
        raise security.CredentialsError(f"{why}: {e}") from None
    return listen


def user_keys(keys: Path, sc: Scenario, swarm: str) -> Path:
    """``--keys DIR``: the user's own credentials, checked against this swarm, never rewritten;
    :class:`ScenarioError` naming ``--keys`` if they do not fit."""
    try:
        why = security.manifest_mismatch(security.load_manifest(keys), sc, swarm)
    except security.CredentialsError as e:
        raise ScenarioError("--keys", str(e)) from None
    if why:
        raise ScenarioError(
            "--keys",
            f"the credentials in {keys} {why}; generate matching ones with "
            f"`zenswarm keys SCENARIO --swarm {swarm} --out DIR` (see docs/security.md)",
        )
    return keys


def run_keys(keys_dir: Path, sc: Scenario, swarm: str, say: Callable[[str], None]) -> Path:
    """Credentials generated for this OUT (``OUT/keys``): reused while they fit this swarm,
    else generated again (and said so)."""
    check_output_dir(keys_dir, "--out")
    manifest = keys_dir / security.MANIFEST_FILE
    why = None
    if manifest.exists():
        try:
            why = security.manifest_mismatch(security.load_manifest(keys_dir), sc, swarm, all_files=True)
        except security.CredentialsError as e:
            why = f"are unreadable ({e})"
    if why is not None or not manifest.exists():
        security.generate_credentials(sc, keys_dir, swarm, force=True)
        if why is None:
            say(f"generated credentials for this run in {keys_dir}")
        else:
            say(f"regenerated the credentials in {keys_dir}: the previous ones {why}")
    return keys_dir

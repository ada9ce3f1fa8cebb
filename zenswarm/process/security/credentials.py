"""The credential files of a swarm: generated and written (``zenswarm keys``), and read back by each process.

Per process (:func:`~zenswarm.process.security.manifest.process_names`, and the feeders): a user
name and a random password (256 bits), and an ECDSA P-256 key and certificate signed by the
swarm's new CA (:mod:`zenswarm.process.security.certificates`), valid ``days`` days.

Layout written by :func:`generate_credentials` (``<p>`` is a process name with ``:`` replaced by
``-``, e.g. ``agent-2``; keys and passwords are 0600, directories 0700)::

    OUT/manifest.json           what was written (no secrets)
    OUT/ca/ca.pem               the swarm's CA certificate
    OUT/ca/ca-key.pem           the CA's private key: keep it off the swarm's hosts
    OUT/router/usrpwd.txt       user:password dictionary, for the router only
    OUT/<p>/credentials.json    {"swarm", "process", "user", "password"}
    OUT/<p>/cert.pem  key.pem   the process's TLS certificate (CN = process name) and key
    OUT/<p>/ca.pem              copy of the CA certificate (the directory is self-contained)

A process reads its own directory (:func:`process_dir`, :func:`load_credentials`): the whole tree,
or just ``<p>/`` copied to its host.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import json
import os
import secrets
from collections.abc import Iterable
from pathlib import Path

from zenswarm.bus import wire
from zenswarm.process.security.certificates import cert_pem, key_pem, make_ca, make_leaf
from zenswarm.process.security.manifest import (
    MANIFEST_FILE,
    ROUTER_PROCESS,
    CredentialsError,
    Manifest,
    ProcessCredentials,
    as_scenario,
    feeder_names,
    load_manifest,
    process_names,
    process_slug,
    username,
)
from zenswarm.scenario.config import Scenario

__all__ = ["DEFAULT_DAYS", "DEFAULT_ROUTER_HOSTS", "generate_credentials", "process_dir", "load_credentials"]

DEFAULT_DAYS = 365
DEFAULT_ROUTER_HOSTS = ("localhost", "127.0.0.1", "::1")

_KEY_MODE = 0o600
_DIR_MODE = 0o700
_PUB_MODE = 0o644


# --------------------------------------------------------------------------- files


def _write(path: Path, data: bytes, mode: int) -> None:
    """Write ``data`` to ``path`` with permissions ``mode`` from the first byte on (no window in
    which a key is world-readable)."""
    path.parent.mkdir(mode=_DIR_MODE, parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    os.replace(tmp, path)


def _mkdir(path: Path) -> None:
    path.mkdir(mode=_DIR_MODE, parents=True, exist_ok=True)
    os.chmod(path, _DIR_MODE)



# --------------------------------------------------------------------------- generation


def _plan(root: Path, swarm: str, sc: Scenario, hosts: tuple[str, ...], not_after: str) -> Manifest:
    procs = []
    for name in process_names(sc.n) + feeder_names(sc):
        d = root / process_slug(name)
        procs.append(
            ProcessCredentials(
                process=name,
                user=username(name, swarm),
                dir=d,
                credentials=d / "credentials.json",
                cert=d / "cert.pem",
                key=d / "key.pem",
                ca_cert=d / "ca.pem",
            )
        )
    return Manifest(
        swarm=swarm,
        scenario=sc.name,
        n=sc.n,
        root=root,
        ca_cert=root / "ca" / "ca.pem",
        ca_key=root / "ca" / "ca-key.pem",
        usrpwd_file=root / "router" / "usrpwd.txt",
        router_hosts=hosts,
        not_after=not_after,
        processes=tuple(procs),
    )


def generate_credentials(
    scenario: Scenario | str | Path,
    out_dir: str | Path,
    swarm: str = "default",
    *,
    router_hosts: Iterable[str] = (),
    days: int = DEFAULT_DAYS,
    force: bool = False,
) -> Manifest:
    """Generate every credential of ``swarm`` flying ``scenario`` under ``out_dir``.

    Per process (:func:`process_names`, and :func:`feeder_names`): a user name (:func:`username`) and a random password
    (``secrets.token_urlsafe(32)``, 256 bits) in ``<p>/credentials.json`` and in the router's
    ``router/usrpwd.txt``; an ECDSA P-256 key and a certificate (CN = process name) signed by the
    swarm's new CA. The supervisor's certificate is also the router's: its subjectAltNames are
    ``localhost``, ``127.0.0.1``, ``::1`` and ``router_hosts`` (names or IP addresses of the
    router host as the other hosts will dial it). Certificates are valid ``days`` days.

    Refuses (CredentialsError) if ``out_dir`` already holds a manifest or any file to be written,
    unless ``force``; with ``force`` the files of the previous manifest are removed first.
    """
    sc = as_scenario(scenario)
    swarm = wire.validate_swarm_name(swarm)
    if not isinstance(days, int) or days < 1:
        raise CredentialsError(f"days: expected an integer >= 1, got {days!r}")
    hosts = _router_hosts(router_hosts)
    root = Path(out_dir).resolve()
    now = _dt.datetime.now(_dt.UTC).replace(microsecond=0)
    not_before = now - _dt.timedelta(hours=1)  # tolerate small clock skew between hosts
    not_after = now + _dt.timedelta(days=days)
    plan = _plan(root, swarm, sc, hosts, not_after.isoformat())
    _clear_previous(root, plan, force)
    _write_credentials(plan, swarm, hosts, not_before, not_after)
    return plan


def _router_hosts(router_hosts: Iterable[str]) -> tuple[str, ...]:
    """The router certificate's names: the defaults, then ``router_hosts`` (stripped, no
    duplicates); :class:`CredentialsError` for one that is neither a DNS name nor an IP address."""
    hosts = tuple(dict.fromkeys([*DEFAULT_ROUTER_HOSTS, *[str(h).strip() for h in router_hosts if str(h).strip()]]))
    for h in hosts:
        if any(c in h for c in " /:") and not _is_ip(h):
            raise CredentialsError(f"router host {h!r}: expected a DNS name or an IP address")
    return hosts


def _clear_previous(root: Path, plan: Manifest, force: bool) -> None:
    """Refuse to overwrite credentials under ``root`` unless ``force``; then remove them."""
    existing = [p for p in plan.files() if p.exists()]
    if (root / MANIFEST_FILE).exists() or existing:
        if not force:
            what = existing[0] if existing else root / MANIFEST_FILE
            raise CredentialsError(f"{what} already exists: refusing to overwrite credentials (use --force)")
        _remove_previous(root, existing)


def _write_credentials(
    plan: Manifest, swarm: str, hosts: tuple[str, ...], not_before: _dt.datetime, not_after: _dt.datetime
) -> None:
    """Write every file of ``plan``: the CA, then per process its password, key and certificate
    (the router's with ``hosts`` as subjectAltNames), the router's user:password file, the manifest."""
    root = plan.root
    _mkdir(root)
    for d in {plan.ca_cert.parent, plan.usrpwd_file.parent, *(p.dir for p in plan.processes)}:
        _mkdir(d)

    ca_key, ca_cert = make_ca(swarm, not_before, not_after)
    ca_pem = cert_pem(ca_cert)
    _write(plan.ca_cert, ca_pem, _PUB_MODE)
    _write(plan.ca_key, key_pem(ca_key), _KEY_MODE)

    lines = []
    for p in plan.processes:
        password = secrets.token_urlsafe(32)
        lines.append(f"{p.user}:{password}\n")
        creds = {"swarm": swarm, "process": p.process, "user": p.user, "password": password}
        _write(p.credentials, (json.dumps(creds, indent=2) + "\n").encode(), _KEY_MODE)
        key, cert = make_leaf(
            ca_key, ca_cert, p.process, hosts if p.process == ROUTER_PROCESS else None, not_before, not_after
        )
        _write(p.cert, cert_pem(cert), _PUB_MODE)
        _write(p.key, key_pem(key), _KEY_MODE)
        _write(p.ca_cert, ca_pem, _PUB_MODE)
    _write(plan.usrpwd_file, "".join(lines).encode(), _KEY_MODE)
    _write(root / MANIFEST_FILE, (json.dumps(plan.to_dict(), indent=2) + "\n").encode(), _PUB_MODE)


def _is_ip(h: str) -> bool:
    try:
        ipaddress.ip_address(h)
        return True
    except ValueError:
        return False


def _remove_previous(root: Path, existing: list[Path]) -> None:
    """--force: remove what the previous manifest lists (and the files about to be rewritten)."""
    old: list[Path] = []
    try:
        old = load_manifest(root).files()
    except CredentialsError:
        pass
    for f in [*old, *existing]:
        try:
            if f.resolve().is_relative_to(root):
                f.unlink(missing_ok=True)
        except OSError:
            pass
    for f in old:  # now-empty process directories of a larger previous swarm
        try:
            f.parent.rmdir()
        except OSError:
            pass


# --------------------------------------------------------------------------- reading credentials


def process_dir(process: str, keys_dir: str | Path) -> Path:
    """The directory holding ``process``'s credentials: ``keys_dir/<p>`` (the tree written by
    :func:`generate_credentials`) or ``keys_dir`` itself if it is that process's directory (what
    gets copied to another host)."""
    slug = process_slug(process)
    d = Path(keys_dir).resolve()
    if (d / slug / "credentials.json").exists():
        return d / slug
    if (d / "credentials.json").exists():
        return d
    raise CredentialsError(f"no credentials for {process} under {d} (expected {d / slug / 'credentials.json'})")


def load_credentials(process: str, keys_dir: str | Path, swarm: str | None = None) -> dict[str, str]:
    """``{"swarm", "process", "user", "password"}`` of ``process`` (see :func:`process_dir`).
    Checks that the file belongs to that process (and swarm, if given)."""
    path = process_dir(process, keys_dir) / "credentials.json"
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        ok = isinstance(d, dict) and all(isinstance(d.get(k), str) and d[k] for k in ("swarm", "process", "user", "password"))
    except (OSError, ValueError) as e:
        raise CredentialsError(f"{path}: unreadable credentials: {e}") from None
    if not ok:
        raise CredentialsError(f"{path}: expected swarm, process, user and password strings")
    if d["process"] != process:
        raise CredentialsError(f"{path} holds the credentials of {d['process']!r}, not {process!r}")
    if swarm is not None and d["swarm"] != swarm:
        raise CredentialsError(f"{path} holds credentials for swarm {d['swarm']!r}, not {swarm!r}")
    creds: dict[str, str] = d  # a JSON object whose four keys were checked to be strings
    return creds


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

Layout written by :func:`generate_credentials` (``<p>`` is a process name with ``:`` replaced by
``-``, e.g. ``agent-2``; keys and passwords are 0600, directories 0700)::

    OUT/manifest.json           what was written (no secrets)
    OUT/ca/ca.pem               the swarm's CA certificate
    OUT/ca/ca-key.pem           the CA's private key: keep it off the swarm's hosts
    OUT/router/usrpwd.txt       user:password dictionary, for the router only
    OUT/<p>/credentials.json    {"swarm", "process", "user", "password"}
    OUT/<p>/cert.pem  key.pem   the process's TLS certificate (CN = process name) and key
    OUT/<p>/ca.pem              copy of the CA certificate (the directory is self-contained)

Zenoh user names may not contain ``:`` (the dictionary file splits at the first ``:``), so a
process's user name is ``<p>@<swarm>``, e.g. ``agent-2@demo``.

Use :func:`router_security_config` / :func:`client_security_config` to get the configuration
fragments ({config path: value}) and :func:`apply_config` to insert them into a ``zenoh.Config``.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import json
import os
import secrets
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from zenswarm.bus import wire
from zenswarm.bus.mocap import mocap_all, mocap_key
from zenswarm.errors import ZenswarmError
from zenswarm.scenario.config import Scenario, load_scenario

if TYPE_CHECKING:  # imported where used: only credential generation needs cryptography
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec

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

AuthMode = Literal["usrpwd", "tls"]
"""``usrpwd``: user/password on plain TCP; ``tls``: mutual TLS, identity = certificate common name."""

ROLES = ("plant", "leader", "recorder", "bridge", "supervisor")
"""Process names other than the agents'."""

MOCAP_FEEDER = "mocap"
"""The motion-capture feed's own user (the simulated Crazyflies' ``--mocap``, or a lab's feeder):
it may only put ``swarm/<name>/mocap/<i>``. Not a swarm process (no liveliness, no diagnostics):
credentials and access rules only, and only for a scenario flying ``positioning = "extpos"``."""

MANIFEST_FILE = "manifest.json"
MANIFEST_VERSION = 1
DEFAULT_DAYS = 365
ROUTER_PROCESS = "supervisor"
"""The router runs inside the supervisor: its certificate is the router's (listen) certificate."""
DEFAULT_ROUTER_HOSTS = ("localhost", "127.0.0.1", "::1")

_KEY_MODE = 0o600
_DIR_MODE = 0o700
_PUB_MODE = 0o644


class CredentialsError(ZenswarmError):
    """Credentials are missing, unreadable, inconsistent, or would be overwritten."""


# --------------------------------------------------------------------------- names


def process_names(n: int) -> list[str]:
    """Every process name of a swarm of ``n`` UAVs: plant, leader, agent:1..n, recorder, bridge, supervisor."""
    return ["plant", "leader"] + [wire.agent(i) for i in range(1, n + 1)] + ["recorder", "bridge", "supervisor"]


def feeder_names(sc: Scenario) -> list[str]:
    """The users beside the swarm's processes that ``sc`` needs: :data:`MOCAP_FEEDER` when its
    Crazyflies fly on an external positioning feed (``[crazyflie] positioning = "extpos"``)."""
    return [MOCAP_FEEDER] if _flies_extpos(sc) else []


def _flies_extpos(sc: Scenario) -> bool:
    return sc.crazyflie is not None and sc.crazyflie.positioning == "extpos"


def process_slug(process: str) -> str:
    """File-system (and user-name) form of a process name: ``agent:2`` -> ``agent-2``."""
    if process == MOCAP_FEEDER:
        return process
    return wire.validate_process(process).replace(":", "-")


def username(process: str, swarm: str) -> str:
    """Zenoh user name of ``process`` in ``swarm``: ``agent-2@demo`` (no ``:``, which the
    router's dictionary file uses as separator)."""
    return f"{process_slug(process)}@{wire.validate_swarm_name(swarm)}"


# --------------------------------------------------------------------------- manifest


@dataclass(frozen=True)
class ProcessCredentials:
    """Where one process's credentials are (paths absolute)."""

    process: str
    user: str
    dir: Path
    credentials: Path  # credentials.json (user, password), 0600
    cert: Path
    key: Path  # 0600
    ca_cert: Path


@dataclass(frozen=True)
class Manifest:
    """What :func:`generate_credentials` wrote. Holds paths and user names, never a secret."""

    swarm: str
    scenario: str
    n: int
    root: Path
    ca_cert: Path
    ca_key: Path
    usrpwd_file: Path
    router_hosts: tuple[str, ...]
    not_after: str  # ISO 8601, UTC
    processes: tuple[ProcessCredentials, ...]

    def process(self, name: str) -> ProcessCredentials:
        for p in self.processes:
            if p.process == name:
                return p
        raise CredentialsError(f"no credentials for process {name!r} in {self.root} (swarm {self.swarm!r})")

    def files(self) -> list[Path]:
        """Every file written, in writing order (manifest last)."""
        out = [self.ca_cert, self.ca_key, self.usrpwd_file]
        for p in self.processes:
            out += [p.credentials, p.cert, p.key, p.ca_cert]
        return out + [self.root / MANIFEST_FILE]

    def to_dict(self) -> dict[str, Any]:

        def rel(p: str | Path) -> str:
            return str(Path(p).relative_to(self.root))

        return {
            "version": MANIFEST_VERSION,
            "swarm": self.swarm,
            "scenario": self.scenario,
            "n": self.n,
            "ca_cert": rel(self.ca_cert),
            "ca_key": rel(self.ca_key),
            "usrpwd_file": rel(self.usrpwd_file),
            "router_process": ROUTER_PROCESS,
            "router_hosts": list(self.router_hosts),
            "not_after": self.not_after,
            "processes": {
                p.process: {
                    "user": p.user,
                    "dir": rel(p.dir),
                    "credentials": rel(p.credentials),
                    "cert": rel(p.cert),
                    "key": rel(p.key),
                    "ca_cert": rel(p.ca_cert),
                }
                for p in self.processes
            },
        }


def load_manifest(out_dir: str | Path) -> Manifest:
    """Read ``OUT/manifest.json`` back (paths made absolute). Raises CredentialsError."""
    root = Path(out_dir).resolve()
    path = root / MANIFEST_FILE
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        if d.get("version") != MANIFEST_VERSION:
            raise CredentialsError(f"{path}: unsupported manifest version {d.get('version')!r}")
        procs = tuple(
            ProcessCredentials(
                process=name,
                user=e["user"],
                dir=root / e["dir"],
                credentials=root / e["credentials"],
                cert=root / e["cert"],
                key=root / e["key"],
                ca_cert=root / e["ca_cert"],
            )
            for name, e in d["processes"].items()
        )
        return Manifest(
            swarm=d["swarm"],
            scenario=d["scenario"],
            n=int(d["n"]),
            root=root,
            ca_cert=root / d["ca_cert"],
            ca_key=root / d["ca_key"],
            usrpwd_file=root / d["usrpwd_file"],
            router_hosts=tuple(d["router_hosts"]),
            not_after=d["not_after"],
            processes=procs,
        )
    except FileNotFoundError:
        raise CredentialsError(f"no manifest at {path}: run `zenswarm keys SCENARIO --out {out_dir}`") from None
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise CredentialsError(f"{path}: unreadable manifest: {e}") from None


def manifest_mismatch(m: Manifest, scenario: Scenario, swarm: str, *, all_files: bool = False) -> str | None:
    """Why the credentials of ``m`` cannot serve ``swarm`` flying ``scenario`` (a phrase such as
    "are for swarm 'a', not 'b'"), or None when they can.

    They can when they are for that swarm, hold every process of a swarm of ``scenario.n`` UAVs
    and have not expired. The scenario's name does not matter: the access rules are generated
    from the scenario at run time, the credentials only name the processes. ``all_files``: every
    file of the manifest must also be present (a tree generated for this run, not one process's
    copy on another host).
    """
    if m.swarm != swarm:
        return f"are for swarm {m.swarm!r}, not {swarm!r}"
    have = {p.process for p in m.processes}
    missing = [p for p in process_names(scenario.n) + feeder_names(scenario) if p not in have]
    if m.n != scenario.n or missing:
        return (f"are for {m.n} UAVs (scenario {m.scenario!r}), not the {scenario.n} of scenario {scenario.name!r}"
                + (f" (no credentials for {', '.join(missing)})" if missing else ""))
    try:
        expires = _dt.datetime.fromisoformat(m.not_after)
    except (TypeError, ValueError):
        return f"have an unreadable expiry date {m.not_after!r}"
    if expires.tzinfo is None:
        expires = expires.replace(tzinfo=_dt.UTC)
    if expires <= _dt.datetime.now(_dt.UTC):
        return f"expired on {m.not_after}"
    if all_files:
        gone = [f for f in m.files() if not f.is_file()]
        if gone:
            return f"are incomplete ({gone[0]} is missing)"
    return None


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


# --------------------------------------------------------------------------- certificates


def _new_key() -> ec.EllipticCurvePrivateKey:
    from cryptography.hazmat.primitives.asymmetric import ec

    # ECDSA P-256: accepted by rustls/webpki with the ring provider that Zenoh's TLS link uses
    # (keys are read as PKCS#8, RSA or SEC1 PEM; PKCS#8 is written).
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _cert_pem(cert: x509.Certificate) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return cert.public_bytes(serialization.Encoding.PEM)


def _san(hosts: Iterable[str]) -> x509.SubjectAlternativeName:
    from cryptography import x509

    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def _make_ca(swarm: str, not_before: _dt.datetime, not_after: _dt.datetime) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import NameOID

    key = _new_key()
    name = x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "zenswarm"),
            x509.NameAttribute(NameOID.COMMON_NAME, f"zenswarm CA {swarm}"),
        ]
    )
    ski = x509.SubjectKeyIdentifier.from_public_key(key.public_key())
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(ski, critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def _make_leaf(
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    common_name: str,
    hosts: Iterable[str] | None,
    not_before: _dt.datetime,
    not_after: _dt.datetime,
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A certificate for one process. ``hosts`` (router only) become subjectAltNames and add the
    serverAuth usage; the other processes' certificates are clientAuth only and carry no name a
    client would accept for the router."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    key = _new_key()
    usages = [ExtendedKeyUsageOID.CLIENT_AUTH]
    if hosts:
        usages.append(ExtendedKeyUsageOID.SERVER_AUTH)
    b = (
        x509.CertificateBuilder()
        .subject_name(
            x509.Name(
                [
                    x509.NameAttribute(NameOID.ORGANIZATION_NAME, "zenswarm"),
                    x509.NameAttribute(NameOID.COMMON_NAME, common_name),
                ]
            )
        )
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(not_after)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
    )
    if hosts:
        b = b.add_extension(_san(hosts), critical=False)
    return key, b.sign(ca_key, hashes.SHA256())


# --------------------------------------------------------------------------- generation


def _as_scenario(scenario: Scenario | str | Path) -> Scenario:
    return scenario if isinstance(scenario, Scenario) else load_scenario(scenario)


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
    sc = _as_scenario(scenario)
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

    ca_key, ca_cert = _make_ca(swarm, not_before, not_after)
    ca_pem = _cert_pem(ca_cert)
    _write(plan.ca_cert, ca_pem, _PUB_MODE)
    _write(plan.ca_key, _key_pem(ca_key), _KEY_MODE)

    lines = []
    for p in plan.processes:
        password = secrets.token_urlsafe(32)
        lines.append(f"{p.user}:{password}\n")
        creds = {"swarm": swarm, "process": p.process, "user": p.user, "password": password}
        _write(p.credentials, (json.dumps(creds, indent=2) + "\n").encode(), _KEY_MODE)
        key, cert = _make_leaf(
            ca_key, ca_cert, p.process, hosts if p.process == ROUTER_PROCESS else None, not_before, not_after
        )
        _write(p.cert, _cert_pem(cert), _PUB_MODE)
        _write(p.key, _key_pem(key), _KEY_MODE)
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


# --------------------------------------------------------------------------- access control


_ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
)


_Grant = tuple[tuple[str, ...], str, list[str]]
"""(messages, flow, key expressions) of an ACL rule: see :func:`_grants`."""

_OBSERVERS = ("recorder", "supervisor")


def _grants(process: str, sc: Scenario, k: wire.Keys) -> list[_Grant]:
    """What ``process`` may do, as (messages, flow, key expressions).

    flow ``ingress`` = from the process into the router, ``egress`` = from the router to it.
    A subscription needs both the declaration (ingress ``declare_subscriber``) and the data
    (egress ``put``). Every process is also shown the swarm's subscriber declarations (egress
    ``declare_subscriber`` on ``swarm/<name>/**``: key expressions only, no data): a client
    session sends a put to the router only if it knows a matching subscriber, and the rule must
    *include* the declared expression, so a rule on the process's own keys would hide the plant's
    ``uav/*/cmd`` and the recorder's ``swarm/<name>/**`` and the puts would be dropped at the
    publisher (observed with 1.10.2).

    Liveliness: every process declares ``alive/<self>``; the swarm's processes (not the recorder
    and the supervisor) also ``alive/<self>/<zid>``, which session is this process: the receivers'
    input guard pins each key to the session holding its sender's token, so a second session with
    the same credentials is a foreign sender. Each watches exactly the tokens it follows:
    ``alive/<p>`` of the processes it waits for or outlives (the leader: the plant, whose exit
    ends the flight) and ``alive/<p>/*`` of its inputs' senders.
    """
    if process == MOCAP_FEEDER:  # puts the positions, nothing more (it sees the subscribers' declarations: see above)
        return [(("put",), "ingress", [mocap_key(k.prefix, i) for i in range(1, sc.n + 1)]), (("declare_subscriber",), "egress", [k.all])]
    i = wire.process_uav(process)
    if i is not None:  # agent i: its graph row, nothing more
        pub, sub, extra = _agent_grants(process, i, sc, k)
    elif process in ("plant", "bridge"):
        pub, sub, extra = _vehicles_grants(process, sc, k)
    elif process == "leader":
        pub, sub, extra = _leader_grants(k)
    elif process in _OBSERVERS:
        pub, sub = [], [k.all]
        extra = _query_mission(k) + [
            (("liveliness_query", "declare_liveliness_subscriber"), "ingress", [k.all]),
            (("liveliness_token",), "egress", [k.all]),
        ]
    else:  # pragma: no cover - validate_process above rejects anything else
        raise CredentialsError(f"unknown process {process!r}")
    own_alive = k.alive(process)
    grants: list[_Grant] = [
        (("put",), "ingress", [k.diag(process)] + pub),
        (("declare_subscriber",), "egress", [k.all]),
        # its token, and (a swarm process, not the observers) its session's: alive/<self>/<zid>
        (("liveliness_token",), "ingress", [own_alive] + ([] if process in _OBSERVERS else [own_alive + "/*"])),
    ]
    if sub:
        grants += [(("declare_subscriber",), "ingress", sub), (("put",), "egress", sub)]
    return grants + extra


def _query_mission(k: wire.Keys) -> list[_Grant]:
    """Every process may fetch the mission (late joiners, other hosts without the scenario file)."""
    return [(("query",), "ingress", [k.mission]), (("reply",), "egress", [k.mission])]


def _watching(tokens: list[str]) -> list[_Grant]:
    """Watch the liveliness ``tokens``: a liveliness subscriber with history also queries, both
    need the tokens sent back."""
    return [
        (("liveliness_query", "declare_liveliness_subscriber"), "ingress", tokens),
        (("liveliness_token",), "egress", tokens),
    ]


def _sender_tokens(k: wire.Keys, names: list[str]) -> list[str]:
    """The session tokens ``alive/<p>/*`` of the processes ``names``."""
    return [k.alive(p) + "/*" for p in names]


def _agent_grants(process: str, i: int, sc: Scenario, k: wire.Keys) -> tuple[list[str], list[str], list[_Grant]]:
    """Agent i's own keys to put, keys to subscribe and further rules (:func:`_grants`)."""
    if i > sc.n:
        raise CredentialsError(f"{process}: scenario {sc.name!r} has only {sc.n} UAVs")
    pub = [k.ref(i), k.cmd(i)]
    sub = [k.state(i)] + [k.ref(j + 1) for j in sc.neighbours(i - 1)]
    if sc.graph.pinning[i - 1] > 0:
        sub.append(k.leader_ref)
    # an agent watches the liveliness of the processes it waits for (not to wait on the dead),
    # and the sender tokens of its inputs (its state comes from the plant or the bridge)
    nbrs = [wire.agent(j + 1) for j in sc.neighbours(i - 1)]
    lead = ["leader"] if sc.graph.pinning[i - 1] > 0 else []
    watch = [k.alive(p) for p in ["plant"] + nbrs + lead] + _sender_tokens(k, ["plant", "bridge"] + nbrs + lead)
    return pub, sub, _query_mission(k) + _watching(watch)


def _vehicles_grants(process: str, sc: Scenario, k: wire.Keys) -> tuple[list[str], list[str], list[_Grant]]:
    """The plant's or the MAVLink bridge's keys to put, keys to subscribe and further rules (:func:`_grants`)."""
    P = k.prefix
    pub = [f"{P}/uav/*/state", k.clock]
    sub = [f"{P}/uav/*/cmd"]
    if process == "bridge":  # the MAVLink bridge forwards commands, or references as position setpoints
        sub += [f"{P}/uav/*/ref"]
        if _flies_extpos(sc):  # the Crazyflie bridge forwards the positioning feed
            sub += [mocap_all(P)]
    liveliness_watch: list[_Grant] = [
        (("liveliness_query", "declare_liveliness_subscriber"), "ingress", [k.alive_all]),
        (("liveliness_token",), "egress", [k.alive_all]),
    ]
    agents = [wire.agent(j) for j in range(1, sc.n + 1)]
    return pub, sub, _query_mission(k) + liveliness_watch + _watching(_sender_tokens(k, agents))


def _leader_grants(k: wire.Keys) -> tuple[list[str], list[str], list[_Grant]]:
    """The leader's keys to put, keys to subscribe and further rules (:func:`_grants`)."""
    extra: list[_Grant] = [
        (("declare_queryable", "reply"), "ingress", [k.mission]),
        (("query",), "egress", [k.mission]),
    ]
    # it keeps its token until the plant is gone (the end of a lockstep flight), and follows
    # who sends the clock
    extra += _query_mission(k) + _watching([k.alive("plant")] + _sender_tokens(k, ["plant", "bridge"]))
    return [k.leader_ref], [k.clock], extra


def acl_rules(
    scenario: Scenario | str | Path,
    swarm: str = "default",
    *,
    auth: AuthMode = "usrpwd",
    processes: Iterable[str] | None = None,
) -> dict[str, Any]:
    """The router's ``access_control`` section for ``swarm`` flying ``scenario``.

    Default deny. One subject per process, matched by user name (``auth="usrpwd"``, see
    :func:`username`) or by TLS certificate common name = process name (``auth="tls"``); a
    session that matches no subject can do nothing. Per role (``P = swarm/<name>``; every process
    may also put ``P/diag/<self>``, declare its liveliness token ``P/alive/<self>`` and query
    ``P/mission``; the swarm's processes (not the recorder and the supervisor) also declare their
    session's token ``P/alive/<self>/<zid>`` and liveliness-subscribe ``P/alive/<p>/*`` of the
    processes p that send them their inputs):

    * ``agent:<i>``: put ``uav/<i>/ref``, ``uav/<i>/cmd``; subscribe ``uav/<i>/state``,
      ``uav/<j>/ref`` for its neighbours j (a_ij > 0) and ``leader/ref`` if pinned (b_i > 0);
      liveliness-subscribe ``alive/<p>`` of the plant, its neighbours and (if pinned) the leader;
    * ``plant``, ``bridge``: put ``uav/*/state``, ``clock``; subscribe ``uav/*/cmd`` (the
      bridge also ``uav/*/ref``, for position setpoints); liveliness query/subscribe ``alive/*``;
    * ``leader``: put ``leader/ref``; subscribe ``clock``; queryable and replies on ``mission``;
      liveliness-subscribe ``alive/plant`` (it keeps its token until the plant is gone);
    * ``recorder``, ``supervisor``: subscribe and liveliness-subscribe ``P/**`` (read only);
    * ``mocap`` (:data:`MOCAP_FEEDER`, a scenario flying ``positioning = "extpos"``): put
      ``mocap/<i>`` for i = 1..N and nothing else (no diagnostics, no liveliness); the bridge
      then also subscribes ``mocap/*``.

    ``processes`` restricts the policy to some processes (default: all of :func:`process_names`
    and :func:`feeder_names`).
    """
    sc = _as_scenario(scenario)
    k = wire.Keys(swarm)
    if auth not in ("usrpwd", "tls"):
        raise CredentialsError(f"auth: expected 'usrpwd' or 'tls', got {auth!r}")
    names = list(processes) if processes is not None else process_names(sc.n) + feeder_names(sc)
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for name in names:
        slug = process_slug(name)
        rule_ids = []
        for n, (messages, flow, key_exprs) in enumerate(_grants(name, sc, k)):
            for m in messages:
                if m not in _ALL_MESSAGES:  # pragma: no cover - internal consistency
                    raise AssertionError(m)
            rid = f"{swarm}.{slug}.{n}"
            rules.append(
                {
                    "id": rid,
                    "messages": list(messages),
                    "flows": [flow],
                    "permission": "allow",
                    "key_exprs": list(dict.fromkeys(key_exprs)),
                }
            )
            rule_ids.append(rid)
        sid = f"{swarm}.{slug}"
        subject: dict[str, Any] = {"id": sid}
        if auth == "usrpwd":
            subject["usernames"] = [username(name, swarm)]
        else:
            subject["cert_common_names"] = [name]
        subjects.append(subject)
        policies.append({"id": sid, "rules": rule_ids, "subjects": [sid]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# --------------------------------------------------------------------------- zenoh config fragments


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

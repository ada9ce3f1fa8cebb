"""Who is in a swarm, and what a key directory holds: its manifest (paths and user names, no secret).

A swarm of N UAVs is the processes ``plant``, ``leader``, ``agent:1`` .. ``agent:N``, ``recorder``,
``bridge`` and ``supervisor`` (:func:`process_names`), and, for a scenario flying ``positioning =
"extpos"``, one more user: the motion-capture feed (:data:`MOCAP_FEEDER`, :func:`feeder_names`).
Each proves who it is (:data:`AuthMode`) by its Zenoh user name ``<p>@<swarm>`` (:func:`username`)
or by its TLS certificate, whose common name is the process name. ``OUT/manifest.json``
(:class:`Manifest`, :func:`load_manifest`) lists the files ``zenswarm keys`` wrote for each of them
(:mod:`zenswarm.process.security.credentials`); :func:`manifest_mismatch` says whether they serve
a flight. Expiry dates are ISO 8601, UTC.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from zenswarm.bus import wire
from zenswarm.errors import ZenswarmError
from zenswarm.scenario.config import Scenario, load_scenario

__all__ = [
    "CredentialsError",
    "AuthMode",
    "ROLES",
    "MOCAP_FEEDER",
    "ROUTER_PROCESS",
    "MANIFEST_FILE",
    "MANIFEST_VERSION",
    "process_names",
    "feeder_names",
    "flies_extpos",
    "process_slug",
    "username",
    "as_scenario",
    "ProcessCredentials",
    "Manifest",
    "load_manifest",
    "manifest_mismatch",
]

AuthMode = Literal["usrpwd", "tls"]
"""``usrpwd``: user/password on plain TCP; ``tls``: mutual TLS, identity = certificate common name."""

ROLES = ("plant", "leader", "recorder", "bridge", "supervisor")
"""Process names other than the agents'."""

MOCAP_FEEDER = "mocap"
"""The motion-capture feed's own user (the simulated Crazyflies' ``--mocap``, or a lab's feeder):
it may only put ``swarm/<name>/mocap/<i>``. Not a swarm process (no liveliness, no diagnostics):
credentials and access rules only, and only for a scenario flying ``positioning = "extpos"``."""

ROUTER_PROCESS = "supervisor"
"""The router runs inside the supervisor: its certificate is the router's (listen) certificate."""

MANIFEST_FILE = "manifest.json"
MANIFEST_VERSION = 1


class CredentialsError(ZenswarmError):
    """Credentials are missing, unreadable, inconsistent, or would be overwritten."""


# --------------------------------------------------------------------------- names


def process_names(n: int) -> list[str]:
    """Every process name of a swarm of ``n`` UAVs: plant, leader, agent:1..n, recorder, bridge, supervisor."""
    return ["plant", "leader"] + [wire.agent(i) for i in range(1, n + 1)] + ["recorder", "bridge", "supervisor"]


def feeder_names(sc: Scenario) -> list[str]:
    """The users beside the swarm's processes that ``sc`` needs: :data:`MOCAP_FEEDER` when its
    Crazyflies fly on an external positioning feed (``[crazyflie] positioning = "extpos"``)."""
    return [MOCAP_FEEDER] if flies_extpos(sc) else []



def flies_extpos(sc: Scenario) -> bool:
    """Whether ``sc``'s Crazyflies fly on an external positioning feed (``positioning = "extpos"``)."""
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



def as_scenario(scenario: Scenario | str | Path) -> Scenario:
    """``scenario`` itself, or the scenario its file holds."""
    return scenario if isinstance(scenario, Scenario) else load_scenario(scenario)


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


"""The router's access control, generated from the scenario's graph (:func:`acl_rules`).

Default deny; one subject per process, matched by its Zenoh user name or by its TLS certificate's
common name (:data:`~zenswarm.process.security.manifest.AuthMode`), allowed only the key
expressions of its role: an agent its own references and commands and its neighbours' (a_ij > 0)
and, if pinned (b_i > 0), the leader's reference; the plant and the bridges every UAV's state and
command; the observers (recorder, supervisor) read only. The result is the plain Zenoh 1.x
``access_control`` section (checked against eclipse-zenoh 1.10.2).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from zenswarm.bus import wire
from zenswarm.bus.mocap import mocap_all, mocap_key
from zenswarm.process.security.manifest import (
    MOCAP_FEEDER,
    AuthMode,
    CredentialsError,
    as_scenario,
    feeder_names,
    flies_extpos,
    process_names,
    process_slug,
    username,
)
from zenswarm.scenario.config import Scenario

__all__ = ["acl_rules"]


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
        if flies_extpos(sc):  # the Crazyflie bridge forwards the positioning feed
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
    sc = as_scenario(scenario)
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


"""Where each role of a swarm runs on a cluster: ``zenswarm up --scheduler ... --placement RULE``.

Pure: the rules are parsed (:func:`parse_rule`) and the roles planned onto the cluster's workers
(:func:`plan`) without any process or connection, so both are unit-tested
(``tests/test_placement.py``). :mod:`zenswarm.compose.cluster` asks the Dask scheduler for its
workers (:class:`Worker`) and starts each role where the plan says.

A rule is ``ROLES=TARGET`` (``--placement``, repeatable):

- ROLES: ``plant``, ``leader``, ``agent:I``, ``agent:I-J`` (UAVs I to J, inclusive), ``agents``
  (every agent), or several of these separated by commas (``plant,leader``).
- TARGET: a worker's name (``dask worker --name w1``) or address (``tcp://10.0.0.2:40123``), or
  ``resource:NAME``: the workers that offer the Dask resource NAME (``dask worker --resources
  "NAME=1"``), the roles spread evenly over them.

Roles no rule names are spread evenly over every worker. A role restarted (``--restart``) after its
worker was lost goes to the least loaded live worker its rule allows (:func:`replace`; a rule
naming the lost worker allows any). Spreading is deterministic: each role,
in start order, goes to the worker holding the fewest roles so far (ties: the workers in the
order of their names), so the same cluster and rules give the same plan.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from zenswarm.errors import ScenarioError

__all__ = ["Worker", "Rule", "parse_rule", "plan", "replace", "PLACEMENT_HELP"]

RESOURCE_PREFIX = "resource:"

PLACEMENT_HELP = (
    "with --scheduler: where roles run, ROLES=TARGET (repeatable). ROLES: plant, leader, agent:I, agent:I-J, agents, "
    "or several joined by commas; TARGET: a worker's name or address, or resource:NAME (the workers offering that Dask "
    "resource). Roles no rule names are spread evenly over all workers (docs/cluster.md)"
)


@dataclass(frozen=True)
class Worker:
    """A Dask worker as the scheduler describes it: ``address`` (``tcp://HOST:PORT``), ``name``
    (``--name``; the address when not given), ``host`` (the address it listens on) and the
    ``resources`` it offers (name -> amount)."""

    address: str
    name: str
    host: str
    resources: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Rule:
    """One ``--placement`` rule: the roles it names and where they go (``worker``: a name or an
    address; or ``resource``: a Dask resource name). ``text`` is the rule as given."""

    text: str
    roles: tuple[str, ...]  # role patterns: plant, leader, agent:I, agent:I-J, agents
    worker: str | None = None
    resource: str | None = None

    def names(self, n: int) -> list[str]:
        """The roles of an ``n``-UAV swarm this rule names, in start order; ScenarioError naming
        ``--placement`` for a role the swarm does not have."""
        out: list[str] = []
        for pat in self.roles:
            if pat in ("plant", "leader"):
                out.append(pat)
            elif pat == "agents":
                out += [f"agent:{i}" for i in range(1, n + 1)]
            else:
                lo, hi = _agent_range(pat, self.text)
                if hi > n:
                    raise ScenarioError("--placement", f"{self.text!r}: agent:{hi} is not a role of this swarm "
                                        f"({n} UAVs: plant, leader, agent:1..agent:{n})")  # fmt: skip
                out += [f"agent:{i}" for i in range(lo, hi + 1)]
        return out

    def matches(self, w: Worker) -> bool:
        """Whether ``w`` is a worker this rule sends its roles to."""
        if self.resource is not None:
            return w.resources.get(self.resource, 0) > 0
        return self.worker in (w.name, w.address)


def _agent_range(pat: str, text: str) -> tuple[int, int]:
    """``agent:I`` or ``agent:I-J`` -> (I, J), 1 <= I <= J; ScenarioError otherwise."""
    kind, sep, ids = pat.partition(":")
    lo_s, dash, hi_s = ids.partition("-")
    try:
        if kind != "agent" or not sep:
            raise ValueError
        lo = int(lo_s)
        hi = int(hi_s) if dash else lo
    except ValueError:
        raise ScenarioError(
            "--placement", f"{text!r}: unknown role {pat!r}; expected plant, leader, agent:I, agent:I-J or agents"
        ) from None
    if not 1 <= lo <= hi:
        raise ScenarioError("--placement", f"{text!r}: {pat!r} is not a range of UAVs 1 <= I <= J")
    return lo, hi


def parse_rule(text: str) -> Rule:
    """``ROLES=TARGET`` as a :class:`Rule` (the roles' syntax checked; whether they exist is checked
    by :func:`plan`, which knows the swarm's size). ScenarioError naming ``--placement``."""
    roles_s, sep, target = text.partition("=")
    target = target.strip()
    if not sep or not roles_s.strip() or not target:
        raise ScenarioError("--placement", f"{text!r}: expected ROLES=TARGET, e.g. agent:1-4=w1 or plant=resource:gpu")
    roles = tuple(r.strip() for r in roles_s.split(","))
    for r in roles:
        if r not in ("plant", "leader", "agents"):
            _agent_range(r, text)
    if target.startswith(RESOURCE_PREFIX):
        res = target[len(RESOURCE_PREFIX) :].strip()
        if not res:
            raise ScenarioError("--placement", f"{text!r}: resource: needs a resource name (resource:gpu)")
        return Rule(text, roles, resource=res)
    return Rule(text, roles, worker=target)


def _rules_by_role(roles: Sequence[str], rules: Iterable[Rule], n: int) -> dict[str, Rule]:
    """role -> the rule naming it; a role named by two rules, or a rule naming no role of
    ``roles``, is a ScenarioError."""
    by_role: dict[str, Rule] = {}
    for rule in rules:
        for role in rule.names(n):
            if role not in roles:
                raise ScenarioError("--placement", f"{rule.text!r}: {role} is not started on the cluster "
                                    f"(placed roles: {', '.join(roles)})")  # fmt: skip
            if role in by_role:
                raise ScenarioError("--placement", f"{role} is named by two rules: {by_role[role].text!r} and {rule.text!r}")
            by_role[role] = rule
    return by_role


def _least_loaded(candidates: Sequence[Worker], load: dict[str, int]) -> Worker:
    """The candidate holding the fewest roles (ties: the first by name, then address)."""
    return min(candidates, key=lambda w: (load.get(w.address, 0), w.name, w.address))


def plan(roles: Sequence[str], workers: Sequence[Worker], rules: Sequence[Rule], n: int) -> dict[str, str]:
    """role -> the address of the worker it starts on, for the ``roles`` of an ``n``-UAV swarm
    (in start order). Pinned roles first, then the rest spread evenly over all workers.
    ScenarioError naming ``--placement`` (a rule naming an unknown role or worker, a resource no
    worker offers) or ``--scheduler`` (no worker)."""
    if not workers:
        raise ScenarioError("--scheduler", "the Dask scheduler has no workers: start some (dask worker tcp://HOST:PORT)")
    by_role = _rules_by_role(roles, rules, n)
    known = ", ".join(f"{w.name} ({w.address})" if w.name != w.address else w.address for w in workers)
    for rule in {id(r): r for r in by_role.values()}.values():
        if not any(rule.matches(w) for w in workers):
            what = f"no worker offers the resource {rule.resource!r}" if rule.resource else f"no worker is named {rule.worker!r}"
            raise ScenarioError("--placement", f"{rule.text!r}: {what}; the workers: {known}")
    load: dict[str, int] = {}
    where: dict[str, str] = {}
    for role in [r for r in roles if r in by_role] + [r for r in roles if r not in by_role]:
        pin = by_role.get(role)
        w = _least_loaded([w for w in workers if pin is None or pin.matches(w)], load)
        where[role] = w.address
        load[w.address] = load.get(w.address, 0) + 1
    return {r: where[r] for r in roles}


def replace(role: str, rule: Rule | None, workers: Sequence[Worker], where: dict[str, str]) -> str | None:
    """Where a role goes again when it is restarted and its worker is gone: the least loaded of
    the live ``workers`` its rule allows (``where``: the roles' current workers). A role pinned to
    a worker by name or address goes to the least loaded live worker once that one is lost; one
    that needs a resource only to a live worker offering it. None if there is none."""
    load: dict[str, int] = {}
    for r, addr in where.items():
        if r != role:
            load[addr] = load.get(addr, 0) + 1
    candidates = [w for w in workers if rule is None or rule.matches(w)]
    if not candidates and rule is not None and rule.worker is not None:
        candidates = list(workers)
    return _least_loaded(candidates, load).address if candidates else None


def rules_by_role(roles: Sequence[str], rules: Sequence[Rule], n: int) -> dict[str, Rule]:
    """role -> the rule naming it (the roles no rule names are absent); see :func:`plan`."""
    return _rules_by_role(roles, rules, n)

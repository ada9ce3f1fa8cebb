"""Names on the swarm's links: processes (``plant``, ``leader``, ``agent:<i>``), the message kinds
and which directed links ``(src, dst, kind)`` a swarm has.

Process names are ``plant``, ``leader`` and ``agent:<i>`` (UAVs numbered 1..N as in the paper).
A link carries one kind of message:

=========  =====================  ===========================================
kind       direction              wire key
=========  =====================  ===========================================
``ref``    ``agent:j -> agent:i``  ``uav/<j>/ref``   (q*_j, v*_j), eqs (16)-(17)
``leader`` ``leader -> agent:i``   ``leader/ref``    (q0, v0), eq. (15)
``state``  ``plant -> agent:i``    ``uav/<i>/state`` measured state
``cmd``    ``agent:i -> plant``    ``uav/<i>/cmd``   thrust and attitude
=========  =====================  ===========================================

(Both reference messages are ``k: "ref"`` on the wire; the fault model tells them apart so that the
leader's reference can be faulted separately.) The rest of the model (:mod:`zenswarm.link.plan`,
:mod:`zenswarm.link.trace`, ...) names links with these.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

from zenswarm.errors import ScenarioError

__all__ = [
    "KINDS", "KIND_ROLES", "PROCESS_RE", "parse_process", "role_of", "link_kind", "agent_links", "plant_links", "parse_target",
    "check_exists",
]  # fmt: skip

#: Message kinds, see the module docstring.
KINDS: tuple[str, ...] = ("ref", "leader", "state", "cmd")
#: The roles (sender, receiver) of each kind.
KIND_ROLES: dict[str, tuple[str, str]] = {
    "ref": ("agent", "agent"),
    "leader": ("leader", "agent"),
    "state": ("plant", "agent"),
    "cmd": ("agent", "plant"),
}

PROCESS_RE = re.compile(r"^(plant|leader|agent:(\d+))$")


def parse_process(name: str) -> str:
    """Canonical process name: ``plant``, ``leader`` or ``agent:<i>`` with i >= 1 (``agent:02`` -> ``agent:2``).

    Raises ValueError naming the bad text.
    """
    if not isinstance(name, str):
        raise ValueError(f"expected a process name (plant, leader, agent:<i>), got {name!r}")
    m = PROCESS_RE.match(name.strip())
    if not m:
        raise ValueError(f"invalid process name {name!r}: expected plant, leader or agent:<i> (i >= 1)")
    if m.group(2) is not None:
        i = int(m.group(2))
        if i < 1:
            raise ValueError(f"invalid process name {name!r}: UAVs are numbered from 1")
        return f"agent:{i}"
    return m.group(1)


def role_of(name: str) -> str:
    """The role of a canonical process name: ``agent`` for ``agent:<i>``, else the name."""
    return "agent" if name.startswith("agent:") else name


def link_kind(src: str, dst: str) -> str:
    """The message kind a directed link carries (see the module table); ValueError if none does."""
    s, d = parse_process(src), parse_process(dst)
    roles = (role_of(s), role_of(d))
    for kind, r in KIND_ROLES.items():
        if r == roles and s != d:
            return kind
    raise ValueError(f"no message kind flows {src!r} -> {dst!r}")


def agent_links(i: int, neighbours: Iterable[int], pinned: bool) -> list[tuple[str, str, str]]:
    """Incoming links ``(src, dst, kind)`` of agent ``i`` (1-based): its state, its neighbours'
    refs (1-based indices, in the order given) and, if pinned, the leader's ref. The graph row."""
    me = f"agent:{int(i)}"
    links = [("plant", me, "state")]
    links += [(f"agent:{int(j)}", me, "ref") for j in neighbours]
    if pinned:
        links.append(("leader", me, "leader"))
    return links


def plant_links(n: int) -> list[tuple[str, str, str]]:
    """Incoming links of the plant: every agent's command, agents 1..n."""
    return [(f"agent:{i}", "plant", "cmd") for i in range(1, int(n) + 1)]


def parse_target(text: str) -> str:
    """``agent:2`` (a process: every link to and from it) or ``agent:1->agent:2`` (one directed link)."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"invalid partition target {text!r}: expected a process or src->dst")
    if "->" in text:
        a, _, b = text.partition("->")
        try:
            sa, sb = parse_process(a), parse_process(b)
        except ValueError as e:
            raise ValueError(f"invalid partition target {text!r}: {e}") from None
        if sa == sb:
            raise ValueError(f"invalid partition target {text!r}: a link needs two different processes")
        return f"{sa}->{sb}"
    try:
        return parse_process(text)
    except ValueError as e:
        raise ValueError(f"invalid partition target {text!r}: {e}") from None


def check_exists(path: str, target: str, n: int | None) -> None:
    """Raise :class:`ScenarioError` naming ``path`` when ``target`` (a process, a link
    ``src->dst`` or a glob) names an agent beyond the scenario's ``n`` UAVs; ``n=None``: no check."""
    if n is None:
        return
    for part in target.split("->"):
        m = PROCESS_RE.match(part.strip())
        if m and m.group(2) is not None and not 1 <= int(m.group(2)) <= n:
            raise ScenarioError(path, f"{part.strip()} does not exist: the scenario has {n} UAVs (agent:1 to agent:{n})")

"""Names on the swarm's links: processes (``plant``, ``leader``, ``agent:<i>``), the message kinds
and which directed links ``(src, dst, kind)`` a swarm has.

``ref``: agent -> agent, ``leader``: leader -> agent, ``state``: plant -> agent, ``cmd``: agent ->
plant (:mod:`zenswarm.link.faults` and :mod:`zenswarm.link.trace` name links with these).
"""

from __future__ import annotations

import re
from collections.abc import Iterable

__all__ = ["KINDS", "KIND_ROLES", "PROCESS_RE", "parse_process", "role_of", "link_kind", "agent_links", "plant_links"]

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

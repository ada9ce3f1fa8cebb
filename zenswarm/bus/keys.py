"""Key space of the swarm bus: the key expressions of one swarm and the names in them.

Pure: the standard library only (no zenoh). The messages carried on these keys and their codec
are :mod:`zenswarm.bus.wire` (which re-exports every name here).

Key layout (see :class:`Keys`)::

    swarm/<name>/clock | mission | leader/ref
    swarm/<name>/uav/<i>/state | ref | cmd        i = 1..N, decimal, no leading zero
    swarm/<name>/diag/<process> | alive/<process>

Process names are ``plant``, ``leader``, ``agent:<i>``, ``recorder``, ``bridge``, ``supervisor``.
``:`` is a legal character in a Zenoh key chunk (only ``* $ ? #``, empty chunks and leading or
trailing ``/`` are forbidden; checked against eclipse-zenoh 1.10.2), so a process name is used in
keys verbatim: ``swarm/demo/alive/agent:2``.
"""

from __future__ import annotations

import re
from types import MappingProxyType
from typing import Final

from zenswarm.errors import ZenswarmError

__all__ = [
    "KEY_KINDS",
    "InvalidKeyError",
    "Keys",
    "validate_swarm_name",
    "validate_process",
    "agent",
    "process_uav",
    "message_kind",
]

KEY_KINDS: Final = MappingProxyType({
    "clock": "clock",
    "mission": "mission",
    "leader_ref": "ref",
    "state": "state",
    "ref": "ref",
    "cmd": "cmd",
    "diag": "diag",
    "alive": None,
})
"""Key kind (as returned by :meth:`Keys.parse`) -> message kind carried there (None: a token)."""

_SWARM_RE: Final = re.compile(r"[A-Za-z0-9_-]{1,64}")
PROCESS_PATTERN: Final = r"(plant|leader|recorder|bridge|supervisor)|agent:([1-9][0-9]{0,8})"
"""A process name, whole: one of the named roles, or ``agent:<i>`` (i = 1..999999999, no leading zero)."""
_PROCESS_RE: Final = re.compile(PROCESS_PATTERN)
_INDEX_RE: Final = re.compile(r"[1-9][0-9]{0,8}")


class InvalidKeyError(ZenswarmError, ValueError):
    """A swarm name, process name, UAV index or key expression is not valid."""


# --------------------------------------------------------------------------- names and keys


def validate_swarm_name(name: str) -> str:
    """Return ``name`` if it matches ``[A-Za-z0-9_-]{1,64}``, else raise InvalidKeyError."""
    if not isinstance(name, str) or _SWARM_RE.fullmatch(name) is None:
        raise InvalidKeyError(f"invalid swarm name {name!r}: expected 1-64 characters of [A-Za-z0-9_-]")
    return name


def validate_process(process: str) -> str:
    """Return ``process`` if it is a valid process name (``plant``, ``leader``, ``agent:<i>``
    with i >= 1, ``recorder``, ``bridge``, ``supervisor``), else raise InvalidKeyError."""
    if not isinstance(process, str) or _PROCESS_RE.fullmatch(process) is None:
        raise InvalidKeyError(
            f"invalid process name {process!r}: expected plant, leader, agent:<i> (i >= 1), "
            "recorder, bridge or supervisor"
        )
    return process


def _uav_index(i: int) -> int:
    if type(i) is not int or not 1 <= i <= 999_999_999:
        raise InvalidKeyError(f"invalid UAV index {i!r}: expected an int in 1..999999999 (UAVs are numbered from 1)")
    return i


def agent(i: int) -> str:
    """Process name of UAV ``i``'s agent: ``agent(2) == "agent:2"``."""
    return f"agent:{_uav_index(i)}"


def process_uav(process: str) -> int | None:
    """UAV index of an ``agent:<i>`` process name, None for the other processes."""
    m = _PROCESS_RE.fullmatch(process) if isinstance(process, str) else None
    if m is None:
        raise InvalidKeyError(f"invalid process name {process!r}")
    return int(m.group(2)) if m.group(2) else None


def message_kind(key_kind: str) -> str | None:
    """Message kind carried on keys of ``key_kind`` (``"leader_ref"`` -> ``"ref"``; ``"alive"`` -> None)."""
    return KEY_KINDS[key_kind]


class Keys:
    """Key expressions of one swarm, all under ``swarm/<name>``.

    Attributes ``clock``, ``mission``, ``leader_ref``, ``all`` (``swarm/<name>/**``),
    ``alive_all`` (``swarm/<name>/alive/*``) and ``diag_all`` are plain strings; ``state(i)``,
    ``ref(i)``, ``cmd(i)`` take the UAV index i >= 1; ``diag(p)``, ``alive(p)`` a process name.
    """

    __slots__ = ("name", "prefix", "clock", "mission", "leader_ref", "all", "alive_all", "diag_all", "_plen")

    def __init__(self, swarm: str) -> None:
        self.name: str = validate_swarm_name(swarm)
        self.prefix: str = f"swarm/{swarm}"
        self.clock: str = f"{self.prefix}/clock"
        self.mission: str = f"{self.prefix}/mission"
        self.leader_ref: str = f"{self.prefix}/leader/ref"
        self.all: str = f"{self.prefix}/**"
        self.alive_all: str = f"{self.prefix}/alive/*"
        self.diag_all: str = f"{self.prefix}/diag/*"
        self._plen = len(self.prefix) + 1

    def __repr__(self) -> str:
        return f"Keys({self.name!r})"

    def state(self, i: int) -> str:
        """``swarm/<name>/uav/<i>/state``: plant -> agent i."""
        return f"{self.prefix}/uav/{_uav_index(i)}/state"

    def ref(self, i: int) -> str:
        """``swarm/<name>/uav/<i>/ref``: agent i -> its neighbours (q*_i, v*_i)."""
        return f"{self.prefix}/uav/{_uav_index(i)}/ref"

    def cmd(self, i: int) -> str:
        """``swarm/<name>/uav/<i>/cmd``: agent i -> plant."""
        return f"{self.prefix}/uav/{_uav_index(i)}/cmd"

    def diag(self, process: str) -> str:
        """``swarm/<name>/diag/<process>``: counters of a process."""
        return f"{self.prefix}/diag/{validate_process(process)}"

    def alive(self, process: str) -> str:
        """``swarm/<name>/alive/<process>``: liveliness token of a process."""
        return f"{self.prefix}/alive/{validate_process(process)}"

    def parse(self, key: str) -> tuple[str, int | None, str | None]:
        """Split a concrete key of this swarm into ``(kind, uav_index, process)``.

        kind is one of :data:`KEY_KINDS` (``clock``, ``mission``, ``leader_ref``, ``state``,
        ``ref``, ``cmd``, ``diag``, ``alive``); uav_index is set for ``uav/<i>/...`` keys,
        process for ``diag/<p>`` and ``alive/<p>``. Raises InvalidKeyError for anything else
        (another swarm, unknown layout, bad index or process name).
        """
        key = str(key)
        if not key.startswith(self.prefix) or key[self._plen - 1 : self._plen] != "/":
            raise InvalidKeyError(f"key {key!r} is not under {self.prefix!r}")
        parts = key[self._plen :].split("/")
        n = len(parts)
        head = parts[0]
        if n == 1 and head in ("clock", "mission"):
            return head, None, None
        if n == 2:
            if head == "leader" and parts[1] == "ref":
                return "leader_ref", None, None
            if head in ("diag", "alive"):
                try:
                    return head, None, validate_process(parts[1])
                except InvalidKeyError:
                    raise InvalidKeyError(f"key {key!r}: invalid process name {parts[1]!r}") from None
        if n == 3 and head == "uav" and parts[2] in ("state", "ref", "cmd"):
            if _INDEX_RE.fullmatch(parts[1]) is None:
                raise InvalidKeyError(f"key {key!r}: invalid UAV index {parts[1]!r}")
            return parts[2], int(parts[1]), None
        raise InvalidKeyError(f"key {key!r}: unknown key layout under {self.prefix!r}")

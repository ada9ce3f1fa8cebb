"""Wire protocol of the swarm bus: key expressions, message types, msgpack codec.

Pure: msgpack, numpy and the standard library only (no zenoh). Every payload is a msgpack map
that carries the schema version ``"v"`` and a kind tag ``"k"``; ``t`` is sim time in integer
nanoseconds and ``seq`` a non-negative integer. Vectors are float64 ``(3,)`` arrays, SI units,
inertial frame ENU (z up). Floats are packed as msgpack float64, so they round-trip bit-exactly.

Wire layout (``v`` is always :data:`SCHEMA_VERSION`; velocity travels as ``"vel"`` because
``"v"`` is the version)::

    clock    {v, k:"clock",   t, seq}
    state    {v, k:"state",   t, seq, q[3], vel[3], rpy[3], w[3]}
    ref      {v, k:"ref",     t, seq, q[3], vel[3]}              uav/<i>/ref and leader/ref
    cmd      {v, k:"cmd",     t, seq, thrust, rpy[3], u[3], d_hat[3]}
    mission  {v, k:"mission", t, seq, scenario{...}}
    diag     {v, k:"diag",    t, seq, process, counters{str: number}, info{...}}

Key layout (see :class:`Keys`)::

    swarm/<name>/clock | mission | leader/ref
    swarm/<name>/uav/<i>/state | ref | cmd        i = 1..N, decimal, no leading zero
    swarm/<name>/diag/<process> | alive/<process>

Process names are ``plant``, ``leader``, ``agent:<i>``, ``recorder``, ``bridge``, ``supervisor``.
``:`` is a legal character in a Zenoh key chunk (only ``* $ ? #``, empty chunks and leading or
trailing ``/`` are forbidden; checked against eclipse-zenoh 1.10.2), so a process name is used in
keys verbatim: ``swarm/demo/alive/agent:2``.

Decoding (:func:`decode`) checks, in this order: payload type and size (before unpacking), msgpack
well-formedness (with ``max_*_len`` limits), map, schema version, kind tag, exact field set,
field types (``bool`` is not a number), vector lengths, finiteness, ranges. A rejection raises
:class:`WireDecodeError` (a :class:`zenswarm.errors.DecodeError`) whose ``reason`` is one of
:data:`REASONS`. :class:`Decoder` wraps it for a process loop: it never raises and counts.
"""

from __future__ import annotations

import math
import re
import threading
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar, Final, Union

import msgpack
import numpy as np

from .errors import DecodeError, ZenswarmError

__all__ = [
    "SCHEMA_VERSION",
    "MAX_PAYLOAD",
    "MAX_MISSION_PAYLOAD",
    "MAX_T_NS",
    "MAX_SEQ",
    "MAX_DEPTH",
    "REASONS",
    "KINDS",
    "KEY_KINDS",
    "InvalidKeyError",
    "MessageError",
    "WireDecodeError",
    "Keys",
    "validate_swarm_name",
    "validate_process",
    "agent",
    "process_uav",
    "message_kind",
    "t_ns",
    "t_s",
    "Clock",
    "State",
    "Ref",
    "Cmd",
    "Mission",
    "Diag",
    "Message",
    "encode",
    "decode",
    "Decoder",
]

SCHEMA_VERSION: Final = 1
MAX_PAYLOAD: Final = 64 * 1024
"""Size bound of every payload but a mission, bytes."""
MAX_MISSION_PAYLOAD: Final = 1024 * 1024
"""Size bound of a mission payload, bytes."""
MAX_T_NS: Final = 10 * 86_400 * 1_000_000_000
"""Largest accepted sim time: 10 days, ns."""
MAX_SEQ: Final = 2**63 - 1
MAX_DEPTH: Final = 16
"""Deepest nesting of containers accepted inside ``Mission.scenario`` and ``Diag.info``."""

REASONS: Final = (
    "oversize",  # payload longer than the bound for its kind (checked before unpacking)
    "malformed",  # not bytes, msgpack garbage, trailing bytes, over a max_*_len limit
    "not_map",  # the top-level object is not a map
    "version",  # "v" missing or not SCHEMA_VERSION
    "kind",  # "k" missing or not the expected kind (or an unknown kind was asked for)
    "missing_field",
    "extra_field",
    "type",  # a field has the wrong type (bool is not a number, float is not an int)
    "length",  # a vector does not have 3 elements
    "nonfinite",  # NaN or +-inf anywhere
    "negative",  # t or seq < 0
    "out_of_range",  # t > MAX_T_NS, seq > MAX_SEQ
    "nesting",  # containers nested deeper than MAX_DEPTH (or than msgpack's unpacker allows)
    "value",  # a well-typed value that is not allowed (e.g. an unknown process name)
    "stale",  # Decoder with check_seq: seq not greater than the last accepted on that key
)

KINDS: Final = ("clock", "state", "ref", "cmd", "mission", "diag")
"""Message kinds (the ``"k"`` tag)."""

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
_PROCESS_RE: Final = re.compile(r"(plant|leader|recorder|bridge|supervisor)|agent:([1-9][0-9]{0,8})")
_INDEX_RE: Final = re.compile(r"[1-9][0-9]{0,8}")


class InvalidKeyError(ZenswarmError, ValueError):
    """A swarm name, process name, UAV index or key expression is not valid."""


class MessageError(ZenswarmError, ValueError):
    """A message could not be built or encoded (bad field value, or encoding over the size bound).

    ``field`` names the offending field, ``reason`` is one of :data:`REASONS`.
    """

    def __init__(self, field: str, reason: str, message: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {message} [{reason}]")


class WireDecodeError(DecodeError):
    """A payload was rejected. ``reason`` is one of :data:`REASONS`; ``field`` names the field
    (or is None when the payload as a whole is at fault)."""

    def __init__(self, reason: str, message: str, field: str | None = None) -> None:
        self.reason = reason
        self.field = field
        where = f"{field}: " if field else ""
        super().__init__(f"{reason}: {where}{message}")


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


# --------------------------------------------------------------------------- time


def t_ns(seconds: float) -> int:
    """Seconds -> integer nanoseconds, rounded to nearest (exact for tick multiples such as
    ``k * 0.01``). Raises MessageError for a non-finite input."""
    if not math.isfinite(seconds):
        raise MessageError("t", "nonfinite", f"time {seconds!r} s is not finite")
    return round(seconds * 1e9)


def t_s(t: int) -> float:
    """Integer nanoseconds -> seconds (float)."""
    return t / 1e9


# --------------------------------------------------------------------------- message types

Vec3 = np.ndarray  # float64, shape (3,), read-only inside a message


def _mk_vec3(name: str, value: Any) -> np.ndarray:
    """Copy ``value`` into a read-only float64 (3,) array; MessageError if not finite or wrong shape."""
    if type(value) is np.ndarray and value.dtype is _F64 and value.shape == (3,):  # the usual case, fast
        x, y, z = value.tolist()
        if _isfinite(x + y + z):  # a finite sum means three finite elements (inf - inf is nan)
            a = value.copy()
            a.flags.writeable = False
            return a
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise MessageError(name, "type", f"not a float vector: {e}") from None
    if a.shape != (3,):
        raise MessageError(name, "length", f"expected shape (3,), got {a.shape}")
    x, y, z = a.tolist()
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise MessageError(name, "nonfinite", f"non-finite element in {a.tolist()}")
    a.setflags(write=False)
    return a


_F64: Final = np.dtype(np.float64)
_isfinite: Final = math.isfinite


def _mk_int(name: str, value: Any, hi: int) -> int:
    if type(value) is int and 0 <= value <= hi:  # the usual case, fast
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise MessageError(name, "type", f"expected an int, got {type(value).__name__}")
    v = int(value)
    if v < 0:
        raise MessageError(name, "negative", f"{v} < 0")
    if v > hi:
        raise MessageError(name, "out_of_range", f"{v} > {hi}")
    return v


def _mk_float(name: str, value: Any) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise MessageError(name, "type", f"expected a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise MessageError(name, "nonfinite", f"{v!r} is not finite")
    return v


def _mk_plain(name: str, value: Any, depth: int = 0) -> Any:
    """Deep-copy a nested structure of plain types (None, bool, int, finite float, str, list,
    dict with str keys; tuples become lists, numpy scalars become Python scalars)."""
    if depth > MAX_DEPTH:
        raise MessageError(name, "nesting", f"nested deeper than {MAX_DEPTH}")
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        v = int(value)
        if not -(2**63) <= v < 2**64:
            raise MessageError(name, "out_of_range", f"integer {v} does not fit 64 bits")
        return v
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if not math.isfinite(v):
            raise MessageError(name, "nonfinite", f"{v!r} is not finite")
        return v
    if isinstance(value, (list, tuple)):
        return [_mk_plain(f"{name}[{j}]", x, depth + 1) for j, x in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for k, x in value.items():
            if not isinstance(k, str):
                raise MessageError(name, "type", f"map key {k!r} is not a str")
            out[k] = _mk_plain(f"{name}.{k}", x, depth + 1)
        return out
    raise MessageError(name, "type", f"{type(value).__name__} is not a plain type")


def _set(obj: Any, name: str, value: Any) -> None:
    object.__setattr__(obj, name, value)


class _Msg:
    """Common behaviour: value equality (numpy arrays compared elementwise), unhashable."""

    __slots__ = ()
    kind: ClassVar[str]
    _fields: ClassVar[tuple[str, ...]]

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for f in self._fields:
            a, b = getattr(self, f), getattr(other, f)
            if isinstance(a, np.ndarray):
                if not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, slots=True, eq=False)
class Clock(_Msg):
    """Lockstep tick published by the plant. t: sim time, ns; seq: tick number."""

    t: int
    seq: int
    kind: ClassVar[str] = "clock"
    _fields: ClassVar[tuple[str, ...]] = ("t", "seq")

    def __post_init__(self) -> None:
        _set(self, "t", _mk_int("t", self.t, MAX_T_NS))
        _set(self, "seq", _mk_int("seq", self.seq, MAX_SEQ))

    def _to_wire(self) -> dict[str, Any]:
        return {"v": SCHEMA_VERSION, "k": "clock", "t": self.t, "seq": self.seq}


@dataclass(frozen=True, slots=True, eq=False)
class State(_Msg):
    """State of UAV i (plant -> agent i; eq. (1)-(5)).

    q: (3,) m, ENU position; v: (3,) m/s, ENU velocity; rpy: (3,) rad, roll/pitch/yaw;
    w: (3,) rad/s, body (FLU) angular rate. t: sim time, ns.
    """

    t: int
    seq: int
    q: Vec3
    v: Vec3
    rpy: Vec3
    w: Vec3
    kind: ClassVar[str] = "state"
    _fields: ClassVar[tuple[str, ...]] = ("t", "seq", "q", "v", "rpy", "w")

    def __post_init__(self) -> None:
        _set(self, "t", _mk_int("t", self.t, MAX_T_NS))
        _set(self, "seq", _mk_int("seq", self.seq, MAX_SEQ))
        _set(self, "q", _mk_vec3("q", self.q))
        _set(self, "v", _mk_vec3("v", self.v))
        _set(self, "rpy", _mk_vec3("rpy", self.rpy))
        _set(self, "w", _mk_vec3("w", self.w))

    def _to_wire(self) -> dict[str, Any]:
        return {
            "v": SCHEMA_VERSION,
            "k": "state",
            "t": self.t,
            "seq": self.seq,
            "q": self.q.tolist(),
            "vel": self.v.tolist(),
            "rpy": self.rpy.tolist(),
            "w": self.w.tolist(),
        }


@dataclass(frozen=True, slots=True, eq=False)
class Ref(_Msg):
    """Reference position and velocity: q*_i, v*_i of eqs. (16)-(17) on ``uav/<i>/ref``, or the
    leader's q0, v0 on ``leader/ref``. q: (3,) m, ENU; v: (3,) m/s, ENU; t: sim time, ns."""

    t: int
    seq: int
    q: Vec3
    v: Vec3
    kind: ClassVar[str] = "ref"
    _fields: ClassVar[tuple[str, ...]] = ("t", "seq", "q", "v")

    def __post_init__(self) -> None:
        _set(self, "t", _mk_int("t", self.t, MAX_T_NS))
        _set(self, "seq", _mk_int("seq", self.seq, MAX_SEQ))
        _set(self, "q", _mk_vec3("q", self.q))
        _set(self, "v", _mk_vec3("v", self.v))

    def _to_wire(self) -> dict[str, Any]:
        return {
            "v": SCHEMA_VERSION,
            "k": "ref",
            "t": self.t,
            "seq": self.seq,
            "q": self.q.tolist(),
            "vel": self.v.tolist(),
        }


@dataclass(frozen=True, slots=True, eq=False)
class Cmd(_Msg):
    """Command of agent i to the plant (eq. (28) and the attitude inversion after it).

    thrust: N, collective thrust F; rpy: (3,) rad, desired roll/pitch/yaw; u: (3,) m/s^2,
    virtual control u_i; d_hat: (3,) m/s^2, ESO disturbance estimate (eq. 27); t: sim time, ns.
    """

    t: int
    seq: int
    thrust: float
    rpy: Vec3
    u: Vec3
    d_hat: Vec3
    kind: ClassVar[str] = "cmd"
    _fields: ClassVar[tuple[str, ...]] = ("t", "seq", "thrust", "rpy", "u", "d_hat")

    def __post_init__(self) -> None:
        _set(self, "t", _mk_int("t", self.t, MAX_T_NS))
        _set(self, "seq", _mk_int("seq", self.seq, MAX_SEQ))
        _set(self, "thrust", _mk_float("thrust", self.thrust))
        _set(self, "rpy", _mk_vec3("rpy", self.rpy))
        _set(self, "u", _mk_vec3("u", self.u))
        _set(self, "d_hat", _mk_vec3("d_hat", self.d_hat))

    def _to_wire(self) -> dict[str, Any]:
        return {
            "v": SCHEMA_VERSION,
            "k": "cmd",
            "t": self.t,
            "seq": self.seq,
            "thrust": self.thrust,
            "rpy": self.rpy.tolist(),
            "u": self.u.tolist(),
            "d_hat": self.d_hat.tolist(),
        }


@dataclass(frozen=True, slots=True, eq=False)
class Mission(_Msg):
    """The scenario (e.g. :func:`zenswarm.config.scenario_to_dict`), published by the leader.

    scenario: nested dict of plain types (None, bool, int, finite float, str, list, dict with
    str keys; at most :data:`MAX_DEPTH` levels). Copied on construction; tuples become lists.
    """

    t: int
    seq: int
    scenario: dict[str, Any] = field(default_factory=dict)
    kind: ClassVar[str] = "mission"
    _fields: ClassVar[tuple[str, ...]] = ("t", "seq", "scenario")

    def __post_init__(self) -> None:
        _set(self, "t", _mk_int("t", self.t, MAX_T_NS))
        _set(self, "seq", _mk_int("seq", self.seq, MAX_SEQ))
        if not isinstance(self.scenario, dict):
            raise MessageError("scenario", "type", "expected a dict")
        _set(self, "scenario", _mk_plain("scenario", self.scenario))

    def _to_wire(self) -> dict[str, Any]:
        return {"v": SCHEMA_VERSION, "k": "mission", "t": self.t, "seq": self.seq, "scenario": self.scenario}


@dataclass(frozen=True, slots=True, eq=False)
class Diag(_Msg):
    """Diagnostics of a process: counters (rejected, dropped, late, loop timing in s, ...) and
    free-form info (plain types, like :class:`Mission`). t: sim time, ns."""

    t: int
    seq: int
    process: str
    counters: dict[str, int | float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)
    kind: ClassVar[str] = "diag"
    _fields: ClassVar[tuple[str, ...]] = ("t", "seq", "process", "counters", "info")

    def __post_init__(self) -> None:
        _set(self, "t", _mk_int("t", self.t, MAX_T_NS))
        _set(self, "seq", _mk_int("seq", self.seq, MAX_SEQ))
        try:
            validate_process(self.process)
        except InvalidKeyError as e:
            raise MessageError("process", "value", str(e)) from None
        if not isinstance(self.counters, dict):
            raise MessageError("counters", "type", "expected a dict")
        counters: dict[str, int | float] = {}
        for k, x in self.counters.items():
            if not isinstance(k, str):
                raise MessageError("counters", "type", f"key {k!r} is not a str")
            if isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_)):
                counters[k] = _mk_plain(f"counters.{k}", x)
            else:
                counters[k] = _mk_float(f"counters.{k}", x)
        _set(self, "counters", counters)
        if not isinstance(self.info, dict):
            raise MessageError("info", "type", "expected a dict")
        _set(self, "info", _mk_plain("info", self.info))

    def _to_wire(self) -> dict[str, Any]:
        return {
            "v": SCHEMA_VERSION,
            "k": "diag",
            "t": self.t,
            "seq": self.seq,
            "process": self.process,
            "counters": self.counters,
            "info": self.info,
        }


Message = Union[Clock, State, Ref, Cmd, Mission, Diag]

_LIMIT: Final = MappingProxyType({k: (MAX_MISSION_PAYLOAD if k == "mission" else MAX_PAYLOAD) for k in KINDS})


# --------------------------------------------------------------------------- encode


_tls = threading.local()  # one msgpack.Packer per thread (a Packer is not thread-safe), for encode


def encode(msg: Message) -> bytes:
    """Pack a message into msgpack bytes (floats as float64). Raises MessageError if the
    result is over the size bound for its kind (:data:`MAX_PAYLOAD`, missions
    :data:`MAX_MISSION_PAYLOAD`), so nothing is sent that every decoder would reject."""
    try:
        to_wire = msg._to_wire
    except AttributeError:
        raise MessageError("msg", "type", f"{type(msg).__name__} is not a wire message") from None
    packer = getattr(_tls, "packer", None)
    if packer is None:
        packer = _tls.packer = msgpack.Packer(use_bin_type=True)
    data: bytes = packer.pack(to_wire())
    if len(data) > _LIMIT[msg.kind]:
        raise MessageError("msg", "oversize", f"{len(data)} bytes > {_LIMIT[msg.kind]} for {msg.kind}")
    return data


# --------------------------------------------------------------------------- decode

_FIELDS: Final = MappingProxyType({
    "clock": frozenset({"v", "k", "t", "seq"}),
    "state": frozenset({"v", "k", "t", "seq", "q", "vel", "rpy", "w"}),
    "ref": frozenset({"v", "k", "t", "seq", "q", "vel"}),
    "cmd": frozenset({"v", "k", "t", "seq", "thrust", "rpy", "u", "d_hat"}),
    "mission": frozenset({"v", "k", "t", "seq", "scenario"}),
    "diag": frozenset({"v", "k", "t", "seq", "process", "counters", "info"}),
})


def _d_int(obj: dict[str, Any], name: str, hi: int) -> int:
    x = obj[name]
    if type(x) is not int:
        raise WireDecodeError("type", f"expected an int, got {type(x).__name__}", name)
    if x < 0:
        raise WireDecodeError("negative", f"{x} < 0", name)
    if x > hi:
        raise WireDecodeError("out_of_range", f"{x} > {hi}", name)
    return x


def _d_float(obj: dict[str, Any], name: str) -> float:
    x = obj[name]
    tx = type(x)
    if tx is float:
        if not math.isfinite(x):
            raise WireDecodeError("nonfinite", f"{x!r}", name)
        return x
    if tx is int:
        return float(x)
    raise WireDecodeError("type", f"expected a number, got {tx.__name__}", name)


_NUM_TYPES: Final = frozenset({float, int})


def _d_vecs(obj: dict[str, Any], *names: str) -> np.ndarray:
    """Validate the named fields as arrays of 3 finite numbers; one read-only (n, 3) float64
    array whose rows are the vectors (one numpy call for all of them: decode runs ~10 kHz)."""
    flat: list[Any] = []
    for name in names:
        x = obj[name]
        if type(x) is not list or len(x) != 3:
            break
        flat += x
    else:
        # every field a list of 3: fast path when all elements are floats or ints with a finite
        # sum (which means each is finite); anything else is judged element by element below
        try:
            if _NUM_TYPES.issuperset(map(type, flat)) and _isfinite(sum(flat)):
                a = np.array(flat, dtype=np.float64)
                a.flags.writeable = False
                return a.reshape(len(names), 3)
        except OverflowError:  # an int too large for a float
            pass
    flat = []
    for name in names:
        x = obj[name]
        if type(x) is not list:
            raise WireDecodeError("type", f"expected an array of 3 numbers, got {type(x).__name__}", name)
        if len(x) != 3:
            raise WireDecodeError("length", f"expected 3 elements, got {len(x)}", name)
        for e in x:
            te = type(e)
            if te is float:
                if not math.isfinite(e):
                    raise WireDecodeError("nonfinite", f"element {e!r}", name)
            elif te is not int:
                raise WireDecodeError("type", f"element of type {te.__name__} is not a number", name)
        flat += x
    a = np.array(flat, dtype=np.float64)
    a.setflags(write=False)
    return a.reshape(len(names), 3)


def _d_plain(name: str, x: Any, depth: int) -> None:
    """Check a decoded nested structure: plain msgpack types only, finite floats, str map keys."""
    if depth > MAX_DEPTH:
        raise WireDecodeError("nesting", f"nested deeper than {MAX_DEPTH}", name)
    tx = type(x)
    if tx is float:
        if not math.isfinite(x):
            raise WireDecodeError("nonfinite", f"{x!r}", name)
    elif tx is list:
        for e in x:
            _d_plain(name, e, depth + 1)
    elif tx is dict:
        for k, e in x.items():
            if type(k) is not str:
                raise WireDecodeError("type", f"map key {k!r} is not a str", name)
            _d_plain(name, e, depth + 1)
    elif not (x is None or tx is bool or tx is int or tx is str):
        raise WireDecodeError("type", f"{tx.__name__} is not a plain type", name)


def _new(cls: type, names: tuple[str, ...], values: tuple[Any, ...]) -> Any:
    """Build a message from already validated values, skipping __post_init__."""
    obj = _object_new(cls)
    for k, v in zip(names, values):
        _object_setattr(obj, k, v)
    return obj


_object_new: Final = object.__new__
_object_setattr: Final = object.__setattr__


def _unpack(kind: str, payload: bytes) -> dict[str, Any]:
    limit = _LIMIT.get(kind)
    if limit is None:
        raise WireDecodeError("kind", f"unknown message kind {kind!r}; expected one of {KINDS}")
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise WireDecodeError("malformed", f"payload is {type(payload).__name__}, not bytes")
    n = payload.nbytes if isinstance(payload, memoryview) else len(payload)
    if n > limit:
        raise WireDecodeError("oversize", f"{n} bytes > {limit} for {kind}")
    try:
        obj = msgpack.unpackb(
            payload,
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_str_len=n,
            max_bin_len=n,
            max_array_len=n,
            max_map_len=n,
            max_ext_len=n,
        )
    except msgpack.StackError:
        raise WireDecodeError("nesting", "nested deeper than msgpack's unpacker allows") from None
    except Exception as e:  # msgpack raises ValueError, its own exception types, UnicodeDecodeError...
        raise WireDecodeError("malformed", f"not msgpack ({type(e).__name__}: {e})") from None
    if type(obj) is not dict:
        raise WireDecodeError("not_map", f"top-level object is {type(obj).__name__}, not a map")
    if "v" not in obj:
        raise WireDecodeError("version", "missing schema version", "v")
    ver = obj["v"]
    if type(ver) is not int or ver != SCHEMA_VERSION:
        raise WireDecodeError("version", f"schema version {ver!r}, expected {SCHEMA_VERSION}", "v")
    if "k" not in obj:
        raise WireDecodeError("kind", "missing kind tag", "k")
    if obj["k"] != kind:
        raise WireDecodeError("kind", f"kind tag {obj['k']!r}, expected {kind!r}", "k")
    expected = _FIELDS[kind]
    if obj.keys() != expected:
        missing = expected - obj.keys()
        if missing:
            raise WireDecodeError("missing_field", f"missing {sorted(missing)}", sorted(missing)[0])
        extra = sorted(map(repr, obj.keys() - expected))
        raise WireDecodeError("extra_field", f"unexpected {', '.join(extra)}", extra[0])
    return obj


def decode(kind: str, payload: bytes) -> Message:
    """Decode and validate a payload of the given kind (one of :data:`KINDS`).

    payload: bytes-like (``sample.payload.to_bytes()``). Raises :class:`WireDecodeError` (a
    :class:`zenswarm.errors.DecodeError`) with ``reason`` in :data:`REASONS`. Work is bounded:
    size is checked before unpacking, msgpack lengths are capped by the payload size, nesting by
    msgpack's and :data:`MAX_DEPTH`. Returned vectors are read-only float64 (3,) arrays.
    """
    o = _unpack(kind, payload)
    t = _d_int(o, "t", MAX_T_NS)
    seq = _d_int(o, "seq", MAX_SEQ)
    if kind == "state":
        q, v, rpy, w = _d_vecs(o, "q", "vel", "rpy", "w")
        return _new(State, State._fields, (t, seq, q, v, rpy, w))
    if kind == "ref":
        q, v = _d_vecs(o, "q", "vel")
        return _new(Ref, Ref._fields, (t, seq, q, v))
    if kind == "cmd":
        thrust = _d_float(o, "thrust")
        rpy, u, d_hat = _d_vecs(o, "rpy", "u", "d_hat")
        return _new(Cmd, Cmd._fields, (t, seq, thrust, rpy, u, d_hat))
    if kind == "clock":
        return _new(Clock, Clock._fields, (t, seq))
    if kind == "mission":
        sc = o["scenario"]
        if type(sc) is not dict:
            raise WireDecodeError("type", f"expected a map, got {type(sc).__name__}", "scenario")
        _d_plain("scenario", sc, 0)
        return _new(Mission, Mission._fields, (t, seq, sc))
    # diag
    process = o["process"]
    if type(process) is not str:
        raise WireDecodeError("type", f"expected a str, got {type(process).__name__}", "process")
    if _PROCESS_RE.fullmatch(process) is None:
        raise WireDecodeError("value", f"unknown process name {process!r}", "process")
    counters = o["counters"]
    if type(counters) is not dict:
        raise WireDecodeError("type", f"expected a map, got {type(counters).__name__}", "counters")
    for k, x in counters.items():
        tx = type(x)
        if type(k) is not str:
            raise WireDecodeError("type", f"key {k!r} is not a str", "counters")
        if tx is float:
            if not math.isfinite(x):
                raise WireDecodeError("nonfinite", f"{k}={x!r}", "counters")
        elif tx is not int:
            raise WireDecodeError("type", f"{k} is {tx.__name__}, not a number", "counters")
    info = o["info"]
    if type(info) is not dict:
        raise WireDecodeError("type", f"expected a map, got {type(info).__name__}", "info")
    _d_plain("info", info, 0)
    return _new(Diag, Diag._fields, (t, seq, process, counters, info))


class Decoder:
    """Never-raising decoder for a process loop; counts what it rejects.

    ``rejects``: key -> number of rejected payloads (at most ``max_keys`` distinct keys; the
    rest are counted under ``"<other>"``); ``reasons``: reason -> count; ``accepted``: count.
    With ``check_seq`` a payload whose seq is not greater than the last accepted on the same
    key is rejected as ``"stale"`` (call :meth:`forget` when a publisher restarts).
    Not thread-safe: use one Decoder per thread.
    """

    OTHER: ClassVar[str] = "<other>"

    def __init__(self, *, check_seq: bool = False, max_keys: int = 1024) -> None:
        self.check_seq = check_seq
        self.max_keys = max_keys
        self.accepted = 0
        self.rejects: dict[str, int] = {}
        self.reasons: dict[str, int] = {}
        self.last_error: str | None = None
        self._last_seq: dict[str, int] = {}

    def decode(self, key: str, kind: str, payload: bytes) -> Message | None:
        """Decoded message, or None (counted under ``key`` and the reason) if rejected."""
        try:
            key = str(key)
            msg = decode(kind, payload)
            if self.check_seq:
                last = self._last_seq.get(key)
                if last is not None and msg.seq <= last:
                    raise WireDecodeError("stale", f"seq {msg.seq} <= last accepted {last}", "seq")
                if last is not None or len(self._last_seq) < self.max_keys:
                    self._last_seq[key] = msg.seq
        except WireDecodeError as e:
            self._reject(key, e.reason, str(e))
            return None
        except Exception as e:  # noqa: BLE001 - the contract is: never raise into the loop
            self._reject(str(key) if isinstance(key, str) else self.OTHER, "malformed", f"{type(e).__name__}: {e}")
            return None
        self.accepted += 1
        return msg

    def _reject(self, key: str, reason: str, text: str) -> None:
        if key not in self.rejects and len(self.rejects) >= self.max_keys:
            key = self.OTHER
        self.rejects[key] = self.rejects.get(key, 0) + 1
        self.reasons[reason] = self.reasons.get(reason, 0) + 1
        self.last_error = f"{key}: {text}"

    def forget(self, key: str | None = None) -> None:
        """Drop the last-seq memory of ``key`` (or of every key), e.g. after a publisher restart."""
        if key is None:
            self._last_seq.clear()
        else:
            self._last_seq.pop(str(key), None)

    @property
    def rejected(self) -> int:
        """Total rejected payloads."""
        return sum(self.reasons.values())

    def counters(self) -> dict[str, int]:
        """Flat counters for :class:`Diag`: ``decoded``, ``rejected``, ``rejected.<reason>``."""
        out = {"decoded": self.accepted, "rejected": self.rejected}
        for r, n in self.reasons.items():
            out[f"rejected.{r}"] = n
        return out

"""Wire protocol of the swarm bus: key expressions, message types, msgpack codec.

Pure: msgspec, numpy and the standard library only (no zenoh). Every payload is a msgpack map
that carries the schema version ``"v"`` and a kind tag ``"k"``; ``t`` is sim time in integer
nanoseconds and ``seq`` a non-negative integer. Vectors are float64 ``(3,)`` arrays, SI units,
inertial frame ENU (z up). Floats are packed as msgpack float64, so they round-trip bit-exactly.

Each message is defined once, as a typed :class:`msgspec.Struct` (:class:`Clock`, :class:`State`,
:class:`Ref`, :class:`Cmd`, :class:`Mission`, :class:`Diag`): its field types (:data:`TimeNs`,
:data:`Seq`, :data:`Number`, :data:`Vec3`, :data:`Process`, :data:`PlainMap`, :data:`Counters`)
carry both the wire constraints msgspec checks when decoding and the checks a Python constructor
runs; the encoder, the decoder and the header fields ``v`` and ``k`` are derived from them.

Wire layout (``v`` is always :data:`SCHEMA_VERSION`; velocity travels as ``"vel"`` because
``"v"`` is the version; fields are packed in this order)::

    clock    {v, k:"clock",   t, seq}
    state    {v, k:"state",   t, seq, q[3], vel[3], rpy[3], w[3] [, ts] [, x{name: [float...]}]}
    ref      {v, k:"ref",     t, seq, q[3], vel[3] [, x{name: [float...]}]}   uav/<i>/ref, leader/ref
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

Decoding (:func:`decode`) first checks the kind asked for, the payload type and its size (before
unpacking); msgspec then decodes the map straight into the message type, checking msgpack
well-formedness (lengths against the payload), the map, and each field as it comes: schema
version, kind tag, field types (``bool`` is not a number, an int is accepted for a float), vector
lengths, finiteness, ranges, then the exact field set (missing or unknown fields). The first
offending field in payload order is the one reported. Nested maps (``scenario``, ``info``) are
then checked for plain types, finiteness and depth. A rejection raises :class:`WireDecodeError`
(a :class:`zenswarm.errors.DecodeError`) whose ``reason`` is one of :data:`REASONS`.
:class:`Decoder` wraps it for a process loop: it never raises and counts.
"""

from __future__ import annotations

import inspect
import math
import re
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import (
    TYPE_CHECKING,
    Annotated,
    Any,
    ClassVar,
    Final,
    Literal,
    TypeAlias,
    cast,
    overload,
)

import msgspec
import numpy as np
import numpy.typing as npt
from msgspec import Meta, Struct, StructMeta

from zenswarm.errors import DecodeError, ZenswarmError

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
    "TimeNs",
    "Seq",
    "Number",
    "Vec3",
    "Process",
    "PlainMap",
    "Counters",
    "Extra",
    "MAX_EXTRA",
    "encode",
    "encode_state",
    "encode_ref",
    "encode_cmd",
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
MAX_EXTRA: Final = 64
"""Most extra quantities a plug-in's reference (:attr:`Ref.extra`) carries."""
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


# --------------------------------------------------------------------------- constructor checks
# A message built in Python (``State(t=..., q=array, ...)``) is checked and normalised by these,
# raising MessageError; a decoded payload is checked by msgspec against the same field types.


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


def _mk_t(name: str, value: Any) -> int:
    return _mk_int(name, value, MAX_T_NS)


def _mk_stamp(name: str, value: Any) -> int | None:
    """None (absent), or a signed time in ns within +-MAX_T_NS (a measurement before the
    mission's start is negative)."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise MessageError(name, "type", f"expected an int or None, got {type(value).__name__}")
    v = int(value)
    if not -MAX_T_NS <= v <= MAX_T_NS:
        raise MessageError(name, "out_of_range", f"|{v}| > {MAX_T_NS}")
    return v


def _mk_seq(name: str, value: Any) -> int:
    return _mk_int(name, value, MAX_SEQ)


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
        f = float(value)
        if not math.isfinite(f):
            raise MessageError(name, "nonfinite", f"{f!r} is not finite")
        return f
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


def _mk_extra(name: str, value: Any) -> dict[str, tuple[float, ...]]:
    """A plug-in's extra shared quantities: str -> flat sequence (or array) of finite numbers,
    stored as tuples of float64 (what the wire carries)."""
    if not isinstance(value, Mapping):
        raise MessageError(name, "type", "expected a mapping of str to sequences of numbers")
    if len(value) > MAX_EXTRA:
        raise MessageError(name, "length", f"at most {MAX_EXTRA} extra quantities, got {len(value)}")
    out: dict[str, tuple[float, ...]] = {}
    for k, x in value.items():
        if not isinstance(k, str):
            raise MessageError(name, "type", f"key {k!r} is not a str")
        flat = np.asarray(x).reshape(-1) if isinstance(x, np.ndarray) else x
        if not isinstance(flat, (list, tuple, np.ndarray)):
            raise MessageError(f"{name}.{k}", "type", "expected a sequence of numbers")
        out[k] = tuple(_mk_float(f"{name}.{k}[{j}]", e) for j, e in enumerate(flat))
    return out


def _mk_pos(name: str, value: Any) -> tuple[float, ...]:
    """A sender's position stamp: 3 finite numbers, or none (no stamp)."""
    flat = np.asarray(value).reshape(-1) if isinstance(value, np.ndarray) else value
    if not isinstance(flat, (list, tuple, np.ndarray)):
        raise MessageError(name, "type", "expected 3 numbers (or none)")
    if len(flat) not in (0, 3):
        raise MessageError(name, "length", f"expected 3 numbers (or none), got {len(flat)}")
    return tuple(_mk_float(f"{name}[{j}]", e) for j, e in enumerate(flat))


def _d_pos(name: str, x: Any, depth: int) -> None:
    """Check a decoded position stamp: 0 or 3 numbers (msgspec checked they are finite)."""
    if len(x) not in (0, 3):
        raise WireDecodeError("length", f"expected 3 numbers (or none), got {len(x)}", name)


def _mk_map(name: str, value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise MessageError(name, "type", "expected a dict")
    out: dict[str, Any] = _mk_plain(name, value)
    return out


def _mk_process(name: str, value: Any) -> str:
    try:
        return validate_process(value)
    except InvalidKeyError as e:
        raise MessageError(name, "value", str(e)) from None


def _mk_counters(name: str, value: Any) -> dict[str, int | float]:
    if not isinstance(value, dict):
        raise MessageError(name, "type", "expected a dict")
    out: dict[str, int | float] = {}
    for k, x in value.items():
        if not isinstance(k, str):
            raise MessageError(name, "type", f"key {k!r} is not a str")
        if isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_)):
            n: int = _mk_plain(f"{name}.{k}", x)
            out[k] = n
        else:
            out[k] = _mk_float(f"{name}.{k}", x)
    return out


# --------------------------------------------------------------------------- decode-side checks
# What msgspec's types cannot say: the nested plain maps of Mission.scenario and Diag.info.


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


# --------------------------------------------------------------------------- field types


@dataclass(frozen=True)
class _Check:
    """Annotated metadata of a field type: ``make(name, value)`` checks and normalises a value
    given to a constructor (raising MessageError); ``post(name, value, 0)`` checks a decoded value
    beyond what msgspec checked (raising WireDecodeError); ``default`` makes the constructor
    argument optional (the payload field is always required)."""

    make: Callable[[str, Any], Any]
    post: Callable[[str, Any, int], None] | None = None
    default: Callable[[], Any] | None = None


_FMAX: Final = sys.float_info.max
_Finite = Annotated[float, Meta(ge=-_FMAX, le=_FMAX)]  # NaN fails both bounds, +-inf one of them
TimeNs = Annotated[int, Meta(ge=0, le=MAX_T_NS), _Check(_mk_t)]
"""Sim time, integer ns in [0, MAX_T_NS]."""
Stamp = Annotated[Annotated[int, Meta(ge=-MAX_T_NS, le=MAX_T_NS)] | None, _Check(_mk_stamp, None, lambda: None)]
"""An optional signed time, integer ns in [-MAX_T_NS, MAX_T_NS], or None (left out of the payload)."""
Seq = Annotated[int, Meta(ge=0, le=MAX_SEQ), _Check(_mk_seq)]
"""Sequence number in [0, MAX_SEQ]."""
Number = Annotated[float, Meta(ge=-_FMAX, le=_FMAX), _Check(_mk_float)]
"""Finite float64 (an int on the wire is accepted, bool is not)."""
Process = Annotated[str, Meta(pattern=r"\A(?:plant|leader|recorder|bridge|supervisor|agent:[1-9][0-9]{0,8})\Z"),
                    _Check(_mk_process)]
"""A process name (see :func:`validate_process`)."""
PlainMap = Annotated[dict[str, Any], _Check(_mk_map, _d_plain, dict)]
"""Nested plain types: None, bool, int, finite float, str, list, dict with str keys, <= MAX_DEPTH deep."""
Counters = Annotated[dict[str, int | _Finite], _Check(_mk_counters, None, dict)]
"""str -> int or finite float."""
Extra = Annotated[dict[str, tuple[_Finite, ...]], Meta(max_length=MAX_EXTRA), _Check(_mk_extra, None, dict)]
"""A plug-in's extra shared quantities: str -> flat tuple of finite float64 (at most MAX_EXTRA keys)."""
Pos = Annotated[tuple[_Finite, ...], Meta(max_length=3), _Check(_mk_pos, _d_pos, tuple)]
"""A position stamp: 3 finite float64 (m, ENU), or the empty tuple (no stamp)."""
if TYPE_CHECKING:
    Vec3: TypeAlias = npt.NDArray[np.float64]
else:
    Vec3 = Annotated[tuple[_Finite, _Finite, _Finite], _Check(_mk_vec3)]
"""A vector: 3 finite float64 on the wire; a read-only float64 (3,) array in a message."""


# --------------------------------------------------------------------------- message types


class _MsgMeta(StructMeta):
    """Metaclass of the wire messages. For a class with a ``kind`` it adds the header fields
    ``schema`` (wire ``"v"``, ``Literal[SCHEMA_VERSION]``) and ``tag`` (wire ``"k"``,
    ``Literal[kind]``) in front of the declared ones, so the payload carries them first and a
    decoder requires both; it derives from the field types what a constructor checks, which fields
    are vectors and the decoder; and it makes calling the class a checked construction (positional
    or keyword arguments in declaration order, MessageError for a bad value)."""

    def __new__(mcls, name: str, bases: tuple[type, ...], ns: dict[str, Any], **kw: Any) -> Any:
        kind = ns.get("kind")
        if kind is not None:
            ns["__annotations__"] = {
                "schema": Literal[SCHEMA_VERSION],
                "tag": Literal[kind],
                **ns.get("__annotations__", {}),
            }
            ns["schema"] = msgspec.field(name="v")
            ns["tag"] = msgspec.field(name="k")
        cls: Any = super().__new__(mcls, name, bases, ns, **kw)
        if kind is not None:
            checks = {f.name: next(m for m in f.type.__metadata__ if isinstance(m, _Check))
                      for f in msgspec.structs.fields(cls)[2:]}
            cls._args = tuple(checks)
            cls._checks = checks
            cls._makes = tuple((n, c.make) for n, c in checks.items())
            vec_names = [n for n, c in checks.items() if c.make is _mk_vec3]
            cls._vecs = tuple((n, slice(3 * j, 3 * j + 3)) for j, n in enumerate(vec_names))
            cls._posts = tuple((n, c.post) for n, c in checks.items() if c.post is not None)
            cls._decoder = msgspec.msgpack.Decoder(cls)
            cls._sig = inspect.Signature([  # what calling the class takes (see __call__)
                inspect.Parameter(f.name, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                  default=inspect.Parameter.empty if checks[f.name].default is None else {})
                for f in msgspec.structs.fields(cls)[2:]
            ])
        return cls

    @property
    def __signature__(cls) -> inspect.Signature:
        sig = cls.__dict__.get("_sig")
        return sig if sig is not None else cast(inspect.Signature, StructMeta.__signature__.__get__(cls))

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        cls: Any = self
        if args:
            if len(args) > len(cls._args):
                raise TypeError(f"{cls.__name__} takes at most {len(cls._args)} positional arguments")
            for k, x in zip(cls._args, args, strict=False):  # fewer positional arguments than fields is fine
                if k in kwargs:
                    raise TypeError(f"{cls.__name__}: argument {k!r} given twice")
                kwargs[k] = x
        if len(kwargs) != len(cls._args):  # an optional argument left out, or an unknown one
            unknown = kwargs.keys() - cls._checks.keys()
            if unknown:
                raise TypeError(f"{cls.__name__}: unexpected argument {min(unknown)!r}")
            for k, c in cls._checks.items():
                if k not in kwargs:
                    if c.default is None:
                        raise TypeError(f"{cls.__name__}: missing argument {k!r}")
                    kwargs[k] = c.default()
        vals = {k: make(k, kwargs[k]) for k, make in cls._makes}
        return super().__call__(schema=SCHEMA_VERSION, tag=cls.kind, **vals)


class _Msg(Struct, metaclass=_MsgMeta, frozen=True, eq=False, kw_only=True, forbid_unknown_fields=True):
    """Common behaviour: value equality (numpy arrays compared elementwise), unhashable, frozen."""

    kind: ClassVar[str]
    _args: ClassVar[tuple[str, ...]]
    _checks: ClassVar[dict[str, _Check]]
    _makes: ClassVar[tuple[tuple[str, Callable[[str, Any], Any]], ...]]
    _vecs: ClassVar[tuple[tuple[str, slice], ...]]
    _posts: ClassVar[tuple[tuple[str, Callable[[str, Any, int], None]], ...]]
    _decoder: ClassVar[msgspec.msgpack.Decoder[Any]]

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for f in self._args:
            a, b = getattr(self, f), getattr(other, f)
            if isinstance(a, np.ndarray):
                if not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]


class Clock(_Msg, frozen=True):
    """Lockstep tick published by the plant. t: sim time, ns; seq: tick number."""

    kind: ClassVar[str] = "clock"
    t: TimeNs
    seq: Seq


class State(_Msg, frozen=True, omit_defaults=True):
    """State of UAV i (plant -> agent i; eq. (1)-(5)).

    q: (3,) m, ENU position; v: (3,) m/s, ENU velocity (wire ``"vel"``); rpy: (3,) rad,
    roll/pitch/yaw; w: (3,) rad/s, body (FLU) angular rate. t: sim time, ns (the tick).
    stamp (wire ``"ts"``, optional): when the vehicle measured q and v, on the same mission
    clock as t, ns, signed (the MAVLink bridge: the vehicle's ``time_boot_ms`` mapped through
    the TIMESYNC clock offset), so ``t - stamp`` is the state's age by the vehicle's clock;
    None (left out of the payload) when the publisher has no such clock (the simulated plant:
    its states are exact at t).
    extra (wire ``"x"``, optional): what the plant model records with this state
    (:attr:`zenswarm.plant.api.PlantModel.records`), name -> flat float64 values (row-major);
    left out of the payload when empty (a model that records nothing, a real vehicle's bridge).
    """

    kind: ClassVar[str] = "state"
    t: TimeNs
    seq: Seq
    q: Vec3
    v: Vec3 = msgspec.field(name="vel")
    rpy: Vec3
    w: Vec3
    stamp: Stamp = msgspec.field(default=None, name="ts")
    extra: Extra = msgspec.field(default_factory=dict, name="x")


class Ref(_Msg, frozen=True, omit_defaults=True):
    """Reference position and velocity: q*_i, v*_i of eqs. (16)-(17) on ``uav/<i>/ref``, or the
    leader's q0, v0 on ``leader/ref``. q: (3,) m, ENU; v: (3,) m/s, ENU (wire ``"vel"``);
    t: sim time, ns. extra (wire ``"x"``, optional): a controller plug-in's other shared
    quantities (:attr:`zenswarm.agents.api.Controller.shares`), name -> flat float64 values;
    left out of the payload when empty (the paper's controller shares none). pos (wire ``"p"``,
    optional): the sender's true position (m, ENU; its plant's state of the tick it sent this on),
    stamped only when a radio model is active (:mod:`zenswarm.link.radio`); left out when empty."""

    kind: ClassVar[str] = "ref"
    t: TimeNs
    seq: Seq
    q: Vec3
    v: Vec3 = msgspec.field(name="vel")
    extra: Extra = msgspec.field(default_factory=dict, name="x")
    pos: Pos = msgspec.field(default_factory=tuple, name="p")


class Cmd(_Msg, frozen=True):
    """Command of agent i to the plant (eq. (28) and the attitude inversion after it).

    thrust: N, collective thrust F; rpy: (3,) rad, desired roll/pitch/yaw; u: (3,) m/s^2,
    virtual control u_i; d_hat: (3,) m/s^2, ESO disturbance estimate (eq. 27); t: sim time, ns.
    """

    kind: ClassVar[str] = "cmd"
    t: TimeNs
    seq: Seq
    thrust: Number
    rpy: Vec3
    u: Vec3
    d_hat: Vec3


class Mission(_Msg, frozen=True):
    """The scenario (e.g. :func:`zenswarm.scenario.config.scenario_to_dict`), published by the leader.

    scenario: nested dict of plain types (None, bool, int, finite float, str, list, dict with
    str keys; at most :data:`MAX_DEPTH` levels). Copied on construction; tuples become lists.
    Optional for the constructor (default ``{}``), required in a payload.
    """

    kind: ClassVar[str] = "mission"
    t: TimeNs
    seq: Seq
    scenario: PlainMap


class Diag(_Msg, frozen=True):
    """Diagnostics of a process: counters (rejected, dropped, late, loop timing in s, ...) and
    free-form info (plain types, like :class:`Mission`). t: sim time, ns. counters and info are
    optional for the constructor (default ``{}``), required in a payload."""

    kind: ClassVar[str] = "diag"
    t: TimeNs
    seq: Seq
    process: Process
    counters: Counters
    info: PlainMap


Message = Clock | State | Ref | Cmd | Mission | Diag

_CLASSES: Final[Mapping[str, type[_Msg]]] = MappingProxyType({c.kind: c for c in (Clock, State, Ref, Cmd, Mission, Diag)})
_LIMIT: Final = MappingProxyType({k: (MAX_MISSION_PAYLOAD if k == "mission" else MAX_PAYLOAD) for k in KINDS})


# --------------------------------------------------------------------------- encode


def _enc_hook(obj: Any) -> Any:
    if type(obj) is np.ndarray:  # a vector of a message: float64 (3,)
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not a wire type")


_encoder: Final = msgspec.msgpack.Encoder(enc_hook=_enc_hook)  # thread-safe


def encode(msg: Message) -> bytes:
    """Pack a message into msgpack bytes (floats as float64). Raises MessageError if the
    result is over the size bound for its kind (:data:`MAX_PAYLOAD`, missions
    :data:`MAX_MISSION_PAYLOAD`), so nothing is sent that every decoder would reject."""
    if not isinstance(msg, _Msg):
        raise MessageError("msg", "type", f"{type(msg).__name__} is not a wire message")
    data = _encoder.encode(msg)
    if len(data) > _LIMIT[msg.kind]:
        raise MessageError("msg", "oversize", f"{len(data)} bytes > {_LIMIT[msg.kind]} for {msg.kind}")
    return data


# --------------------------------------------------------------------------- encode, hot paths
# The swarm's per-tick messages are encoded straight from their fields: the same bytes as
# ``encode(State(...))`` (tests/test_wire.py checks it), without building the message (a
# constructor copies and checks every vector, then the encoder calls back into Python for each
# one). The checks are the constructor's, done at once on the plain floats: when a field is not a
# float64 (3,) array, a float or an int in range, or a value is not finite, the checked path runs
# (the same bytes, or the constructor's MessageError).

_plain_encoder: Final = msgspec.msgpack.Encoder()


def _floats3(x: Any) -> list[float] | None:
    """``x`` as a list of 3 Python floats if it is a float64 (3,) array, else None."""
    if type(x) is np.ndarray and x.dtype is _F64 and x.shape == (3,):
        return x.tolist()  # type: ignore[no-any-return]
    return None


def _ok_t_seq(t: Any, seq: Any) -> bool:
    return type(t) is int and 0 <= t <= MAX_T_NS and type(seq) is int and 0 <= seq <= MAX_SEQ


def encode_state(
    t: int, seq: int, q: Vec3, v: Vec3, rpy: Vec3, w: Vec3, extra: Mapping[str, list[float]] | None = None
) -> bytes:
    """``encode(State(t=t, seq=seq, q=q, v=v, rpy=rpy, w=w, extra=extra))``, the same bytes,
    faster (the plant's states: one per UAV per tick). No ``stamp``. ``extra``: name -> list of
    Python floats (what the plant model records; None or empty: none). Raises MessageError as the
    constructor."""
    a, b, c, d = _floats3(q), _floats3(v), _floats3(rpy), _floats3(w)
    if a is not None and b is not None and c is not None and d is not None and _ok_t_seq(t, seq) \
            and _isfinite(sum(a) + sum(b) + sum(c) + sum(d)):  # finite sum: every element finite
        if not extra:
            return _plain_encoder.encode({"v": SCHEMA_VERSION, "k": "state", "t": t, "seq": seq,
                                          "q": a, "vel": b, "rpy": c, "w": d})
        if _plain_extra(extra):
            return _plain_encoder.encode({"v": SCHEMA_VERSION, "k": "state", "t": t, "seq": seq,
                                          "q": a, "vel": b, "rpy": c, "w": d, "x": extra})
    return encode(State(t=t, seq=seq, q=q, v=v, rpy=rpy, w=w, extra=cast(Any, extra or {})))


def _plain_extra(extra: Mapping[str, Any]) -> bool:
    """``extra`` is what the constructor would keep unchanged: at most MAX_EXTRA str keys, each
    a list of Python floats whose sum is finite (so every one is)."""
    if type(extra) is not dict or len(extra) > MAX_EXTRA:
        return False
    for k, x in extra.items():
        if type(k) is not str or type(x) is not list or not all(type(e) is float for e in x) or not _isfinite(sum(x)):
            return False
    return True


def encode_ref(t: int, seq: int, q: Vec3, v: Vec3) -> bytes:
    """``encode(Ref(t=t, seq=seq, q=q, v=v))`` (no ``extra``, no ``pos``), the same bytes, faster
    (an agent's reference, the leader's). Raises MessageError as the constructor."""
    a, b = _floats3(q), _floats3(v)
    if a is not None and b is not None and _ok_t_seq(t, seq) and _isfinite(sum(a) + sum(b)):
        return _plain_encoder.encode({"v": SCHEMA_VERSION, "k": "ref", "t": t, "seq": seq, "q": a, "vel": b})
    return encode(Ref(t=t, seq=seq, q=q, v=v))


def encode_cmd(t: int, seq: int, thrust: float, rpy: Vec3, u: Vec3, d_hat: Vec3) -> bytes:
    """``encode(Cmd(t=t, seq=seq, thrust=thrust, rpy=rpy, u=u, d_hat=d_hat))``, the same bytes,
    faster (an agent's command). Raises MessageError as the constructor."""
    a, b, c = _floats3(rpy), _floats3(u), _floats3(d_hat)
    if type(thrust) is np.float64:
        thrust = float(thrust)  # the same float64
    if a is not None and b is not None and c is not None and type(thrust) is float and _ok_t_seq(t, seq) \
            and _isfinite(thrust + sum(a) + sum(b) + sum(c)):
        return _plain_encoder.encode({"v": SCHEMA_VERSION, "k": "cmd", "t": t, "seq": seq,
                                      "thrust": thrust, "rpy": a, "u": b, "d_hat": c})
    return encode(Cmd(t=t, seq=seq, thrust=thrust, rpy=rpy, u=u, d_hat=d_hat))


# --------------------------------------------------------------------------- decode

_PATH_FIELD: Final = re.compile(r"- at `\$\.([^`\[]+)")
_QUOTED: Final = re.compile(r"`([^`]*)`")


def _reason(text: str) -> tuple[str, str | None]:
    """(reason, field) of a msgspec ValidationError message (field: its wire name)."""
    m = _PATH_FIELD.search(text)
    if text.startswith(("Object missing required field", "Object contains unknown field")):
        field = _QUOTED.search(text).group(1)  # type: ignore[union-attr]
        reason = "missing_field" if text.startswith("Object missing") else "extra_field"
    elif m is None:  # about the payload as a whole: a map key that is not a str, or not a map
        return ("malformed" if "at `key` in `$`" in text else "not_map"), None
    else:
        field = m.group(1)
        if " of length " in text:
            reason = "length"
        elif text.startswith(("Expected `float` >=", "Expected `float` <=")):
            reason = "nonfinite"  # only NaN and +-inf fail the bounds of a finite float
        elif text.startswith("Expected `int` >= 0"):
            reason = "negative"
        elif text.startswith(("Expected `int` <=", "Expected `int` >= -")):
            reason = "out_of_range"
        elif "matching regex" in text:
            reason = "value"
        else:
            reason = "type"
    return {"v": "version", "k": "kind"}.get(field, reason), field


def _whole_payload(payload: Any, text: str) -> WireDecodeError:
    """The error of a payload that is not a map: garbage or too deep inside it is told first."""
    try:
        msgspec.msgpack.decode(payload)
    except RecursionError:
        return WireDecodeError("nesting", "nested deeper than the decoder allows")
    except msgspec.DecodeError as e:
        return WireDecodeError("malformed", f"not msgpack ({e})")
    return WireDecodeError("not_map", f"top-level object is not a map ({text})")


def _check_payload(kind: str, payload: Any) -> type[_Msg]:
    """Class of ``kind``; WireDecodeError for an unknown kind, a non-bytes or oversize payload."""
    cls = _CLASSES.get(kind)
    if cls is None:
        raise WireDecodeError("kind", f"unknown message kind {kind!r}; expected one of {KINDS}")
    tp = type(payload)
    if tp is bytes or tp is bytearray:
        n = len(payload)
    elif tp is memoryview:
        n = payload.nbytes
    else:
        raise WireDecodeError("malformed", f"payload is {tp.__name__}, not bytes")
    if n > _LIMIT[kind]:
        raise WireDecodeError("oversize", f"{n} bytes > {_LIMIT[kind]} for {kind}")
    return cls


@overload
def decode(kind: Literal["clock"], payload: bytes | bytearray | memoryview) -> Clock: ...
@overload
def decode(kind: Literal["state"], payload: bytes | bytearray | memoryview) -> State: ...
@overload
def decode(kind: Literal["ref"], payload: bytes | bytearray | memoryview) -> Ref: ...
@overload
def decode(kind: Literal["cmd"], payload: bytes | bytearray | memoryview) -> Cmd: ...
@overload
def decode(kind: Literal["mission"], payload: bytes | bytearray | memoryview) -> Mission: ...
@overload
def decode(kind: Literal["diag"], payload: bytes | bytearray | memoryview) -> Diag: ...
@overload
def decode(kind: str, payload: bytes | bytearray | memoryview) -> Message: ...
def decode(kind: str, payload: bytes | bytearray | memoryview) -> Message:
    """Decode and validate a payload of the given kind (one of :data:`KINDS`).

    payload: bytes-like (``sample.payload.to_bytes()``). Raises :class:`WireDecodeError` (a
    :class:`zenswarm.errors.DecodeError`) with ``reason`` in :data:`REASONS`. Work is bounded:
    size is checked before unpacking, msgpack lengths are checked against the payload, nesting by
    the decoder's recursion limit and :data:`MAX_DEPTH`. Returned vectors are read-only float64
    (3,) arrays.
    """
    cls = _check_payload(kind, payload)
    try:
        msg: Any = cls._decoder.decode(payload)
    except msgspec.ValidationError as e:
        text = str(e)
        reason, field = _reason(text)
        if reason == "not_map":
            raise _whole_payload(payload, text) from None
        raise WireDecodeError(reason, text, field) from None
    except msgspec.DecodeError as e:
        raise WireDecodeError("malformed", f"not msgpack ({e})") from None
    except RecursionError:
        raise WireDecodeError("nesting", "nested deeper than the decoder allows") from None
    vecs = cls._vecs
    if vecs:  # the tuples msgspec checked -> read-only float64 (3,) views of one array
        flat: tuple[float, ...] = ()
        for n, _ in vecs:
            flat += getattr(msg, n)
        a = _fromiter(flat, _F64, len(flat))
        a.setflags(write=False)
        for n, sl in vecs:
            _force_setattr(msg, n, a[sl])
    for n, post in cls._posts:
        post(n, getattr(msg, n), 0)
    return msg  # type: ignore[no-any-return]


_force_setattr: Final = msgspec.structs.force_setattr
_fromiter: Final = np.fromiter


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

    @overload
    def decode(self, key: str, kind: Literal["clock"], payload: bytes) -> Clock | None: ...
    @overload
    def decode(self, key: str, kind: Literal["state"], payload: bytes) -> State | None: ...
    @overload
    def decode(self, key: str, kind: Literal["ref"], payload: bytes) -> Ref | None: ...
    @overload
    def decode(self, key: str, kind: Literal["cmd"], payload: bytes) -> Cmd | None: ...
    @overload
    def decode(self, key: str, kind: Literal["mission"], payload: bytes) -> Mission | None: ...
    @overload
    def decode(self, key: str, kind: Literal["diag"], payload: bytes) -> Diag | None: ...
    @overload
    def decode(self, key: str, kind: str, payload: bytes) -> Message | None: ...
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

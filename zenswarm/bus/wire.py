"""Wire protocol of the swarm bus: the message types and their msgpack codec.

Pure: msgspec, numpy and the standard library only (no zenoh). Every payload is a msgpack map
that carries the schema version ``"v"`` and a kind tag ``"k"``; ``t`` is sim time in integer
nanoseconds and ``seq`` a non-negative integer. Vectors are float64 ``(3,)`` arrays, SI units,
inertial frame ENU (z up). Floats are packed as msgpack float64, so they round-trip bit-exactly.

Each message is defined once, as a typed :class:`msgspec.Struct` (:class:`Clock`, :class:`State`,
:class:`Ref`, :class:`Cmd`, :class:`Mission`, :class:`Diag`): its field types (:data:`TimeNs`,
:data:`Seq`, :data:`Number`, :data:`Vec3`, :data:`Process`, :data:`PlainMap`, :data:`Counters`;
they, their checks and bounds, the errors and :func:`t_ns` are in :mod:`zenswarm.bus.fields`)
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

The keys these messages travel on (:class:`Keys`, the process names) are the key space,
:mod:`zenswarm.bus.keys`.

Decoding (:func:`decode`) first checks the kind asked for, the payload type and its size (before
unpacking); msgspec then decodes the map straight into the message type, checking msgpack
well-formedness (lengths against the payload), the map, and each field as it comes: schema
version, kind tag, field types (``bool`` is not a number, an int is accepted for a float), vector
lengths, finiteness, ranges, then the exact field set (missing or unknown fields). The first
offending field in payload order is the one reported. Nested maps (``scenario``, ``info``) are
then checked for plain types, finiteness and depth. A rejection raises :class:`WireDecodeError`
(a :class:`zenswarm.errors.DecodeError`) whose ``reason`` is one of :data:`REASONS`.
:class:`Decoder` wraps it for a process loop: it never raises and counts.

This module re-exports the key space (:mod:`zenswarm.bus.keys`) and the field types
(:mod:`zenswarm.bus.fields`): ``zenswarm.bus.wire.Keys``, ``zenswarm.bus.wire.t_ns``, ... are the
same objects.
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any, ClassVar, Final, Literal, cast, overload

import msgspec
import numpy as np
from msgspec import Struct, StructMeta

from zenswarm.bus.fields import (
    _F64,
    MAX_DEPTH,
    MAX_EXTRA,
    MAX_SEQ,
    MAX_T_NS,
    Counters,
    Extra,
    MessageError,
    Number,
    PlainMap,
    Pos,
    Process,
    Seq,
    Stamp,
    TimeNs,
    Vec3,
    WireDecodeError,
    _Check,
    _isfinite,
    _mk_vec3,
    t_ns,
    t_s,
)
from zenswarm.bus.keys import (
    KEY_KINDS,
    InvalidKeyError,
    Keys,
    agent,
    message_kind,
    process_uav,
    validate_process,
    validate_swarm_name,
)

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

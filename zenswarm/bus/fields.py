"""Field types of the wire messages (:mod:`zenswarm.bus.wire`): what each field may hold.

Pure: msgspec, numpy and the standard library only (no zenoh). A field type (:data:`TimeNs`,
:data:`Seq`, :data:`Number`, :data:`Vec3`, :data:`Process`, :data:`PlainMap`, :data:`Counters`,
:data:`Extra`, ...) is an ``Annotated`` type that carries both sides of one check: the
:class:`msgspec.Meta` constraints msgspec checks when decoding a payload, and a :class:`_Check`
with what a Python constructor runs (``_mk_*``: check and normalise, raising :class:`MessageError`)
and what a decoder runs after msgspec (``_d_*``: what msgspec's types cannot say, such as the nested
plain maps, raising :class:`WireDecodeError`). Here too the bounds (:data:`MAX_T_NS`,
:data:`MAX_SEQ`, :data:`MAX_EXTRA`, :data:`MAX_DEPTH`), the two errors and sim time in integer
nanoseconds (:func:`t_ns`, :func:`t_s`). :mod:`zenswarm.bus.wire` builds the messages from these
types and re-exports every public name here.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, Final, TypeAlias

import numpy as np
import numpy.typing as npt
from msgspec import Meta

from zenswarm.bus.keys import PROCESS_PATTERN, InvalidKeyError, validate_process
from zenswarm.errors import DecodeError, ZenswarmError

__all__ = [
    "MAX_T_NS",
    "MAX_SEQ",
    "MAX_EXTRA",
    "MAX_DEPTH",
    "MessageError",
    "WireDecodeError",
    "t_ns",
    "t_s",
    "TimeNs",
    "Stamp",
    "Seq",
    "Number",
    "Vec3",
    "Process",
    "PlainMap",
    "Counters",
    "Extra",
    "Pos",
]

MAX_T_NS: Final = 10 * 86_400 * 1_000_000_000
"""Largest accepted sim time: 10 days, ns."""
MAX_SEQ: Final = 2**63 - 1
MAX_EXTRA: Final = 64
"""Most extra quantities a plug-in's reference (:attr:`zenswarm.bus.wire.Ref.extra`) carries."""
MAX_DEPTH: Final = 16
"""Deepest nesting of containers accepted inside ``Mission.scenario`` and ``Diag.info``."""


class MessageError(ZenswarmError, ValueError):
    """A message could not be built or encoded (bad field value, or encoding over the size bound).

    ``field`` names the offending field, ``reason`` is one of :data:`zenswarm.bus.wire.REASONS`.
    """

    def __init__(self, field: str, reason: str, message: str) -> None:
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {message} [{reason}]")


class WireDecodeError(DecodeError):
    """A payload was rejected. ``reason`` is one of :data:`zenswarm.bus.wire.REASONS`; ``field``
    names the field (or is None when the payload as a whole is at fault)."""

    def __init__(self, reason: str, message: str, field: str | None = None) -> None:
        self.reason = reason
        self.field = field
        where = f"{field}: " if field else ""
        super().__init__(f"{reason}: {where}{message}")


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
Process = Annotated[str, Meta(pattern=rf"\A(?:{PROCESS_PATTERN})\Z"), _Check(_mk_process)]
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

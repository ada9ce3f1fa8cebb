"""Quantities of the link model: durations and probabilities as a scenario or a command line writes
them (``"50ms"``, ``0.2`` or ``"20%"``), and the tick a delayed message lands on in lockstep.
"""

from __future__ import annotations

import math
import re

__all__ = ["EPS_TICK", "parse_duration", "parse_loss", "delivery_tick"]

EPS_TICK = 1e-9
"""A delay of exactly n ticks (``n * dt`` up to rounding) lands on tick n, not n + 1."""

_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_DUR_RE = re.compile(rf"^\s*(?P<num>{_NUM})\s*(?P<unit>ns|us|µs|ms|s|min)?\s*$")
_UNIT_S = {"ns": 1e-9, "us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0, "min": 60.0}


def parse_duration(text: str) -> float:
    """``"50ms"``, ``"1.5s"``, ``"200us"``, ``"0"`` -> seconds (float >= 0).

    Units: ns, us (or µs), ms, s, min. A bare number is accepted only for zero. Raises ValueError
    naming the bad text.
    """
    if not isinstance(text, str):
        raise ValueError(f"invalid duration {text!r}: expected a string such as '50ms'")
    m = _DUR_RE.match(text)
    if not m:
        if text.strip().startswith("-"):
            raise ValueError(f"invalid duration {text!r}: must be >= 0")
        raise ValueError(f"invalid duration {text!r}: expected a number with a unit (ns, us, ms, s, min), e.g. '50ms'")
    value = float(m.group("num"))
    unit = m.group("unit")
    if unit is None:
        if value != 0.0:
            raise ValueError(f"invalid duration {text!r}: missing unit (ns, us, ms, s, min), e.g. '{m.group('num')}ms'")
        return 0.0
    s = value * _UNIT_S[unit]
    if not math.isfinite(s):
        raise ValueError(f"invalid duration {text!r}: not finite")
    return s


def parse_loss(text: str | float | int) -> float:
    """A probability in [0, 1]: ``0.2``, ``"0.2"`` or ``"20%"``. Raises ValueError naming the bad text."""
    if isinstance(text, bool):
        raise ValueError(f"invalid loss {text!r}: expected a probability in [0, 1]")
    if isinstance(text, (int, float)):
        p = float(text)
    elif isinstance(text, str):
        t = text.strip()
        try:
            p = float(t[:-1]) / 100.0 if t.endswith("%") else float(t)
        except ValueError:
            raise ValueError(f"invalid loss {text!r}: expected a probability in [0, 1] such as 0.2 or 20%") from None
    else:
        raise ValueError(f"invalid loss {text!r}: expected a probability in [0, 1]")
    if not (0.0 <= p <= 1.0):  # also rejects NaN
        raise ValueError(f"invalid loss {text!r}: must be in [0, 1]")
    return p


def delivery_tick(send_tick: int, delay_s: float, dt: float) -> int:
    """First tick at which a message of ``send_tick`` with ``delay_s`` is available:
    ``send_tick + ceil(delay_s / dt - 1e-9)`` (0 delay: the same tick; 50 ms at dt 10 ms: +5)."""
    if not dt > 0:
        raise ValueError(f"dt must be > 0, got {dt!r}")
    return int(send_tick) + max(0, math.ceil(delay_s / dt - EPS_TICK))

"""Radio links: delivery that depends on the distance between sender and receiver.

Pure (numpy and the standard library only; no zenoh, no files, no clock). The link-fault model of
:mod:`zenswarm.link.decisions` decides a message's fate from (seed, link, tick); a :class:`RadioModel` on a
link adds a decision that also depends on the *geometry*: the distance ``d`` (m) between the
sender's and the receiver's true positions. Two models, combinable with each other and with the
independent and Gilbert-Elliott losses, delays and partitions of :mod:`zenswarm.link.decisions`:

* **hard range** ``range_m``: a message with ``d > range_m`` is dropped (reason ``range``);
* **logistic fall-off** ``fade_50_m``, ``fade_width_m``: delivered with probability
  ``p(d) = 1 / (1 + exp((d - fade_50_m) / fade_width_m))``: 50 % at ``fade_50_m``, 73 % / 27 %
  one width inside / outside it, 98 % / 2 % at four widths (the smooth version of a range, as
  used for packet-reception-rate curves of low-power radios). Dropped with reason ``fade`` when
  ``u < 1 - p(d)``, ``u`` the link's uniform of stream ``radio`` at the message's sequence number
  (:meth:`zenswarm.link.decisions.FaultState.uniform`: counter-based, so a decision is a pure function of
  (seed, link, tick, d)).

No distance-dependent latency: propagation over the tens of metres of a formation takes
nanoseconds, and the extra latency a real radio shows at long range comes from retries and
queueing, which these models do not simulate (the links' ``delay``/``jitter`` stay as configured).

Which links are radio
---------------------
Only the links between vehicles and the leader: ``ref`` (``agent:j -> agent:i``) and ``leader``
(``leader -> agent:i``), :data:`RADIO_KINDS`. The ``state`` and ``cmd`` links join an agent and
its own vehicle's autopilot (on board, a wire or a serial line): a radio model never applies to
them. The leader is a virtual vehicle: it is modelled as a transmitter that flies the virtual
leader's path ``q0`` (a lead vehicle, or a ground station that tracks it); to exempt its link
give the ``leader`` kind its own ``[[faults.links]]`` entry with ``range = "inf"``.

Which positions, at which tick
------------------------------
A position is the plant's true position of a UAV as the plant publishes it (``uav/<i>/state``,
raw, before any fault of the state link), and the virtual leader's ``q0``.

* ``ref`` of tick k (the generator's (q*_j, v*_j)_k) is computed and sent at the end of tick
  k - 1, right after the state of tick k - 1: its geometry is the *send* tick ``k - 1``:
  ``d = |q_j(k-1) - q_i(k-1)|``. The sender stamps its position (the state of tick k - 1 it
  received from its plant) on the message (wire field ``p`` of ``ref``, present only when a radio
  model is active, so the paper's bytes are unchanged otherwise); the receiver uses its own state
  of tick k - 1. The simulator uses the plant's states of tick k - 1.
* ``leader`` of tick k carries q0_k itself: ``d = |q0_k - q_i(k)|``, the receiver using its own
  state of tick k.
* Tick 0 (the start-up exchange) is never faulted (:class:`zenswarm.link.swarm.Box`).

In lockstep a receiver therefore decides a radio link's message once it has the message and its
own state of the geometry tick (it waits for both anyway); in realtime it decides on receipt with
the newest own state it has (the wall clock applies the same model, approximately).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "RADIO_KINDS",
    "GEOMETRY_TICK_OFFSET",
    "RadioModel",
    "parse_distance",
    "parse_fade",
    "drop_probability",
    "radio_reason",
    "components",
    "leader_reaches_all",
]

#: Message kinds a radio model applies to (see the module docstring).
RADIO_KINDS: tuple[str, ...] = ("ref", "leader")

#: Geometry tick of a message of tick k: ``k + GEOMETRY_TICK_OFFSET[kind]``.
GEOMETRY_TICK_OFFSET: dict[str, int] = {"ref": -1, "leader": 0}

_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_DIST_RE = re.compile(rf"^\s*(?P<sign>[+-]?)(?P<num>{_NUM})\s*(?P<unit>mm|cm|m|km)?\s*$")
_UNIT_M = {"mm": 1e-3, "cm": 1e-2, "m": 1.0, "km": 1e3, None: 1.0}


def parse_distance(text: str | float | int, *, allow_inf: bool = True) -> float:
    """``"1.5m"``, ``"150cm"``, ``"2km"``, ``1.5`` (metres), ``"inf"`` -> metres, > 0.

    Raises ValueError naming the bad text (zero, negative, NaN or malformed)."""
    if isinstance(text, bool):
        raise ValueError(f"invalid distance {text!r}: expected metres such as '1.5m'")
    if isinstance(text, (int, float)):
        v = float(text)
    elif isinstance(text, str):
        if text.strip() in ("inf", "infinity") and allow_inf:
            return math.inf
        m = _DIST_RE.match(text)
        if not m:
            raise ValueError(f"invalid distance {text!r}: expected a number with a unit (mm, cm, m, km), e.g. '1.5m'")
        v = float(m.group("num")) * _UNIT_M[m.group("unit")]
        if m.group("sign") == "-":
            v = -v
    else:
        raise ValueError(f"invalid distance {text!r}: expected metres such as '1.5m'")
    if math.isnan(v) or v <= 0.0:
        raise ValueError(f"invalid distance {text!r}: must be > 0")
    if math.isinf(v) and not allow_inf:
        raise ValueError(f"invalid distance {text!r}: must be finite")
    return v


def parse_fade(text: str) -> tuple[float, float]:
    """``"R50,WIDTH"`` (e.g. ``"1.2m,0.1m"``) -> (fade_50_m, fade_width_m); ValueError naming the text."""
    if not isinstance(text, str) or text.count(",") != 1:
        raise ValueError(f"invalid fade {text!r}: expected R50,WIDTH such as '1.2m,0.1m'")
    a, _, b = text.partition(",")
    return parse_distance(a, allow_inf=False), parse_distance(b, allow_inf=False)


@dataclass(frozen=True)
class RadioModel:
    """Geometry-dependent delivery of one directed link (see the module docstring).

    range_m: hard range, m, > 0 (inf: none). fade_50_m: 50 % range of the logistic fall-off,
    m, > 0 (inf: no fall-off); fade_width_m: its width, m, > 0 (used when fade_50_m is finite).
    """

    range_m: float = math.inf
    fade_50_m: float = math.inf
    fade_width_m: float = 1.0

    def __post_init__(self) -> None:
        for name in ("range_m", "fade_50_m", "fade_width_m"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v) or v <= 0.0:
                raise ValueError(f"{name} must be a number > 0, got {v!r}")
            object.__setattr__(self, name, float(v))
        if math.isinf(self.fade_width_m):
            raise ValueError(f"fade_width_m must be finite, got {self.fade_width_m!r}")

    @property
    def active(self) -> bool:
        """False when no distance drops a message (no range, no fall-off)."""
        return math.isfinite(self.range_m) or math.isfinite(self.fade_50_m)

    @property
    def uses_uniform(self) -> bool:
        """True when decisions draw the ``radio`` stream (a fall-off is set)."""
        return math.isfinite(self.fade_50_m)

    def __str__(self) -> str:
        parts = []
        if math.isfinite(self.range_m):
            parts.append(f"range {self.range_m:g} m")
        if math.isfinite(self.fade_50_m):
            parts.append(f"fade 50% at {self.fade_50_m:g} m, width {self.fade_width_m:g} m")
        return ", ".join(parts) or "no radio model"


def drop_probability(model: RadioModel, d: Any) -> Any:
    """Probability that a message over distance ``d`` (m, scalar or array) is dropped:
    1 beyond the range, else ``1 - p(d)`` of the logistic fall-off (0 without one)."""
    x = np.asarray(d, dtype=float)
    if math.isfinite(model.fade_50_m):
        z = np.clip((x - model.fade_50_m) / model.fade_width_m, -700.0, 700.0)
        q = 1.0 / (1.0 + np.exp(-z))
    else:
        q = np.zeros_like(x)
    q = np.where(x > model.range_m, 1.0, q)
    return float(q) if np.ndim(q) == 0 else q


def radio_reason(model: RadioModel, d: float, u: float) -> str | None:
    """The radio's verdict on one message: ``"range"`` (``d > range_m``), ``"fade"`` (``u`` <
    the fall-off's drop probability) or None (delivered as far as the radio goes). ``d``: m;
    ``u``: the link's uniform of stream ``radio`` at the message's sequence number, [0, 1)."""
    if not math.isfinite(d):
        return "range"
    if d > model.range_m:
        return "range"
    if math.isfinite(model.fade_50_m):
        q = drop_probability(model, d)
        if u < q:
            return "fade"
    return None


# ----------------------------------------------------------------------------------------------
# the effective graph


def components(n_nodes: int, edges: list[tuple[int, int]]) -> int:
    """Connected components of an undirected graph on nodes 0..n_nodes-1 (union-find)."""
    parent = list(range(n_nodes))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in edges:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
    return sum(1 for a in range(n_nodes) if find(a) == a)


def leader_reaches_all(n_agents: int, edges: list[tuple[int, int]]) -> bool:
    """Is there a directed spanning tree rooted at the leader (Lemma 1)? Nodes: 0 the leader,
    1..n the agents; ``edges`` (src, dst) directed (dst hears src)."""
    out: dict[int, list[int]] = {}
    for a, b in edges:
        out.setdefault(a, []).append(b)
    seen = {0}
    stack = [0]
    while stack:
        a = stack.pop()
        for b in out.get(a, ()):
            if b not in seen:
                seen.add(b)
                stack.append(b)
    return len(seen) == n_agents + 1

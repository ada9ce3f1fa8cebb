"""Trace replay: per-link delay and delivery read from a CSV file, applied in place of the model.

Pure apart from :func:`load_trace` (which reads the file); numpy and the standard library.

Format
------
A CSV file with the header ``time,link,delay,delivered`` and one row per sample::

    # measured on the bench, 2024-05-01   (lines starting with # and blank lines are ignored)
    time,link,delay,delivered
    0.0,agent:1->agent:2,0.012,1
    0.5,agent:1->agent:2,0.030,0
    0.0,leader->agent:1,0.004,1

* ``time``: seconds of sim time since the start, a finite number >= 0; non-decreasing down the
  file (rows of different links interleave freely; one link may not have two rows at the same time).
* ``link``: a directed link ``src->dst`` named as in :mod:`zenswarm.link.names` (``plant``,
  ``leader``, ``agent:<i>``); the message kind follows from the two ends (``agent->agent``:
  ``ref``, ``leader->agent``: ``leader``, ``plant->agent``: ``state``, ``agent->plant``: ``cmd``).
  It must be a link of the scenario's graph (:func:`LinkTrace.check_links`).
* ``delay``: seconds, a finite number >= 0.
* ``delivered``: ``1`` (delivered after ``delay``) or ``0`` (dropped).

Semantics
---------
A message sent at ``t_send`` on a traced link takes the row *in force* at ``t_send``: the last row
of that link with ``time <= t_send``; before a link's first row its first row applies, after its
last row the last row holds (no looping). On a traced link the trace replaces the model's delay,
jitter, independent and burst loss (a dropped message reports reason ``trace``); timed partitions
and the link's capacity queue (:mod:`zenswarm.link.queue`) still apply. Untraced links keep the
model. Everything is a pure function of (trace, link, t_send), so the simulator and the lockstep
swarm agree bit for bit.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.link.names import link_kind, parse_process

__all__ = ["HEADER", "LinkTrace", "parse_trace", "load_trace"]

HEADER = ("time", "link", "delay", "delivered")

Link = tuple[str, str, str]


@dataclass(frozen=True, eq=False)
class LinkTrace:
    """Parsed trace: ``rows[(src, dst, kind)] = (time_s (m,), delay_s (m,), delivered (m,) bool)``,
    times strictly increasing per link. ``name``: where it came from (for messages)."""

    rows: dict[Link, tuple[np.ndarray, np.ndarray, np.ndarray]]
    name: str = "trace"
    _lines: dict[Link, int] = field(default_factory=dict, repr=False)

    def __contains__(self, link: object) -> bool:
        return link in self.rows

    @property
    def links(self) -> list[Link]:
        return list(self.rows)

    def lookup(self, link: Link, t_send_s: float) -> tuple[float, bool]:
        """(delay_s, delivered) of the row in force at ``t_send_s`` on ``link`` (which must be traced)."""
        t, d, ok = self.rows[link]
        i = max(0, int(np.searchsorted(t, float(t_send_s), side="right")) - 1)
        return float(d[i]), bool(ok[i])

    def lookup_batch(self, link: Link, t_send_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`lookup` over send times (m,): (delay_s (m,), delivered (m,) bool)."""
        t, d, ok = self.rows[link]
        i = np.maximum(0, np.searchsorted(t, np.asarray(t_send_s, dtype=float), side="right") - 1)
        return d[i], ok[i]

    def max_delay_s(self, link: Link) -> float:
        """Largest delay of ``link``'s rows (0 if untraced)."""
        r = self.rows.get(link)
        return 0.0 if r is None else float(r[1].max())

    def check_links(self, existing: Iterable[Link]) -> None:
        """Raise :class:`ScenarioError` naming the CSV line of the first row whose link is not
        one of ``existing`` (the scenario's links)."""
        have = set(existing)
        for link in self.rows:
            if link not in have:
                line = self._lines.get(link, 0)
                raise ScenarioError(
                    f"{self.name}:{line}",
                    f"link {link[0]}->{link[1]} does not exist in the scenario's graph "
                    f"({'no such UAV' if not _uavs_exist(link, have) else 'not a link of the graph or pinning'})",
                )


def _uavs_exist(link: Link, have: set[Link]) -> bool:
    names = {x for lk in have for x in lk[:2]}
    return link[0] in names and link[1] in names


def _number(name: str, line: int, col: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ScenarioError(f"{name}:{line}", f"{col} {text!r} is not a number") from None
    if not math.isfinite(v):
        raise ScenarioError(f"{name}:{line}", f"{col} {text!r} is not finite")
    if v < 0:
        raise ScenarioError(f"{name}:{line}", f"{col} {text!r} must be >= 0")
    return v


def parse_trace(text: str, name: str = "trace") -> LinkTrace:
    """Parse the CSV ``text`` (see the module docstring). ``name`` (the file's name) prefixes
    errors: :class:`ScenarioError` with field ``NAME:LINE`` (1-based line of the file)."""
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise ScenarioError(name, f"empty trace: expected the header {','.join(HEADER)} and at least one row")
    hline, htext = lines[0]
    header = tuple(c.strip().lower() for c in next(csv.reader(io.StringIO(htext))))
    if header != HEADER:
        raise ScenarioError(f"{name}:{hline}", f"bad header {htext.strip()!r}: expected {','.join(HEADER)}")
    if len(lines) < 2:
        raise ScenarioError(f"{name}:{hline}", "the trace has a header but no rows")
    acc: dict[Link, list[tuple[float, float, bool]]] = {}
    first_line: dict[Link, int] = {}
    last_t = -math.inf
    for line, ln in lines[1:]:
        cells = [c.strip() for c in next(csv.reader(io.StringIO(ln)))]
        if len(cells) != 4:
            raise ScenarioError(f"{name}:{line}", f"expected 4 columns ({','.join(HEADER)}), got {len(cells)}")
        ts, lk, ds, ok = cells
        t = _number(name, line, "time", ts)
        if t < last_t:
            raise ScenarioError(f"{name}:{line}", f"time {ts} is before the previous row's {last_t:g}: times must not decrease")
        last_t = t
        if "->" not in lk:
            raise ScenarioError(f"{name}:{line}", f"link {lk!r}: expected src->dst, e.g. agent:1->agent:2")
        a, _, b = lk.partition("->")
        try:
            src, dst = parse_process(a), parse_process(b)
            kind = link_kind(src, dst)
        except ValueError as e:
            raise ScenarioError(f"{name}:{line}", f"link {lk!r}: {e}") from None
        d = _number(name, line, "delay", ds)
        if ok not in ("0", "1"):
            raise ScenarioError(f"{name}:{line}", f"delivered {ok!r} must be 0 or 1")
        key = (src, dst, kind)
        rows = acc.setdefault(key, [])
        first_line.setdefault(key, line)
        if rows and rows[-1][0] == t:
            raise ScenarioError(f"{name}:{line}", f"a second row for {src}->{dst} at time {ts}")
        rows.append((t, d, ok == "1"))
    out = {
        k: (np.array([r[0] for r in v]), np.array([r[1] for r in v]), np.array([r[2] for r in v], dtype=bool)) for k, v in acc.items()
    }
    return LinkTrace(out, name, first_line)


def load_trace(path: str | Path, name: str | None = None) -> LinkTrace:
    """Read and parse a trace file; ``name`` (default: the path as given) prefixes errors.
    Raises :class:`ScenarioError` when it cannot be read or is malformed."""
    p = Path(path)
    label = str(path) if name is None else name
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ScenarioError(label, f"trace file not found: {p}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ScenarioError(label, f"cannot read trace {p}: {e}") from None
    return parse_trace(text, label)

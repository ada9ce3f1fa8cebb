"""The statistics of a campaign per parameter cell (all inputs but the seed).

:func:`summarize` gives one :class:`CellStats` per cell of a
:class:`zenswarm.bridge.reports.sweep_campaign.Campaign`. Conventions: crashed runs (``error`` not null)
are counted on their own and left out of every rate and metric. The success rate of a cell is k/n
over its finished runs, with the 95 % Wilson score interval (:func:`wilson_interval`). The
formation error is the verdict's ``max_formation_error_m`` (the vehicles', docs/verdict.md).
Clearances are the minima over the cell's runs of ``min_obstacle_clearance_m`` and
``min_inter_uav_distance_m`` (raw distances from the UAV centres).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenswarm.bridge.reports.sweep_campaign import CLEARANCE, FORMATION, SEPARATION, Campaign, _cell_keys, _num, _sort_key

__all__ = ["Z95", "CellStats", "wilson_interval", "summarize"]

Z95 = 1.959963984540054
"""The standard normal quantile of 0.975: a two-sided 95 % interval."""


# =========================================================================== the interval


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion: k successes out of n trials.

    With p = k/n::

        centre    = (p + z^2 / (2 n)) / (1 + z^2 / n)
        halfwidth = z / (1 + z^2 / n) * sqrt(p (1 - p) / n + z^2 / (4 n^2))
        interval  = [centre - halfwidth, centre + halfwidth]

    (Wilson 1927; Newcombe 1998, method 3). z = :data:`Z95` gives 95 %. Unlike p +- z sqrt(p(1-p)/n)
    it stays inside [0, 1] and is not empty at k = 0 or k = n: there the bounds are
    [0, z^2 / (n + z^2)] and [n / (n + z^2), 1]. n = 0 gives [0, 1] (nothing known).
    Raises ValueError unless 0 <= k <= n.
    """
    if n < 0 or successes < 0 or successes > n:
        raise ValueError(f"wilson_interval: need 0 <= successes <= n, got {successes}/{n}")
    if n == 0:
        return 0.0, 1.0
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2.0 * n)) / denom
    half = z / denom * math.sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n))
    # at k = 0 (k = n) the bound is 0 (1) exactly: no rounding below (above) the observed rate
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return lo, hi


# =========================================================================== per cell


@dataclass
class CellStats:
    """The runs of one parameter cell (all inputs but the seed).

    values: the cell's value of each axis (campaign order). runs: rows in the table; crashed:
    rows with an error; finished = runs - crashed; successes among the finished. rate = k/n over
    the finished runs (None when none finished), ci its 95 % Wilson interval. formation: the
    finished runs' ``max_formation_error_m`` (nulls left out), m. min_clearance, min_separation:
    the minima of ``min_obstacle_clearance_m`` and ``min_inter_uav_distance_m``, m (None when not
    measured). causes: failure cause -> number of failed finished runs that name it.
    """

    key: str
    values: tuple[Any, ...]
    runs: int = 0
    crashed: int = 0
    successes: int = 0
    formation: list[float] = field(default_factory=list)
    min_clearance: float | None = None
    min_separation: float | None = None
    causes: Counter[str] = field(default_factory=Counter)

    @property
    def finished(self) -> int:
        return self.runs - self.crashed

    @property
    def rate(self) -> float | None:
        return self.successes / self.finished if self.finished else None

    @property
    def ci(self) -> tuple[float, float] | None:
        return wilson_interval(self.successes, self.finished) if self.finished else None

    @property
    def median_formation(self) -> float | None:
        return float(np.median(self.formation)) if self.formation else None

    @property
    def worst_formation(self) -> float | None:
        return max(self.formation) if self.formation else None


def _min(a: float | None, b: float | None) -> float | None:
    return b if a is None else a if b is None else min(a, b)


def _causes(v: Any) -> list[str]:
    if not v:
        return []
    return sorted({c.strip() for c in str(v).split(",") if c.strip()})


def summarize(c: Campaign) -> list[CellStats]:
    """One :class:`CellStats` per parameter cell that has rows, sorted by the axes' values."""
    keys = _cell_keys(c)
    crashed = c.crashed()
    success, causes = c.column("success"), c.column("causes")
    ferr, clear, sep = c.column(FORMATION), c.column(CLEARANCE), c.column(SEPARATION)
    cells: dict[str, CellStats] = {}
    for i, k in enumerate(keys):
        cs = cells.get(k)
        if cs is None:
            cs = cells[k] = CellStats(k, tuple(c.columns[a.path][i] for a in c.axes))
        cs.runs += 1
        if crashed[i]:
            cs.crashed += 1
            continue
        if success[i] is True:
            cs.successes += 1
        else:
            cs.causes.update(_causes(causes[i]) or ["(none given)"])
        f = _num(ferr[i])
        if f is not None:
            cs.formation.append(f)
        cs.min_clearance = _min(cs.min_clearance, _num(clear[i]))
        cs.min_separation = _min(cs.min_separation, _num(sep[i]))
    return sorted(cells.values(), key=lambda s: (tuple(_sort_key(a, v) for a, v in zip(c.axes, s.values, strict=True)), s.key))


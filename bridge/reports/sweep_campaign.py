"""A campaign directory of ``zenswarm sweep``, loaded: what ``zenswarm sweep report`` reads.

:func:`load_campaign` reads ``DIR/campaign.json`` (its ``axes``: :class:`Axis`, a grid axis or a
sampled field) and ``DIR/runs.parquet`` (docs/campaigns.md) into a :class:`Campaign`: the table as
columns of Python values, one row per run. A run *crashed* when its ``error`` is not null (the run
raised instead of being judged). The cell of a row (all inputs but the seed) and the order of an
axis' values are here too; the statistics per cell are :mod:`zenswarm.bridge.reports.sweep_stats`,
the plots :mod:`zenswarm.bridge.reports.sweep_figures`, the report
:mod:`zenswarm.bridge.reports.sweep_report`.

pyarrow is imported inside the function that reads the table: this module imports without it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm.errors import CampaignError

__all__ = ["CAMPAIGN_VERSION", "FORMATION", "CLEARANCE", "SEPARATION", "Axis", "Campaign", "load_campaign"]

CAMPAIGN_VERSION = 1
"""The ``version`` of campaign.json this module reads."""

# the columns of runs.parquet the statistics and the plots read (the verdict's, docs/verdict.md)
FORMATION = "max_formation_error_m"
CLEARANCE = "min_obstacle_clearance_m"
SEPARATION = "min_inter_uav_distance_m"


# =========================================================================== the campaign


@dataclass(frozen=True)
class Axis:
    """One swept input of campaign.json ``axes``: a grid axis (``values``) or a sampled field
    (``low``, ``high``, ``samples``). numeric: its values are numbers (plotted on a numeric axis,
    sorted numerically); otherwise categorical (strings such as controller names, booleans)."""

    path: str
    values: tuple[Any, ...] = ()
    low: float | None = None
    high: float | None = None
    samples: int | None = None
    numeric: bool = True

    @property
    def sampled(self) -> bool:
        return self.low is not None

    def describe(self) -> str:
        if self.sampled:
            return f"`{self.path}` sampled uniformly in [{_fmt_value(self.low)}, {_fmt_value(self.high)}], {self.samples} draws"
        return f"`{self.path}` = " + ", ".join(_fmt_value(v) for v in self.values)


@dataclass
class Campaign:
    """A campaign directory, read: campaign.json (``meta``), its axes, and runs.parquet as columns
    of Python values (``None`` for null), one row per run (a run index listed twice keeps its last
    row; ``duplicates`` counts the dropped ones)."""

    directory: Path
    meta: dict[str, Any]
    axes: list[Axis]
    columns: dict[str, list[Any]]
    n_rows: int
    has_table: bool
    duplicates: int = 0

    @property
    def grid_axes(self) -> list[Axis]:
        return [a for a in self.axes if not a.sampled]

    @property
    def sampled_axes(self) -> list[Axis]:
        return [a for a in self.axes if a.sampled]

    @property
    def planned(self) -> int:
        return int(self.meta["runs"])

    @property
    def seeds(self) -> int | None:
        s = self.meta.get("seeds")
        return s if isinstance(s, int) and not isinstance(s, bool) else None

    def column(self, name: str) -> list[Any]:
        """The column, or nulls when the table does not have it."""
        return self.columns.get(name, [None] * self.n_rows)

    def crashed(self) -> np.ndarray:
        """Boolean mask of the crashed rows (error not null)."""
        return np.array([e is not None for e in self.column("error")], dtype=bool)

    def missing_runs(self) -> list[int]:
        """Run indices of the campaign's expansion (0 .. runs-1) without a row yet."""
        have = {int(r) for r in self.column("run") if r is not None}
        return [r for r in range(self.planned) if r not in have]


def _require(cond: bool, message: str) -> None:
    if not cond:
        raise CampaignError(message)


def _parse_axes(raw: Any, where: Path) -> list[Axis]:
    _require(isinstance(raw, list), f"{where}: 'axes' must be a list")
    axes: list[Axis] = []
    for i, a in enumerate(raw):
        field_ = f"{where}: axes[{i}]"
        _require(isinstance(a, dict) and isinstance(a.get("path"), str) and a["path"], f"{field_}: needs a 'path' (a dotted scenario path)")
        if "values" in a:
            _require(isinstance(a["values"], list) and len(a["values"]) > 0, f"{field_}.values: must be a non-empty list")
            vals = tuple(a["values"])
            axes.append(Axis(a["path"], values=vals, numeric=all(_is_number(v) for v in vals)))
        elif "low" in a and "high" in a:
            lo, hi = a["low"], a["high"]
            _require(_is_number(lo) and _is_number(hi), f"{field_}: 'low' and 'high' must be numbers")
            k = a.get("samples")
            _require(k is None or (isinstance(k, int) and not isinstance(k, bool)), f"{field_}.samples: must be an integer")
            axes.append(Axis(a["path"], low=float(lo), high=float(hi), samples=k))
        else:
            raise CampaignError(f"{field_} ({a['path']}): needs 'values' (a grid axis) or 'low' and 'high' (a sampled field)")
    paths = [a.path for a in axes]
    dup = sorted({p for p in paths if paths.count(p) > 1})
    _require(not dup, f"{where}: axes: path swept twice: {', '.join(dup)}")
    return axes


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _read_table(path: Path) -> dict[str, list[Any]]:
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise CampaignError(f"{path}: reading runs.parquet needs pyarrow: pip install 'zenswarm[sweep]'") from None
    try:
        table = pq.read_table(path)
        cols: dict[str, list[Any]] = table.to_pydict()
    except Exception as e:  # noqa: BLE001 - pyarrow raises ArrowInvalid, OSError, ... for a bad file: one message
        raise CampaignError(f"{path}: runs.parquet unreadable: {type(e).__name__}: {e}") from None
    return cols


def load_campaign(out_dir: str | Path) -> Campaign:
    """Read a campaign directory. A directory whose runs.parquet does not exist yet (no run has
    finished) is a campaign with no rows.

    Raises :class:`zenswarm.errors.CampaignError` naming the file and the field: not a directory,
    campaign.json missing or not valid JSON, a bad or missing key (``runs``, ``axes``), an
    unsupported ``version``, runs.parquet unreadable, or a column missing from it (``run``,
    ``success``, one per axis).
    """
    d = Path(out_dir)
    _require(d.is_dir(), f"{d}: not a campaign directory: no such directory")
    cj = d / "campaign.json"
    _require(cj.is_file(), f"{d}: not a campaign directory: campaign.json missing")
    try:
        meta = json.loads(cj.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CampaignError(f"{cj}: campaign.json unreadable: {e}") from None
    _require(isinstance(meta, dict), f"{cj}: campaign.json must hold a JSON object")
    version = meta.get("version", CAMPAIGN_VERSION)
    _require(version == CAMPAIGN_VERSION, f"{cj}: version: {version!r} is not supported (this zenswarm reads {CAMPAIGN_VERSION})")
    runs = meta.get("runs")
    ok = isinstance(runs, int) and not isinstance(runs, bool) and runs >= 0
    _require(ok, f"{cj}: runs: must be a non-negative integer (got {runs!r})")
    axes = _parse_axes(meta.get("axes", []), cj)

    rp = d / "runs.parquet"
    has_table = rp.exists()
    cols = _read_table(rp) if has_table else {}
    lengths = {len(v) for v in cols.values()}
    n = lengths.pop() if lengths else 0
    if n or cols:
        for name in ("run", "success", *(a.path for a in axes)):
            _require(name in cols, f"{rp}: column '{name}' missing (columns: {', '.join(cols) or 'none'})")
    # one row per run: a run listed twice keeps its last row
    keep: dict[int, int] = {}
    for i, r in enumerate(cols.get("run", [])):
        _require(r is not None, f"{rp}: column 'run': null in row {i}")
        keep[int(r)] = i
    duplicates = n - len(keep)
    if duplicates:
        idx = sorted(keep.values())
        cols = {k: [v[i] for i in idx] for k, v in cols.items()}
        n = len(idx)
    # an axis of numbers in campaign.json may be stored as numbers only: trust the table
    fixed: list[Axis] = []
    for a in axes:
        seen = [v for v in cols.get(a.path, []) if v is not None]
        numeric = all(_is_number(v) for v in seen) and (a.sampled or all(_is_number(v) for v in a.values) or bool(seen))
        fixed.append(Axis(a.path, a.values, a.low, a.high, a.samples, numeric))
    return Campaign(d, meta, fixed, cols, n, has_table, duplicates)


# =========================================================================== a row's values


def _num(v: Any) -> float | None:
    """A finite float, or None (null, NaN)."""
    if v is None or isinstance(v, bool) or not isinstance(v, int | float):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def _sort_key(axis: Axis, v: Any) -> tuple[int, float, str]:
    """Numbers numerically; categories in the order of campaign.json, then by name; nulls last."""
    if v is None:
        return (2, 0.0, "")
    if axis.numeric and _is_number(v):
        return (0, float(v), "")
    order = [str(x) for x in axis.values]
    s = str(v)
    return (0, float(order.index(s)), s) if s in order else (1, 0.0, s)


def _cell_keys(c: Campaign) -> list[str]:
    """The cell of each row: the ``cell`` column, or (if absent) the axes' values joined."""
    if "cell" in c.columns:
        return ["" if k is None else str(k) for k in c.columns["cell"]]
    return [",".join(f"{a.path}={_fmt_value(c.columns[a.path][i])}" for a in c.axes) for i in range(c.n_rows)]


def _fmt_value(v: Any) -> str:
    """A value as the report spells it (in a cell key, the tables, the plots' ticks): null, floats to 6 significant digits."""
    if v is None:
        return "null"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


"""``zenswarm sweep report DIR``: the analysis of a campaign directory (issue 17, point 4).

Reads the campaign directory of ``zenswarm sweep`` (``DIR/campaign.json`` and ``DIR/runs.parquet``,
docs/campaigns.md) and writes

``DIR/report.md``      the header (scenario, command, zenswarm version, runs planned, finished,
                       crashed, and the runs still missing when the campaign is incomplete), one
                       summary line per parameter cell (all inputs but the seed), the crashed runs
                       with their errors, and the plots with their captions;
``DIR/plots/*.png``    (matplotlib, Agg canvas, no display needed):

  ``heatmap_success_rate.png``, ``heatmap_formation_error.png``
      with two grid axes or more: success rate and median formation error over the first two
      grid axes (pooled over seeds and over any further axis or sampled field, as the caption says);
  ``curve_<path>.png``
      per grid axis: success rate (with its 95 % Wilson interval) and formation error (median,
      interquartile band, min/max) against the parameter; numeric axes on a numeric x axis, string
      axes (controller names) categorical; one line per value of the next grid axis when it has
      at most :data:`MAX_SERIES` values;
  ``scatter_<path>.png``
      per sampled field: each finished run's success and formation error against the drawn value;
  ``formation_error_hist.png``
      the formation error of every finished run (the only plot of a seeds-only campaign).

Conventions. A run *crashed* when its ``error`` is not null (the run raised instead of being
judged); crashed runs are counted on their own and left out of every rate and metric. The success
rate of a cell is k/n over its finished runs, with the 95 % Wilson score interval
(:func:`wilson_interval`). The formation error is the verdict's ``max_formation_error_m`` (the
vehicles', docs/verdict.md). Clearances are the minima over the cell's runs of
``min_obstacle_clearance_m`` and ``min_inter_uav_distance_m`` (raw distances from the UAV centres).

pyarrow and matplotlib are imported inside the functions that use them: this module imports
without them.
"""

from __future__ import annotations

import json
import math
import os
import re
import shlex
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm.errors import CampaignError

__all__ = [
    "Z95",
    "MAX_SERIES",
    "CAMPAIGN_VERSION",
    "Axis",
    "Campaign",
    "CellStats",
    "wilson_interval",
    "load_campaign",
    "summarize",
    "write_report",
]

Z95 = 1.959963984540054
"""The standard normal quantile of 0.975: a two-sided 95 % interval."""

MAX_SERIES = 6
"""A curve gets one line per value of the next grid axis when that axis has at most this many values."""

CAMPAIGN_VERSION = 1
"""The ``version`` of campaign.json this module reads."""

FORMATION = "max_formation_error_m"
CLEARANCE = "min_obstacle_clearance_m"
SEPARATION = "min_inter_uav_distance_m"

_DPI = 100
_PAIR = {"left": 0.07, "right": 0.98, "bottom": 0.15, "top": 0.9, "wspace": 0.25}
"""Margins of the two-panel figures (curves, scatters)."""
_MAX_CRASHES_LISTED = 20


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


def _num(v: Any) -> float | None:
    """A finite float, or None (null, NaN)."""
    if v is None or isinstance(v, bool) or not isinstance(v, int | float):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def _min(a: float | None, b: float | None) -> float | None:
    return b if a is None else a if b is None else min(a, b)


def _causes(v: Any) -> list[str]:
    if not v:
        return []
    return sorted({c.strip() for c in str(v).split(",") if c.strip()})


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


# =========================================================================== Markdown


def _fmt_value(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def _fmt_m(v: float | None) -> str:
    return "–" if v is None else f"{v:.3f}"


def _fmt_pct(v: float) -> str:
    return f"{100.0 * v:.1f} %"


def _md(s: str) -> str:
    """Text safe inside a Markdown table cell."""
    return s.replace("\\", "\\\\").replace("|", "\\|").replace("\n", " ")


def _ranges(xs: Sequence[int], limit: int = 40) -> str:
    """[1, 2, 3, 7] -> '1-3, 7' (at most ``limit`` ranges, then how many more runs)."""
    parts: list[str] = []
    i = 0
    while i < len(xs):
        j = i
        while j + 1 < len(xs) and xs[j + 1] == xs[j] + 1:
            j += 1
        parts.append(str(xs[i]) if i == j else f"{xs[i]}-{xs[j]}")
        i = j + 1
        if len(parts) == limit and i < len(xs):
            parts.append(f"... ({len(xs) - i} more)")
            break
    return ", ".join(parts)


def _top_causes(causes: Counter[str], n: int = 3) -> str:
    if not causes:
        return ""
    common = causes.most_common()
    shown = ", ".join(f"{k}: {v}" for k, v in common[:n])
    return shown + (f" (+{len(common) - n} more)" if len(common) > n else "")


def _header(c: Campaign, missing: list[int]) -> list[str]:
    m = c.meta
    crashed = int(c.crashed().sum())
    command = m.get("command")
    cmd = shlex.join(str(x) for x in command) if isinstance(command, list) else str(command or "?")
    scenario = str(m.get("scenario", "?"))
    name = m.get("scenario_name")
    versions = Counter(str(v) for v in c.column("zenswarm_version") if v is not None)
    version = str(m.get("zenswarm_version", "?"))
    if versions and set(versions) != {version}:
        version += " (campaign); runs by " + ", ".join(f"{k} ({n})" for k, n in sorted(versions.items()))
    seeds = c.seeds
    rows = [
        ("scenario", f"`{scenario}`" + (f" ({name})" if name and name != scenario else "")),
        ("command", f"`{cmd}`"),
        ("zenswarm version", version),
        ("mode", str(m.get("mode", "?"))),
        ("swept", "; ".join(a.describe() for a in c.axes) or "nothing (seeds only)"),
        ("seeds", "?" if seeds is None else f"{seeds} per cell (base seed {m.get('base_seed', '?')})"),
        ("runs", f"{c.planned} planned, {c.n_rows} in runs.parquet: {c.n_rows - crashed} finished, {crashed} crashed"),
    ]
    if missing:
        rows.append(
            (
                "incomplete",
                f"{len(missing)} of {c.planned} runs missing (run index): {_ranges(missing)}; "
                "running the same `zenswarm sweep` command again resumes the campaign",
            )
        )
    else:
        rows.append(("complete", "every planned run is in the table"))
    if c.duplicates:
        rows.append(("duplicates", f"{c.duplicates} rows repeat a run index; the last row of each run is used"))
    title = name or scenario
    out = [f"# Campaign report: {title}", "", "| | |", "| --- | --- |"]
    out += [f"| {k} | {_md(v)} |" for k, v in rows]
    return out


def _summary_table(c: Campaign, cells: list[CellStats]) -> list[str]:
    out = [
        "## Summary per parameter cell",
        "",
        "One line per parameter cell (every input but the seed). *crashed*: runs that raised instead of "
        "being judged (`error` not null); they are counted here and left out of every rate and metric. "
        "*success* k/n and *rate* are over the finished runs, with the 95 % Wilson score interval. "
        "Formation error: the vehicles' `max_formation_error_m` per run, its median and worst over the "
        "cell's runs. Clearances: the smallest `min_obstacle_clearance_m` and `min_inter_uav_distance_m` "
        "(from the UAV centres) of the cell's runs. Failure causes: how many failed runs name each.",
        "",
    ]
    axis_cols = [f"`{a.path}`" for a in c.axes] or ["cell"]
    head = [
        *axis_cols,
        "runs",
        "crashed",
        "success",
        "rate",
        "95 % CI",
        "median formation error (m)",
        "worst formation error (m)",
        "min obstacle clearance (m)",
        "min inter-UAV distance (m)",
        "failure causes",
    ]
    out.append("| " + " | ".join(head) + " |")
    out.append("|" + " --- |" * len(head))
    seeds = c.seeds
    for s in cells:
        label = [_md(_fmt_value(v)) for v in s.values] or [_md(s.key or "all runs")]
        runs = f"{s.runs}" + (f" (of {seeds})" if seeds is not None and s.runs < seeds else "")
        rate, ci = s.rate, s.ci
        row = [
            *label,
            runs,
            str(s.crashed),
            f"{s.successes}/{s.finished}",
            "–" if rate is None else _fmt_pct(rate),
            "–" if ci is None else f"[{_fmt_pct(ci[0])}, {_fmt_pct(ci[1])}]",
            _fmt_m(s.median_formation),
            _fmt_m(s.worst_formation),
            _fmt_m(s.min_clearance),
            _fmt_m(s.min_separation),
            _md(_top_causes(s.causes)),
        ]
        out.append("| " + " | ".join(row) + " |")
    if not cells:
        out.append("| " + " | ".join(["–"] * len(head)) + " |")
        out += ["", "No run has finished yet."]
    return out


def _crash_list(c: Campaign) -> list[str]:
    crashed = np.flatnonzero(c.crashed())
    if not len(crashed):
        return []
    runs, seeds, errors, keys = c.column("run"), c.column("seed"), c.column("error"), _cell_keys(c)
    order = sorted(crashed, key=lambda i: int(runs[i]))
    out = ["## Crashed runs", "", f"{len(order)} runs crashed (left out of the rates above); the last line of each error:", ""]
    out += ["| run | cell | seed | error |", "| --- | --- | --- | --- |"]
    for i in order[:_MAX_CRASHES_LISTED]:
        err = str(errors[i]).strip().splitlines()
        first = err[-1] if err else ""
        first = first if len(first) <= 160 else first[:157] + "..."
        out.append(f"| {runs[i]} | {_md(keys[i])} | {_fmt_value(seeds[i])} | {_md(first)} |")
    if len(order) > _MAX_CRASHES_LISTED:
        out += ["", f"... and {len(order) - _MAX_CRASHES_LISTED} more (column `error` of runs.parquet)."]
    return out


# =========================================================================== plots


@dataclass
class _Runs:
    """The finished runs, as arrays for the plots."""

    values: dict[str, list[Any]]  # axis path -> value per finished run
    success: np.ndarray  # bool
    formation: np.ndarray  # float, NaN when not measured


def _finished(c: Campaign) -> _Runs:
    keep = np.flatnonzero(~c.crashed())
    success = np.array([c.column("success")[i] is True for i in keep], dtype=bool)
    ferr = c.column(FORMATION)
    formation = np.array([np.nan if _num(ferr[i]) is None else _num(ferr[i]) for i in keep], dtype=float)
    values = {a.path: [c.columns[a.path][i] for i in keep] for a in c.axes}
    return _Runs(values, success, formation)


def _levels(c: Campaign, a: Axis) -> list[Any]:
    """The axis' values to plot, sorted: campaign.json's (runs not finished yet leave a gap) and the table's."""
    seen = [v for v in c.columns.get(a.path, []) if v is not None]
    if a.numeric:
        pool = [v for v in (*a.values, *seen) if _is_number(v)]
        return sorted(set(pool), key=float)
    names = list(dict.fromkeys(str(v) for v in (*a.values, *seen)))
    return sorted(names, key=lambda s: _sort_key(a, s))


def _match(a: Axis, col: list[Any], level: Any) -> np.ndarray:
    if a.numeric:
        return np.array([_is_number(v) and float(v) == float(level) for v in col], dtype=bool)
    return np.array([v is not None and str(v) == level for v in col], dtype=bool)


def _slug(path: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", path)


def _figure(w: float, h: float, **adjust: float) -> Any:
    """A figure without pyplot (no global state; PNG through the Agg canvas), with fixed margins
    (``subplots_adjust``): a layout engine would cost more than the drawing."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h))
    fig.subplots_adjust(**adjust)
    return fig


def _save(fig: Any, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=_DPI)
    os.replace(tmp, path)


def _pooled_note(c: Campaign, used: Iterable[str]) -> str:
    rest = [a.path for a in c.axes if a.path not in set(used)]
    return "pooled over seeds" + (" and over " + ", ".join(f"`{p}`" for p in rest) if rest else "")


def _heatmaps(c: Campaign, r: _Runs, plots: Path) -> list[tuple[str, str]]:
    ax_x, ax_y = c.grid_axes[0], c.grid_axes[1]
    lx, ly = _levels(c, ax_x), _levels(c, ax_y)
    rate = np.full((len(ly), len(lx)), np.nan)
    med = np.full((len(ly), len(lx)), np.nan)
    count = np.zeros((len(ly), len(lx)), dtype=int)
    wins = np.zeros((len(ly), len(lx)), dtype=int)
    mx = [_match(ax_x, r.values[ax_x.path], v) for v in lx]
    my = [_match(ax_y, r.values[ax_y.path], v) for v in ly]
    for j in range(len(ly)):
        for i in range(len(lx)):
            sel = mx[i] & my[j]
            count[j, i], wins[j, i] = int(sel.sum()), int(r.success[sel].sum())
            if count[j, i]:
                rate[j, i] = wins[j, i] / count[j, i]
            f = r.formation[sel]
            f = f[np.isfinite(f)]
            if len(f):
                med[j, i] = float(np.median(f))
    pooled = _pooled_note(c, (ax_x.path, ax_y.path))
    out: list[tuple[str, str]] = []
    rate_text = np.vectorize(lambda r, w, n: f"{100 * r:.0f} %\n{w}/{n}")(rate, wins, count)
    med_text = np.vectorize(lambda m: f"{m:.3g}")(med)
    for name, data, text, title, cmap, vlim in (
        ("heatmap_success_rate.png", rate, rate_text, "success rate", "RdYlGn", (0.0, 1.0)),
        ("heatmap_formation_error.png", med, med_text, "median formation error (m)", "viridis", None),
    ):
        fig = _figure(2.4 + 1.1 * max(3, len(lx)), 1.6 + 0.8 * max(3, len(ly)), left=0.16, right=0.97, bottom=0.14, top=0.9)
        ax = fig.add_subplot()
        from matplotlib import colormaps

        cm = colormaps[cmap].with_extremes(bad="0.85")
        finite = data[np.isfinite(data)]
        lo, hi = vlim if vlim else ((float(finite.min()), float(finite.max())) if len(finite) else (0.0, 1.0))
        im = ax.imshow(np.ma.masked_invalid(data), origin="lower", aspect="auto", cmap=cm, vmin=lo, vmax=hi if hi > lo else lo + 1e-9)
        fig.colorbar(im, ax=ax, label=title)
        for j in range(len(ly)):
            for i in range(len(lx)):
                ax.text(i, j, text[j, i] if np.isfinite(data[j, i]) else "no run", ha="center", va="center", fontsize=8)
        ax.set_xticks(range(len(lx)), [_fmt_value(v) for v in lx])
        ax.set_yticks(range(len(ly)), [_fmt_value(v) for v in ly])
        ax.set_xlabel(ax_x.path)
        ax.set_ylabel(ax_y.path)
        ax.set_title(f"{title}, {pooled.replace('`', '')}", fontsize=9)
        _save(fig, plots / name)
        out.append((name, f"{title.capitalize()} over `{ax_x.path}` x `{ax_y.path}`, {pooled} (finished runs; grey: no finished run)."))
    return out


def _spread(f: np.ndarray) -> tuple[float, float, float, float, float]:
    """(median, q25, q75, min, max) of the finite values; NaNs when there are none."""
    f = f[np.isfinite(f)]
    if not len(f):
        return (math.nan,) * 5
    q = np.percentile(f, [50, 25, 75])
    return float(q[0]), float(q[1]), float(q[2]), float(f.min()), float(f.max())


def _curve(c: Campaign, r: _Runs, a: Axis, plots: Path) -> tuple[str, str]:
    levels = _levels(c, a)
    xs = np.array([float(v) for v in levels]) if a.numeric else np.arange(len(levels), dtype=float)
    others = [b for b in c.grid_axes if b.path != a.path]
    series_axis = others[0] if others and len(_levels(c, others[0])) <= MAX_SERIES else None
    series: list[tuple[str, np.ndarray]] = [("all", np.ones(len(r.success), dtype=bool))]
    if series_axis is not None:
        series = [
            (f"{series_axis.path} = {_fmt_value(v)}", _match(series_axis, r.values[series_axis.path], v)) for v in _levels(c, series_axis)
        ]
    fig = _figure(10.0, 4.0, **_PAIR)
    ax_s, ax_f = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    masks = [_match(a, r.values[a.path], v) for v in levels]
    for label, smask in series:
        rate, lo, hi = (np.full(len(levels), np.nan) for _ in range(3))
        stats = np.full((len(levels), 5), np.nan)
        for k, m in enumerate(masks):
            sel = m & smask
            n = int(sel.sum())
            if n:
                w = int(r.success[sel].sum())
                rate[k] = w / n
                lo[k], hi[k] = wilson_interval(w, n)
            stats[k] = _spread(r.formation[sel])
        line = ax_s.plot(xs, rate, "o-", label=label)[0]
        ax_s.fill_between(xs, lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
        line = ax_f.plot(xs, stats[:, 0], "o-", label=label)[0]
        ax_f.fill_between(xs, stats[:, 1], stats[:, 2], color=line.get_color(), alpha=0.2, linewidth=0)
        if series_axis is None:
            ax_f.plot(xs, stats[:, 3], ":", color=line.get_color(), linewidth=1, label="min / max")
            ax_f.plot(xs, stats[:, 4], ":", color=line.get_color(), linewidth=1)
    for ax in (ax_s, ax_f):
        ax.set_xlabel(a.path)
        ax.grid(True, alpha=0.3)
        if not a.numeric:
            ax.set_xticks(xs, [str(v) for v in levels], rotation=20 if len(levels) > 4 else 0)
    ax_s.set_ylim(-0.03, 1.03)
    ax_s.set_ylabel("success rate (95 % Wilson band)")
    ax_f.set_ylabel("formation error (m): median, IQR band")
    if series_axis is not None or ax_f.get_legend_handles_labels()[0]:
        ax_f.legend(fontsize=8)
    if series_axis is not None:
        ax_s.legend(fontsize=8)
    used = (a.path,) + ((series_axis.path,) if series_axis else ())
    pooled = _pooled_note(c, used)
    fig.suptitle(f"against {a.path}, {pooled.replace('`', '')}", fontsize=9)
    name = f"curve_{_slug(a.path)}.png"
    _save(fig, plots / name)
    per = f", one line per value of `{series_axis.path}`" if series_axis else ""
    caption = (
        f"Success rate (band: 95 % Wilson interval) and formation error (median; band: interquartile range"
        f"{'; dotted: min and max' if series_axis is None else ''}) against `{a.path}`{per}, {pooled}."
    )
    return name, caption


def _scatter(c: Campaign, r: _Runs, a: Axis, plots: Path) -> tuple[str, str]:
    x = np.array([float(v) if _is_number(v) else np.nan for v in r.values[a.path]])
    fig = _figure(10.0, 4.0, **_PAIR)
    ax_s, ax_f = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    jitter = np.random.default_rng(0).uniform(-0.04, 0.04, len(x))
    ax_s.plot(x, r.success.astype(float) + jitter, ".", alpha=0.6)
    fin = np.isfinite(x)
    if fin.any():
        lo, hi = float(x[fin].min()), float(x[fin].max())
        edges = np.linspace(lo, hi, min(8, max(2, int(fin.sum()) // 5)) + 1) if hi > lo else np.array([lo - 0.5, lo + 0.5])
        idx = np.clip(np.digitize(x[fin], edges) - 1, 0, len(edges) - 2)
        s = r.success[fin]
        centres = 0.5 * (edges[:-1] + edges[1:])
        rates = np.array([s[idx == k].mean() if (idx == k).any() else np.nan for k in range(len(centres))])
        ax_s.plot(centres, rates, "s-", color="k", label="binned rate")
        ax_s.legend(fontsize=8)
    ok = r.success
    ax_f.plot(x[ok], r.formation[ok], "o", color="tab:green", alpha=0.6, label="success")
    ax_f.plot(x[~ok], r.formation[~ok], "x", color="tab:red", alpha=0.8, label="failure")
    ax_f.legend(fontsize=8)
    ax_s.set_ylabel("success (1) / failure (0), jittered")
    ax_f.set_ylabel("formation error (m)")
    for ax in (ax_s, ax_f):
        ax.set_xlabel(a.path)
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"against the sampled {a.path}, every finished run", fontsize=9)
    name = f"scatter_{_slug(a.path)}.png"
    _save(fig, plots / name)
    return name, f"Each finished run's success (with the rate in bins) and formation error against the sampled `{a.path}`."


def _histogram(r: _Runs, plots: Path) -> tuple[str, str]:
    f = r.formation[np.isfinite(r.formation)]
    fig = _figure(6.0, 3.6, left=0.11, right=0.97, bottom=0.15, top=0.95)
    ax = fig.add_subplot()
    if len(f):
        ax.hist([f[r.success[np.isfinite(r.formation)]], f[~r.success[np.isfinite(r.formation)]]], bins=20, stacked=True,
                color=["tab:green", "tab:red"], label=["success", "failure"])  # fmt: skip
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no formation error measured yet", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("formation error (m)")
    ax.set_ylabel("runs")
    name = "formation_error_hist.png"
    _save(fig, plots / name)
    return name, f"Formation error of the {len(f)} finished runs that measured it (all cells and seeds)."


def _plots(c: Campaign, plots: Path) -> list[tuple[str, str]]:
    plots.mkdir(exist_ok=True)
    r = _finished(c)
    out: list[tuple[str, str]] = []
    if len(c.grid_axes) >= 2:
        out += _heatmaps(c, r, plots)
    out += [_curve(c, r, a, plots) for a in c.grid_axes]
    out += [_scatter(c, r, a, plots) for a in c.sampled_axes]
    out.append(_histogram(r, plots))
    return out


# =========================================================================== the report


def write_report(out_dir: Path) -> Path:
    """Write ``out_dir/report.md`` and ``out_dir/plots/*.png`` for the campaign in ``out_dir`` and
    return the path of report.md. Works on a partial campaign (the header lists the missing runs)
    and on one with no finished run yet. Each file is replaced atomically (written beside, then
    renamed), so a report read while a sweep rewrites it is whole.

    Raises :class:`zenswarm.errors.CampaignError` (see :func:`load_campaign`) for a directory that
    is not a readable campaign; nothing is written then.
    """
    c = load_campaign(out_dir)
    cells = summarize(c)
    missing = c.missing_runs()
    lines = _header(c, missing)
    lines += ["", *_summary_table(c, cells)]
    crashes = _crash_list(c)
    if crashes:
        lines += ["", *crashes]
    figures = _plots(c, c.directory / "plots")
    lines += ["", "## Plots", ""]
    if len(c.grid_axes) > 2:
        g = c.grid_axes
        rest = ", ".join(f"`{a.path}`" for a in g[2:])
        lines += [f"The heatmaps are over the first two grid axes, `{g[0].path}` and `{g[1].path}`; "
                  f"the runs of every value of {rest} are pooled in each square.", ""]
    for name, caption in figures:
        lines += [f"![{name}](plots/{name})", "", f"*{caption}*", ""]
    lines += ["The table behind this report: `runs.parquet` (docs/campaigns.md, Reading a campaign's report)."]
    path = c.directory / "report.md"
    tmp = path.with_name("report.md.tmp")
    tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path

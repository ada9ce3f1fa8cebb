"""``zenswarm sweep report DIR``: the analysis of a campaign directory (issue 17, point 4).

Reads the campaign directory of ``zenswarm sweep`` (``DIR/campaign.json`` and ``DIR/runs.parquet``,
docs/campaigns.md; :func:`load_campaign`, :mod:`zenswarm.bridge.reports.sweep_campaign`) and writes

``DIR/report.md``      the header (scenario, command, zenswarm version, runs planned, finished,
                       crashed, and the runs still missing when the campaign is incomplete), one
                       summary line per parameter cell (all inputs but the seed; :func:`summarize`,
                       :mod:`zenswarm.bridge.reports.sweep_stats`), the crashed runs with their
                       errors, and the plots with their captions: this module, the Markdown;
``DIR/plots/*.png``    heatmaps, curves per grid axis, scatters per sampled field, the histogram of
                       the formation error (:mod:`zenswarm.bridge.reports.sweep_figures`).

Conventions. A run *crashed* when its ``error`` is not null (the run raised instead of being
judged); crashed runs are counted on their own and left out of every rate and metric. The success
rate of a cell is k/n over its finished runs, with the 95 % Wilson score interval
(:func:`wilson_interval`). The formation error is the verdict's ``max_formation_error_m`` (the
vehicles', docs/verdict.md). Clearances are the minima over the cell's runs of
``min_obstacle_clearance_m`` and ``min_inter_uav_distance_m`` (raw distances from the UAV centres).

pyarrow and matplotlib are imported inside the functions that use them: this module and the three
it reads from import without them. Every name of the module it was before that split (issue 44;
``load_campaign``, ``wilson_interval``, ``summarize``, ``Z95``, ... and the private helpers) is
still importable from here.
"""

from __future__ import annotations

import os
import shlex
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

# The private helpers among them lived here before the split (issue 44): still importable from here.
from zenswarm.bridge.reports.sweep_campaign import (  # noqa: F401
    CAMPAIGN_VERSION,
    CLEARANCE,
    FORMATION,
    SEPARATION,
    Axis,
    Campaign,
    _cell_keys,
    _fmt_value,
    _is_number,
    _num,
    _parse_axes,
    _read_table,
    _require,
    _sort_key,
    load_campaign,
)
from zenswarm.bridge.reports.sweep_figures import (  # noqa: F401
    _DPI,
    _PAIR,
    MAX_SERIES,
    _curve,
    _figure,
    _finished,
    _heatmaps,
    _histogram,
    _levels,
    _match,
    _pooled_note,
    _Runs,
    _save,
    _scatter,
    _slug,
    _spread,
    draw_plots,
)
from zenswarm.bridge.reports.sweep_stats import Z95, CellStats, _causes, _min, summarize, wilson_interval  # noqa: F401

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

_MAX_CRASHES_LISTED = 20
_plots = draw_plots  # its name before the split


# =========================================================================== Markdown


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
    figures = draw_plots(c, c.directory / "plots")
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

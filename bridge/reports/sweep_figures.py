"""The plots of a campaign's report, ``DIR/plots/*.png`` (matplotlib, Agg canvas, no display needed):

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

:func:`draw_plots` draws those of a :class:`zenswarm.bridge.reports.sweep_campaign.Campaign` (its finished
runs only) and returns each file's name and caption for the report,
:mod:`zenswarm.bridge.reports.sweep_report`.

matplotlib is imported inside the functions that draw: this module imports without it.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm.bridge.reports.sweep_campaign import FORMATION, Axis, Campaign, _fmt_value, _is_number, _num, _sort_key
from zenswarm.bridge.reports.sweep_stats import wilson_interval

__all__ = ["MAX_SERIES", "draw_plots"]

MAX_SERIES = 6
"""A curve gets one line per value of the next grid axis when that axis has at most this many values."""
_DPI = 100
_PAIR = {"left": 0.07, "right": 0.98, "bottom": 0.15, "top": 0.9, "wspace": 0.25}
"""Margins of the two-panel figures (curves, scatters)."""


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


def draw_plots(c: Campaign, plots: Path) -> list[tuple[str, str]]:
    """Write the plots of the campaign (its finished runs) in ``plots`` (made if missing), each PNG
    replaced atomically; return (file name, caption) of each, in the report's order."""
    plots.mkdir(exist_ok=True)
    r = _finished(c)
    out: list[tuple[str, str]] = []
    if len(c.grid_axes) >= 2:
        out += _heatmaps(c, r, plots)
    out += [_curve(c, r, a, plots) for a in c.grid_axes]
    out += [_scatter(c, r, a, plots) for a in c.sampled_axes]
    out.append(_histogram(r, plots))
    return out

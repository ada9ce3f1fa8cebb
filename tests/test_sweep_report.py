"""zenswarm.bridge.reports.sweep_report: the report of a campaign directory (issue 17, point 4).

Pure tests on synthetic campaign directories (campaign.json + runs.parquet written with pyarrow, the
contract of docs/campaigns.md); every expected figure is computed here from the rows, independently
of the module.
"""

from __future__ import annotations

import ast
import json
import math
import re
from collections import Counter
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from zenswarm.bridge.reports import sweep_campaign, sweep_figures, sweep_report, sweep_stats
from zenswarm.bridge.reports.sweep_report import load_campaign, wilson_interval, write_report
from zenswarm.errors import CampaignError, ZenswarmError

PNG = b"\x89PNG\r\n\x1a\n"
CAUSES = ["timeout", "collision_uav", "uav_off_slot", "leader_stalled"]

SCHEMA = {
    "run": pa.int64(),
    "cell": pa.string(),
    "seed": pa.int64(),
    "success": pa.bool_(),
    "causes": pa.string(),
    "error": pa.string(),
    "attempts": pa.int64(),
    "max_formation_error_m": pa.float64(),
    "min_obstacle_clearance_m": pa.float64(),
    "min_inter_uav_distance_m": pa.float64(),
    "wall_s": pa.float64(),
    "zenswarm_version": pa.string(),
    "mode": pa.string(),
}


def make_campaign(
    d: Path, axes: list[dict[str, Any]], rows: list[dict[str, Any]], runs: int | None = None, seeds: int = 10, write_table: bool = True
) -> Path:
    """A campaign directory as `zenswarm sweep` writes it (docs/campaigns.md)."""
    d.mkdir(parents=True, exist_ok=True)
    meta = {
        "version": 1,
        "zenswarm_version": "0.1.0",
        "scenario": "paper_example1",
        "scenario_name": "paper_example1",
        "command": ["zenswarm", "sweep", "paper_example1", "--seeds", str(seeds), "--out", "camp dir"],
        "mode": "sim",
        "axes": axes,
        "seeds": seeds,
        "base_seed": 0,
        "runs": len(rows) if runs is None else runs,
    }
    (d / "campaign.json").write_text(json.dumps(meta))
    if write_table:
        fields = dict(SCHEMA)
        for a in axes:
            v = a["values"][0] if "values" in a else a["low"]
            fields[a["path"]] = pa.string() if isinstance(v, str) else pa.int64() if isinstance(v, int) else pa.float64()
        cols = {k: [r.get(k) for r in rows] for k in fields}
        table = pa.table({k: pa.array(v, type=fields[k]) for k, v in cols.items()})
        pq.write_table(table, d / "runs.parquet")
    return d


def synth_rows(axes: list[dict[str, Any]], seeds: int, rng: np.random.Generator, crash_every: int = 0) -> list[dict[str, Any]]:
    """Runs over the grid (first axis slowest), seeds innermost; random outcomes and metrics."""
    grids = [a["values"] for a in axes]
    cells = [()]
    for g in grids:
        cells = [(*c, v) for c in cells for v in g]
    rows = []
    for cell in cells:
        for s in range(seeds):
            i = len(rows)
            ok = bool(rng.random() < 0.3 + 0.6 * rng.random())
            causes = "" if ok else ",".join(sorted(set(rng.choice(CAUSES, size=int(rng.integers(1, 3))).tolist())))
            crashed = crash_every and i % crash_every == crash_every - 1
            r = {
                "run": i,
                "cell": ",".join(f"{a['path']}={v}" for a, v in zip(axes, cell)),
                "seed": 1000 + s,
                "success": None if crashed else ok,
                "causes": None if crashed else causes,
                "error": "Traceback ...\nRuntimeError: boom | pipe" if crashed else None,
                "attempts": 2 if crashed else 1,
                "max_formation_error_m": None if crashed or rng.random() < 0.05 else float(rng.gamma(2.0, 0.1)),
                "min_obstacle_clearance_m": None if crashed else float(rng.uniform(0.05, 2.0)),
                "min_inter_uav_distance_m": None if crashed else float(rng.uniform(0.1, 1.5)),
                "wall_s": 1.0,
                "zenswarm_version": "0.1.0",
                "mode": "sim",
            }
            r.update({a["path"]: v for a, v in zip(axes, cell)})
            rows.append(r)
    return rows


def table_rows(report: str, first_header: str) -> list[list[str]]:
    """The summary table's data rows, split into cells."""
    lines = report.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(f"| {first_header} |"))
    out = []
    for ln in lines[start + 2 :]:
        if not ln.startswith("|"):
            break
        out.append([c.strip() for c in re.split(r"(?<!\\)\|", ln)[1:-1]])
    return out


def expected_cells(rows: list[dict[str, Any]], paths: list[str]) -> dict[tuple[Any, ...], dict[str, Any]]:
    by: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        by.setdefault(tuple(r[p] for p in paths), []).append(r)
    out = {}
    for key, rs in by.items():
        fin = [r for r in rs if r["error"] is None]
        k = sum(1 for r in fin if r["success"])
        ferr = [r["max_formation_error_m"] for r in fin if r["max_formation_error_m"] is not None]
        causes = Counter(c for r in fin if not r["success"] for c in r["causes"].split(","))
        out[key] = {
            "runs": len(rs),
            "crashed": len(rs) - len(fin),
            "k": k,
            "n": len(fin),
            "median": float(np.median(ferr)) if ferr else None,
            "worst": max(ferr) if ferr else None,
            "clear": min((r["min_obstacle_clearance_m"] for r in fin), default=None),
            "sep": min((r["min_inter_uav_distance_m"] for r in fin), default=None),
            "causes": causes,
        }
    return out


def check_row(cells: list[str], nax: int, e: dict[str, Any]) -> None:
    runs, crashed, success, rate, ci, med, worst, clear, sep, causes = cells[nax:]
    assert int(runs.split()[0]) == e["runs"]
    assert int(crashed) == e["crashed"]
    assert success == f"{e['k']}/{e['n']}"
    assert float(rate.rstrip(" %")) == pytest.approx(100 * e["k"] / e["n"], abs=0.05)
    lo, hi = (float(x.strip(" %")) for x in ci.strip("[]").split(","))
    # the Wilson interval, independently: centre +- half (formula of the docstring)
    z, n, p = 1.959963984540054, e["n"], e["k"] / e["n"]
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    assert lo == pytest.approx(100 * max(0.0, centre - half), abs=0.05)
    assert hi == pytest.approx(100 * min(1.0, centre + half), abs=0.05)
    for got, want in ((med, e["median"]), (worst, e["worst"]), (clear, e["clear"]), (sep, e["sep"])):
        assert float(got) == pytest.approx(want, abs=5e-4)
    got_causes = dict(kv.split(": ") for kv in re.sub(r" \(\+\d+ more\)$", "", causes).split(", ")) if causes else {}
    top = e["causes"].most_common()
    assert {k: int(v) for k, v in got_causes.items()}.items() <= dict(top).items()
    assert len(got_causes) == min(3, len(top))
    if top:
        assert max(int(v) for v in got_causes.values()) == top[0][1]


def assert_png(p: Path) -> None:
    data = p.read_bytes()
    assert data[:8] == PNG, p
    from matplotlib.image import imread

    img = imread(p)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert float(np.std(img[..., :3])) > 0.01  # something is drawn


# =========================================================================== the interval


@pytest.mark.parametrize(
    ("k", "n", "lo", "hi"),
    [
        # Newcombe (1998), Stat. Med. 17:857, Table I, method 3 (score interval without correction)
        (81, 263, 0.2553, 0.3662),
        (15, 148, 0.0624, 0.1605),
        (0, 20, 0.0, 0.1611),
        (1, 29, 0.0061, 0.1718),
    ],
)
def test_wilson_matches_published_values(k: int, n: int, lo: float, hi: float) -> None:
    got = wilson_interval(k, n)
    assert got[0] == pytest.approx(lo, abs=6e-5)
    assert got[1] == pytest.approx(hi, abs=6e-5)


@pytest.mark.parametrize("n", [1, 3, 10, 100])
def test_wilson_closed_forms_at_the_ends(n: int) -> None:
    z2 = 1.959963984540054**2
    assert wilson_interval(0, n) == pytest.approx((0.0, z2 / (n + z2)), abs=1e-12)
    assert wilson_interval(n, n) == pytest.approx((n / (n + z2), 1.0), abs=1e-12)
    # p = 1/2: centred on 1/2, half-width z / (2 sqrt(n + z^2))
    if n % 2 == 0:
        lo, hi = wilson_interval(n // 2, n)
        assert (lo + hi) / 2 == pytest.approx(0.5, abs=1e-12)
        assert (hi - lo) / 2 == pytest.approx(math.sqrt(z2) / (2 * math.sqrt(n + z2)), abs=1e-12)
    for k in range(n + 1):  # symmetric: the interval of failures mirrors the one of successes
        lo, hi = wilson_interval(k, n)
        lo2, hi2 = wilson_interval(n - k, n)
        assert lo == pytest.approx(1 - hi2, abs=1e-12) and hi == pytest.approx(1 - lo2, abs=1e-12)
        assert 0.0 <= lo <= k / n <= hi <= 1.0


def test_wilson_rejects_impossible_counts() -> None:
    assert wilson_interval(0, 0) == (0.0, 1.0)
    for k, n in ((3, 2), (-1, 4), (0, -1)):
        with pytest.raises(ValueError):
            wilson_interval(k, n)


# =========================================================================== campaigns


GRID = [{"path": "faults.loss", "values": [0.0, 0.1, 0.2]}, {"path": "faults.delay", "values": [0.0, 0.05, 0.1]}]


@pytest.mark.slow  # ~2 s of CPU: 5-7 figures
def test_grid_3x3x10(tmp_path: Path) -> None:
    rows = synth_rows(GRID, 10, np.random.default_rng(7), crash_every=13)
    d = make_campaign(tmp_path / "camp", GRID, rows)
    path = write_report(d)
    assert path == d / "report.md"
    text = path.read_text()
    crashed = sum(r["error"] is not None for r in rows)
    assert crashed >= 5
    assert f"90 planned, 90 in runs.parquet: {90 - crashed} finished, {crashed} crashed" in text
    assert "every planned run is in the table" in text
    assert "`zenswarm sweep paper_example1 --seeds 10 --out 'camp dir'`" in text
    assert "0.1.0" in text and "paper_example1" in text
    got = table_rows(text, "`faults.loss`")
    assert len(got) == 9
    exp = expected_cells(rows, ["faults.loss", "faults.delay"])
    seen = []
    for cells in got:
        key = (float(cells[0]), float(cells[1]))
        seen.append(key)
        check_row(cells, 2, exp[key])
    assert seen == sorted(exp)  # sorted numerically, loss then delay
    assert "## Crashed runs" in text and "RuntimeError: boom \\| pipe" in text
    plots = d / "plots"
    names = {"heatmap_success_rate.png", "heatmap_formation_error.png", "curve_faults.loss.png", "curve_faults.delay.png"}
    names.add("formation_error_hist.png")
    assert {p.name for p in plots.glob("*.png")} == names
    for n in names:
        assert_png(plots / n)
        assert f"](plots/{n})" in text


def test_one_integer_axis(tmp_path: Path) -> None:
    axes = [{"path": "n", "values": [8, 4, 6]}]
    rows = synth_rows(axes, 5, np.random.default_rng(1))
    d = make_campaign(tmp_path / "c", axes, rows, seeds=5)
    text = write_report(d).read_text()
    got = table_rows(text, "`n`")
    assert [c[0] for c in got] == ["4", "6", "8"]  # numerically
    exp = expected_cells(rows, ["n"])
    for cells in got:
        check_row(cells, 1, exp[(int(cells[0]),)])
    assert {p.name for p in (d / "plots").glob("*.png")} == {"curve_n.png", "formation_error_hist.png"}
    assert_png(d / "plots" / "curve_n.png")


def test_seeds_only(tmp_path: Path) -> None:
    rows = synth_rows([], 20, np.random.default_rng(2), crash_every=7)
    for r in rows:
        r["cell"] = ""
    d = make_campaign(tmp_path / "c", [], rows, seeds=20)
    text = write_report(d).read_text()
    assert "nothing (seeds only)" in text
    got = table_rows(text, "cell")
    assert len(got) == 1 and got[0][0] == "all runs"
    check_row(got[0], 1, expected_cells(rows, [])[()])
    assert [p.name for p in (d / "plots").glob("*.png")] == ["formation_error_hist.png"]
    assert_png(d / "plots" / "formation_error_hist.png")


@pytest.mark.slow  # ~2 s of CPU: 5-7 figures
def test_string_axis_three_axes_and_a_sampled_field(tmp_path: Path) -> None:
    axes = [
        {"path": "agents.controller", "values": ["paper", "pid", "lqr"]},
        {"path": "faults.loss", "values": [0.2, 0.0]},
        {"path": "n", "values": [4, 5]},
    ]
    rows = synth_rows(axes, 3, np.random.default_rng(3))
    draws = np.random.default_rng(5).uniform(0.0, 3.0, len(rows) // 3)  # one draw per grid cell, its 3 seeds share it
    for r in rows:
        r["disturbance.wind"] = float(draws[r["run"] // 3])
        del r["cell"]  # no `cell` column: the cells come from the axes' columns
    sampled = {"path": "disturbance.wind", "low": 0.0, "high": 3.0, "samples": 1}
    d = make_campaign(tmp_path / "c", [*axes, sampled], rows, seeds=3)
    pq.write_table(pq.read_table(d / "runs.parquet").drop(["cell"]), d / "runs.parquet")
    text = write_report(d).read_text()
    assert "pooled over seeds and over `n`, `disturbance.wind`" in text
    assert "`disturbance.wind` sampled uniformly in [0, 3], 1 draws" in text
    assert "the runs of every value of `n` are pooled in each square" in text
    got = table_rows(text, "`agents.controller`")
    # the controller in campaign order (not alphabetical), the loss numerically
    assert [(c[0], c[1], c[2]) for c in got] == [(a, b, c) for a in ("paper", "pid", "lqr") for b in ("0", "0.2") for c in ("4", "5")]
    exp = expected_cells(rows, ["agents.controller", "faults.loss", "n"])
    wind = {(r["agents.controller"], r["faults.loss"], r["n"]): r["disturbance.wind"] for r in rows}
    for cells in got:
        key = (cells[0], float(cells[1]), int(cells[2]))
        assert float(cells[3]) == pytest.approx(wind[key], rel=1e-5)
        check_row(cells, 4, exp[key])
    names = ["heatmap_success_rate.png", "heatmap_formation_error.png", "curve_agents.controller.png", "curve_faults.loss.png"]
    names += ["curve_n.png", "scatter_disturbance.wind.png", "formation_error_hist.png"]
    assert sorted(p.name for p in (d / "plots").glob("*.png")) == sorted(names)
    for n in names:
        assert_png(d / "plots" / n)


LOSS9 = [{"path": "faults.loss", "values": [round(0.05 * i, 2) for i in range(9)]}]


def test_partial_campaign(tmp_path: Path) -> None:
    rows = synth_rows(LOSS9, 10, np.random.default_rng(6))
    gone = {5, 17, 18, 19} | set(range(80, 90))  # run 5, 17-19 and the whole last cell
    kept = [r for r in rows if r["run"] not in gone]
    d = make_campaign(tmp_path / "c", LOSS9, kept, runs=90)
    text = write_report(d).read_text()
    assert "14 of 90 runs missing (run index): 5, 17-19, 80-89" in text
    assert "76 in runs.parquet" in text
    got = table_rows(text, "`faults.loss`")
    assert len(got) == 8
    assert [c[1] for c in got[:3]] == ["9 (of 10)", "7 (of 10)", "10"]
    exp = expected_cells(kept, ["faults.loss"])
    for cells in got:
        check_row(cells, 1, exp[(float(cells[0]),)])
    assert_png(d / "plots" / "curve_faults.loss.png")


def test_campaign_before_its_first_run(tmp_path: Path) -> None:
    d = make_campaign(tmp_path / "c", LOSS9, [], runs=90, write_table=False)
    text = write_report(d).read_text()
    assert "90 of 90 runs missing (run index): 0-89" in text
    assert "No run has finished yet." in text
    assert_png(d / "plots" / "curve_faults.loss.png")


# =========================================================================== errors


def test_errors_are_typed_and_name_the_problem(tmp_path: Path) -> None:
    with pytest.raises(CampaignError, match="no such directory"):
        write_report(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CampaignError, match="not a campaign directory: campaign.json missing"):
        write_report(tmp_path / "empty")
    d = make_campaign(tmp_path / "c", GRID, synth_rows(GRID, 2, np.random.default_rng(0)), seeds=2)
    (d / "runs.parquet").write_bytes(b"PAR1 this is not parquet")
    with pytest.raises(CampaignError, match="runs.parquet unreadable"):
        write_report(d)
    assert not (d / "report.md").exists()
    (d / "campaign.json").write_text("{not json")
    with pytest.raises(CampaignError, match="campaign.json unreadable"):
        write_report(d)
    for meta, msg in (
        ({"runs": "ten", "axes": []}, "runs: must be a non-negative integer"),
        ({"runs": 3, "axes": [{"values": [1]}]}, r"axes\[0\]: needs a 'path'"),
        ({"runs": 3, "axes": [{"path": "n"}]}, r"axes\[0\] \(n\): needs 'values'"),
        ({"runs": 3, "version": 2, "axes": []}, "version: 2 is not supported"),
    ):
        (d / "campaign.json").write_text(json.dumps(meta))
        with pytest.raises(CampaignError, match=msg):
            load_campaign(d)
    # a swept input without its column
    e = make_campaign(tmp_path / "e", GRID, synth_rows(GRID, 1, np.random.default_rng(0)), seeds=1)
    pq.write_table(pq.read_table(e / "runs.parquet").drop(["faults.delay"]), e / "runs.parquet")
    with pytest.raises(CampaignError, match="column 'faults.delay' missing") as ei:
        write_report(e)
    assert isinstance(ei.value, ZenswarmError)


def test_without_pyarrow_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    d = make_campaign(tmp_path / "c", [], synth_rows([], 2, np.random.default_rng(0)), seeds=2)
    monkeypatch.setitem(__import__("sys").modules, "pyarrow", None)
    monkeypatch.setitem(__import__("sys").modules, "pyarrow.parquet", None)
    with pytest.raises(CampaignError, match="needs pyarrow"):
        write_report(d)


@pytest.mark.parametrize("module", [sweep_report, sweep_campaign, sweep_stats, sweep_figures], ids=lambda m: m.__name__.rsplit(".", 1)[1])
def test_module_imports_pyarrow_and_matplotlib_lazily(module: ModuleType) -> None:
    # the report's module and the three it reads from (the campaign, the statistics, the plots; issue 44)
    tree = ast.parse(Path(module.__file__ or "").read_text())
    top = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    names = {a.name for n in top if isinstance(n, ast.Import) for a in n.names} | {n.module for n in top if isinstance(n, ast.ImportFrom)}
    assert not {m for m in names if m and m.split(".")[0] in ("pyarrow", "matplotlib", "pandas")}

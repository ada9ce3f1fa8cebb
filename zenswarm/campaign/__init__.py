"""The plan of an experiment campaign (``zenswarm sweep``): its axes, and the list of runs.

Pure planning, no flight: :mod:`zenswarm.sweep` validates the plan against the scenario, flies
the runs and writes the table (docs/campaigns.md). Its companion
:mod:`zenswarm.campaign.delaymargin` is the generator's delay margin (eqs 16-17) that ``zenswarm
margin`` and a campaign's delay axes are read against.

A campaign is a scenario, grid axes (every combination of their values), optional sampled axes
(``samples`` uniform draws, shared by every grid cell), and ``seeds`` Monte Carlo seeds
``base_seed, base_seed + 1, ...`` (the run's ``scenario.seed``: disturbances and fault decisions).
The runs are numbered in a fixed order (grid cells in the order given, the last axis fastest;
then the draws; then the seeds), so the same command always gives the same run indices.

An axis names a scenario field by its dotted path (``faults.loss``, ``faults.delay``,
``generator.mu1``, ``agents.controller``, ``leader.planner``, ``obstacles[0].radius``) or, when
the scenario is the word ``generate``, a parameter of :func:`zenswarm.scenario.generate.generate_scenario`
(:data:`GENERATOR_FIELDS`: ``n``, ``shape``, ``topology``, ``k``, ``pinning``, ``n_obstacles``,
``spacing``). Values are TOML values (``0.1``, ``3``, ``true``, ``"ring"``, ``[1, 2, 0.5]``) or
bare words (``ring``, ``50ms``). Durations with a unit (``50ms``) reach the scenario as written and
are stored in the table in seconds; distances (``0.3m``: ``faults.range``) in metres, rates
(``64kB/s``: ``faults.capacity``) in bytes/s.
"""

from __future__ import annotations

import itertools
import json
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.link import parse_capacity, parse_distance, parse_duration
from zenswarm.schema import MAX_SEED

__all__ = [
    "GENERATE",
    "GENERATOR_FIELDS",
    "PLUGIN_FIELDS",
    "GridAxis",
    "SampleAxis",
    "Plan",
    "Run",
    "parse_value",
    "split_values",
    "parse_grid",
    "parse_sample",
    "column_value",
    "column_kind",
    "cell_text",
    "check_plan",
    "expand",
    "plan_from_toml",
    "is_campaign_document",
]

GENERATE = "generate"
"""The scenario word that makes every run's scenario a generated one (``zenswarm scenario generate``)."""

GENERATOR_FIELDS: dict[str, type] = {
    "n": int, "shape": str, "topology": str, "k": int, "pinning": str, "n_obstacles": int, "spacing": float,
}
"""Axes of a generated scenario: keyword arguments of :func:`zenswarm.scenario.generate.generate_scenario`
(its ``seed`` is the run's seed)."""

PLUGIN_FIELDS: tuple[str, ...] = ("agents.controller", "leader.planner")
"""Plug-in selections: flown as ``fly(controller=..., planner=...)`` (a planner also sets ``leader.adaptive``)."""


@dataclass(frozen=True)
class GridAxis:
    """``--grid PATH=V1,V2,...``: every value is flown (in every combination with the other axes)."""

    path: str
    values: tuple[Any, ...]


@dataclass(frozen=True)
class SampleAxis:
    """``--sample PATH=LOW:HIGH``: uniform draws in [low, high] (integers inclusive when both ends
    are integers; durations in seconds when the ends are durations such as ``0ms:100ms``)."""

    path: str
    low: Any
    high: Any


@dataclass(frozen=True)
class Plan:
    """What a campaign flies. scenario: a built-in name, a TOML file or :data:`GENERATE`.
    duration: the flights' ``timing.time_limit_s`` in s (None: the scenario's). mode: ``sim`` or
    ``swarm``. check_swarm: that many random runs are flown again as lockstep swarms."""

    scenario: str
    grid: tuple[GridAxis, ...] = ()
    samples: tuple[SampleAxis, ...] = ()
    n_samples: int = 0
    seeds: int = 1
    base_seed: int = 0
    mode: str = "sim"
    duration: float | None = None
    check_swarm: int = 0

    def axes_json(self) -> list[dict[str, Any]]:
        """``campaign.json``'s ``axes``: grid axes (values in table units), then sampled fields."""
        kinds = [column_kind([column_value(v) for v in a.values]) for a in self.grid]
        out: list[dict[str, Any]] = [
            {"path": a.path, "values": [float(column_value(v)) if k == "float" else column_value(v) for v in a.values]}
            for a, k in zip(self.grid, kinds, strict=True)
        ]
        out += [{"path": s.path, "low": column_value(s.low), "high": column_value(s.high), "samples": self.n_samples} for s in self.samples]
        return out


@dataclass(frozen=True)
class Run:
    """One run of a campaign. run: its index; cell: its parameter cell (all inputs but the seed);
    seed: its ``scenario.seed``; inputs: ``{path: value}`` as given to the scenario (``"50ms"``);
    columns: ``{path: value}`` as the table stores them (0.05)."""

    run: int
    cell: str
    seed: int
    inputs: Mapping[str, Any]
    columns: Mapping[str, Any]


# ----------------------------------------------------------------------------- values


def split_values(text: str) -> list[str]:
    """``"0,0.1,[1, 2],'a,b'"`` -> ["0", "0.1", "[1, 2]", "'a,b'"]: commas outside brackets and quotes."""
    out: list[str] = []
    cur: list[str] = []
    depth, quote = 0, ""
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur).strip())
    return out


def parse_value(text: str) -> Any:
    """A value as written on the command line: a TOML value (``0.1``, ``3``, ``true``,
    ``"ring"``, ``[1, 2]``), else the text itself (``ring``, ``50ms``, ``plugin_fixtures:X``)."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text.strip()


def _duration_s(v: Any) -> float | None:
    """Seconds of a duration text with a unit (``"50ms"``); None for anything else."""
    if not isinstance(v, str) or not v.strip() or v.strip()[-1].isdigit():
        return None
    try:
        return parse_duration(v)
    except ValueError:
        return None


def _unit_number(v: Any) -> float | None:
    """Metres of a distance with a unit (``"0.3m"``, ``"150cm"``: ``faults.range``) or bytes/s of a
    rate with a unit (``"64kB/s"``, ``"1Mbps"``: ``faults.capacity``); None for anything else (a
    bare number, a word, a queue in bytes such as ``"4kB"``)."""
    if not isinstance(v, str) or not v.strip() or v.strip()[-1].isdigit():
        return None
    for parse in (parse_distance, parse_capacity):
        try:
            x = parse(v)
        except ValueError:
            continue
        return x if math.isfinite(x) else None
    return None


def column_value(v: Any) -> Any:
    """A value as the table stores it: durations in seconds, distances with a unit in metres,
    rates with a unit in bytes/s, lists and tables as JSON text."""
    d = _duration_s(v)
    if d is not None:
        return d
    u = _unit_number(v)
    if u is not None:
        return u
    if isinstance(v, (list, dict)):
        return json.dumps(v, separators=(",", ":"))
    return v


def column_kind(values: Sequence[Any]) -> str:
    """The column type of these table values: ``bool``, ``int``, ``float`` or ``string``."""
    vals = [v for v in values if v is not None]
    if vals and all(isinstance(v, bool) for v in vals):
        return "bool"
    if vals and all(isinstance(v, int) and not isinstance(v, bool) for v in vals):
        return "int"
    if vals and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
        return "float"
    return "string"


def _fmt(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def cell_text(columns: Mapping[str, Any]) -> str:
    """The cell's name: ``faults.loss=0.1,faults.delay=0.05`` (table values, axes in order)."""
    return ",".join(f"{k}={_fmt(v)}" for k, v in columns.items())


# ----------------------------------------------------------------------------- axes


def _check_path(path: str, flag: str) -> str:
    import re

    if not re.fullmatch(r"[A-Za-z_][\w-]*(\[\d+\]|\.[A-Za-z_][\w-]*)*", path or ""):
        raise ScenarioError(flag, f"{path!r} is not a dotted path to a scenario field (e.g. faults.loss, obstacles[0].radius)")
    return path


def parse_grid(text: str, flag: str = "--grid") -> GridAxis:
    """``"faults.loss=0,0.1,0.2"`` -> GridAxis; ScenarioError naming ``flag`` on bad syntax."""
    path, sep, rest = text.partition("=")
    if not sep or not rest.strip():
        raise ScenarioError(flag, f"{text!r}: expected PATH=V1,V2,... (e.g. faults.loss=0,0.1,0.2)")
    parts = split_values(rest)
    if any(not p for p in parts):
        raise ScenarioError(path.strip(), f"{text!r}: an empty value in the list")
    return GridAxis(_check_path(path.strip(), flag), tuple(parse_value(p) for p in parts))


def parse_sample(text: str, flag: str = "--sample") -> SampleAxis:
    """``"faults.loss=0:0.3"`` or ``"faults.delay=0ms:100ms"`` -> SampleAxis (ends checked by :func:`check_plan`)."""
    path, sep, rest = text.partition("=")
    low, sep2, high = rest.partition(":")
    if not sep or not sep2 or not low.strip() or not high.strip():
        raise ScenarioError(flag, f"{text!r}: expected PATH=LOW:HIGH (e.g. faults.loss=0:0.3, faults.delay=0ms:100ms)")
    return SampleAxis(_check_path(path.strip(), flag), parse_value(low), parse_value(high))


def _sample_ends(s: SampleAxis) -> tuple[float, float, str]:
    """(low, high, kind) of a sampled axis in table units; kind ``int``, ``float`` or ``duration``."""
    lo, hi = column_value(s.low), column_value(s.high)
    kind = "duration" if _duration_s(s.low) is not None or _duration_s(s.high) is not None else column_kind([lo, hi])
    if kind == "duration" and not all(_duration_s(x) is not None or x == 0 for x in (s.low, s.high)):
        raise ScenarioError(s.path, f"sample range {s.low!r}:{s.high!r}: give both ends as durations (e.g. 0ms:100ms)")
    if kind not in ("int", "float", "duration"):
        raise ScenarioError(s.path, f"sample range {s.low!r}:{s.high!r}: the ends must be numbers or durations")
    lo_f, hi_f = float(lo), float(hi)
    if not (math.isfinite(lo_f) and math.isfinite(hi_f)) or lo_f > hi_f:
        raise ScenarioError(s.path, f"sample range {s.low!r}:{s.high!r}: expected finite LOW <= HIGH")
    return lo_f, hi_f, kind


def check_plan(plan: Plan) -> None:
    """Everything about the plan that needs no scenario: counts, seeds, duplicate or misplaced
    axes, sample ranges. ScenarioError naming the flag or the path."""
    _check_counts(plan)
    seen: set[str] = set()
    for path in [a.path for a in plan.grid] + [s.path for s in plan.samples]:
        if path in seen:
            raise ScenarioError(path, "given twice (as --grid or --sample)")
        seen.add(path)
        if path in ("scenario.seed", "seed"):
            raise ScenarioError(path, "the seed is the campaign's: use --seeds N and --base-seed S")
        if path == "timing.time_limit_s" and plan.duration is not None:
            raise ScenarioError(path, "both swept and set by --duration")
        if path in GENERATOR_FIELDS and plan.scenario != GENERATE:
            raise ScenarioError(path, f"a parameter of generated scenarios: give the scenario as {GENERATE!r}")
    for a in plan.grid:
        if not a.values:
            raise ScenarioError(a.path, "no values")
        for v in a.values:
            _check_generator_value(a.path, v)
    for s in plan.samples:
        _check_sample(s)


def _check_counts(plan: Plan) -> None:
    if plan.mode not in ("sim", "swarm"):
        raise ScenarioError("--mode", f"expected sim or swarm, got {plan.mode!r}")
    for name, v, lo in (("--seeds", plan.seeds, 1), ("--base-seed", plan.base_seed, 0), ("--samples", plan.n_samples, 0),
                        ("--check-swarm", plan.check_swarm, 0)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise ScenarioError(name, f"expected an integer >= {lo}, got {v!r}")
    if plan.base_seed + plan.seeds - 1 > MAX_SEED:
        raise ScenarioError("--base-seed", f"the seeds run past {MAX_SEED}")
    d = plan.duration
    if d is not None and (isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or d <= 0):
        raise ScenarioError("--duration", f"expected seconds > 0, got {d!r}")
    if plan.samples and plan.n_samples < 1:
        raise ScenarioError("--samples", "--sample needs --samples K >= 1 (the number of draws)")
    if plan.n_samples and not plan.samples:
        raise ScenarioError("--samples", "--samples needs at least one --sample PATH=LOW:HIGH")
    if plan.check_swarm and plan.mode != "sim":
        raise ScenarioError("--check-swarm", "compares swarm flights with the simulator: needs --mode sim")


def _check_sample(s: SampleAxis) -> None:
    _, _, kind = _sample_ends(s)
    if s.path in PLUGIN_FIELDS or s.path in GENERATOR_FIELDS and GENERATOR_FIELDS[s.path] is str:
        raise ScenarioError(s.path, "a name cannot be sampled from a range: use --grid")
    if s.path in GENERATOR_FIELDS and GENERATOR_FIELDS[s.path] is int and kind != "int":
        raise ScenarioError(s.path, f"sample range {s.low!r}:{s.high!r}: expected integer ends")


def _check_generator_value(path: str, v: Any) -> None:
    """A value of a generator axis: its type, and a known word for shape, topology and pinning."""
    if path not in GENERATOR_FIELDS:
        return
    from zenswarm.scenario.generate import PINNINGS, SHAPES, TOPOLOGIES

    want = GENERATOR_FIELDS[path]
    num = isinstance(v, int) and not isinstance(v, bool)
    if not (isinstance(v, want) and not isinstance(v, bool) or want is float and num):
        raise ScenarioError(path, f"expected {want.__name__} values, got {v!r}")
    words = {"shape": SHAPES, "topology": TOPOLOGIES, "pinning": PINNINGS}.get(path)
    if words is not None and v not in words:
        raise ScenarioError(path, f"unknown {path} {v!r} (choose from {', '.join(words)})")
    if path in ("n", "k") and v < 1 or path == "n_obstacles" and v < 0 or path == "spacing" and not v > 0:
        raise ScenarioError(path, f"out of range: {v!r}")


def _draws(plan: Plan) -> list[dict[str, tuple[Any, Any]]]:
    """The sampled values, ``samples`` draws of every sampled axis: {path: (input, table value)}."""
    if not plan.samples:
        return [{}]
    rng = np.random.default_rng(np.random.SeedSequence([plan.base_seed, 17]))
    out: list[dict[str, tuple[Any, Any]]] = [{} for _ in range(plan.n_samples)]
    for s in plan.samples:
        lo, hi, kind = _sample_ends(s)
        for d in out:
            if kind == "int":
                v_i = int(rng.integers(int(lo), int(hi) + 1))
                d[s.path] = (v_i, v_i)
            elif kind == "duration":
                x = float(rng.uniform(lo, hi))
                d[s.path] = (f"{x!r}s", parse_duration(f"{x!r}s"))
            else:
                x = float(rng.uniform(lo, hi))
                d[s.path] = (x, x)
    return out


def expand(plan: Plan) -> list[Run]:
    """Every run of the campaign, in run order (see the module docstring). Call :func:`check_plan` first."""
    runs: list[Run] = []
    grids = [[(a.path, v) for v in a.values] for a in plan.grid]
    floats = {a.path for a in plan.grid if column_kind([column_value(v) for v in a.values]) == "float"}

    def col(p: str, v: Any) -> Any:  # one type per column: 0 and 0.1 are 0.0 and 0.1
        c = column_value(v)
        return float(c) if p in floats else c

    draws = _draws(plan)
    for combo in itertools.product(*grids):
        for draw in draws:
            inputs = {p: v for p, v in combo} | {p: iv for p, (iv, _) in draw.items()}
            columns = {p: col(p, v) for p, v in combo} | {p: cv for p, (_, cv) in draw.items()}
            cell = cell_text(columns)
            for i in range(plan.seeds):
                runs.append(Run(len(runs), cell, plan.base_seed + i, inputs, columns))
    return runs


# ----------------------------------------------------------------------------- campaign files


def is_campaign_document(doc: Mapping[str, Any]) -> bool:
    """A TOML document is a campaign file when it has a ``[campaign]`` table (a scenario has none)."""
    return isinstance(doc.get("campaign"), dict)


_CAMPAIGN_KEYS = {"scenario", "seeds", "base_seed", "samples", "mode", "duration", "check_swarm", "out"}


def plan_from_toml(doc: Mapping[str, Any], resolve_scenario: Any = None) -> tuple[Plan, str | None]:
    """A campaign file's plan and its ``out`` (None if absent). ``resolve_scenario(text)`` maps the
    ``scenario`` key (e.g. a path relative to the file); identity by default. Format::

        [campaign]
        scenario = "paper_example1"   # a built-in name, a TOML file (relative to this file) or "generate"
        seeds = 10                    # Monte Carlo seeds base_seed, base_seed + 1, ...
        base_seed = 0                 # optional (0)
        mode = "sim"                  # optional: sim | swarm
        duration = 20.0               # optional: timing.time_limit_s of every flight, s
        samples = 0                   # optional: draws of the [sample] ranges
        check_swarm = 0               # optional
        out = "runs/campaign1"        # optional (--out wins)

        [grid]                        # every combination, in this order
        "faults.loss" = [0, 0.1, 0.2]
        "faults.delay" = ["0ms", "50ms", "100ms"]

        [sample]                      # uniform draws in [low, high]
        "faults.jitter" = ["0ms", "20ms"]

    ScenarioError naming ``campaign.KEY`` / ``grid.PATH`` / ``sample.PATH``."""
    c = doc["campaign"]
    for k in c:
        if k not in _CAMPAIGN_KEYS:
            raise ScenarioError(f"campaign.{k}", f"unknown key (known: {', '.join(sorted(_CAMPAIGN_KEYS))})")
    for k in doc:
        if k not in ("campaign", "grid", "sample"):
            raise ScenarioError(k, "unknown table in a campaign file (known: campaign, grid, sample)")
    if not isinstance(c.get("scenario"), str):
        raise ScenarioError("campaign.scenario", "required: a built-in scenario name, a TOML file or 'generate'")
    grid_t, sample_t = doc.get("grid", {}), doc.get("sample", {})
    if not isinstance(grid_t, dict) or not isinstance(sample_t, dict):
        raise ScenarioError("grid", "[grid] and [sample] are tables of PATH = [values]")
    grid = []
    for path, vals in grid_t.items():
        if not isinstance(vals, list) or not vals:
            raise ScenarioError(f"grid.{path}", "expected a non-empty list of values")
        grid.append(GridAxis(_check_path(path, f"grid.{path}"), tuple(vals)))
    samples = []
    for path, ends in sample_t.items():
        if not isinstance(ends, list) or len(ends) != 2:
            raise ScenarioError(f"sample.{path}", "expected [low, high]")
        samples.append(SampleAxis(_check_path(path, f"sample.{path}"), ends[0], ends[1]))
    scen = c["scenario"] if resolve_scenario is None or c["scenario"] == GENERATE else resolve_scenario(c["scenario"])
    dur = c.get("duration")
    plan = Plan(
        scenario=str(scen), grid=tuple(grid), samples=tuple(samples), n_samples=c.get("samples", 0), seeds=c.get("seeds", 1),
        base_seed=c.get("base_seed", 0), mode=c.get("mode", "sim"), duration=float(dur) if isinstance(dur, int) and not isinstance(
            dur, bool) else dur, check_swarm=c.get("check_swarm", 0),
    )
    out = c.get("out")
    if out is not None and not isinstance(out, str):
        raise ScenarioError("campaign.out", "expected a directory path")
    return plan, out

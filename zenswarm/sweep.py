"""``zenswarm sweep``: fly an experiment campaign in parallel and write its results table.

The plan (axes, seeds, run order) is :mod:`zenswarm.campaign`; each run is one
:func:`zenswarm.api.fly` (the simulator, or the lockstep swarm with ``--mode swarm``). The runs go
to a local process pool (``--workers``, all cores by default) or to a Dask distributed cluster
(``--scheduler tcp://HOST:PORT``) through one interface (:class:`Backend`: submit, wait for the
first finished, cancel). A run's row is a pure function of its inputs, so both give the same rows.

Campaign directory (docs/campaigns.md): ``campaign.json`` (the plan, written before the first
run), ``runs.jsonl`` (the journal: one line per finished run, appended and flushed as it
finishes), ``runs.parquet`` (the table, rebuilt from the journal and replaced atomically as runs
finish). Re-running the same command resumes: the journal's runs are skipped. Ctrl-C loses the runs
in flight only. A run that raises is recorded with its error after one retry (``attempts``); a
run whose plug-in failed (``plugin_error``, deterministic: not retried) has its failure as its
``error``, beside the figures of what it flew.

Exit status: 0 every run recorded without a crash, 1 some run crashed (``error``) or a
``--check-swarm`` run differed from the simulator, 2 bad input (before anything runs), 130 Ctrl-C.
"""

from __future__ import annotations

import abc
import argparse
import concurrent.futures as cf
import hashlib
import json
import math
import multiprocessing
import os
import random
import signal
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from zenswarm import __version__
from zenswarm.api import fly, load, scenario_path
from zenswarm.campaign import (
    GENERATE,
    GENERATOR_FIELDS,
    PLUGIN_FIELDS,
    Plan,
    Run,
    check_plan,
    column_kind,
    expand,
    is_campaign_document,
    parse_grid,
    parse_sample,
    plan_from_toml,
)
from zenswarm.errors import ScenarioError, run_command
from zenswarm.link import plan_for
from zenswarm.process.paths import check_output_dir
from zenswarm.scenario.config import trace_in
from zenswarm.scenario.plugins import check_selection

__all__ = ["main", "run_one", "metric_columns", "read_rows", "INSTALL_HINT"]

INSTALL_HINT = "pip install zenswarm[sweep]"

METRICS_FLOAT: tuple[str, ...] = (
    "max_formation_error_m", "max_generator_formation_error_m", "rms_tracking_error_m", "max_final_slot_error_m",
    "min_obstacle_clearance_m", "min_obstacle_margin_m", "min_inter_uav_distance_m", "min_inter_uav_margin_m",
    "min_altitude_m", "time_to_goal_s", "final_leader_goal_distance_m", "sim_time_s",
)
"""Scalar figures of results.json copied into the table (float64; null when not measured)."""
METRICS_BOOL: tuple[str, ...] = ("goal_reached", "finite", "ended_early")


def metric_columns() -> tuple[str, ...]:
    """The verdict's columns, compared by ``--check-swarm`` and by the tests (wall time excluded)."""
    return ("success", "causes", *METRICS_BOOL, *METRICS_FLOAT)


# ----------------------------------------------------------------------------- one run


def run_one(task: Mapping[str, Any]) -> dict[str, Any]:
    """Fly one run and return its table row (inputs, verdict, figures, wall time). Never raises
    for a run's own failure: an exception is returned as ``error`` (the driver retries once).
    Runs in a worker process (local pool or Dask worker): ``task`` is plain data."""
    t0 = time.perf_counter()
    row: dict[str, Any] = {"run": task["run"], "cell": task["cell"], "seed": task["seed"], **task["columns"]}
    try:
        if task["generate"] is not None:
            from zenswarm.scenario.generate import generate_scenario

            doc: Any = generate_scenario(**task["generate"], seed=task["seed"])
        else:
            doc = task["scenario"]
        f = fly(
            doc, mode=task["mode"], overrides=task["overrides"], duration=task["duration"], seed=task["seed"],
            controller=task["controller"], planner=task["planner"],
        )
        r = f.results
        failed = [x for x in f.failures if x.cause == "plugin_error"]
        error = f"plugin_error: {failed[0].detail}" if failed else None
        row |= {"success": bool(f.success), "causes": ",".join(f.causes), "error": error}
        row |= {k: None if r.get(k) is None else float(r[k]) for k in METRICS_FLOAT}
        row |= {k: None if r.get(k) is None else bool(r[k]) for k in METRICS_BOOL}
    except Exception as e:  # noqa: BLE001 -- a crashing run is data: recorded with its error, retried once by the driver
        row |= {"success": False, "causes": "", "error": f"{type(e).__name__}: {e}"}
        row |= {k: None for k in (*METRICS_FLOAT, *METRICS_BOOL)}
    row |= {"wall_s": time.perf_counter() - t0, "zenswarm_version": __version__, "mode": task["mode"]}
    return row


def _task(run: Run, plan: Plan, doc: dict[str, Any] | None, mode: str | None = None) -> dict[str, Any]:
    gen = {p: v for p, v in run.inputs.items() if p in GENERATOR_FIELDS}
    if plan.scenario == GENERATE and "n" not in gen:
        gen["n"] = 3
    ov = {p: v for p, v in run.inputs.items() if p not in GENERATOR_FIELDS and p not in PLUGIN_FIELDS}
    trace = ov.get("faults.trace")
    if isinstance(trace, str) and not Path(trace).is_absolute():
        # beside the scenario file, as `--set faults.trace=` and api.fly take it; a generated
        # scenario has no file: the working directory
        ov["faults.trace"] = trace_in(trace, Path.cwd() if plan.scenario == GENERATE else scenario_path(plan.scenario).parent)
    return {
        "run": run.run, "cell": run.cell, "seed": run.seed, "columns": dict(run.columns),
        "scenario": doc, "generate": gen if plan.scenario == GENERATE else None, "overrides": ov,
        "controller": run.inputs.get("agents.controller"), "planner": run.inputs.get("leader.planner"),
        "duration": plan.duration, "mode": mode or plan.mode,
    }


# ----------------------------------------------------------------------------- validation


def _validate(plan: Plan, runs: Sequence[Run], doc: dict[str, Any] | None) -> None:
    """Every cell's scenario as its flights will load it: unknown paths, bad values, plug-ins,
    faults. Raises ScenarioError / OverrideError naming the field (nothing has run)."""
    from zenswarm.scenario.generate import generate_scenario

    seen: set[str] = set()
    for run in runs:
        generated = plan.scenario == GENERATE
        if run.cell in seen and not generated:
            continue
        seen.add(run.cell)
        t = _task(run, plan, doc)
        ov = dict(t["overrides"])
        if t["controller"] is not None:
            ov["agents.controller"] = t["controller"]
        if t["planner"] is not None:
            ov["leader.planner"] = t["planner"]
            ov["leader.adaptive"] = t["planner"] != "apf"
        if plan.duration is not None:
            ov["timing.time_limit_s"] = float(plan.duration)
        ov["scenario.seed"] = run.seed
        if generated:
            try:
                base: Any = generate_scenario(**t["generate"], seed=run.seed)
            except ValueError as e:
                name = next((p for p in GENERATOR_FIELDS if str(e).startswith(p + " ") or f"unknown {p} " in str(e)), "generate")
                raise ScenarioError(name, f"{e} (run {run.run}: {run.cell}, seed {run.seed})") from None
        else:
            base = doc
        sc, _ = load(base, ov)
        check_selection(sc)
        plan_for(sc)


# ----------------------------------------------------------------------------- backends


class Backend(abc.ABC):
    """Where runs fly: ``submit(task)`` -> a future with ``result()``; ``wait_first(futures)`` ->
    the finished ones; ``cancel()`` drops what has not finished (Ctrl-C)."""

    @abc.abstractmethod
    def submit(self, task: dict[str, Any]) -> Any: ...

    @abc.abstractmethod
    def wait_first(self, futures: Iterable[Any]) -> set[Any]: ...

    @abc.abstractmethod
    def cancel(self) -> None: ...

    @abc.abstractmethod
    def close(self) -> None: ...


def _worker_init() -> None:
    # Ctrl-C is the driver's: it cancels and stops the pool. A no-op handler (not SIG_IGN) so the
    # processes a swarm run starts get the default again.
    signal.signal(signal.SIGINT, lambda *_: None)
    # A pool worker outlives a driver killed with SIGKILL (it holds its own queue's write end):
    # it ends itself once its parent is gone.
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="zenswarm-sweep-parent-watch", daemon=True).start()


class LocalBackend(Backend):
    """A process pool (spawned processes: no state shared with the driver) of ``workers`` processes."""

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._pool = self._new()

    def _new(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init)

    def submit(self, task: dict[str, Any]) -> Any:
        try:
            return self._pool.submit(run_one, task)
        except cf.process.BrokenProcessPool:  # a worker died (OOM, SIGKILL): a new pool for the rest
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._new()
            return self._pool.submit(run_one, task)

    def wait_first(self, futures: Iterable[Any]) -> set[Any]:
        done, _ = cf.wait(list(futures), timeout=1.0, return_when=cf.FIRST_COMPLETED)
        return set(done)

    def cancel(self) -> None:
        procs = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:  # the runs in flight are lost (the journal has every finished one)
            p.terminate()
        for p in procs:
            p.join(5)

    def close(self) -> None:
        self._pool.shutdown(wait=True)


class DaskBackend(Backend):
    """A Dask distributed cluster at ``address`` (``dask scheduler``): one task per run. A worker
    that dies takes its tasks with it; the scheduler reruns them elsewhere (its allowed-failures)."""

    def __init__(self, address: str) -> None:
        import distributed

        from zenswarm.compose.cluster import connect  # zenswarm up --scheduler's: the same errors

        self._dist: Any = distributed  # untyped
        self.client: Any = connect(address, timeout=10)
        self._futures: list[Any] = []

    def submit(self, task: dict[str, Any]) -> Any:
        f = self.client.submit(run_one, task, pure=False, key=f"zenswarm-run-{task['run']}-{os.urandom(4).hex()}")
        self._futures.append(f)
        return f

    def wait_first(self, futures: Iterable[Any]) -> set[Any]:
        try:
            done, _ = self._dist.wait(list(futures), timeout=1.0, return_when="FIRST_COMPLETED")
        except TimeoutError:
            return set()
        return set(done)

    def cancel(self) -> None:
        self.client.cancel(self._futures)
        self.client.close()

    def close(self) -> None:
        self.client.close()


# ----------------------------------------------------------------------------- the table


def _columns(plan: Plan, runs: Sequence[Run]) -> list[tuple[str, str]]:
    """(name, kind) of every column of runs.parquet, in order (kinds: int, float, bool, string)."""
    inputs = [a.path for a in plan.grid] + [s.path for s in plan.samples]
    cols = [("run", "int"), ("cell", "string"), ("seed", "int")]
    cols += [(p, column_kind([r.columns[p] for r in runs])) for p in inputs]
    cols += [("success", "bool"), ("causes", "string"), ("error", "string"), ("attempts", "int")]
    cols += [(m, "float") for m in METRICS_FLOAT] + [(m, "bool") for m in METRICS_BOOL]
    cols += [("wall_s", "float"), ("zenswarm_version", "string"), ("mode", "string")]
    return cols


def _write_parquet(out: Path, rows: Iterable[Mapping[str, Any]], columns: Sequence[tuple[str, str]]) -> None:
    """runs.parquet from the rows (sorted by run), written to a temporary file and renamed."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {"int": pa.int64(), "float": pa.float64(), "bool": pa.bool_(), "string": pa.string()}
    ordered = sorted(rows, key=lambda r: int(r["run"]))

    def conv(v: Any, kind: str) -> Any:
        if v is None:
            return None
        return str(v) if kind == "string" else float(v) if kind == "float" else v

    arrays = [pa.array([conv(r.get(n), k) for r in ordered], type=types[k]) for n, k in columns]
    table = pa.Table.from_arrays(arrays, names=[n for n, _ in columns])
    tmp = out / "runs.parquet.tmp"
    pq.write_table(table, tmp)
    os.replace(tmp, out / "runs.parquet")


def read_rows(out: Path) -> dict[int, dict[str, Any]]:
    """The journal's finished runs, by run index (a torn last line, from a kill, is ignored)."""
    rows: dict[int, dict[str, Any]] = {}
    p = out / "runs.jsonl"
    if not p.is_file():
        return rows
    for line in p.read_text(encoding="utf-8").splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        rows[int(row["run"])] = row
    return rows


def _append(out: Path, row: Mapping[str, Any]) -> None:
    with open(out / "runs.jsonl", "a", encoding="utf-8") as f:
        f.write(json.dumps(row) + "\n")
        f.flush()
        os.fsync(f.fileno())


# ----------------------------------------------------------------------------- campaign.json


def _campaign_json(plan: Plan, runs: Sequence[Run], argv: Sequence[str], scenario_name: str, digest: str) -> dict[str, Any]:
    return {
        "version": 1, "zenswarm_version": __version__, "scenario": plan.scenario, "scenario_name": scenario_name,
        "command": list(argv), "mode": plan.mode, "axes": plan.axes_json(), "seeds": plan.seeds, "base_seed": plan.base_seed,
        "runs": len(runs), "duration_s": plan.duration, "scenario_sha256": digest,
    }


_SAME = ("scenario", "mode", "axes", "seeds", "base_seed", "runs", "duration_s", "scenario_sha256")
"""Keys of campaign.json that must match for a re-run to resume into the same directory."""


def _check_resume(out: Path, meta: Mapping[str, Any]) -> None:
    p = out / "campaign.json"
    if not p.is_file():
        if (out / "runs.jsonl").exists():
            raise ScenarioError("--out", f"{out} has runs.jsonl but no campaign.json: not a campaign directory of this command")
        return
    try:
        old = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ScenarioError("--out", f"{p} is not readable JSON ({e}): give a new --out") from None
    diff = [k for k in _SAME if old.get(k) != meta.get(k)]
    if diff:
        said = "; ".join(f"{k}: was {old.get(k)!r}, now {meta.get(k)!r}" for k in diff)
        raise ScenarioError(
            "--out", f"{out} holds a different campaign ({said}). Re-run its own command to resume it "
            f"({' '.join(old.get('command') or [])}), or give a new --out"
        )


# ----------------------------------------------------------------------------- progress


class Progress:
    """``sweep: 12/90 done (3 resumed), 2 failed, 0 errors, 41.0 runs/min, ETA 1m02s`` on stderr.

    ``resumed`` are the rows already in the output directory: they count as done, and their
    failures and errors are counted with the new runs'; the rate is the new runs'."""

    def __init__(self, total: int, resumed: Sequence[Mapping[str, Any]], quiet: bool) -> None:
        self.total, self.done, self.resumed, self.failed, self.errors = total, 0, len(resumed), 0, 0
        for row in resumed:
            self._count(row)
        self.t0 = time.monotonic()
        self.last = 0.0
        self.quiet = quiet
        self.tty = sys.stderr.isatty()

    def _count(self, row: Mapping[str, Any]) -> None:
        self.done += 1
        self.errors += row.get("error") is not None
        self.failed += not row.get("success") and row.get("error") is None

    def add(self, row: Mapping[str, Any]) -> None:
        self._count(row)
        self.show()

    def line(self) -> str:
        new = self.done - self.resumed
        el = time.monotonic() - self.t0
        rate = new / el if el > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else math.inf
        eta_s = "?" if not math.isfinite(eta) else f"{int(eta // 60)}m{int(eta % 60):02d}s"
        res = f" ({self.resumed} resumed)" if self.resumed else ""
        return (f"sweep: {self.done}/{self.total} done{res}, {self.failed} failed, {self.errors} errors, "
                f"{rate * 60:.1f} runs/min, ETA {eta_s}")

    def show(self, final: bool = False) -> None:
        if self.quiet:
            return
        now = time.monotonic()
        if self.tty:
            print("\r" + self.line(), end="\n" if final else "", file=sys.stderr, flush=True)
        elif final or now - self.last >= 5.0:
            print(self.line(), file=sys.stderr, flush=True)
            self.last = now


# ----------------------------------------------------------------------------- driving


def _drive(backend: Backend, tasks: Sequence[dict[str, Any]], on_row: Callable[[dict[str, Any]], None]) -> None:
    """Fly the tasks, retrying a crashed run once; ``on_row`` gets each final row (with ``attempts``)."""
    pending: dict[Any, tuple[dict[str, Any], int]] = {backend.submit(t): (t, 1) for t in tasks}
    while pending:
        for f in backend.wait_first(pending):
            task, attempt = pending.pop(f)
            try:
                row = dict(f.result())
            except Exception as e:  # noqa: BLE001 -- the pool or the cluster lost the run (a dead worker): an error, retried
                row = {"run": task["run"], "cell": task["cell"], "seed": task["seed"], **task["columns"], "success": False,
                       "causes": "", "error": f"{type(e).__name__}: {e}", "mode": task["mode"], "zenswarm_version": __version__}
            if row.get("error") is not None and attempt == 1 and not str(row["error"]).startswith("plugin_error"):
                pending[backend.submit(task)] = (task, 2)
                continue
            row["attempts"] = attempt
            on_row(row)


def _check_swarm(backend: Backend, plan: Plan, runs: Sequence[Run], doc: dict[str, Any] | None,
                 rows: Mapping[int, Mapping[str, Any]], out: Path) -> list[str]:
    """Fly ``plan.check_swarm`` random runs (those without an error) as lockstep swarms; the
    differences from their simulator rows, one line per differing figure."""
    ok = [r for r in runs if r.run in rows and rows[r.run].get("error") is None]
    picked = sorted(random.Random(plan.base_seed).sample(ok, min(plan.check_swarm, len(ok))), key=lambda r: r.run)
    print(f"sweep: --check-swarm: flying runs {', '.join(str(r.run) for r in picked)} as lockstep swarms", file=sys.stderr)
    got: dict[int, dict[str, Any]] = {}
    _drive(backend, [_task(r, plan, doc, mode="swarm") for r in picked], lambda row: got.__setitem__(int(row["run"]), row))
    diffs = []
    for r in picked:
        a, b = rows[r.run], got[r.run]
        name = f"run {r.run} ({r.cell + ', ' if r.cell else ''}seed {r.seed})"
        if b.get("error") is not None:
            diffs.append(f"{name}: the swarm flight failed: {b['error']}")
            continue
        for k in metric_columns():
            x, y = a.get(k), b.get(k)
            if not (x == y or isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)):
                diffs.append(f"{name}: {k} {x!r} in the simulator, {y!r} in the swarm")
    (out / "check_swarm.json").write_text(json.dumps({"runs": [r.run for r in picked], "differences": diffs, "swarm_rows": got}, indent=1))
    return diffs


def _maybe_report(out: Path) -> None:
    try:
        from zenswarm.bridge.reports.sweep_report import write_report  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        return
    try:
        path = write_report(out)
    except Exception as e:  # noqa: BLE001 -- the table is written; a report failure must not lose the campaign
        print(f"sweep: warning: the report could not be written: {type(e).__name__}: {e}", file=sys.stderr)
        return
    print(f"sweep: report {path}", file=sys.stderr)


def run_campaign(plan: Plan, out: Path, argv: Sequence[str], workers: int | None = None, scheduler: str | None = None,
                 quiet: bool = False) -> int:
    """Validate, then fly every run not yet in ``out`` and write the table. Exit status (module docstring)."""
    check_plan(plan)
    _need_extra(scheduler)
    if workers is not None and workers < 1:
        raise ScenarioError("--workers", f"expected an integer >= 1, got {workers}")
    doc: dict[str, Any] | None = None
    digest = "generate"
    if plan.scenario == GENERATE:
        name = "generate"
    else:
        path = scenario_path(plan.scenario)
        text = path.read_bytes()
        digest = hashlib.sha256(text).hexdigest()
        _, doc = load(path)
        name = str(doc.get("scenario", {}).get("name", path.stem))
    runs = expand(plan)
    _validate(plan, runs, doc)
    check_output_dir(out, "--out")
    meta = _campaign_json(plan, runs, argv, name, digest)
    _check_resume(out, meta)
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "campaign.json").is_file():
        (out / "campaign.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    rows = {k: v for k, v in read_rows(out).items() if k < len(runs)}
    columns = _columns(plan, runs)
    todo = [r for r in runs if r.run not in rows]
    progress = Progress(len(runs), list(rows.values()), quiet)
    if not quiet:
        where = f"Dask scheduler {scheduler}" if scheduler else f"{workers or os.cpu_count() or 1} local workers"
        print(f"sweep: {len(runs)} runs ({len(rows)} already in {out}), {len(todo)} to fly on {where}", file=sys.stderr)
    backend: Backend = DaskBackend(scheduler) if scheduler else LocalBackend(workers or os.cpu_count() or 1)
    last_write = [0.0]

    def on_row(row: dict[str, Any]) -> None:
        _append(out, row)
        rows[int(row["run"])] = row
        progress.add(row)
        if time.monotonic() - last_write[0] >= 1.0:
            _write_parquet(out, rows.values(), columns)
            last_write[0] = time.monotonic()

    try:
        _drive(backend, [_task(r, plan, doc) for r in todo], on_row)
        diffs = _check_swarm(backend, plan, runs, doc, rows, out) if plan.check_swarm else []
    except KeyboardInterrupt:
        backend.cancel()
        rows = {k: v for k, v in read_rows(out).items() if k < len(runs)}  # the journal is the record (Ctrl-C may hit on_row)
        _write_parquet(out, rows.values(), columns)
        progress.show(final=True)
        print(f"sweep: interrupted: {len(rows)}/{len(runs)} runs recorded in {out}; run the same command again to resume",
              file=sys.stderr)
        return 130
    backend.close()
    _write_parquet(out, rows.values(), columns)
    progress.show(final=True)
    _maybe_report(out)
    errors = [r for r in rows.values() if r.get("error") is not None]
    for d in diffs:
        print(f"sweep: check-swarm: {d}", file=sys.stderr)
    if errors:
        print(f"sweep: {len(errors)} runs crashed (column error); first: run {errors[0]['run']}: {errors[0]['error']}", file=sys.stderr)
    return 1 if errors or diffs else 0


def _need_extra(scheduler: str | None) -> None:
    """The optional dependencies (``zenswarm[sweep]``): pyarrow always, distributed with --scheduler."""
    mods = ["pyarrow"] + (["distributed"] if scheduler else [])
    for m in mods:
        try:
            __import__(m)
        except ImportError:
            raise ScenarioError("sweep", f"needs {m}: {INSTALL_HINT}") from None


# ----------------------------------------------------------------------------- command line


def _int(s: str) -> int:
    try:
        return int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None


def _float(s: str) -> float:
    try:
        return float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {s!r}") from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="zenswarm sweep",
        description=(
            "Fly an experiment campaign: every combination of the --grid values, --samples draws of the --sample ranges, "
            "and --seeds Monte Carlo seeds, in parallel (a local process pool, or a Dask cluster with --scheduler). "
            "One row per run in OUT/runs.parquet, written as runs finish; the same command again resumes. "
            "SCENARIO is a built-in name, a scenario TOML, 'generate' (a generated scenario: axes n, shape, topology, k, "
            "pinning, n_obstacles, spacing), or a campaign file (a TOML with a [campaign] table; docs/campaigns.md). "
            "Also: 'zenswarm sweep report DIR', 'zenswarm sweep margin SCENARIO'."
        ),
        epilog=(
            "Also: 'zenswarm sweep report DIR' writes DIR/report.md (success rate with a confidence interval, "
            "median and worst formation error, minimum clearance per cell) and DIR/plots/ (written at the end of every "
            "sweep too); 'zenswarm sweep margin SCENARIO' finds the empirical delay margin beside the analytic bound "
            "(docs/delay_margin.md). Each has --help. A Dask cluster: 'dask scheduler' and 'dask worker tcp://HOST:8786' "
            "(docs/campaigns.md). "
            "Exit status: 0 all runs recorded, 1 a run crashed or --check-swarm found a difference, 2 bad input, 130 Ctrl-C."
        ),
    )
    p.add_argument("scenario", help="built-in scenario name, scenario TOML, 'generate', or a campaign TOML file")
    p.add_argument("--grid", action="append", default=[], metavar="PATH=V1,V2,...",
                   help="sweep a scenario field by dotted path (faults.loss=0,0.1,0.2; faults.delay=0ms,50ms; "
                        "agents.controller=paper,NAME); repeatable; every combination is flown")
    p.add_argument("--sample", action="append", default=[], metavar="PATH=LOW:HIGH",
                   help="draw a field uniformly from [LOW, HIGH] (--samples times; integers if both ends are); repeatable")
    p.add_argument("--samples", type=_int, default=None, metavar="K", help="number of draws of the --sample ranges")
    p.add_argument("--seeds", type=_int, default=None, metavar="N", help="Monte Carlo seeds per cell (default: 1)")
    p.add_argument("--base-seed", type=_int, default=None, metavar="S", help="first seed (default: 0): seeds S..S+N-1")
    p.add_argument("--out", type=Path, default=None, metavar="DIR", help="campaign directory (required unless the campaign file has out)")
    p.add_argument("--workers", type=_int, default=None, metavar="W", help="local worker processes (default: all cores)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT", help="run on this Dask distributed scheduler instead")
    p.add_argument("--mode", choices=("sim", "swarm"), default=None, help="sim (default): the in-process simulator; swarm: zenswarm up")
    p.add_argument("--check-swarm", type=_int, default=None, metavar="K",
                   help="also fly K random runs as lockstep swarms; exit 1 naming any that differs from the simulator")
    p.add_argument("--duration", type=_float, default=None, metavar="S", help="timing.time_limit_s of every flight, s")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    return p


def _plan_from_args(args: argparse.Namespace) -> tuple[Plan, Path]:
    src = Path(args.scenario)
    if src.suffix == ".toml" and src.is_file():
        try:
            doc = tomllib.loads(src.read_text(encoding="utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ScenarioError("scenario", f"{src} is not valid TOML: {e}") from None
        if is_campaign_document(doc):
            for flag in ("grid", "sample"):
                if getattr(args, flag):
                    raise ScenarioError(f"--{flag}", f"{src} is a campaign file: its axes are in the file")

            def rel(s: str) -> str:
                p = Path(s)
                if p.suffix == ".toml" and not p.is_absolute():
                    return str(src.parent / p)
                return s

            plan, out = plan_from_toml(doc, rel)
            over = {k: getattr(args, a) for k, a in (("n_samples", "samples"), ("seeds", "seeds"), ("base_seed", "base_seed"),
                                                       ("mode", "mode"), ("duration", "duration"), ("check_swarm", "check_swarm"))
                    if getattr(args, a) is not None}
            plan = replace(plan, **over)
            out_dir = args.out or (None if out is None else src.parent / out)
            if out_dir is None:
                raise ScenarioError("--out", "required (or out in the campaign file's [campaign])")
            return plan, out_dir
    if args.out is None:
        raise ScenarioError("--out", "required: the campaign directory")
    plan = Plan(
        scenario=args.scenario,
        grid=tuple(parse_grid(g) for g in args.grid),
        samples=tuple(parse_sample(s) for s in args.sample),
        n_samples=args.samples or 0, seeds=1 if args.seeds is None else args.seeds,
        base_seed=args.base_seed or 0, mode=args.mode or "sim", duration=args.duration, check_swarm=args.check_swarm or 0,
    )
    return plan, args.out


def _report_main(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="zenswarm sweep report", description="Write DIR/report.md and DIR/plots/ from a campaign's table.")
    p.add_argument("dir", type=Path, help="the campaign directory (--out of zenswarm sweep)")
    args = p.parse_args(argv)
    try:
        from zenswarm.bridge.reports.sweep_report import write_report  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        print("zenswarm: error: sweep report is not in this build (zenswarm.bridge.reports.sweep_report)", file=sys.stderr)
        return 2
    print(write_report(args.dir))
    return 0


def _margin_main(argv: Sequence[str]) -> int:
    try:
        from zenswarm.compose.margin import cli  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        print("zenswarm: error: sweep margin is not in this build (zenswarm.compose.margin)", file=sys.stderr)
        return 2
    return int(cli(list(argv)))


def main(argv: Sequence[str] | None = None) -> int:
    """``zenswarm sweep ARGS`` (argv without the word ``sweep``); exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    return run_command(lambda: _sweep(argv))


def _sweep(argv: list[str]) -> int:
    if argv and argv[0] == "report":
        return _report_main(argv[1:])
    if argv and argv[0] == "margin":
        return _margin_main(argv[1:])
    args = build_parser().parse_args(argv)
    plan, out = _plan_from_args(args)
    return run_campaign(plan, out, ["zenswarm", "sweep", *argv], args.workers, args.scheduler, args.quiet)

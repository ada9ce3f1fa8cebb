"""Issue 17 points 1-3: `zenswarm sweep` (docs/campaigns.md).

Pure: the expansion of a campaign (run order, cells, seeds, durations in seconds, sampled draws),
campaign files, and validation (bad paths and values exit 2 naming them, before anything runs or
is written). Processes (short flights of paper example 1, ``--duration 2``): a local campaign
interrupted with SIGINT, resumed, resumed again with nothing left, its rows equal to individual
``fly()`` results; a real loopback Dask cluster (``dask scheduler`` and two ``dask worker``)
giving the same rows as the local pool, a crashing run recorded with its error after a retry on both.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from zenswarm.api import fly
from zenswarm.bus import free_port
from zenswarm.campaign import GridAxis, Plan, SampleAxis, check_plan, expand, parse_grid, parse_sample, plan_from_toml
from zenswarm.errors import ScenarioError
from zenswarm.pytest_plugin import port_free
from zenswarm.sweep import Progress, main, metric_columns

from swarmtest import ROOT, SCENARIOS

pq = pytest.importorskip("pyarrow.parquet", reason="zenswarm[sweep] is in the test extra")

EX1 = "paper_example1"
TESTS = Path(__file__).parent
CRASH = "plugin_fixtures:CrashingController"


def _table(out: Path) -> list[dict[str, Any]]:
    return pq.read_table(out / "runs.parquet").to_pylist()


def _same(x: Any, y: Any) -> bool:
    return x == y or isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)


def _key(row: dict[str, Any], inputs: list[str]) -> tuple:
    return tuple(row[k] for k in ["run", "cell", "seed", *inputs, *metric_columns(), "error", "attempts", "mode"])


# ----------------------------------------------------------------------------- pure


def test_expansion_order_cells_and_units() -> None:
    plan = Plan(EX1, grid=(parse_grid("faults.loss=0,0.1,0.2"), parse_grid("faults.delay=0ms,50ms,100ms")), seeds=10, base_seed=5)
    check_plan(plan)
    runs = expand(plan)
    assert len(runs) == 90 and [r.run for r in runs] == list(range(90))
    assert [r.seed for r in runs[:10]] == list(range(5, 15))
    r = runs[10 * 4 + 3]  # cell 4: loss 0.1 (middle), delay 50ms (middle); seed base + 3
    assert r.inputs == {"faults.loss": 0.1, "faults.delay": "50ms"} and r.seed == 8
    assert r.columns["faults.delay"] == pytest.approx(0.05) and r.cell == f"faults.loss=0.1,faults.delay={r.columns['faults.delay']!r}"
    assert expand(plan) == runs  # the same command, the same indices
    assert plan.axes_json()[1]["values"] == [0.0, r.columns["faults.delay"], runs[20].columns["faults.delay"]]


def test_values_and_samples() -> None:
    g = parse_grid("leader.goal=[2.4, 1.4, 0.6],[2, 1, 0.5]")
    assert g.values == ([2.4, 1.4, 0.6], [2, 1, 0.5])
    assert parse_grid("agents.controller=paper,plugin_fixtures:X").values == ("paper", "plugin_fixtures:X")
    assert parse_grid("eso.enabled=true,false").values == (True, False)
    plan = Plan(EX1, grid=(g,), samples=(parse_sample("faults.loss=0:0.3"), parse_sample("faults.delay=0ms:20ms")), n_samples=4, seeds=2)
    check_plan(plan)
    runs = expand(plan)
    assert len(runs) == 2 * 4 * 2
    draws = [r.columns["faults.loss"] for r in runs[::2]]
    assert draws[:4] == draws[4:]  # the same draws in every grid cell
    assert all(0 <= d <= 0.3 for d in draws) and len(set(draws[:4])) == 4
    assert all(0 <= r.columns["faults.delay"] <= 0.02 and r.inputs["faults.delay"].endswith("s") for r in runs)
    assert [r.columns for r in expand(plan)] == [r.columns for r in runs]  # seeded by base_seed
    n = expand(Plan("generate", samples=(SampleAxis("n", 3, 5),), n_samples=6))
    assert {r.columns["n"] for r in n} <= {3, 4, 5} and all(isinstance(r.columns["n"], int) for r in n)


def test_radio_and_capacity_axes_are_numbers_in_the_table() -> None:
    """faults.range / faults.capacity with units reach the scenario as written and are stored in
    metres and bytes/s (a numeric axis for the report); each cell validates."""
    from zenswarm.sweep import _validate

    plan = Plan("generate", grid=(parse_grid("n=4"), parse_grid("faults.range=0.3m,150cm,2"),
                                  parse_grid("faults.capacity=64kB/s,1Mbps")), seeds=1, duration=2.0)  # fmt: skip
    check_plan(plan)
    runs = expand(plan)
    assert [r.columns["faults.range"] for r in runs[::2]] == [0.3, 1.5, 2]
    assert [r.columns["faults.capacity"] for r in runs[:2]] == [64000.0, 125000.0]
    assert runs[0].inputs["faults.range"] == "0.3m" and runs[0].inputs["faults.capacity"] == "64kB/s"
    assert plan.axes_json()[1]["values"] == [0.3, 1.5, 2.0]
    _validate(plan, runs, None)


@pytest.mark.parametrize(
    ("plan", "field"),
    [
        (Plan(EX1, seeds=0), "--seeds"),
        (Plan(EX1, grid=(GridAxis("n", (3,)),)), "n"),
        (Plan(EX1, grid=(GridAxis("faults.loss", (0,)), GridAxis("faults.loss", (1,)))), "faults.loss"),
        (Plan(EX1, grid=(GridAxis("scenario.seed", (1,)),)), "scenario.seed"),
        (Plan(EX1, samples=(SampleAxis("faults.loss", 0.3, 0.1),), n_samples=2), "faults.loss"),
        (Plan(EX1, samples=(SampleAxis("faults.loss", 0, 1),)), "--samples"),
        (Plan(EX1, mode="swarm", check_swarm=1), "--check-swarm"),
        (Plan("generate", grid=(GridAxis("n", ("three",)),)), "n"),
    ],
)
def test_plan_errors_name_the_field(plan: Plan, field: str) -> None:
    with pytest.raises(ScenarioError) as e:
        check_plan(plan)
    assert e.value.field == field


def test_campaign_file() -> None:
    doc = {"campaign": {"scenario": EX1, "seeds": 3, "duration": 2}, "grid": {"faults.loss": [0, 0.1]},
           "sample": {"faults.jitter": ["0ms", "10ms"]}}
    plan, out = plan_from_toml(doc)
    assert out is None and plan.seeds == 3 and plan.duration == 2.0 and plan.grid[0] == GridAxis("faults.loss", (0, 0.1))
    with pytest.raises(ScenarioError, match="campaign.sedes"):
        plan_from_toml({"campaign": {"scenario": EX1, "sedes": 3}})


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--grid", "faults.nosuch=1,2"], "faults.nosuch"),
        (["--grid", "timing.bogus=1"], "timing.bogus"),
        (["--grid", "faults.loss=0,1.5"], "faults.loss"),
        (["--grid", "faults.delay=0ms,50parsecs"], "faults.delay"),
        (["--grid", "obstacles[7].radius=0.1"], "obstacles[7]"),
        (["--grid", "agents.controller=paper,nosuch_ctrl"], "nosuch_ctrl"),
        (["--grid", "n=3,5"], "n"),
        (["--grid", "faults.loss"], "--grid"),
        (["--sample", "faults.loss=0:x", "--samples", "2"], "faults.loss"),
        (["--grid", "faults.range=0.3m,0m"], "faults.range"),
        (["--grid", "faults.capacity=64kB/s,-1kB/s"], "faults.capacity"),
    ],
)
def test_bad_input_exit_2_before_anything(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], named: str) -> None:
    out = tmp_path / "c"
    assert main([EX1, *args, "--seeds", "2", "--duration", "2", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert named in err and "error" in err
    assert not out.exists()


def test_generated_scenario_bad_value_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["generate", "--grid", "topology=ring,moebius", "--out", str(tmp_path / "c")]) == 2
    assert "moebius" in capsys.readouterr().err


def test_campaign_file_is_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from zenswarm.sweep import _plan_from_args, build_parser

    f = tmp_path / "c.toml"
    f.write_text('[campaign]\nscenario = "paper_example1"\nseeds = 3\nduration = 2\nout = "o"\n'
                 '[grid]\n"faults.loss" = [0, 0.1]\n"faults.delay" = ["0ms", "50ms"]\n')
    from_file, out = _plan_from_args(build_parser().parse_args([str(f)]))
    cli, _ = _plan_from_args(build_parser().parse_args(
        [EX1, "--grid", "faults.loss=0,0.1", "--grid", "faults.delay=0ms,50ms", "--seeds", "3", "--duration", "2", "--out", "x"]))
    assert out == tmp_path / "o" and expand(from_file) == expand(cli) and from_file.axes_json() == cli.axes_json()
    f.write_text('[campaign]\nscenario = "paper_example1"\n[grid]\n"faults.nosuch" = [1]\n')
    assert main([str(f), "--out", str(tmp_path / "x")]) == 2 and "faults.nosuch" in capsys.readouterr().err
    assert main([str(f), "--grid", "faults.loss=0", "--out", str(tmp_path / "x")]) == 2 and "--grid" in capsys.readouterr().err


def test_generated_scenarios_and_plugins_validate() -> None:
    from zenswarm.sweep import _validate

    plan = Plan("generate", grid=(parse_grid("n=2,4"), parse_grid("topology=ring,complete"), parse_grid("leader.planner=aapf,apf")),
                seeds=2, duration=2.0)
    check_plan(plan)
    runs = expand(plan)
    assert len(runs) == 16 and runs[-1].columns == {"n": 4, "topology": "complete", "leader.planner": "apf"}
    _validate(plan, runs, None)  # no error: apf also sets leader.adaptive, as --planner does


def test_without_the_extra_exit_2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow -> ImportError
    assert main([EX1, "--out", str(tmp_path / "c")]) == 2
    assert "pip install zenswarm[sweep]" in capsys.readouterr().err and not (tmp_path / "c").exists()


# ----------------------------------------------------------------------------- processes


def _sweep_args(out: Path, *extra: str) -> list[str]:
    return [EX1, "--grid", "faults.loss=0,0.3", "--seeds", "2", "--duration", "1", "--out", str(out), *extra]


@pytest.mark.swarm  # CLI subprocesses and a process pool
def test_local_campaign_interrupt_resume_and_rows_equal_fly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "camp"
    gate = tmp_path / "gate"  # while it exists, runs after run 0 wait (tests/hold_runs/sitecustomize.py)
    gate.touch()
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "ZENSWARM_TEST_RUN_GATE": str(gate),
           "PYTHONPATH": os.pathsep.join([str(TESTS / "hold_runs"), os.environ.get("PYTHONPATH", "")])}
    cmd = [sys.executable, "-m", "zenswarm", "sweep", *_sweep_args(out, "--workers", "1")]
    # SIGINT as in a terminal's foreground job, also when pytest itself runs as a background job
    # (which inherits SIGINT ignored, and so would the sweep: docs/campaigns.md)
    p = subprocess.Popen(cmd, cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    journal = out / "runs.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and p.poll() is None and not (journal.is_file() and journal.read_text().count("\n") >= 1):
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGINT)  # as Ctrl-C in a terminal: the whole foreground group
    _, err = p.communicate(timeout=30)
    assert p.returncode == 130, err
    first = _table(out)
    assert len(first) == 1 and "resume" in err  # run 0 finished, run 1 was held at the gate
    gate.unlink()
    assert main(_sweep_args(out, "--workers", "1")) == 0  # resumes
    rows = _table(out)
    assert [r["run"] for r in rows] == list(range(4))  # no duplicates, nothing missing
    assert [r for r in rows if r["run"] in {f["run"] for f in first}] == first  # finished runs not flown again
    meta = json.loads((out / "campaign.json").read_text())
    assert meta["runs"] == 4 and meta["axes"] == [{"path": "faults.loss", "values": [0.0, 0.3]}] and meta["seeds"] == 2
    cols = list(pq.read_table(out / "runs.parquet").schema.names)
    for c in ("run", "cell", "seed", "faults.loss", "success", "causes", "error", "attempts", "max_formation_error_m",
              "min_obstacle_clearance_m", "time_to_goal_s", "goal_reached", "sim_time_s", "wall_s", "zenswarm_version", "mode"):
        assert c in cols
    lines = journal.read_text().count("\n")
    capsys.readouterr()
    assert main(_sweep_args(out)) == 0
    assert journal.read_text().count("\n") == lines and "0 to fly" in capsys.readouterr().err
    assert main(_sweep_args(out, "--base-seed", "4")) == 2
    err = capsys.readouterr().err
    assert "different campaign" in err and "base_seed" in err
    for r in (rows[0], rows[3]):  # each row is the flight fly() gives
        f = fly(EX1, seed=r["seed"], duration=1.0, overrides={"faults.loss": r["faults.loss"]})
        assert r["success"] == f.success and r["causes"] == ",".join(f.causes) and r["error"] is None and r["attempts"] == 1
        for k in ("max_formation_error_m", "rms_tracking_error_m", "min_obstacle_clearance_m", "min_inter_uav_distance_m", "sim_time_s"):
            assert _same(r[k], getattr(f.metrics, k)), k
    assert rows[3]["faults.loss"] == 0.3 and rows[3]["seed"] == 1 and r["mode"] == "sim"


@pytest.mark.swarm  # a real Dask scheduler and two workers on loopback
def test_dask_cluster_gives_the_local_rows_and_crashes_are_recorded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A crashing run (a test plug-in that raises) is recorded with its error after one retry, on
    both backends; every other row is the same on the cluster as on the local pool."""
    monkeypatch.syspath_prepend(str(TESTS))  # plugin_fixtures, in the driver and the pool (spawn copies sys.path)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])}  # and the Dask workers
    port = free_port()
    addr = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    worker = [sys.executable, "-m", "distributed.cli.dask_worker"]
    logs = [open(tmp_path / f"dask{i}.log", "w") for i in range(3)]
    procs = [subprocess.Popen([*dask, "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], stdout=logs[0],
                              stderr=subprocess.STDOUT, start_new_session=True)]
    try:
        procs += [subprocess.Popen([*worker, addr, "--nthreads", "1", "--no-dashboard", "--no-nanny"], stdout=logs[i],
                                   stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT, env=env) for i in (1, 2)]
        args = [EX1, "--grid", f"agents.controller=paper,{CRASH}", "--grid", "faults.delay=0ms,50ms", "--duration", "1", "--quiet"]
        assert main([*args, "--scheduler", addr, "--out", str(tmp_path / "dask")]) == 1  # 1: runs crashed
        assert main([*args, "--workers", "1", "--out", str(tmp_path / "local")]) == 1
    finally:
        for p in procs:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)
        for f in logs:
            f.close()
    assert port_free(port)
    inputs = ["agents.controller", "faults.delay"]
    d, loc = _table(tmp_path / "dask"), _table(tmp_path / "local")
    assert len(d) == 4 and [_key(r, inputs) for r in d] == [_key(r, inputs) for r in loc]
    for r in d + loc:
        crashed = r["agents.controller"] == CRASH
        assert r["attempts"] == 1 and (r["error"] is not None) == crashed  # a plug-in's failure is deterministic: not retried
        assert not crashed or "deliberate failure" in r["error"] and r["success"] is False and r["rms_tracking_error_m"] is None
        assert not crashed or r["error"].startswith("plugin_error") and "plugin_error" in r["causes"]
    assert d[0]["rms_tracking_error_m"] is not None


# ----------------------------------------------------------------------------- --check-swarm (no swarm flown)


def test_check_swarm_names_the_differing_run_and_figure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--check-swarm K`` through the command line, without flying a swarm: the runs go to an
    in-process backend, and the "swarm" flight is the simulator's own (so equal), then the same
    with one figure of one run moved by one ulp (exit 1 naming the run and the figure), then a
    swarm flight that cannot be flown (exit 1 naming the run and the error)."""
    import concurrent.futures as cf
    import dataclasses

    from zenswarm import sweep
    from zenswarm.api import FlightError

    class Inline(sweep.Backend):  # the local pool's interface, in this process
        def __init__(self, workers: int) -> None:
            pass

        def submit(self, task: dict[str, Any]) -> Any:
            f: cf.Future[dict[str, Any]] = cf.Future()
            f.set_result(sweep.run_one(task))
            return f

        def wait_first(self, futures: Any) -> set[Any]:
            return set(futures)

        def cancel(self) -> None:
            pass

        def close(self) -> None:
            pass

    calls: list[tuple[str, int]] = []
    swarm = {"bump": None, "fail": False}  # what the fake swarm flight does differently

    def fake_fly(doc: Any, *, mode: str, seed: int, **kw: Any) -> Any:
        calls.append((mode, seed))
        if mode == "swarm" and swarm["fail"]:
            raise FlightError("zenswarm up exited 3", 3, "")
        f = fly(doc, mode="sim", seed=seed, **kw)  # the simulator stands in for the lockstep swarm
        if mode == "swarm" and seed == swarm["bump"]:
            r = dict(f.results)
            r["rms_tracking_error_m"] = math.nextafter(r["rms_tracking_error_m"], math.inf)
            f = dataclasses.replace(f, results=r)
        return f

    monkeypatch.setattr(sweep, "LocalBackend", Inline)
    monkeypatch.setattr(sweep, "fly", fake_fly)
    monkeypatch.setattr(sweep, "_maybe_report", lambda out: None)  # the report has its own tests
    out = tmp_path / "c"
    args = [EX1, "--seeds", "3", "--duration", "0.5", "--check-swarm", "2", "--quiet", "--out", str(out)]
    assert main(args) == 0, capsys.readouterr().err
    picked = json.loads((out / "check_swarm.json").read_text())["runs"]
    assert len(picked) == 2 and calls[:3] == [("sim", 0), ("sim", 1), ("sim", 2)]
    assert sorted(calls[3:]) == [("swarm", r) for r in picked]  # seed == run index here (base seed 0, one cell)
    err = capsys.readouterr().err
    assert "flying runs" in err and "check-swarm: run" not in err

    swarm["bump"] = picked[1]
    calls.clear()
    assert main(args) == 1  # the same command: nothing to fly again, the check flies again
    assert [m for m, _ in calls] == ["swarm", "swarm"]
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "check-swarm: run" in ln]
    assert len(lines) == 1 and f"run {picked[1]} " in lines[0] and "rms_tracking_error_m" in lines[0], lines
    assert json.loads((out / "check_swarm.json").read_text())["differences"] == [lines[0].split("check-swarm: ", 1)[1]]

    swarm["fail"] = True
    assert main(args) == 1
    err = capsys.readouterr().err
    assert all(f"check-swarm: run {r} " in err for r in picked) and "the swarm flight failed: FlightError" in err


# ----------------------------------------------------------------------------- the installed command


@pytest.mark.swarm  # two runs of the console script (about 1.5 s each); the rest in this process
def test_console_script_help_and_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``zenswarm sweep --help`` names every option and the subcommands; ``sweep report`` on a
    missing directory exits 2 with the message (both through the installed ``zenswarm`` script);
    ``sweep report`` on a directory that is no campaign, ``sweep margin --help`` and bad
    ``sweep margin`` input through :func:`main`."""
    import sysconfig

    exe = Path(sysconfig.get_path("scripts")) / "zenswarm"
    assert exe.is_file(), f"the console script {exe} (pip install -e .)"
    helped = subprocess.run([str(exe), "sweep", "--help"], capture_output=True, text=True, timeout=60)
    assert helped.returncode == 0, helped.stderr
    text = " ".join(helped.stdout.split())
    for word in ("--grid", "--sample PATH=LOW:HIGH", "--samples K", "--seeds N", "--base-seed", "--workers W",
                 "--scheduler tcp://HOST:PORT", "--mode {sim,swarm}", "--check-swarm K", "--duration", "--out DIR",
                 "zenswarm sweep report DIR", "zenswarm sweep margin SCENARIO", "dask scheduler", "2 bad input"):
        assert word in text, word
    missing = tmp_path / "nosuch"
    rep = subprocess.run([str(exe), "sweep", "report", str(missing)], capture_output=True, text=True, timeout=60)
    assert rep.returncode == 2 and "not a campaign directory" in rep.stderr and str(missing) in rep.stderr, rep.stderr
    assert not missing.exists()

    (tmp_path / "empty").mkdir()
    assert main(["report", str(tmp_path / "empty")]) == 2
    assert "campaign.json" in capsys.readouterr().err and not (tmp_path / "empty" / "report.md").exists()
    assert main(["margin", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--max-delay" in out and "--tol" in out and "docs/delay_margin.md" in out
    for bad, named in ((["--scan", "1"], "--scan"), (["--max-delay", "5parsecs"], "--max-delay"), ([], "scenario")):
        scenario = ["nosuch_scenario"] if named == "scenario" else [EX1]
        code = main(["margin", *scenario, *bad])
        err = capsys.readouterr().err
        assert code == 2 and named in err and "error" in err, (bad, err)


def test_progress_counts_the_resumed_runs_failures_and_errors() -> None:
    resumed = [{"success": True, "error": None}, {"success": False, "error": None}, {"success": False, "error": "FlightError: x"}]
    p = Progress(5, resumed, quiet=True)
    p.add({"success": False, "error": None})
    line = p.line()
    assert line.startswith("sweep: 4/5 done (3 resumed), 2 failed, 1 errors, "), line


def test_grid_trace_beside_the_scenario(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A relative `--grid faults.trace=` is read beside the scenario file, as `--set` and api.fly
    take it, wherever the sweep runs from (the rows fly those traces; a missing one is named with
    the path looked at, exit 2, before anything flies)."""
    trace = (ROOT / "docs" / "example_trace.csv").read_text()
    (tmp_path / "a.csv").write_text(trace)
    (tmp_path / "b.csv").write_text(trace)
    (tmp_path / "s.toml").write_text((SCENARIOS / "paper_example1.toml").read_text())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    out = tmp_path / "c"
    args = [str(tmp_path / "s.toml"), "--seeds", "1", "--duration", "1", "--workers", "1", "--quiet"]
    assert main([*args, "--grid", "faults.trace=a.csv,nope.csv", "--out", str(out)]) == 2
    assert str(tmp_path.absolute() / "nope.csv") in capsys.readouterr().err and not out.exists()
    assert main([*args, "--grid", "faults.trace=a.csv,b.csv", "--out", str(out)]) == 0, capsys.readouterr().err
    rows = _table(out)
    assert [r["faults.trace"] for r in rows] == ["a.csv", "b.csv"]  # the table keeps what the user wrote
    assert all(r["error"] is None for r in rows), rows

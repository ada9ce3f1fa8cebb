"""`zenswarm plugins check` (issue 15 item 4): every built-in plug-in passes it, with one short
lockstep flight each (the example package's is in tests/test_examples.py); plug-ins that break
the interface, are impure or not deterministic fail the check that says so; bad input exits 2."""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from zenswarm.agents.api import Command, Shared
from zenswarm.agents.paper import PaperController
from zenswarm.compose.cli import main
from zenswarm.compose.plugcheck import check_plugin
from zenswarm.leader.planner import AapfPlanner
from zenswarm.plant.api import QuadrotorModel
from zenswarm.scenario.config import load_scenario
from zenswarm.scenario.plugins import KINDS, available

from swarmtest import SCENARIOS

EX1 = load_scenario(SCENARIOS / "paper_example1.toml")
BUILTINS = [(kind, p.name) for kind in KINDS for p in available(kind) if p.origin == "builtin"]

# ----------------------------------------------------------------------------- plug-ins that break the rules


class ClockController(PaperController):
    two_phase = False  # ticked through step()
    name = "clock"
    description = "reads the clock in its tick"

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        time.monotonic()
        return super().step(q, v, neighbours, leader, dt)


_COUNTER = itertools.count()


class DriftController(PaperController):
    two_phase = False  # ticked through step()
    name = "drift"
    description = "its output depends on how often any instance ran (a module-level counter)"

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        cmd = super().step(q, v, neighbours, leader, dt)
        return Command(cmd.thrust + 1e-9 * next(_COUNTER), cmd.rpy, cmd.u, cmd.d_hat)


class NanController(PaperController):
    two_phase = False  # ticked through step()
    name = "nan"
    description = "commands a NaN thrust from tick 5"

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        self.k = getattr(self, "k", 0) + 1
        cmd = super().step(q, v, neighbours, leader, dt)
        return Command(float("nan") if self.k > 5 else cmd.thrust, cmd.rpy, cmd.u, cmd.d_hat)


class BadSharesController(PaperController):
    name = "bad-shares"
    description = "declares a shape of zero"
    shares = {"meas": (0, 3)}


class NotMappingSharesController(PaperController):
    name = "not-a-mapping"
    description = "declares its shares as a list"
    shares = ["meas"]  # type: ignore[assignment]  # the wrong type on purpose


class LateRaiseController(PaperController):
    name = "late-raise"
    description = "raises at its tick 150 (past the first second), UAV 2 only"

    def finish(self, q: np.ndarray, v: np.ndarray, rates: Any, dt: float) -> Command:
        self.k = getattr(self, "k", 0) + 1
        if self.ctx.i == 1 and self.k > 150:
            raise RuntimeError("late failure")
        return super().finish(q, v, rates, dt)


class WrongSignatureController(PaperController):
    two_phase = False
    name = "signature"
    description = "its step takes no dt"

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None) -> Command:  # type: ignore[override]
        return super().step(q, v, neighbours, leader, 0.01)


class BrokenInitController(PaperController):
    name = "broken-init"
    description = "its constructor raises"

    def __init__(self, ctx: Any, params: Any) -> None:
        raise KeyError("no such gain")


class CrossTalkController(PaperController):
    """Deterministic in one process, but its UAVs share a class-level table: in the simulator
    (every UAV in one process) UAV 2 and 3 see more entries than in the swarm (one per process)."""

    two_phase = False
    name = "cross-talk"
    description = "state shared between instances through a class variable"
    table: dict[int, float] = {}

    def __init__(self, ctx: Any, params: Any) -> None:
        if ctx.i == 0:
            CrossTalkController.table = {}
        super().__init__(ctx, params)

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        cmd = super().step(q, v, neighbours, leader, dt)
        self.table[self.ctx.i] = cmd.thrust
        return Command(cmd.thrust + 1e-6 * len(self.table), cmd.rpy, cmd.u, cmd.d_hat)


class CounterPlant(QuadrotorModel):
    """Counts its steps in a class attribute: every instance in the process adds to one count."""

    name = "counter"
    description = "a class-level step counter nudges every UAV"
    steps = 0

    def step(self, thrust: np.ndarray, rpy: np.ndarray, disturbance: Any) -> None:
        CounterPlant.steps += 1
        super().step(thrust, rpy, disturbance)
        self.state.q[:, 2] += 1e-9 * CounterPlant.steps


class SwarmOnlyController(PaperController):
    """Passes every in-process check, but UAV 2's thrust depends on the process it runs in (an
    agent process of the swarm: ``python -m zenswarm agent``): only the sim == swarm flight sees it."""

    two_phase = False
    name = "swarm-only"
    description = "UAV 2 flies differently in a swarm process"

    def step(self, q: np.ndarray, v: np.ndarray, neighbours: Sequence[Shared | None], leader: Shared | None, dt: float) -> Command:
        import sys

        cmd = super().step(q, v, neighbours, leader, dt)
        nudge = 1e-6 if self.ctx.i == 1 and "agent" in sys.argv else 0.0
        return Command(cmd.thrust + nudge, cmd.rpy, cmd.u, cmd.d_hat)


class MutableParamsController(PaperController):
    name = "mutable"
    description = "Params not frozen"

    class Params(msgspec.Struct, forbid_unknown_fields=True):
        gain: float = 1.0


class FilePlanner(AapfPlanner):
    name = "file"
    description = "opens a file in its tick"

    def advance(self) -> None:
        open("/dev/null").close()
        super().advance()


class UnseededPlanner(AapfPlanner):
    name = "unseeded"
    description = "draws from numpy's global generator"

    def advance(self) -> None:
        np.random.random()
        super().advance()


def _status(name: str, **kw: Any) -> dict[str, str]:
    """The checks of ``test_plugcheck:NAME`` (no swarm flight): check name -> "STATUS detail".

    Several parametrizations below look for different words in the same check of the same
    plug-in: the checks are run once per plug-in and arguments in this process, and each of
    those tests reads that report (a copy). The checks are deterministic in what they report,
    DriftController's module-level counter included (its detail names tick 0 whatever the count)."""
    key = (name, tuple(sorted(kw.items())))
    if key not in _STATUS:
        _, _, checks = check_plugin(f"test_plugcheck:{name}", EX1, swarm=False, **kw)
        _STATUS[key] = {c.name: f"{c.status} {c.detail}" for c in checks}
    return dict(_STATUS[key])


_STATUS: dict[tuple[str, tuple[tuple[str, Any], ...]], dict[str, str]] = {}


@pytest.mark.parametrize(
    ("plugin", "check", "needle"),
    [
        ("ClockController", "pure ticks", "time.monotonic()"),
        ("FilePlanner", "pure ticks", "open()"),
        ("UnseededPlanner", "pure ticks", "numpy.random.random()"),
        ("DriftController", "deterministic", "UAV 1 step().thrust at tick 0 differs between two fresh runs in one process"),
        ("DriftController", "deterministic", "Cause: state kept outside the instance (a class or module attribute)"),
        ("CrossTalkController", "shared state", "UAV 1 step().thrust at tick 1 differs when UAV 1 flies alone"),
        ("CrossTalkController", "shared state", "Cause: state shared between UAVs (a class or module attribute)"),
        ("CounterPlant", "deterministic", "UAV 1 state.q after tick 0 differs between two fresh runs in one process"),
        ("CounterPlant", "deterministic", "Cause: state kept outside the instance"),
        ("NanController", "outputs", "step().thrust at tick 5: not finite"),
        ("MutableParamsController", "interface", "Params must be frozen"),
        ("WrongSignatureController", "interface", "step must accept step(self, q, v, neighbours, leader, dt)"),
        ("LateRaiseController", "outputs", "RuntimeError: late failure"),
        ("BrokenInitController", "outputs", "KeyError"),
    ],
)
def test_a_plug_in_that_breaks_a_rule_fails_that_check(plugin: str, check: str, needle: str) -> None:
    got = _status(plugin)
    assert got[check].startswith("FAIL") and needle in got[check], got
    assert got["sim == swarm"].startswith("SKIP"), got


def test_a_failure_past_the_first_second_is_found_and_named_in_the_flight() -> None:
    """The outputs check covers the whole (shortened) flight, and the flight check names the
    plug-in's failure as the simulator does (plugin_error, UAV, tick, the exception)."""
    got = _status("LateRaiseController", duration=2.0)
    assert got["outputs"].startswith("FAIL") and "late failure" in got["outputs"], got
    assert got["flight"].startswith("FAIL") and "plugin_error uav 2 at 1.50 s" in got["flight"] and "late failure" in got["flight"], got
    assert _status("LateRaiseController", duration=1.0)["flight"].startswith("PASS")  # 1 s: it never fails


def test_a_plug_in_that_raises_gets_every_check_reported_never_a_traceback(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins", "check", "test_plugcheck:BrokenInitController", "--no-swarm"]) == 1
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err
    lines = [ln.split()[:2] for ln in out.out.splitlines() if ln.startswith("  ")]
    assert [ln[1] for ln in lines] == ["interface", "outputs", "deterministic", "pure", "shared", "flight", "sim"], out.out
    assert out.out.rstrip().endswith("result: FAIL (outputs, flight)"), out.out


def test_exit_status_and_report(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plugins", "check", "test_plugcheck:ClockController", "--no-swarm"]) == 1
    out = capsys.readouterr().out
    assert "FAIL  pure ticks" in out and out.rstrip().endswith("result: FAIL (pure ticks)")
    assert main(["plugins", "check", "paper", "--no-swarm"]) == 0
    assert capsys.readouterr().out.rstrip().endswith("result: PASS")
    assert main(["plugins", "check", "no-such-plugin"]) == 2
    assert "no controller, planner or plant model named 'no-such-plugin'" in capsys.readouterr().err
    assert main(["plugins", "check", "paper", "--duration", "0"]) == 2
    assert "--duration" in capsys.readouterr().err


@pytest.mark.parametrize("plugin", ["BadSharesController", "NotMappingSharesController"])
def test_a_bad_shares_declaration_is_bad_input_exit_2_naming_shares(capsys: pytest.CaptureFixture[str], plugin: str) -> None:
    """As a plant model's bad ``records``: exit 2 before any check, naming the field."""
    assert main(["plugins", "check", f"test_plugcheck:{plugin}", "--no-swarm"]) == 2
    out = capsys.readouterr()
    assert "shares: " in out.err and "must map names to shapes" in out.err, out.err
    assert "PASS" not in out.out and "FAIL" not in out.out, out.out


def test_set_overrides_the_scenario_as_on_sim_and_up(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """``plugins check --set KEY=VALUE``: the plug-in's parameters (and any field) as ``sim --set``
    gives them; a bad override is exit 2 naming it."""
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    args = ["plugins", "check", "plugin_fixtures:MisbehavingController", "--no-swarm", "--duration", "1"]
    assert main([*args, "--set", "agents.params.how=nan", "--set", "agents.params.tick=7"]) == 1
    out = capsys.readouterr().out
    assert "FAIL  outputs" in out and "UAV 2 step().thrust at tick 7: not finite" in out, out
    assert main([*args, "--set", "agents.params.tick=100000"]) == 0, capsys.readouterr().out  # never misbehaves in 1 s
    assert main([*args, "--set", "timing.no_such_field=1"]) == 2
    assert "timing.no_such_field" in capsys.readouterr().err


@pytest.mark.swarm
@pytest.mark.parametrize(("kind", "name"), BUILTINS)
def test_every_built_in_plug_in_passes(kind: str, name: str) -> None:
    """One short lockstep flight each (2 s, link loss, delay and jitter), bit for bit."""
    got_kind, _, checks = check_plugin(name, EX1, duration=2.0)
    assert got_kind == kind
    assert [(c.name, c.status) for c in checks] == [
        ("interface", "PASS"), ("outputs", "PASS"), ("deterministic", "PASS"), ("pure ticks", "PASS"), ("shared state", "PASS"),
        ("flight", "PASS"), ("sim == swarm", "PASS"),
    ], "\n".join(f"{c.name}: {c.status}: {c.detail}" for c in checks)  # text: pytest shortens a list's repr


@pytest.mark.swarm
def test_a_sim_swarm_mismatch_names_the_first_field_tick_uav_and_the_usual_causes(monkeypatch: pytest.MonkeyPatch) -> None:
    import os

    tests = str(Path(__file__).parent)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")]))
    _, _, checks = check_plugin("test_plugcheck:SwarmOnlyController", EX1, duration=1.0)
    got = {c.name: (c.status, c.detail) for c in checks}
    assert [got[n][0] for n in ("interface", "outputs", "deterministic", "pure ticks", "shared state", "flight")] == ["PASS"] * 6, got
    status, detail = got["sim == swarm"]
    assert status == "FAIL" and "first difference: series.thrust" in detail and "first at tick 0" in detail, detail
    assert "UAV 2)" in detail and "Usual causes:" in detail and "module or class variable" in detail, detail


def test_a_difference_after_a_lockstep_timeout_names_the_stall_not_the_plug_in() -> None:
    """A swarm flight whose processes waited out the lockstep timeout (``forced_ticks`` in their
    final diagnostics) did not fly the simulator's flight: the check's detail names which and how
    many ticks, instead of the plug-in's usual causes; without a stall, the usual causes."""
    from zenswarm.compose.plugcheck import LOCKSTEP_TIMEOUT_S, difference_text

    diffs = ["series.thrust: 3 values differ, first at tick 148 (t = 2.960 s, UAV 2): 1.0 != 2.0"]
    calm = {"diagnostics": {"plant": {"forced_ticks": 0, "cmd_timeouts": 0}, "agent:1": {"forced_ticks": 0}}}
    stalled = {"diagnostics": {"plant": {"forced_ticks": 1}, "agent:1": {"forced_ticks": 0}, "agent:3": {"forced_ticks": 4}}}
    assert difference_text([], stalled, 5.0) == ""
    usual = difference_text(diffs, calm, 5.0)
    assert usual.startswith("first difference: series.thrust") and "Usual causes:" in usual and "lockstep" not in usual, usual
    named = difference_text(diffs, stalled, 5.0)
    assert "Usual causes" not in named and "waited out the lockstep timeout (5 s)" in named, named
    assert "(agent:3 4 ticks, plant 1 tick)" in named and "not the plug-in" in named, named
    assert LOCKSTEP_TIMEOUT_S > 5.0  # the check's swarm waits longer than `up`'s default

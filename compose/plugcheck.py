"""``zenswarm plugins check NAME [SCENARIO]``: the conformance check of a controller, planner or plant model plug-in.

What any plug-in author can run on their plug-in before flying it (and what the test suite runs on
every built-in and on the example in ``examples/``). In order; a failed check skips the ones after
it that need it:

1. **interface**: the class resolves (:func:`zenswarm.scenario.plugins.resolve`), has a one-line ``name``
   and ``description``, a ``Params`` that is a frozen :class:`msgspec.Struct` refusing unknown
   keys (checked by decoding an unknown key), and the scenario's params table decodes; a
   plant model's ``vehicle()`` gives a :class:`zenswarm.vehicle.params.QuadParams`; a controller's
   ``shares`` (names to shapes of positive ints) and a plant model's ``records`` declaration (names
   to :class:`zenswarm.scenario.plugins.Signal` with shapes and units) are checked before anything
   (a bad one is bad input: exit 2 naming ``shares`` or ``records.<name>``); the methods the runners call
   take the arguments they are called with (``step(q, v, neighbours, leader, dt)``, a two-phase
   controller's ``prepare(neighbours, leader)`` and ``finish(q, v, prepared, dt)``, ``reset(q,
   v)``, ``share()``; a planner's ``ref()`` and ``advance()``; a plant model's
   ``step(thrust, rpy, disturbance)``).
2. **outputs**: every tick of the (shortened) flight on synthetic, deterministic inputs (every UAV of the scenario,
   each fed its neighbours' shared values and the leader's reference): a controller's shared q, v
   are (3,) and finite, its declared extras have their shapes, its command has a finite thrust
   >= 0, rpy (3,), u (3,), d_hat (3,); a planner's (q0, v0) are (3,) and finite and ``ref()``
   does not change its state; a plant model, stepped by :class:`zenswarm.plant.core.PlantCore` with
   synthetic commands about hover (thrust, attitude setpoints within +-0.1 rad) and the scenario's
   disturbance, keeps its state (q, v, rpy, w) (N, 3) and finite, and its ``record()`` gives every
   declared signal and no other, each (N, *shape) and finite (else the failure ``plugin_error``
   of call ``record``, as the runners report it); the records are outputs of the checks below too.
3. **deterministic**: the same ticks again with fresh instances give identical outputs, bit for bit.
   A difference names the first differing output (field, tick, UAV) and, when no clock or global
   randomness was touched, its cause: state kept outside the instance (a class or module attribute).
4. **pure ticks**: during ``reset``/``share``/``step`` (``ref``/``advance``; a plant model's ``step``) the clock (``time``),
   sockets, ``open`` and unseeded randomness (``random``, numpy's global generator) raise;
   constructing the plug-in may do what it likes.
   **shared state** (a controller's): each UAV's controller flown alone in a fresh process of its
   own (as ``zenswarm up`` runs it; its neighbours' shared values replayed) gives the outputs it
   gave beside the others in one process (as ``zenswarm sim`` runs them); a difference is state
   shared between UAVs, named by field, tick and UAV. A planner or a plant model is one instance
   in both modes (what outlives it is the deterministic check's).
5. **flight**: the short flight (:data:`DEFAULT_DURATION_S` of SCENARIO) in the in-process
   simulator, on the vehicles' real states: the plug-in must not fail there (``plugin_error``:
   an exception, a non-finite or wrongly shaped output, named with its tick and UAV).
6. **sim == swarm**: the same flight with link loss and delay on every link in the in-process
   simulator and as the lockstep swarm (``zenswarm up``), compared bit for bit
   (:func:`zenswarm.judge.metrics.flight_differences`: the first differing field, tick and UAV), with
   the usual causes of a difference when there is one. The swarm waits up to
   :data:`LOCKSTEP_TIMEOUT_S` for a tick's inputs; if a process still waited it out (a starved
   machine), the detail says so instead of blaming the plug-in.

Every check is reported (PASS, FAIL or SKIP with why), never a traceback, then a ``result:``
line. Exit status 0 every check passed, 1 a check failed, 2 bad input (an unknown name, a
scenario that does not load).
"""

from __future__ import annotations

import argparse
import builtins
import io
import os
import random
import socket
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from msgspec.structs import replace as replace_table

from zenswarm.errors import ScenarioError
from zenswarm.scenario.config import Scenario, scenario_to_dict
from zenswarm.scenario.plugins import (
    GROUPS,
    KINDS,
    PluginError,
    decode_params,
    plant_vehicle,
    plugin_rng,
    records_of,
    resolve,
    select,
    shares_of,
)

__all__ = ["add_check_parser", "run_check", "Check", "check_plugin"]

MISMATCH_CAUSES = (
    "state kept outside the instance (a module or class variable: the simulator runs every UAV's "
    "controller in one process, the swarm one per process)",
    "randomness not from ctx.rng, or the clock",
    "mutating an array after share() returned it, or the inputs it was given",
    "depending on the order of dict/set iteration, object ids or hash seeds",
)
"""What usually makes a plug-in fly differently in the simulator and in the swarm."""

DEFAULT_DURATION_S = 3.0
"""Sim seconds of the sim-versus-swarm flight."""

LOCKSTEP_TIMEOUT_S = 60.0
"""Wall seconds a process of the check's swarm waits for a tick's inputs before ticking on held
ones. The check's flight loses no process and every lost message is known to its receiver, so
in a healthy flight the timeout never fires; it is long so that a busy machine (slow imports,
CPU contention) cannot turn into a difference blamed on the plug-in (``up``'s default is 5 s)."""

FAULTS = {"link_loss": "0.2", "link_delay": "30ms", "link_jitter": "10ms"}
"""The link faults of the sim-versus-swarm flight (on every link)."""


@dataclass
class Check:
    """One line of the report: ``status`` PASS, FAIL or SKIP; ``detail`` says what was checked or
    what went wrong."""

    name: str
    status: str
    detail: str


class Impure(RuntimeError):
    """A plug-in touched the clock, a socket, a file or unseeded randomness during a tick."""


# ----------------------------------------------------------------------------- purity guard


def _raiser(what: str) -> Callable[..., Any]:
    def refuse(*args: Any, **kwargs: Any) -> Any:
        raise Impure(f"called {what} during a tick")

    return refuse


def _guarded() -> list[tuple[Any, str, str]]:
    """(object, attribute, what) patched to raise while a plug-in ticks."""
    out: list[tuple[Any, str, str]] = []
    for f in ("time", "monotonic", "perf_counter", "process_time", "time_ns", "monotonic_ns", "perf_counter_ns", "sleep"):
        out.append((time, f, f"time.{f}()"))
    out += [(socket, "socket", "socket.socket()"), (socket, "create_connection", "socket.create_connection()")]
    out += [(builtins, "open", "open()"), (io, "open", "io.open()"), (os, "open", "os.open()")]
    for f in ("random", "randint", "uniform", "gauss", "choice", "shuffle", "normalvariate", "seed"):
        out.append((random, f, f"random.{f}() (unseeded; use ctx.rng)"))
    for f in ("rand", "randn", "random", "normal", "uniform", "randint", "choice", "shuffle", "seed"):
        out.append((np.random, f, f"numpy.random.{f}() (the global generator; use ctx.rng)"))
    return out


@contextmanager
def pure_ticks() -> Iterator[None]:
    """While inside: the clock, sockets, ``open`` and unseeded randomness raise :class:`Impure`
    (and ``numpy.random.default_rng()`` without a seed)."""
    saved = [(obj, attr, getattr(obj, attr)) for obj, attr, _ in _guarded()]
    real_rng = np.random.default_rng

    def seeded_only(seed: Any = None) -> np.random.Generator:
        if seed is None:
            raise Impure("called numpy.random.default_rng() without a seed during a tick (use ctx.rng)")
        return real_rng(seed)

    try:
        for obj, attr, what in _guarded():
            setattr(obj, attr, _raiser(what))
        np.random.default_rng = seeded_only  # type: ignore[assignment]
        yield
    finally:
        for obj, attr, fn in saved:
            setattr(obj, attr, fn)
        np.random.default_rng = real_rng  # type: ignore[assignment]


# ----------------------------------------------------------------------------- interface


def _interface(kind: str, cls: type, sc: Scenario) -> tuple[list[str], Any]:
    """Problems with the class's declared interface, and the decoded params."""
    problems: list[str] = []
    for attr in ("name", "description"):
        v = getattr(cls, attr, None)
        if not isinstance(v, str) or not v.strip() or "\n" in v.strip():
            problems.append(f"{attr} must be a non-empty one-line string, got {v!r}")
    P = getattr(cls, "Params", None)
    params = None
    if not (isinstance(P, type) and issubclass(P, msgspec.Struct)):
        problems.append(f"Params must be a msgspec.Struct subclass, got {P!r}")
    else:
        cfg = P.__struct_config__
        if not cfg.frozen:
            problems.append("Params must be frozen (class Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True))")
        if not cfg.forbid_unknown_fields:
            problems.append("Params must refuse unknown keys (forbid_unknown_fields=True)")
        try:
            decode_params(cls, {"zz_not_a_parameter": 1}, "params")
            problems.append("Params accepted an unknown key")
        except ScenarioError:
            pass
        table = {"controller": sc.agents.params, "planner": sc.leader.params, "plant": sc.plant.params}[kind]
        field = {"controller": "agents.params", "planner": "leader.params", "plant": "plant.params"}[kind]
        try:
            params = decode_params(cls, table, field)
        except ScenarioError as e:
            problems.append(f"the scenario's [{field}] does not decode: {e} (give a SCENARIO with the plug-in's parameters)")
        if kind == "plant" and params is not None:
            try:
                plant_vehicle(sc)
            except ScenarioError as e:
                problems.append(f"vehicle(): {e}")
            except Exception as e:  # noqa: BLE001 - a plug-in's own error is a failed check, reported
                problems.append(f"vehicle() raised {type(e).__name__}: {e}")
    problems += _signatures(kind, cls)  # a controller's shares: checked before (shares_of, bad input)
    return problems, params


def _signatures(kind: str, cls: type) -> list[str]:
    """Problems with the methods' signatures: each must accept the arguments a runner passes."""
    import inspect

    calls: dict[str, tuple[str, ...]]
    if kind == "controller":
        calls = {"reset": ("q", "v"), "share": (), "step": ("q", "v", "neighbours", "leader", "dt")}
        if getattr(cls, "two_phase", False):
            calls.update({"prepare": ("neighbours", "leader"), "finish": ("q", "v", "prepared", "dt")})
    elif kind == "plant":
        calls = {"step": ("thrust", "rpy", "disturbance")}
    else:
        calls = {"ref": (), "advance": ()}
    problems = []
    for meth, args in calls.items():
        fn = getattr(cls, meth, None)
        if not callable(fn):
            problems.append(f"{meth}() is missing")
            continue
        try:
            inspect.signature(fn).bind(None, *args)
        except TypeError as e:
            want = f"{meth}(self{''.join(', ' + a for a in args)})"
            problems.append(f"{meth} must accept {want}: {e}")
        except ValueError:  # no signature (a builtin): cannot tell
            continue
    return problems


# ----------------------------------------------------------------------------- ticking


def _finite(x: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.shape != shape:
        raise AssertionError(f"{what}: shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise AssertionError(f"{what}: not finite ({a.tolist()})")
    return a


def _mass_g(sc: Scenario) -> tuple[float, float]:
    from zenswarm.scenario.plugins import plant_vehicle

    p = plant_vehicle(sc)
    return float(p.mass), float(p.g)


def _leader_refs(sc: Scenario, ticks: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The scenario's own planner's (q0, v0) for ``ticks`` ticks (the controllers' leader input)."""
    from zenswarm.leader.core import make_planner

    pl = make_planner(sc)
    out = []
    for _ in range(ticks):
        q0, v0 = pl.ref()
        out.append((np.array(q0, dtype=float), np.array(v0, dtype=float)))
        pl.advance()
    return out


def _synthetic_state(sc: Scenario, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic vehicle states (N, 3) for tick k: the initial positions drifting slowly."""
    q0 = np.asarray(sc.initial_positions, dtype=float)
    n = len(q0)
    drift = np.array([0.01, 0.005, 0.002]) * np.sin(0.05 * k + np.arange(n))[:, None]
    return q0 + drift, 0.05 * np.cos(0.05 * k + np.arange(n))[:, None] * np.array([1.0, 0.5, 0.2])


Output = tuple[str, np.ndarray]
"""One output of a plug-in in the check's flight: what it is (field, tick, UAV, e.g. ``UAV 2
step().thrust at tick 37``) and its value."""


def _tick_controllers(
    cls: type, params: Any, sc: Scenario, ticks: int, guard: bool, alone: int | None = None,
    replay: list[list[Any]] | None = None, record: list[list[Any]] | None = None,
) -> list[Output]:
    """Every UAV's controller (built and ticked as every runner does: :func:`zenswarm.agents.api.make_controller`,
    :func:`~zenswarm.agents.api.prepare`, :func:`~zenswarm.agents.api.finish`) for ``ticks``
    ticks on synthetic inputs; the outputs, labelled. ``alone`` (0-based): only that UAV's
    controller is built and ticked (as in its own swarm process), its neighbours' shared values
    taken from ``replay`` (per tick, per UAV: ``(q, v, extra)`` as ``record`` collects them from a
    run of all)."""
    from zenswarm.agents.api import Shared, finish, make_controller, prepare

    mass, g = _mass_g(sc)
    uavs = list(range(sc.n)) if alone is None else [alone]
    ctrls = {i: make_controller(sc, i, mass, g) for i in uavs}
    leads = _leader_refs(sc, ticks)
    shares = dict(getattr(cls, "shares", {}))
    out: list[Output] = []
    dt = sc.timing.dt
    cm = pure_ticks if guard else _nothing

    def put(x: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
        a = _finite(x, shape, what)
        out.append((what, a))
        return a

    for k in range(ticks):
        q, v = _synthetic_state(sc, k)
        with cm():
            if k == 0:
                for i, c in ctrls.items():
                    c.reset(q[i].copy(), v[i].copy())
            mine = {i: c.share() for i, c in ctrls.items()}
        shared: list[Any] = [Shared(q_, v_, extra) for q_, v_, extra in replay[k]] if replay is not None else [None] * sc.n
        for i, s in mine.items():
            shared[i] = s
            put(s.q, (3,), f"UAV {i + 1} share().q at tick {k}")
            put(s.v, (3,), f"UAV {i + 1} share().v at tick {k}")
            for name, shape in shares.items():
                if name not in s.extra:
                    raise AssertionError(f"UAV {i + 1} share() at tick {k}: declared extra {name!r} missing")
                put(s.extra[name], tuple(shape), f"UAV {i + 1} share().extra[{name!r}] at tick {k}")
        if record is not None:
            record.append([(np.array(x.q, dtype=float), np.array(x.v, dtype=float), {n: np.array(e) for n, e in x.extra.items()})
                           for x in shared])
        with cm():
            cmds = {}
            for i, c in ctrls.items():
                nbrs = [shared[nb.index] for nb in c.ctx.neighbours]
                lead = Shared(*leads[k]) if c.ctx.pinned else None
                cmds[i] = finish(c, q[i].copy(), v[i].copy(), prepare(c, nbrs, lead), dt)
        for i, cmd in cmds.items():
            t = put(cmd.thrust, (), f"UAV {i + 1} step().thrust at tick {k}")
            if t < 0:
                raise AssertionError(f"UAV {i + 1} step().thrust at tick {k}: negative ({float(t)} N)")
            put(cmd.rpy, (3,), f"UAV {i + 1} step().rpy at tick {k}")
            put(cmd.u, (3,), f"UAV {i + 1} step().u at tick {k}")
            put(cmd.d_hat, (3,), f"UAV {i + 1} step().d_hat at tick {k}")
    return out


def _tick_plant(cls: type, params: Any, sc: Scenario, ticks: int, guard: bool) -> list[Output]:
    """The plant model (in a :class:`zenswarm.plant.core.PlantCore`, as every runner has it) for
    ``ticks`` ticks of synthetic commands about hover; its state of every tick."""
    from zenswarm.plant.core import STATE_FIELDS, PlantCore

    core = PlantCore(sc)  # PluginFailure (a non-finite or mis-shaped state) is the check's failure
    n, p = sc.n, core.params
    out: list[Output] = []
    cm = pure_ticks if guard else _nothing
    phase = np.arange(n)[:, None] + np.array([0.0, 1.0, 2.0])
    for k in range(ticks):
        thrust = p.mass * p.g * (1.0 + 0.05 * np.sin(0.07 * k + np.arange(n)))
        rpy = 0.1 * np.sin(0.05 * k + phase)
        rpy[:, 2] = sc.controller.yaw
        core.hold_all(thrust, rpy, k)
        with cm():
            core.step(k)
        st = core.state
        out += [(f"state.{f} after tick {k}", _finite(getattr(st, f), (n, 3), f"state.{f} after tick {k}").copy()) for f in STATE_FIELDS]
        for name, sig in core.records.items():  # checked by the core (names, shapes, finite): kept per UAV
            what = f"record.{name} after tick {k}"
            out.append((what, _finite(core.recorded[name], (n, *sig.shape), what).reshape(n, -1).copy()))
    return out


def _tick_planner(cls: type, params: Any, sc: Scenario, ticks: int, guard: bool) -> list[Output]:
    """The planner for ``ticks`` ticks; its (q0, v0) of every tick."""
    from zenswarm.leader.planner import PlannerContext

    tm = sc.timing
    ctx = PlannerContext(
        start=np.asarray(sc.leader.start, dtype=float), goal=np.asarray(sc.leader.goal, dtype=float), obstacles=tuple(sc.obstacles),
        r_f=sc.r_f, dt=tm.dt, substeps=tm.substeps, rng=plugin_rng(sc.seed, 0), leader=sc.leader,
    )
    pl = cls(ctx, params)
    out: list[Output] = []
    cm = pure_ticks if guard else _nothing
    for k in range(ticks):
        with cm():
            q0, v0 = pl.ref()
            q0, v0 = np.array(q0, dtype=float), np.array(v0, dtype=float)
            again = [np.array(x, dtype=float) for x in pl.ref()]
        out += [(f"ref().q0 at tick {k}", _finite(q0, (3,), f"ref().q0 at tick {k}")),
                (f"ref().v0 at tick {k}", _finite(v0, (3,), f"ref().v0 at tick {k}"))]
        if not (np.array_equal(again[0], q0) and np.array_equal(again[1], v0)):
            raise AssertionError(f"ref() at tick {k} changed the state: a second call gave {again[0].tolist()}, {again[1].tolist()}")
        with cm():
            pl.advance()
    return out


@contextmanager
def _nothing() -> Iterator[None]:
    yield


# ----------------------------------------------------------------------------- the check


def _scenario_for(kind: str, name: str, sc: Scenario, duration: float) -> Scenario:
    """SCENARIO with the plug-in selected (as --controller/--planner/--plant-model) and a short time limit."""
    sc = select(sc, name if kind == "controller" else None, name if kind == "planner" else None, name if kind == "plant" else None)
    return replace(sc, timing=replace_table(sc.timing, time_limit_s=min(duration, sc.timing.time_limit_s)))


def _sim_vs_swarm(sc: Scenario, seed: int) -> str:
    """Fly ``sc`` in-process and as the lockstep swarm with :data:`FAULTS`; "" when bit equal,
    else what differs."""
    from zenswarm.bus.wire import Keys
    from zenswarm.compose.launch import run_up
    from zenswarm.compose.sim import simulate
    from zenswarm.judge.metrics import TimeSeries, flight_differences
    from zenswarm.link import LinkFaults
    from zenswarm.process.settings import FlightSettings
    from zenswarm.scenario.generate import to_toml

    faults = LinkFaults(FAULTS["link_delay"], FAULTS["link_jitter"], FAULTS["link_loss"], (), seed)
    ref = simulate(sc, faults=faults.plan(sc))
    import json
    import uuid

    with tempfile.TemporaryDirectory(prefix="zenswarm-check-") as tmp:
        scen = Path(tmp) / "scenario.toml"
        scen.write_text(to_toml(scenario_to_dict(sc)))
        swarm = f"check{uuid.uuid4().hex[:10]}"
        Keys(swarm)  # a valid swarm name
        # no --listen: the supervisor chooses the router's port (another one if it is taken before the bind)
        # the swarm flies sc itself (its supervisor and roles get it typed); the file is its label
        opts = FlightSettings(scenario=sc, scenario_file=scen, swarm=swarm, out=Path(tmp) / "out", faults=faults,
                              lockstep_timeout=LOCKSTEP_TIMEOUT_S, progress_every=5.0)
        run = run_up(opts, timeout=600.0)
        if run.timed_out or not (opts.out / "results.json").is_file():
            tail = "\n".join(run.log.splitlines()[-15:])
            return f"the lockstep swarm did not finish (exit status {run.exit_code}):\n{tail}"
        got = TimeSeries.load(str(opts.out / "timeseries.npz"))
        res = json.loads((opts.out / "results.json").read_text())
    diffs = flight_differences(ref.series, ref.results, got, res)
    if run.leftovers:
        diffs.append(f"processes left behind (killed): {list(run.leftovers)}")
    return difference_text(diffs, res, opts.lockstep_timeout)


def difference_text(diffs: list[str], res: dict[str, Any], lockstep_timeout: float) -> str:
    """The sim == swarm check's detail for the differences ``diffs`` of the swarm flight whose
    results are ``res``: "" when none; else the first few, and their cause: the swarm's
    processes waiting out the lockstep timeout (:func:`zenswarm.judge.metrics.lockstep_stalls`;
    a loaded machine, not the plug-in), or else the usual causes in a plug-in."""
    from zenswarm.judge.metrics import lockstep_stalls

    if not diffs:
        return ""
    first = diffs[0]
    more = f" (and {len(diffs) - 1} more: {'; '.join(diffs[1:4])})" if len(diffs) > 1 else ""
    stalls = lockstep_stalls(res)
    if stalls:
        who = ", ".join(f"{p} {n} tick{'s' if n > 1 else ''}" for p, n in stalls.items())
        return (f"first difference: {first}{more}. Cause: processes of the swarm waited out the lockstep timeout "
                f"({lockstep_timeout:g} s) and ticked on held inputs ({who}), so the swarm did not fly the "
                "simulator's flight: a starved machine or a stalled process, not the plug-in; check again on a less loaded machine")
    return f"first difference: {first}{more}. Usual causes: " + "; ".join(MISMATCH_CAUSES)


def _flight(sc: Scenario) -> Check:
    """The short flight in the simulator: no plug-in failure (``plugin_error``)."""
    from zenswarm.compose.sim import simulate
    from zenswarm.judge.results import failure_text

    res = simulate(sc).results
    bad = [f for f in res["failures"] if f["cause"] == "plugin_error"]
    what = f"{sc.timing.time_limit_s:g} s of {sc.name} in the simulator"
    if bad:
        return Check("flight", "FAIL", f"{what}: " + "; ".join(failure_text(f) for f in bad) + f" ({bad[0]['detail']})")
    verdict = "success" if res["success"] else "no plug-in failure; verdict " + ", ".join(sorted({f["cause"] for f in res["failures"]}))
    return Check("flight", "PASS", f"{what}: {verdict}")


def resolve_kind(name: str, kind: str | None) -> tuple[str, type]:
    """(kind, class) of the plug-in ``name``; without ``kind``, whichever kind has it (both:
    ScenarioError asking for --kind). Raises :class:`PluginError` naming what was tried."""
    if kind is not None:
        return kind, resolve(kind, name, "NAME")
    found: dict[str, type] = {}
    errors: list[str] = []
    for k in KINDS:
        try:
            found[k] = resolve(k, name, "NAME")
        except PluginError as e:
            errors.append(e.message)
    if len(found) > 1:
        raise ScenarioError("--kind", f"{name!r} names more than one kind of plug-in ({', '.join(found)}): say which with --kind")
    if not found:
        raise PluginError("NAME", f"no controller, planner or plant model named {name!r}: " + " / ".join(errors))
    ((which, cls),) = found.items()
    return which, cls


def check_plugin(
    name: str, sc: Scenario, kind: str | None = None, duration: float = DEFAULT_DURATION_S, swarm: bool = True
) -> tuple[str, type, list[Check]]:
    """Run the checks of the module docstring on plug-in ``name`` with scenario ``sc``; returns
    (kind, class, the checks in order). Bad input (an unknown name) raises ScenarioError; what
    the plug-in does wrong, whatever it raises, is a failed check."""
    kind, cls = resolve_kind(name, kind)
    if kind == "plant":
        records_of(cls, f"plant {name!r}")  # a bad declaration is bad input (exit 2, naming records.<name>)
    elif kind == "controller":
        shares_of(cls, f"controller {name!r}")  # the same for a controller's (exit 2, naming shares)
    sc = _scenario_for(kind, name, sc, duration)
    checks: list[Check] = []
    try:
        problems, params = _interface(kind, cls, sc)
    except Exception as e:  # noqa: BLE001 - a plug-in's own error is a failed check, reported
        problems, params = [f"{type(e).__name__}: {e}"], None
    checks.append(Check("interface", "FAIL" if problems else "PASS", "; ".join(problems) or _interface_text(kind, cls)))
    ticker: dict[str, Callable[[type, Any, Scenario, int, bool], list[Output]]] = {
        "controller": _tick_controllers, "planner": _tick_planner, "plant": _tick_plant,
    }  # fmt: skip
    tick = ticker[kind]
    ticks = sc.timing.n_ticks
    first: list[Output] | None = None
    replay: list[list[Any]] = []  # a controller's: every UAV's shared values per tick (for the shared-state check)
    if problems:
        checks.append(Check("outputs", "SKIP", "the interface check failed"))
    else:
        try:
            first = _tick_controllers(cls, params, sc, ticks, False, record=replay) if kind == "controller" else tick(
                cls, params, sc, ticks, False)
            what = f"{ticks} ticks x {sc.n} UAVs" if kind != "planner" else f"{ticks} ticks"
            checks.append(Check("outputs", "PASS", f"{what}: shapes and finiteness as declared"))
        except Exception as e:  # noqa: BLE001 - a plug-in's own error is a failed check, reported
            first = None
            checks.append(Check("outputs", "FAIL", _raised(e)))
    if first is None:
        checks.append(Check("deterministic", "SKIP", "the outputs check failed"))
        checks.append(Check("pure ticks", "SKIP", "the outputs check failed"))
        checks.append(Check("shared state", "SKIP", "the outputs check failed"))
    else:
        checks += _repeatable(cls, params, sc, ticks, tick, first)
        if kind != "controller":
            checks.append(Check("shared state", "PASS", f"one {kind} instance flies every UAV, in the simulator and in the "
                                "swarm alike; state outliving the instance is the deterministic check's"))
        elif checks[-2].status != "PASS":
            checks.append(Check("shared state", "SKIP", "the deterministic check failed"))
        else:
            checks.append(_shared_state(name, sc, ticks, first, replay))
    if problems:
        checks.append(Check("flight", "SKIP", "the interface check failed"))
    else:
        try:
            checks.append(_flight(sc))
        except Exception as e:  # noqa: BLE001 - reported as the check's failure
            checks.append(Check("flight", "FAIL", _raised(e)))
    if not swarm:
        checks.append(Check("sim == swarm", "SKIP", "not asked (--no-swarm)"))
    elif any(c.status != "PASS" for c in checks):
        checks.append(Check("sim == swarm", "SKIP", "an earlier check failed"))
    else:
        seed = 1
        faults = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in FAULTS.items())
        what = f"{sc.timing.time_limit_s:g} s of {sc.name}, {faults}, seed {seed}"
        try:
            diff = _sim_vs_swarm(replace(sc, seed=seed), seed)
            detail = f"{what}: {diff}" if diff else f"{what}: identical, bit for bit"
            checks.append(Check("sim == swarm", "FAIL" if diff else "PASS", detail))
        except Exception as e:  # noqa: BLE001 - reported as the check's failure
            checks.append(Check("sim == swarm", "FAIL", f"{what}: {_raised(e)}"))
    return kind, cls, checks


def _raised(e: BaseException) -> str:
    """An exception as a check's detail: its type, message and where in the plug-in it came from."""
    import traceback

    where = ""
    frames = traceback.extract_tb(e.__traceback__)
    if frames:
        f = frames[-1]
        where = f" (at {Path(f.filename).name}:{f.lineno} in {f.name})"
    return f"{type(e).__name__}: {e}{where}"


OUTLIVES_INSTANCE = (
    "state kept outside the instance (a class or module attribute): it outlives the instance, so a fresh one "
    "in the same process starts from what the last left. The simulator (and api.fly, a campaign's worker) runs "
    "every UAV's controller and many flights in one process, the swarm one per process: they would fly differently"
)
"""The cause named when two fresh runs differ without touching the clock or global randomness."""

SHARED_BETWEEN_UAVS = (
    "state shared between UAVs (a class or module attribute): in `zenswarm sim` every UAV's controller runs in one "
    "process and sees the others' writes, in `zenswarm up` each runs in its own process and does not, so the two "
    "modes fly differently. Keep per-UAV state on self"
)
"""The cause named when a UAV flown alone differs from the same UAV flown beside the others."""


def _repeatable(
    cls: type, params: Any, sc: Scenario, ticks: int, tick: Callable[[type, Any, Scenario, int, bool], list[Output]],
    first: list[Output],
) -> list[Check]:
    """The deterministic and pure-ticks checks: the outputs again, fresh, then under the guard.
    Two fresh runs that differ while the guard saw no clock or global randomness: the state
    outlived the instance (:data:`OUTLIVES_INSTANCE`), named with the first differing output."""
    out: list[Check] = []
    impure: str | None = None
    guarded: list[Output] | BaseException | None = None
    try:
        guarded = tick(cls, params, sc, ticks, True)
    except Impure as e:
        impure = str(e)
    except Exception as e:  # noqa: BLE001 - reported as the check's failure
        guarded = e
    try:
        again = tick(cls, params, sc, ticks, False)
        diff = _first_diff(first, again, "between two fresh runs in one process")
        if not diff:
            out.append(Check("deterministic", "PASS", "two fresh runs on the same inputs: identical, bit for bit"))
        else:
            cause = OUTLIVES_INSTANCE if impure is None else f"the clock or global randomness (see pure ticks: {impure})"
            out.append(Check("deterministic", "FAIL", f"{diff}. Cause: {cause}"))
    except Exception as e:  # noqa: BLE001 - reported as the check's failure
        again, diff = None, "raised"
        out.append(Check("deterministic", "FAIL", _raised(e)))
    if impure is not None:
        out.append(Check("pure ticks", "FAIL", impure))
    elif isinstance(guarded, BaseException):
        out.append(Check("pure ticks", "FAIL", _raised(guarded)))
    else:
        assert guarded is not None
        changed = _first_diff(first, guarded, "when the clock, sockets, files and global randomness are unavailable")
        if not changed:
            out.append(Check("pure ticks", "PASS", "no clock, socket, file or unseeded randomness during ticks"))
        elif diff:
            out.append(Check("pure ticks", "PASS", "no clock, socket, file or unseeded randomness called during ticks "
                             "(the outputs differ from run to run anyway: see deterministic)"))
        else:
            out.append(Check("pure ticks", "FAIL", f"{changed} (the plug-in caught their failure and did something else)"))
    return out


def _first_diff(a: list[Output], b: list[Output], how: str) -> str:
    """The first output that differs between runs ``a`` and ``b`` ("" if none), named by field,
    tick and UAV (a plant model's state row: its UAV), with both values."""
    for (label, x), (label_b, y) in zip(a, b, strict=False):
        if label != label_b:
            return f"the runs' outputs differ in kind {how}: {label} where {label_b}"
        if np.array_equal(x, y):
            continue
        if x.ndim == 2 and x.shape == y.shape:  # (N, 3): one row per UAV
            row = int(np.flatnonzero(~np.all(x == y, axis=1))[0])
            return f"UAV {row + 1} {label} differs {how}: {x[row].tolist()} != {y[row].tolist()}"
        return f"{label} differs {how}: {x.tolist()} != {y.tolist()}"
    if len(a) != len(b):
        return f"{len(b)} outputs {how}, {len(a)} in the first run"
    return ""


ALONE_MAX_UAVS = 4
"""UAVs the shared-state check flies alone, each in a process of its own: all up to this many,
else the first two and the last two."""


def _shared_state(name: str, sc: Scenario, ticks: int, together: list[Output], replay: list[list[Any]]) -> Check:
    """Each UAV's controller flown alone in a fresh process of its own (as ``zenswarm up`` runs
    it), its neighbours' shared values replayed from the run of all UAVs in one process (as
    ``zenswarm sim`` runs them), must give that UAV's outputs of the run of all, bit for bit.
    One fresh interpreter (:func:`_alone_child`) imports zenswarm once and forks a process per
    UAV before the plug-in's module is imported: each starts from the plug-in's pristine state."""
    import pickle
    import subprocess
    import sys

    n = sc.n
    uavs = list(range(n)) if n <= ALONE_MAX_UAVS else [0, 1, n - 2, n - 1]
    payload = pickle.dumps({"path": list(sys.path), "name": name, "sc": sc, "uavs": uavs, "ticks": ticks, "replay": replay})
    p = subprocess.run([sys.executable, "-c", "from zenswarm.compose.plugcheck import _alone_child; _alone_child()"],
                       input=payload, capture_output=True, timeout=600)
    try:
        results: dict[int, Any] = pickle.loads(p.stdout)
    except Exception:  # noqa: BLE001 - reported as the check's failure
        tail = p.stderr.decode(errors="replace").strip()[-500:]
        return Check("shared state", "FAIL", f"the UAVs flown alone, each in a process of its own, gave nothing "
                     f"(exit status {p.returncode}): {tail}")
    for i in uavs:
        got = results.get(i)
        if not isinstance(got, list):
            return Check("shared state", "FAIL", f"UAV {i + 1}'s controller alone in a process of its own: {got}")
        mine = [o for o in together if o[0].startswith(f"UAV {i + 1} ")]
        diff = _first_diff(mine, got, f"when UAV {i + 1} flies alone (its own process, as in `zenswarm up`) and beside "
                                      "the others (one process, as in `zenswarm sim`)")
        if diff:
            return Check("shared state", "FAIL", f"{diff}. Cause: {SHARED_BETWEEN_UAVS}")
    who = ", ".join(str(i + 1) for i in uavs)
    return Check("shared state", "PASS", f"UAV {who} alone, each in a process of its own: the same outputs as beside the others")


def _alone_child() -> None:
    """The shared-state check's fresh interpreter (pickled request on stdin): for each UAV a
    forked process builds and ticks that UAV's controller alone, from the plug-in's pristine
    module state; {UAV: its labelled outputs, or the error's text} pickled on stdout."""
    import pickle
    import sys

    req = pickle.loads(sys.stdin.buffer.read())
    sys.path[:] = req["path"]
    sc: Scenario = req["sc"]
    results: dict[int, Any] = {}
    with tempfile.TemporaryDirectory(prefix="zenswarm-alone-") as tmp:
        for i in req["uavs"]:
            path = Path(tmp) / f"uav{i}.pickle"
            pid = os.fork()
            if pid == 0:  # the UAV's own process: nothing of the plug-in imported or run yet
                try:
                    cls = resolve("controller", req["name"], "NAME")
                    params = decode_params(cls, sc.agents.params, "agents.params")
                    got: Any = _tick_controllers(cls, params, sc, req["ticks"], False, alone=i, replay=req["replay"])
                except BaseException as e:  # noqa: BLE001 - the parent reports it
                    got = _raised(e)
                path.write_bytes(pickle.dumps(got))
                os._exit(0)
            os.waitpid(pid, 0)
            results[i] = pickle.loads(path.read_bytes()) if path.is_file() else "its process died"
    sys.stdout.buffer.write(pickle.dumps(results))


def _interface_text(kind: str, cls: type) -> str:
    shares = dict(getattr(cls, "shares", {})) if kind == "controller" else {}
    extra = f", shares {shares}" if shares else ""
    if kind == "plant":
        recs = records_of(cls)
        extra += (", records " + ", ".join(f"{n} {s.shape} {s.unit}" for n, s in recs.items())) if recs else ""
    return f"name, description, Params (frozen msgspec Struct, unknown keys refused, the scenario's table decodes){extra}"


# ----------------------------------------------------------------------------- command line


def add_check_parser(psub: argparse._SubParsersAction) -> None:
    """``zenswarm plugins check``."""
    c = psub.add_parser(
        "check",
        help="conformance check of a controller, planner or plant model plug-in",
        description=(
            "Check plug-in NAME (a built-in name, module:attribute or an installed entry point of "
            f"{', '.join(GROUPS.values())}): its interface, its outputs' shapes and finiteness, determinism, "
            "no clock or I/O during ticks, then a short flight of SCENARIO (default: paper example 1) with link faults "
            "in the in-process simulator and as the lockstep swarm, bit for bit. Prints PASS/FAIL per check. Exit "
            "status 0 all passed, 1 a check failed, 2 bad input."
        ),
    )
    c.add_argument("name", metavar="NAME", help="the plug-in")
    c.add_argument("scenario", metavar="SCENARIO", type=Path, nargs="?", help="scenario TOML (default: the built-in paper_example1)")
    c.add_argument("--kind", choices=KINDS, help="controller, planner or plant (default: whichever NAME names)")
    c.add_argument("--duration", type=float, default=DEFAULT_DURATION_S, metavar="S",
                   help=f"sim seconds of the sim-versus-swarm flight (default {DEFAULT_DURATION_S:g})")
    c.add_argument("--no-swarm", action="store_true", help="skip the sim-versus-swarm flight (no process started)")
    c.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="override a field of SCENARIO by its dotted path, as on sim and up, e.g. --set agents.params.gain=0.8 "
        "(VALUE read as TOML, else as a string; repeatable; validated as the file is)",
    )
    c.set_defaults(func=run_check)


def run_check(args: argparse.Namespace) -> int:
    from zenswarm.scenario.overrides import load_file, parse_assignment

    if not (args.duration > 0 and np.isfinite(args.duration)):
        raise ScenarioError("--duration", f"must be a finite number > 0, got {args.duration!r}")
    path = args.scenario or Path(__file__).resolve().parent / "scenarios" / "paper_example1.toml"
    overrides = dict(parse_assignment(text) for text in getattr(args, "overrides", None) or [])
    sc = load_file(path, overrides)
    kind, cls, checks = check_plugin(args.name, sc, args.kind, args.duration, swarm=not args.no_swarm)
    print(f"zenswarm plugins check {args.name}: {kind} {cls.__module__}:{cls.__qualname__}, scenario {sc.name} ({path})")
    for ck in checks:
        print(f"  {ck.status:<4}  {ck.name:<14} {ck.detail}", flush=True)
    failed = [ck.name for ck in checks if ck.status == "FAIL"]
    print(f"result: {'FAIL (' + ', '.join(failed) + ')' if failed else 'PASS'}")
    return 1 if failed else 0

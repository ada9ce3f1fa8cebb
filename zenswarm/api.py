"""The public Python API: fly a scenario in-process or as the lockstep swarm, get typed results.

For users' own tests and scripts (the pytest plugin, :mod:`zenswarm.pytest_plugin`, builds on it)::

    from zenswarm.api import fly

    f = fly("paper_example1", mode="swarm", link_loss=0.2, link_delay="50ms", duration=5.0)
    assert not f.failures_other_than("timeout"), f.summary
    print(f.metrics.max_formation_error_m, f.series.q.shape)   # m; (T, N, 3)

:func:`fly` runs the code the command line runs, nothing else: ``mode="sim"`` is
:func:`zenswarm.compose.sim.simulate` in this process (``zenswarm sim``); ``mode="swarm"`` is
``zenswarm up`` in lockstep (or realtime) as a child process group, one OS process per UAV
over a Zenoh router on loopback. With the same scenario, seed and link faults both give the same
flight bit for bit (lockstep); :func:`differences` checks it.

Any scenario field can be overridden by its dotted path (``timing.time_limit_s``,
``leader.goal``, ``obstacles[0].radius``, ``restart.initial_delay_s``): the scenario is then
validated as a file would be, and a bad path or value raises :class:`OverrideError` naming it.
Every bad input raises a :class:`zenswarm.errors.ScenarioError` (``field`` names the argument or
the scenario field) before anything is flown or started.

Units are SI, positions in the inertial ENU frame (z up); times are sim time unless named
``wall``. This module is the top layer (beside ``__main__``): nothing in zenswarm imports it.
"""

from __future__ import annotations

import json
import os
import tempfile
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import msgspec
import numpy as np

from zenswarm.bus.wire import validate_process, validate_swarm_name
from zenswarm.compose.flight_checks import check_up_args
from zenswarm.compose.launch import kill_processes_of, live_flights, processes_of, run_up, stop_flight
from zenswarm.compose.sim import simulate, summary_line, write_outputs
from zenswarm.errors import EXIT_PLUGIN_FAILED, ScenarioError, ZenswarmError
from zenswarm.judge.metrics import TimeSeries, exit_code_of, flight_differences
from zenswarm.link import FaultPlan, LinkFaults
from zenswarm.process import rtsched
from zenswarm.process.paths import check_output_dir
from zenswarm.process.settings import FlightSettings
from zenswarm.scenario.config import Scenario, document_trace_beside, read_document, scenario_to_dict, trace_beside
from zenswarm.scenario.generate import to_toml
from zenswarm.scenario.overrides import OverrideError, apply, copy_document, validated
from zenswarm.scenario.plugins import check_selection

__all__ = [
    "fly",
    "Flight",
    "Failure",
    "Metrics",
    "Mode",
    "OverrideError",
    "FlightError",
    "differences",
    "scenario_path",
    "builtin_scenarios",
    "load",
    "unique_swarm_name",
    "processes_of",
    "kill_processes_of",
    "live_flights",
    "stop_flight",
]

Mode = Literal["sim", "swarm"]
"""``sim``: the in-process simulator; ``swarm``: ``zenswarm up``, one OS process per role."""

DEFAULT_SWARM_TIMEOUT_S = 600.0
"""Wall seconds a swarm flight may take before :func:`fly` stops it (:class:`FlightError`)."""


class FlightError(ZenswarmError):
    """A swarm flight could not be flown to its end: ``zenswarm up`` refused its input, timed out
    or was interrupted. ``exit_code`` is the supervisor's (None on a timeout), ``log`` its output."""

    def __init__(self, message: str, exit_code: int | None, log: str) -> None:
        super().__init__(message)
        self.exit_code = exit_code
        self.log = log


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class Failure:
    """One named failure of a flight's verdict (docs/verdict.md lists the causes).

    cause: ``collision_obstacle``, ``collision_uav``, ``collision_ground``, ``uav_diverged``,
    ``not_finite``, ``leader_stalled``, ``timeout``, ``off_slot``, ``process_died``,
    ``interrupted``, ... t_s: sim time of the failure, s (None when it has none). uavs: the UAVs
    concerned, 1-based. extra: the cause's other fields (``obstacle``, ``where``, ``process``)."""

    cause: str
    detail: str
    t_s: float | None
    uavs: tuple[int, ...]
    extra: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Failure:
        rest = {k: v for k, v in d.items() if k not in ("cause", "detail", "t_s", "uavs")}
        return cls(str(d["cause"]), str(d.get("detail", "")), d.get("t_s"), tuple(int(u) for u in d.get("uavs") or ()), rest)


@dataclass(frozen=True)
class Metrics:
    """The headline figures of a flight (``results.json``), judged on the vehicles' real states.
    Distances in m, times in s; None where there was nothing to measure (no obstacle, one UAV,
    no tick after ``timing.settle_time_s``)."""

    goal_reached: bool
    time_to_goal_s: float | None
    final_leader_goal_distance_m: float | None
    max_formation_error_m: float | None
    """Largest distance of a vehicle from its slot q0 + h_i after the settle time."""
    max_generator_formation_error_m: float | None
    rms_tracking_error_m: float | None
    max_final_slot_error_m: float | None
    min_obstacle_clearance_m: float | None
    """Smallest distance of a vehicle's centre to an obstacle's surface."""
    min_obstacle_margin_m: float | None
    """Clearance minus the vehicle radius (< 0: contact)."""
    min_inter_uav_distance_m: float | None
    min_inter_uav_margin_m: float | None
    min_altitude_m: float | None
    finite: bool
    ended_early: bool
    sim_time_s: float
    wall_time_s: float | None

    @classmethod
    def from_results(cls, r: Mapping[str, Any]) -> Metrics:
        values: dict[str, Any] = {f: r.get(f) for f in cls.__dataclass_fields__}
        return cls(**values)


@dataclass(frozen=True)
class Flight:
    """A flown scenario: its verdict, figures and time series.

    series: one sample per control tick (:class:`zenswarm.judge.metrics.TimeSeries`: ``t`` (T,) s,
    ``q0``/``v0`` (T, 3) leader, ``qref``/``vref`` (T, N, 3) references, ``q``/``v``/``rpy``
    (T, N, 3) measured vehicle states, ``u`` (T, N, 3) m/s^2, ``thrust`` (T, N) N commanded,
    ``d_hat`` (T, N, 3), ``rpy_cmd`` (T, N, 3) rad commanded attitude).
    results: ``results.json`` as a dict (schema in docs/verdict.md). exit_code: what the command
    line would have returned (0 success, 1 mission failed, 3 a process died, 4 a plug-in failed:
    ``plugin_error``, 130 interrupted). ``formation_error``: (T, N) m, per tick.
    out: where results.json and timeseries.npz were written (None: not kept). log: the
    supervisor's output (swarm mode). leftovers: processes of the swarm found alive after the
    flight and killed (empty unless something went wrong). port: the router's TCP port on
    127.0.0.1 (swarm mode; the one given, else the free one its supervisor chose)."""

    mode: Mode
    scenario: Scenario
    success: bool
    failures: tuple[Failure, ...]
    metrics: Metrics
    series: TimeSeries
    results: Mapping[str, Any]
    exit_code: int
    out: Path | None = None
    swarm: str | None = None
    log: str = ""
    leftovers: tuple[str, ...] = ()
    port: int | None = None

    @property
    def causes(self) -> tuple[str, ...]:
        """The failures' causes, in the verdict's order."""
        return tuple(f.cause for f in self.failures)

    def failure(self, cause: str) -> Failure | None:
        """The first failure with this cause, if any."""
        return next((f for f in self.failures if f.cause == cause), None)

    def failures_other_than(self, *causes: str) -> tuple[Failure, ...]:
        """The failures whose cause is not one of ``causes`` (e.g. ``"timeout"``, ``"off_slot"``
        for a flight cut short by ``duration``)."""
        return tuple(f for f in self.failures if f.cause not in causes)

    @property
    def summary(self) -> str:
        """The verdict and headline figures in the words of ``zenswarm sim`` (for assertion messages)."""
        return summary_line(dict(self.results))

    @property
    def formation_error(self) -> np.ndarray:
        """The vehicles' formation error ||q_i - q0 - h_i|| per tick and UAV, (T, N) m
        (:meth:`zenswarm.judge.metrics.TimeSeries.formation_error`; its maximum from
        ``timing.settle_time_s`` on is ``metrics.max_formation_error_m``)."""
        return self.series.formation_error(self.scenario.offsets)

    @property
    def restarts(self) -> dict[str, int]:
        """Swarm mode: restarts per process (``--restart``)."""
        return dict(self.results.get("restarts") or {})

    @property
    def process_deaths(self) -> list[dict[str, Any]]:
        """Swarm mode: every process death the supervisor saw (process, how, sim_time_s)."""
        return list(self.results.get("process_deaths") or [])

    @property
    def diagnostics(self) -> dict[str, dict[str, Any]]:
        """Swarm mode: each process's final diagnostics (link counters, subscriptions, ...)."""
        return dict(self.results.get("diagnostics") or {})


def differences(a: Flight, b: Flight) -> list[str]:
    """What differs between two flights of the same scenario: the time series compared bit for
    bit (NaN equal to NaN, shapes included) and the flight fields of the verdict
    (:data:`zenswarm.judge.metrics.FLIGHT_FIELDS`). Empty when the flights are identical (the
    lockstep swarm's guarantee against the simulator)."""
    return flight_differences(a.series, dict(a.results), b.series, dict(b.results))


# ----------------------------------------------------------------------------- scenarios


def builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped with zenswarm (``paper_example1``, ...)."""
    return sorted(p.stem for p in _scenario_dir().glob("*.toml"))


def _scenario_dir() -> Path:
    import zenswarm.compose as compose

    return Path(compose.__file__).resolve().parent / "scenarios"


def scenario_path(name: str | Path) -> Path:
    """The file of a scenario: a path to a TOML file, or the name of a built-in one
    (``paper_example1``). Raises :class:`ScenarioError` (field ``scenario``) if there is none."""
    p = Path(name)
    if p.suffix == ".toml" or p.exists() or os.sep in str(name):
        if not p.is_file():
            raise ScenarioError("scenario", f"scenario file not found: {p}")
        return p
    q = _scenario_dir() / f"{name}.toml"
    if not q.is_file():
        raise ScenarioError("scenario", f"no built-in scenario {str(name)!r} (built in: {', '.join(builtin_scenarios())}) and no such file")
    return q


def _resolve(
    scenario: str | Path | Scenario | Mapping[str, Any], overrides: Mapping[str, Any] | None
) -> tuple[Scenario, dict[str, Any] | None]:
    """The flight's scenario, converted once: a :class:`Scenario` without overrides is used as it
    is (its plug-ins checked); a file or document, with the overrides set in it, becomes one.
    Also the document it came from (None for a Scenario used as it is). A file's relative
    ``[faults] trace``, its own or one an override names, is relative to the file's directory, as
    ``zenswarm up/sim --set`` take it (:func:`zenswarm.scenario.overrides.load_file`)."""
    ov = dict(overrides or {})
    if isinstance(scenario, Scenario):
        if not ov:
            check_selection(scenario)
            return scenario, None
        doc = scenario_to_dict(scenario)  # overrides are edits of the document
    elif isinstance(scenario, Mapping):
        doc = copy_document(dict(scenario))
    else:
        path = scenario_path(scenario)
        doc = read_document(path)
        return trace_beside(validated(doc, ov), path), document_trace_beside(apply(doc, ov), path)
    return validated(doc, ov), apply(doc, ov) if ov else doc


def load(
    scenario: str | Path | Scenario | Mapping[str, Any],
    overrides: Mapping[str, Any] | None = None,
) -> tuple[Scenario, dict[str, Any]]:
    """The scenario with ``overrides`` applied and validated, and its TOML document.

    scenario: a built-in name, a TOML file, a :class:`Scenario` or a parsed document. overrides:
    ``{"dotted.path": value}``, applied in order. Errors of the scenario itself raise
    :class:`ScenarioError`; errors an override caused raise :class:`OverrideError` naming the
    field and the override."""
    sc, doc = _resolve(scenario, overrides)
    return sc, doc if doc is not None else scenario_to_dict(sc)


# ----------------------------------------------------------------------------- processes


def unique_swarm_name(prefix: str = "api") -> str:
    """A swarm name no other flight uses (the key prefix ``swarm/<name>``)."""
    return f"{prefix}{uuid.uuid4().hex[:10]}"


# ----------------------------------------------------------------------------- flying


def _duration_text(value: float | str | None, name: str) -> str | None:
    """A duration argument (seconds as a number, or a text such as ``"50ms"``) as the CLI's text."""
    if value is None or isinstance(value, str):
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
        raise ScenarioError(name, f"expected a duration >= 0 in seconds or a text such as '50ms', got {value!r}")
    return f"{float(value)!r}s" if value else "0"


def _kills(kill: Iterable[tuple[str, float] | str]) -> tuple[tuple[str, float], ...]:
    """``[("agent:2", 1.0), "leader@2s"]`` -> ((process, sim time s), ...), checked."""
    from zenswarm.compose.flight_checks import parse_kill

    out = []
    for k in kill:
        if isinstance(k, str):
            import argparse

            try:
                out.append(parse_kill(k))
            except argparse.ArgumentTypeError as e:
                raise ScenarioError("kill", str(e)) from None
            continue
        try:
            role, t = k
            validate_process(role)
            t = float(t)
        except (TypeError, ValueError, ZenswarmError):
            raise ScenarioError("kill", f"{k!r}: expected (process, sim time s) such as ('agent:2', 1.0) or 'agent:2@1s'") from None
        if not (np.isfinite(t) and t >= 0):
            raise ScenarioError("kill", f"{k!r}: time must be >= 0")
        out.append((role, t))
    return tuple(out)


# Over 80 lines only by its signature (36 keyword arguments, one a line) and their docstring: the
# body is 15 lines, the steps in helpers below.
def fly(
    scenario: str | Path | Scenario | Mapping[str, Any],
    *,
    mode: Mode = "sim",
    overrides: Mapping[str, Any] | None = None,
    duration: float | None = None,
    seed: int | None = None,
    controller: str | None = None,
    planner: str | None = None,
    plant_model: str | None = None,
    link_loss: float | str | None = None,
    link_delay: float | str | None = None,
    link_jitter: float | str | None = None,
    partitions: Sequence[str] = (),
    link_range: float | str | None = None,
    link_fade: str | None = None,
    link_capacity: str | None = None,
    link_queue: str | int | None = None,
    link_medium: str | None = None,
    link_trace: str | Path | None = None,
    kill: Iterable[tuple[str, float] | str] = (),
    restart: bool = False,
    realtime: bool = False,
    full_time: bool = False,
    record: str | Path | None = None,
    out: str | Path | None = None,
    swarm: str | None = None,
    port: int | None = None,
    lockstep_timeout: float = 5.0,
    timeout: float = DEFAULT_SWARM_TIMEOUT_S,
    rt_priority: int | None = None,
    scheduler: str | None = None,
    placement: Sequence[str] = (),
    listen: str | None = None,
) -> Flight:
    """Fly ``scenario`` and return the judged :class:`Flight`.

    scenario: a built-in name (``"paper_example1"``), a TOML file, a :class:`Scenario` or a
    parsed document. mode: ``"sim"`` (in this process, as ``zenswarm sim``) or ``"swarm"``
    (``zenswarm up``: a router and one process per role, lockstep unless ``realtime``).

    Scenario: ``overrides`` ``{"dotted.path": value}`` (:func:`load`); ``duration`` (s) sets
    ``timing.time_limit_s``; ``seed`` sets ``scenario.seed`` (disturbances and fault decisions);
    ``controller`` / ``planner`` / ``plant_model`` set ``agents.controller`` / ``leader.planner`` /
    ``plant.model`` (a plug-in name; a plant model that fails mid-flight raises
    :class:`zenswarm.errors.PluginFailure` in sim mode).

    Link faults on every link (docs/faults.md), as ``--link-loss`` and friends: ``link_loss``
    probability in [0, 1] (or ``"20%"``), ``link_delay`` / ``link_jitter`` seconds (or ``"50ms"``),
    ``partitions`` (``"agent:2@1s-2s"``), ``link_range`` metres (or ``"1.5m"``) and ``link_fade``
    (``"1.2m,0.1m"``) the radio models of :mod:`zenswarm.link.radio`; ``link_capacity`` (``"20kB/s"``),
    ``link_queue`` (8 or ``"4kB"``), ``link_medium`` (``"sender"`` or ``"link"``) and ``link_trace``
    (a CSV file) as ``--link-capacity`` and friends. Process faults (swarm mode only): ``kill`` SIGKILLs a
    process at a sim time (``("agent:2", 1.0)`` or ``"agent:2@1s"``), ``restart`` restarts it
    with the scenario's ``[restart]`` backoff.

    Runs: ``full_time`` flies the whole time limit after the outcome is decided; ``out`` keeps
    results.json and timeseries.npz there (default: not kept); ``record`` writes an MCAP
    recording (swarm mode); ``swarm`` / ``port`` name the swarm and its router's TCP port on
    127.0.0.1 (default: a unique name, a free port); ``timeout`` bounds a swarm flight's wall
    time (s). A swarm flight's processes are all stopped when :func:`fly` returns or raises.
    ``rt_priority`` (realtime swarm flights only): the flying processes under ``SCHED_FIFO`` at
    this priority once started, as ``zenswarm up --rt-priority`` (:mod:`zenswarm.process.rtsched`; needs
    root or an ``RLIMIT_RTPRIO``, else :class:`ScenarioError` naming ``rt_priority``).

    Cluster (swarm mode, as ``zenswarm up --scheduler``, docs/cluster.md): ``scheduler`` a Dask
    scheduler's address (``tcp://HOST:8786``) whose workers run the plant, the leader and the agents;
    ``placement`` its ``--placement`` rules (``"agent:1-4=w1"``); ``listen`` the router's endpoint
    (``tcp/ADDRESS:PORT``), an address of this host the workers reach (default: loopback, enough for
    workers on this host only).

    Raises :class:`ScenarioError` / :class:`OverrideError` naming the argument or field on bad
    input (nothing flown), :class:`FlightError` when the swarm could not fly to its end.
    A failed mission is not an error: see ``Flight.success`` and ``Flight.failures``.
    """
    _check_mode(mode)
    # the scenario converted once; the plug-ins resolve, their params decode (errors naming them)
    sc, doc = _resolve(scenario, _shortcut_overrides(overrides, duration, seed, controller, planner, plant_model))
    faults, plan = _link_faults(sc, link_loss, link_delay, link_jitter, partitions, link_range, link_fade, link_capacity,
                                link_queue, link_medium, link_trace)  # bad values: ScenarioError naming the argument
    kills, record, out = _kills(kill), _path(record), _path(out)
    rtsched.validate(rt_priority, realtime=realtime and mode == "swarm", how="mode='swarm', realtime=True", field="rt_priority")
    if mode == "sim":
        _swarm_only(kill=bool(kills), restart=restart, realtime=realtime, record=record is not None, scheduler=scheduler is not None,
                    placement=bool(placement), listen=listen is not None)  # fmt: skip
        return _fly_sim(sc, plan, full_time, out)
    where = {"scheduler": scheduler, "placement": tuple(placement), "listen": (listen,) if listen else ()}
    return _fly_swarm(sc, doc, faults, kills, restart, realtime, full_time, record, out, swarm, port, lockstep_timeout, timeout,
                      rt_priority, where)


def _check_mode(mode: Any) -> None:
    if mode not in ("sim", "swarm"):
        raise ScenarioError("mode", f"expected 'sim' or 'swarm', got {mode!r}")


def _shortcut_overrides(
    overrides: Mapping[str, Any] | None, duration: float | None, seed: int | None, controller: str | None, planner: str | None,
    plant_model: str | None,
) -> dict[str, Any]:
    """:func:`fly`'s ``overrides`` with its shortcut arguments (those not None) as dotted paths."""
    ov: dict[str, Any] = dict(overrides or {})
    shortcuts = {
        "timing.time_limit_s": duration, "scenario.seed": seed, "agents.controller": controller, "leader.planner": planner,
        "plant.model": plant_model,
    }  # fmt: skip
    ov.update({key: value for key, value in shortcuts.items() if value is not None})
    if planner is not None:  # as --planner: the named planner decides ([leader] adaptive is its older spelling)
        ov["leader.adaptive"] = planner != "apf"
    return ov


def _link_faults(
    sc: Scenario, link_loss: float | str | None, link_delay: float | str | None, link_jitter: float | str | None, partitions: Sequence[str],
    link_range: float | str | None, link_fade: str | None, link_capacity: str | None, link_queue: str | int | None,
    link_medium: str | None, link_trace: str | Path | None,
) -> tuple[LinkFaults, FaultPlan | None]:
    """:func:`fly`'s link-fault arguments as the ``--link-*`` flags' :class:`LinkFaults` and their plan for ``sc``
    (bad values: :class:`ScenarioError` naming the flag, before any work)."""
    loss = None if link_loss is None else (link_loss if isinstance(link_loss, str) else repr(float(link_loss)))
    rng = None if link_range is None else (link_range if isinstance(link_range, str) else repr(float(link_range)))
    faults = LinkFaults(
        _duration_text(link_delay, "link_delay"), _duration_text(link_jitter, "link_jitter"), loss, tuple(partitions), None,
        link_range=rng, link_fade=link_fade,
        link_capacity=link_capacity, link_queue=None if link_queue is None else str(link_queue), link_medium=link_medium,
        link_trace=None if link_trace is None else str(Path(link_trace).absolute()),
    )  # fmt: skip
    return faults, faults.plan(sc)


def _path(path: str | Path | None) -> Path | None:
    """A path given as text works as well."""
    return None if path is None else Path(path)


def _swarm_only(**given: bool) -> None:
    """Refuse, in sim mode, the first of :func:`fly`'s swarm-only arguments that was given (by its name)."""
    for name, was_given in given.items():
        if was_given:
            raise ScenarioError(name, "process faults, realtime and recordings need mode='swarm' (the simulator has no processes)")


def _fly_sim(sc: Scenario, plan: FaultPlan | None, full_time: bool, out: Path | None) -> Flight:
    """:func:`fly` in sim mode: ``zenswarm sim`` in this process; its outputs kept in ``out`` if given."""
    if out is not None:
        check_output_dir(out, "out")
    res = simulate(sc, faults=plan, full_time=full_time)
    if out is not None:
        write_outputs(out, res.series, res.results)
    return _flight("sim", sc, res.results, res.series, exit_code_of(res.results), out)


def _check_lockstep_timeout(lockstep_timeout: Any) -> None:
    """As ``--lockstep-timeout`` (exit 2 of the supervisor before the settings went typed)."""
    if isinstance(lockstep_timeout, bool) or not isinstance(lockstep_timeout, (int, float)) or not (
        np.isfinite(lockstep_timeout) and lockstep_timeout > 0
    ):
        raise ScenarioError("lockstep_timeout", f"must be a finite number of wall seconds > 0, got {lockstep_timeout!r}")


def _flight(
    mode: Mode, sc: Scenario, results: Mapping[str, Any], series: TimeSeries, code: int,
    out: Path | None, swarm: str | None = None, log: str = "", leftovers: tuple[str, ...] = (), port: int | None = None,
) -> Flight:
    return Flight(
        mode=mode,
        scenario=sc,
        success=bool(results["success"]),
        failures=tuple(Failure.from_json(f) for f in results["failures"]),
        metrics=Metrics.from_results(results),
        series=series,
        results=results,
        exit_code=code,
        out=out,
        swarm=swarm,
        log=log,
        leftovers=leftovers,
        port=port,
    )


def _fly_swarm(
    sc: Scenario, doc: dict[str, Any] | None, faults: LinkFaults, kills: tuple[tuple[str, float], ...], restart: bool,
    realtime: bool, full_time: bool, record: Path | None, out: Path | None, swarm: str | None, port: int | None,
    lockstep_timeout: float, timeout: float, rt_priority: int | None = None, where: Mapping[str, Any] | None = None,
) -> Flight:
    """``zenswarm up`` as a child process group; its results read back from its output directory.
    Without ``port`` the supervisor chooses a free one for its router (and another if that one is
    taken before the router binds it: two flights started at once)."""
    _check_lockstep_timeout(lockstep_timeout)
    _check_swarm_and_port(swarm, port)
    swarm = swarm or unique_swarm_name()
    with tempfile.TemporaryDirectory(prefix="zenswarm-fly-") as tmp:
        run_dir = Path(tmp)
        out_dir = out if out is not None else run_dir / "out"
        scen_file = run_dir / "scenario.toml"
        # the swarm flies sc itself (the supervisor and its roles get it typed, :class:`FlightSettings`); the
        # file, the document flown or the Scenario's own, is for the recorder (it takes a file)
        scen_file.write_text(to_toml(doc if doc is not None else scenario_to_dict(sc)))
        opts = FlightSettings(
            scenario=sc, scenario_file=scen_file, swarm=swarm, out=out_dir, realtime=realtime, record=record,
            lockstep_timeout=lockstep_timeout, kill=kills, restart=restart, full_time=full_time, faults=faults,
            listen=(f"tcp/127.0.0.1:{port}",) if port else (), rt_priority=rt_priority, progress_every=5.0,
        )
        if where:  # a cluster (scheduler, placement) and the router's endpoint the workers reach
            opts = msgspec.structs.replace(opts, **{k: v for k, v in where.items() if v})
        check_up_args(opts, sc)  # the supervisor's own checks, here: bad input raises before anything starts
        run = run_up(opts, timeout)
        code, log, leftovers = run.exit_code, run.log, run.leftovers
        if run.timed_out:
            raise FlightError(f"the swarm flight took more than {timeout:g} s of wall time; stopped", None, log)
        if code not in (0, 1, 3, EXIT_PLUGIN_FAILED) or not (out_dir / "results.json").is_file():
            tail = "\n".join(log.splitlines()[-20:])
            raise FlightError(f"zenswarm up ended with exit status {code} and no results:\n{tail}", code, log)
        results = json.loads((out_dir / "results.json").read_text())
        series = TimeSeries.load(str(out_dir / "timeseries.npz"))
    return _flight("swarm", sc, results, series, code, out, swarm, log, leftovers, port or _router_port(results))


def _check_swarm_and_port(swarm: Any, port: Any) -> None:
    """``swarm`` (``[A-Za-z0-9_-]{1,64}``; None or empty: a unique one) and ``port`` (a TCP port; 0 or None: a free one), named
    by their arguments before anything starts (the supervisor would refuse them with exit 2)."""
    if swarm:  # None or "": a unique name
        try:
            validate_swarm_name(swarm)
        except ZenswarmError as e:
            raise ScenarioError("swarm", str(e)) from None
    if port is not None and (isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535):
        raise ScenarioError("port", f"expected a TCP port in 1..65535 (or 0/None: a free one), got {port!r}")


def _router_port(results: Mapping[str, Any]) -> int | None:
    """The port of the router's first endpoint in ``results.json`` (``router``), if it has one."""
    eps = results.get("router") or []
    try:
        return int(str(eps[0]).rpartition(":")[2])
    except (IndexError, ValueError):
        return None




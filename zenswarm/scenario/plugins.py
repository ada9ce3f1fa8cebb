"""Plug-in registry: which agent controller, leader planner and plant model a flight runs.

A plug-in is a class implementing :class:`zenswarm.agents.api.Controller` (kind ``"controller"``),
:class:`zenswarm.leader.planner.Planner` (kind ``"planner"``) or
:class:`zenswarm.plant.api.PlantModel` (kind ``"plant"``: the vehicles' dynamics). It is named, in
the scenario (``[agents] controller = NAME``, ``[leader] planner = NAME``, ``[plant] model = NAME``)
or on the command line (``--controller NAME``, ``--planner NAME``, ``--plant-model NAME``), by one of:

* a built-in name (:data:`BUILTINS`: ``paper`` for the controller; ``aapf``, ``apf``, ``escape`` for
  the planner; ``quadrotor`` (zenswarm's own, the default) and ``rotorpy`` (extra ``rotorpy``) for the plant);
* ``module:attribute``, e.g. ``my_pkg.control:Consensus`` (imported as is; the module must be
  importable, e.g. installed or on ``PYTHONPATH``);
* the name of an installed entry point in the group :data:`GROUPS` ``[kind]``
  (``zenswarm.controllers`` / ``zenswarm.planners`` / ``zenswarm.plants``), e.g. in a plug-in package's pyproject::

      [project.entry-points."zenswarm.controllers"]
      consensus = "my_pkg.control:Consensus"

Built-ins are registered as ``module:attribute`` strings, so this base module imports no role.
A name that resolves to nothing raises :class:`PluginError` (a :class:`ScenarioError`: exit 2),
naming the name and what was tried, before any work starts.

Deterministic randomness (:func:`plugin_rng`): a plug-in gets a :class:`numpy.random.Generator`
seeded from the scenario's seed and its role (0: the leader's planner, i: UAV i's controller,
1-based; :data:`PLANT_ROLE` for the plant model), the same in the simulator, the swarm's processes and ``zenswarm verify``.
"""

from __future__ import annotations

import importlib
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import metadata
from typing import TYPE_CHECKING, Any, Final, Literal

import msgspec
import numpy as np

from zenswarm.errors import PluginFailure, ScenarioError
from zenswarm.schema import convert
from zenswarm.vehicle.params import QuadParams

if TYPE_CHECKING:  # pragma: no cover
    from zenswarm.scenario.config import Scenario

__all__ = [
    "KINDS",
    "GROUPS",
    "BUILTINS",
    "DEFAULTS",
    "PluginError",
    "PluginFailure",
    "PluginInfo",
    "resolve",
    "available",
    "decode_params",
    "plugin_rng",
    "PLUGIN_STREAM",
    "planner_name",
    "select",
    "check_selection",
    "PLANT_ROLE",
    "plant_vehicle",
    "plant_selection",
    "Signal",
    "plant_records",
    "records_of",
    "shares_of",
    "MAX_RECORDS",
    "MAX_RECORD_VALUES",
    "PluginFailure",
    "Boundary",
    "STAGES",
    "STAGE_BUILD",
    "STAGE_PLANNER",
    "STAGE_SHARE",
    "STAGE_STEP",
    "STAGE_PLANT",
    "bad_vector",
    "bad_scalar",
    "first_failures",
]

Kind = Literal["controller", "planner", "plant"]
KINDS: Final[tuple[Kind, ...]] = ("controller", "planner", "plant")

GROUPS: Final[Mapping[str, str]] = {"controller": "zenswarm.controllers", "planner": "zenswarm.planners", "plant": "zenswarm.plants"}
"""Entry point group of each kind (fixed: installed plug-in packages register under these)."""

BUILTINS: Final[Mapping[str, Mapping[str, str]]] = {
    "controller": {"paper": "zenswarm.agents.paper:PaperController"},
    "planner": {
        "aapf": "zenswarm.leader.planner:AapfPlanner",
        "apf": "zenswarm.leader.planner:ApfPlanner",
        "escape": "zenswarm.leader.planner:EscapePlanner",
    },
    "plant": {
        "quadrotor": "zenswarm.plant.api:QuadrotorModel",
        "rotorpy": "zenswarm.plant.rotorpy_model:RotorPyModel",
    },
}
"""Built-in plug-ins: kind -> name -> ``module:attribute``."""

DEFAULTS: Final[Mapping[str, str]] = {"controller": "paper", "planner": "aapf", "plant": "quadrotor"}
"""The plug-in of each kind when the scenario names none."""

PLUGIN_STREAM: Final = 0x706C7567
"""Spawn key of the plug-ins' random streams (``"plug"``), apart from the other seeded streams."""

PLANT_ROLE: Final = 1 << 32
"""Role of the plant model's random stream in :func:`plugin_rng` (apart from every UAV number)."""

FIELDS: Final[Mapping[str, str]] = {"controller": "agents.controller", "planner": "leader.planner", "plant": "plant.model"}
"""Where each kind is named in a scenario (the field a bad name is reported under)."""

_BASES: Final[Mapping[str, str]] = {
    "controller": "zenswarm.agents.api:Controller",
    "planner": "zenswarm.leader.planner:Planner",
    "plant": "zenswarm.plant.api:PlantModel",
}


class PluginError(ScenarioError):
    """A plug-in name that resolves to nothing usable (exit 2). ``field``: where it was given."""


@dataclass(frozen=True)
class PluginInfo:
    """One available plug-in: ``name`` (what to write in the scenario), one-line ``description``,
    ``origin`` (``builtin``, ``entry point <group>`` or ``module``) and ``target`` (``module:attribute``)."""

    kind: str
    name: str
    description: str
    origin: str
    target: str


def _load_target(target: str) -> Any:
    """The object ``module:attribute`` names (ImportError / AttributeError as raised)."""
    mod, _, attr = target.partition(":")
    obj: Any = importlib.import_module(mod)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def _entry_points(kind: str) -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=GROUPS[kind])}


def _base(kind: str) -> type:
    base: type = _load_target(_BASES[kind])
    return base


def resolve(kind: str, name: str, field: str | None = None) -> type:
    """The plug-in class ``name`` of ``kind`` ("controller", "planner" or "plant"): a built-in name,
    ``module:attribute`` or an entry point of :data:`GROUPS` ``[kind]``, in that order.
    ``field`` names where it was given (default :data:`FIELDS` ``[kind]``).
    Raises :class:`PluginError` naming the name and what was tried."""
    if kind not in GROUPS:
        raise PluginError("kind", f"unknown plug-in kind {kind!r}; expected one of {KINDS}")
    where = field or FIELDS[kind]
    if not isinstance(name, str) or not name:
        raise PluginError(where, f"expected a {kind} name (built-in, module:attribute or entry point), got {name!r}")
    tried: list[str] = []
    target: str | None = BUILTINS[kind].get(name)
    if target is not None:
        tried.append(f"built-in {name!r} -> {target}")
    elif ":" in name:
        target = name
        tried.append(f"module:attribute {name!r}")
    else:
        tried.append(f"built-ins {sorted(BUILTINS[kind])}")
        ep = _entry_points(kind).get(name)
        tried.append(f"entry points in group {GROUPS[kind]!r}")
        if ep is not None:
            target = ep.value
    if target is None:
        hint = _did_you_mean(kind, name)
        raise PluginError(where, f"no {kind} named {name!r}{hint} (tried {'; '.join(tried)}); `zenswarm plugins` lists them")
    try:
        obj = _load_target(target)
    except Exception as e:  # noqa: BLE001 - ImportError, AttributeError, or whatever its module raised on import
        raise PluginError(where, f"{kind} {name!r}: cannot load {target} ({type(e).__name__}: {e}); tried {'; '.join(tried)}") from None
    base = _base(kind)
    if not (isinstance(obj, type) and issubclass(obj, base)):
        raise PluginError(where, f"{kind} {name!r}: {target} is not a subclass of {_BASES[kind]}")
    abstract = getattr(obj, "__abstractmethods__", None)
    if abstract:
        missing = ", ".join(sorted(abstract))
        raise PluginError(where, f"{kind} {name!r}: {target} does not implement {missing}")
    return obj


def _did_you_mean(kind: str, name: str) -> str:
    """``; did you mean 'aapf'?`` for a name close to a known one of ``kind`` (any kind's, named), else ""."""
    import difflib

    known = {n: kind for n in [*BUILTINS[kind], *_entry_points(kind)]}
    for other in KINDS:
        if other != kind:
            for n in [*BUILTINS[other], *_entry_points(other)]:
                known.setdefault(n, other)
    close = difflib.get_close_matches(name, list(known), n=3, cutoff=0.6)
    if not close:
        return ""
    shown = ", ".join(repr(n) if known[n] == kind else f"{n!r} (a {known[n]})" for n in close)
    return f"; did you mean {shown}?"


def available(kind: str) -> list[PluginInfo]:
    """Every plug-in of ``kind`` that can be named without ``module:attribute``: the built-ins,
    then the installed entry points (one that fails to load is listed with the reason)."""
    out: list[PluginInfo] = []
    for name, target in BUILTINS[kind].items():
        cls = resolve(kind, name)
        out.append(PluginInfo(kind, name, _one_line(cls), "builtin", target))
    for name, ep in sorted(_entry_points(kind).items()):
        if name in BUILTINS[kind]:
            continue
        try:
            desc = _one_line(resolve(kind, name))
        except PluginError as e:
            desc = f"(cannot load: {e.message})"
        out.append(PluginInfo(kind, name, desc, f"entry point {GROUPS[kind]}", ep.value))
    return out


def _one_line(cls: type) -> str:
    text = str(getattr(cls, "description", "") or (cls.__doc__ or "")).strip()
    return text.splitlines()[0] if text else ""


def decode_params(cls: type, table: Mapping[str, Any] | None, field: str) -> Any:
    """The plug-in's ``[... .params]`` table decoded into its ``Params`` (a frozen
    :class:`msgspec.Struct` with ``forbid_unknown_fields=True``): an unknown key or a bad value
    raises :class:`ScenarioError` naming ``field.key`` (exit 2)."""
    params_type = getattr(cls, "Params", None)
    if not (isinstance(params_type, type) and issubclass(params_type, msgspec.Struct)):
        raise PluginError(field, f"{cls.__module__}:{cls.__qualname__}.Params must be a msgspec.Struct subclass")
    return convert(dict(table or {}), params_type, field)


def plugin_rng(seed: int, role: int) -> np.random.Generator:
    """The random stream of a plug-in: ``SeedSequence(seed, spawn_key=(PLUGIN_STREAM, role))``,
    role 0 for the leader's planner and i (1-based UAV number) for UAV i's controller. The
    simulator, the processes and ``zenswarm verify`` all draw from this, so they agree."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(PLUGIN_STREAM, int(role))))


def planner_name(scenario: Scenario) -> str:
    """The planner the scenario selects: ``[leader] planner``, else ``aapf`` (``apf`` with
    ``[leader] adaptive = false``, the older spelling, kept). ``planner = "aapf"`` with
    ``adaptive = false`` is a contradiction (ScenarioError naming ``leader.adaptive``)."""
    ld = scenario.leader
    if ld.planner is None:
        return "aapf" if ld.adaptive else "apf"
    if ld.planner == "aapf" and not ld.adaptive:
        raise ScenarioError("leader.adaptive", 'false contradicts leader.planner = "aapf" (the adaptive gain); use planner = "apf"')
    return ld.planner


def select(scenario: Scenario, controller: str | None = None, planner: str | None = None, plant_model: str | None = None) -> Scenario:
    """The scenario with the command line's ``--controller`` / ``--planner`` / ``--plant-model``
    applied (None: the scenario's). They override ``[agents] controller``, ``[leader] planner``
    (and ``adaptive``: the named planner decides) and ``[plant] model``; the params tables stay."""
    from dataclasses import replace

    from msgspec.structs import replace as replace_table

    if controller is not None:
        scenario = replace(scenario, agents=replace_table(scenario.agents, controller=controller))
    if planner is not None:
        scenario = replace(scenario, leader=replace_table(scenario.leader, planner=planner, adaptive=planner != "apf"))
    if plant_model is not None:
        scenario = replace(scenario, plant=replace_table(scenario.plant, model=plant_model))
    return scenario


def check_selection(
    scenario: Scenario, controller_field: str | None = None, planner_field: str | None = None, plant_field: str | None = None
) -> None:
    """Resolve the scenario's controller, planner and plant model and decode their params tables
    (and the plant model's vehicle): a bad name or parameter raises ScenarioError naming it
    (exit 2), before any work starts. A bad name is named by ``controller_field`` /
    ``planner_field`` / ``plant_field`` when given (the flag it came from, e.g. ``--controller``),
    else by its scenario field."""
    decode_params(resolve("controller", scenario.agents.controller, controller_field), scenario.agents.params, "agents.params")
    decode_params(resolve("planner", planner_name(scenario), planner_field), scenario.leader.params, "leader.params")
    resolve("plant", scenario.plant.model, plant_field)
    plant_vehicle(scenario)
    plant_records(scenario)


# ----------------------------------------------------------------------------- the plug-in boundary

STAGE_BUILD, STAGE_PLANNER, STAGE_SHARE, STAGE_STEP, STAGE_PLANT = -1, 0, 1, 2, 3
STAGES: Final[Mapping[int, str]] = {
    STAGE_BUILD: "build (the plug-in's constructor, before tick 0)",
    STAGE_PLANNER: "the leader's reference of the tick (Planner.advance to it, then Planner.ref)",
    STAGE_SHARE: "what the agents share for the tick (Controller.reset on the first, Controller.share)",
    STAGE_STEP: "the agents' commands of the tick (Controller.step, or prepare + finish)",
    STAGE_PLANT: "the vehicles' physics over the tick (the plant model)",
}
"""Where in control tick k a plug-in is called, in the order the simulator calls them (the
module docstring of :mod:`zenswarm.compose.sim`). A run that a plug-in fails ends at its first
(tick, stage): the failures judged are every plug-in failure of that (tick, stage), so the
simulator and the swarm (whose processes run concurrently) name the same ones."""


class Boundary:
    """Where a runner (the simulator, an agent or the leader process, ``zenswarm verify``) calls
    one plug-in instance: :meth:`call` turns an exception into a :class:`PluginFailure` and
    :meth:`fail` reports a bad output, each naming the plug-in, its process, the tick and the
    call. kind: ``controller`` / ``planner`` / ``plant``; plugin: the name it was selected by;
    process: ``agent:<i>``, ``leader`` or ``plant``; uavs: the UAVs it flies, 1-based."""

    def __init__(self, kind: str, plugin: str, process: str, uavs: tuple[int, ...] = ()) -> None:
        self.kind = kind
        self.plugin = plugin
        self.process = process
        self.uavs = uavs

    def call(self, tick: int, stage: int, what: str, fn: Any, *args: Any) -> Any:
        """``fn(*args)``; whatever it raises becomes a :class:`PluginFailure` of ``tick`` and
        ``stage`` naming ``what`` and the exception: any ``Exception``, and also ``SystemExit``
        (``sys.exit()`` in a plug-in), ``GeneratorExit`` and a plug-in's own ``BaseException``
        subclasses. Only a stop the user asked for passes through: ``KeyboardInterrupt`` (Ctrl-C,
        and SIGTERM in ``zenswarm sim``) and :class:`zenswarm.bus.Shutdown` (the signal handlers
        of :func:`zenswarm.bus.open_session`)."""
        try:
            return fn(*args)
        except PluginFailure:
            raise
        except KeyboardInterrupt:
            raise
        except BaseException as e:  # any exception of a plug-in is its failure, named
            if not isinstance(e, Exception) and _stop_requested(e):
                raise
            text = str(e).strip().splitlines()
            detail = f"raised {type(e).__name__}" + (f": {text[0]}" if text else "")
            raise PluginFailure(self.kind, self.plugin, self.process, self.uavs, tick, stage, what, detail) from e

    def fail(self, tick: int, stage: int, what: str, field: str, problem: str) -> PluginFailure:
        """The failure of a bad output ``field`` (``problem``: what is wrong with it), to raise."""
        return PluginFailure(self.kind, self.plugin, self.process, self.uavs, tick, stage, what, f"{field}: {problem}", field)

    def check(self, tick: int, stage: int, what: str, problems: Any) -> None:
        """Raise the failure of the first of ``problems`` ((field, problem) pairs, None: fine)."""
        for item in problems:
            if item is not None:
                raise self.fail(tick, stage, what, *item)


def _stop_requested(e: BaseException) -> bool:
    """Whether ``e`` is the stop a signal handler raised (:class:`zenswarm.bus.Shutdown`), not
    the plug-in's own exit. Imported here, on this rare path: the bus is zenoh's."""
    from zenswarm.bus import Shutdown

    return isinstance(e, Shutdown)


def _show(x: Any) -> str:
    text = np.array2string(x, precision=6, threshold=9) if isinstance(x, np.ndarray) else repr(x)
    return text if len(text) <= 80 else text[:77] + "..."


def bad_vector(x: Any, shape: tuple[int, ...]) -> str | None:
    """What is wrong with ``x`` as a finite float array of ``shape`` (None: nothing). Called
    several times per UAV and tick: a right-shaped numeric array takes a fast path."""
    if type(x) is np.ndarray and x.shape == shape and x.dtype.kind in "fiu" and all(map(math.isfinite, x.ravel().tolist())):
        return None
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        return f"{_show(x)} is not an array of numbers (expected shape {shape})"
    if a.shape != tuple(shape):
        return f"shape {a.shape} != {tuple(shape)}"
    if not np.all(np.isfinite(a)):
        return f"{_show(a)} is not finite"
    return None


def bad_scalar(x: Any) -> str | None:
    """What is wrong with ``x`` as one finite number (None: nothing)."""
    if type(x) is float and math.isfinite(x):
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        if isinstance(x, np.ndarray) and x.shape == ():
            x = x.item()
        else:
            return f"{_show(x)} ({type(x).__name__}) is not a number"
    if not np.isfinite(float(x)):
        return f"{x!r} is not finite"
    return None


def first_failures(failures: list[PluginFailure]) -> list[PluginFailure]:
    """The failures of the first (tick, stage) among ``failures``, ordered by process (the
    leader, then agent 1, 2, ...): what the run ends on."""
    if not failures:
        return []
    first = min(f.order for f in failures)

    def by_process(f: PluginFailure) -> tuple[int, str]:
        name = f.process
        return (int(name.split(":")[1]), name) if name.startswith("agent:") and name.split(":")[1].isdigit() else (0, name)

    return sorted((f for f in failures if f.order == first), key=by_process)
def plant_selection(scenario: Scenario) -> tuple[type, Any]:
    """The scenario's plant model class (``[plant] model``) and its decoded ``[plant.params]``
    (PluginError / ScenarioError naming the field, exit 2)."""
    cls = resolve("plant", scenario.plant.model)
    return cls, decode_params(cls, scenario.plant.params, "plant.params")


def plant_vehicle(scenario: Scenario) -> QuadParams:
    """The vehicle the scenario's plant model flies (its ``vehicle`` classmethod): mass, g,
    inertia and thrust bound as :class:`zenswarm.vehicle.params.QuadParams`. The agents' controllers are
    built with its mass and g (thrust = m |u|, eq. 28), the failsafe hovers with them, so the
    scheme uses the plant model's vehicle in the simulator, the processes and ``verify`` alike.
    A model that cannot be used (e.g. its package is not installed) raises PluginError naming
    ``plant.model``."""
    cls, params = plant_selection(scenario)
    vehicle = getattr(cls, "vehicle")(scenario, params)  # noqa: B009 - a PlantModel (resolve checked it); the base imports no role
    if not isinstance(vehicle, QuadParams):
        got = type(vehicle).__name__
        raise PluginError("plant.model", f"plant {scenario.plant.model!r}: vehicle() must return a QuadParams, got {got}")
    return vehicle


# ----------------------------------------------------------------------------- a plant model's records


@dataclass(frozen=True)
class Signal:
    """One internal signal a plant model records (:attr:`zenswarm.plant.api.PlantModel.records`):
    its ``shape`` per UAV (a tuple of positive ints; ``()`` a scalar), its ``unit`` (SI, e.g.
    ``"N"``, ``"rad/s"``, ``"N m"``; ``"1"`` for a dimensionless one) and a one-line
    ``description``. The series is (T, N, *shape) in ``timeseries.npz`` (``plant.<name>``)."""

    shape: tuple[int, ...]
    unit: str
    description: str = ""

    @property
    def size(self) -> int:
        """Values per UAV: the product of ``shape`` (1 for a scalar)."""
        return math.prod(self.shape)


MAX_RECORDS: Final = 64
"""Most signals a plant model records (they travel in each state message, :attr:`zenswarm.bus.wire.State.extra`)."""

MAX_RECORD_VALUES: Final = 1024
"""Most values per UAV a plant model records, all signals together (a state message stays well under
:data:`zenswarm.bus.wire.MAX_PAYLOAD`)."""

_RECORD_NAME: Final = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}")


def shares_of(cls: type, who: str = "controller") -> dict[str, tuple[int, ...]]:
    """The extra values controller class ``cls`` shares with its neighbours (its ``shares``),
    checked: a mapping of names (str) to shapes (positive ints). A bad declaration raises
    :class:`PluginError` (exit 2) naming ``shares``, as :func:`records_of` does a plant model's."""
    shares = getattr(cls, "shares", {})
    try:
        out = {k: tuple(s) for k, s in dict(shares).items()}
        ok = all(isinstance(k, str) and all(isinstance(d, int) and d > 0 for d in s) for k, s in out.items())
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise PluginError("shares", f"{who}: must map names to shapes (tuples of positive ints), got {shares!r}")
    return out


def records_of(cls: type, who: str = "plant model") -> dict[str, Signal]:
    """The signals plant model class ``cls`` declares (its ``records``), checked: a mapping of
    names (letters, digits, ``_``; not starting with a digit; at most 64 characters) to
    :class:`Signal` with a shape of positive ints and a one-line unit, at most
    :data:`MAX_RECORDS` signals and :data:`MAX_RECORD_VALUES` values per UAV. A bad
    declaration raises :class:`PluginError` (exit 2) naming the field (``records``,
    ``records.NAME``, ``records.NAME.shape`` or ``records.NAME.unit``) before any work starts."""
    decl = getattr(cls, "records", None)
    if decl is None:
        return {}
    if not isinstance(decl, Mapping):
        raise PluginError("records", f"{who}: must map names to zenswarm.plant.api.Signal(shape, unit), got {type(decl).__name__}")
    if len(decl) > MAX_RECORDS:
        raise PluginError("records", f"{who}: at most {MAX_RECORDS} signals, got {len(decl)}")
    out: dict[str, Signal] = {}
    for name, sig in decl.items():
        if not (isinstance(name, str) and _RECORD_NAME.fullmatch(name)):
            raise PluginError("records", f"{who}: signal name {name!r} must be letters, digits and _ (not first a digit), at most 64")
        field = f"records.{name}"
        if not isinstance(sig, Signal):
            raise PluginError(field, f"{who}: must be a zenswarm.plant.api.Signal(shape, unit), got {sig!r}")
        shape = sig.shape
        if not (isinstance(shape, tuple) and all(type(d) is int and d > 0 for d in shape)):
            raise PluginError(f"{field}.shape", f"{who}: must be a tuple of positive ints (() for a scalar), got {shape!r}")
        unit = sig.unit
        if not (isinstance(unit, str) and unit.strip() and "\n" not in unit):
            raise PluginError(f"{field}.unit", f"{who}: must be a non-empty one-line string (SI, e.g. 'N'; '1' if none), got {unit!r}")
        out[name] = sig
    total = sum(s.size for s in out.values())
    if total > MAX_RECORD_VALUES:
        raise PluginError("records", f"{who}: at most {MAX_RECORD_VALUES} values per UAV in all, got {total}")
    return out


def plant_records(scenario: Scenario) -> dict[str, Signal]:
    """The signals the scenario's plant model records (:func:`records_of` of its class; PluginError
    naming the field for a bad name, parameter or declaration)."""
    cls, _ = plant_selection(scenario)
    return records_of(cls, f"plant {scenario.plant.model!r}")

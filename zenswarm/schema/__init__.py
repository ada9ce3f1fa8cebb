"""The scenario file's schema: every TOML table as a typed, frozen :mod:`msgspec` Struct.

This is the one definition of the scenario format. :func:`convert` turns a parsed TOML document
(or one table of it) into these Structs in one pass: unknown keys and unknown sections are
rejected, types and ranges are checked (``Meta`` constraints), bools are not numbers, NaN, inf
and integers too large for a float are refused, and the math-free cross-field checks run in
``__post_init__`` (a table at a fixed place raises :class:`ScenarioError` naming its key; one
inside a list raises ``ValueError("@key: ...")``, which gets the path of the list entry). Every
failure is a :class:`zenswarm.errors.ScenarioError` whose ``field`` is the dotted path of the
offending key (``leader.k_att``, ``obstacles[1].radius``, ``mavlink.bogus``, ``network``):
msgspec's path ``$.obstacles[1].radius`` mapped to ours.

Units are SI, positions in the inertial ENU frame (z up). The checks that need numbers of the
whole scenario (the graph's Lemma 1, start/goal clearance, run-size bounds, durations in the
``[faults]`` table) live with their owners (:mod:`zenswarm.scenario.config`, :mod:`zenswarm.link.config`,
:mod:`zenswarm.vehicle.autopilot`), which read these Structs.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any, Literal, Protocol, TypeVar

import msgspec
from msgspec import Meta, field

from zenswarm.errors import ScenarioError

__all__ = [
    "Topology",
    "ScenarioTables",
    "Table",
    "ScenarioMeta",
    "Timing",
    "LeaderConfig",
    "Obstacle",
    "FormationConfig",
    "GraphConfig",
    "GeneratorConfig",
    "EsoConfig",
    "ControllerConfig",
    "AgentsConfig",
    "PlantConfig",
    "VehicleConfig",
    "MissionConfig",
    "DisturbanceConfig",
    "FailsafeConfig",
    "RestartTable",
    "BurstTable",
    "PartitionTable",
    "LinkFaultsTable",
    "FaultsTable",
    "MavlinkTable",
    "CrazyflieTable",
    "ScenarioFile",
    "MAX_SEED",
    "check_seed",
    "convert",
    "to_builtins",
]

MAX_SEED = 2**63 - 1
"""Largest ``scenario.seed`` (and ``--seed``): the seed travels in the mission message and the
recording's metadata as a signed 64-bit integer."""

Pos = Annotated[float, Meta(gt=0)]
"""A finite number > 0."""
NonNeg = Annotated[float, Meta(ge=0)]
"""A finite number >= 0."""
Prob = Annotated[float, Meta(ge=0, le=1)]
"""A probability in [0, 1]."""
Vec3 = tuple[float, float, float]
PosVec3 = tuple[Pos, Pos, Pos]
Duration = str | float
"""A duration string with a unit (``"50ms"``), or the number 0 (checked by :mod:`zenswarm.link.config`)."""


class Table(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Base of every table: immutable, unknown keys rejected.

    Subclasses repeat ``frozen=True``: msgspec inherits it, but type checkers (PEP 681's
    ``dataclass_transform``) read a subclass without it as a mutable one."""


def check_seed(value: Any, field: str = "scenario.seed") -> int:
    """``value`` as a seed: an integer in [0, :data:`MAX_SEED`]; else :class:`ScenarioError`
    naming ``field`` (``scenario.seed``, ``--seed``). The one check of every seed zenswarm takes."""
    if isinstance(value, bool) or not isinstance(value, int) and not hasattr(value, "__index__"):
        raise ScenarioError(field, f"expected a non-negative integer, got {value!r}")
    v = int(value)
    if not 0 <= v <= MAX_SEED:
        raise ScenarioError(field, f"expected a non-negative integer <= 2**63 - 1 ({MAX_SEED}), got {v}")
    return v


# ----------------------------------------------------------------------------- the flight


class ScenarioMeta(Table, frozen=True):
    """``[scenario]``: name (non-empty), description, seed in [0, 2**63 - 1]."""

    name: Annotated[str, Meta(min_length=1)] = "scenario"
    description: str = ""
    seed: int = 0

    def __post_init__(self) -> None:
        check_seed(self.seed, "scenario.seed")


class Timing(Table, frozen=True):
    """``[timing]``: rates, Hz; time limit, settle time, s; goal tolerance, m (all > 0)."""

    control_rate_hz: Pos = 100.0
    physics_rate_hz: Pos = 1000.0
    time_limit_s: Pos = 70.0
    settle_time_s: Pos = 30.0
    goal_tolerance_m: Pos = 0.05

    @property
    def dt(self) -> float:
        """Outer-loop (control) period, s."""
        return 1.0 / self.control_rate_hz

    @property
    def substeps(self) -> int:
        """Physics sub-steps per control tick (integer by validation)."""
        return int(round(self.physics_rate_hz / self.control_rate_hz))

    @property
    def n_ticks(self) -> int:
        """Number of control ticks in the time limit."""
        return int(round(self.time_limit_s * self.control_rate_hz))


class LeaderConfig(Table, frozen=True):
    """``[leader]``: virtual leader and AAPF parameters, eqs 8-15 (start, goal m ENU; gains > 0)."""

    start: Vec3
    goal: Vec3
    k_att: Pos
    k_rep_min: Pos
    k_rep_max: Pos
    d0: Pos
    adaptive: bool = True
    k_rep_fixed: Pos = 1.0
    speed_limit: NonNeg = 0.0  # m/s; 0 means off (fidelity to the paper)
    planner: str | None = None  # plug-in name (zenswarm.scenario.plugins); None: "aapf", or "apf" with adaptive = false
    params: dict[str, Any] = field(default_factory=dict)  # [leader.params]: the planner's Params

    def __post_init__(self) -> None:
        if self.k_rep_max < self.k_rep_min:
            raise ScenarioError("leader.k_rep_max", f"must be >= leader.k_rep_min ({self.k_rep_max} < {self.k_rep_min})")


class AgentsConfig(Table, frozen=True):
    """``[agents]``: the agents' controller plug-in (:mod:`zenswarm.scenario.plugins`) and its parameters
    (``[agents.params]``, decoded into the controller's ``Params``)."""

    controller: str = "paper"
    params: dict[str, Any] = field(default_factory=dict)


class PlantConfig(Table, frozen=True):
    """``[plant]``: the plant model plug-in (:mod:`zenswarm.scenario.plugins`, kind ``plant``: the vehicles'
    dynamics; default ``quadrotor``, zenswarm's own) and its parameters (``[plant.params]``,
    decoded into the model's ``Params``)."""

    model: str = "quadrotor"
    params: dict[str, Any] = field(default_factory=dict)


class Obstacle(Table, frozen=True):
    """``[[obstacles]]``: vertical cylinder capped by an upper hemisphere (paper, Remark 1).

    center: (3,) m, centre of the cylinder base c = [x_c, y_c, z_c]; radius r_o > 0 m;
    height h_o > 0 m (cylinder part; the cap adds r_o above it).
    """

    center: Vec3
    radius: Pos
    height: Pos


class FormationConfig(Table, frozen=True):
    """``[formation]``: offsets h_i (N, 3) m and initial positions q_i(0) (N, 3) m, N >= 1."""

    offsets: tuple[Vec3, ...]
    initial_positions: tuple[Vec3, ...]

    def __post_init__(self) -> None:
        n = len(self.offsets)
        if n == 0:
            raise ScenarioError("formation.offsets", "at least one UAV is required")
        if len(self.initial_positions) != n:
            raise ScenarioError("formation.initial_positions", f"expected {n} rows, got {len(self.initial_positions)}")


Topology = Literal["ring", "star", "complete", "knn"]
"""A named graph topology (:data:`zenswarm.scenario.graph.TOPOLOGIES`)."""


class GraphConfig(Table, frozen=True, kw_only=True):
    """``[graph]``: the undirected communication graph A among followers in one of three forms,
    and the pinning b (N,) (each b_i >= 0):

    * ``adjacency``: the dense matrix A (N, N), symmetric, weights >= 0, zero diagonal;
    * ``edges``: ``[[i, j, a_ij], ...]``, UAV numbers 1..N, weights > 0, each edge once;
    * ``topology`` (``ring``, ``star``, ``complete``, ``knn``) and, for ``knn``, ``k`` >= 1:
      the generator's graph over the formation offsets (unit weights).

    Exactly one form. The graph itself (:class:`zenswarm.scenario.graph.CommGraph`, neighbour
    lists) and the checks that need N or the offsets are the scenario's
    (``Scenario.comm_graph``)."""

    adjacency: tuple[tuple[float, ...], ...] | None = None
    edges: tuple[tuple[int, int, float], ...] | None = None
    topology: Topology | None = None
    k: Annotated[int, Meta(ge=1)] | None = None
    pinning: tuple[float, ...]

    def __post_init__(self) -> None:
        given = [name for name in ("adjacency", "edges", "topology") if getattr(self, name) is not None]
        if len(given) != 1:
            what = " and ".join(given) if given else "none"
            raise ScenarioError("graph", f"give the graph in exactly one form: adjacency, edges or topology (got {what})")
        if self.topology == "knn" and self.k is None:
            raise ScenarioError("graph.k", 'missing required key (topology = "knn" needs k, the neighbours per UAV)')
        if self.k is not None and self.topology != "knn":
            raise ScenarioError("graph.k", 'only with topology = "knn"')

    def neighbours(self, i: int) -> list[int]:
        """0-based indices j with a_ij > 0 for 0-based agent index i, of the ``adjacency`` and
        ``edges`` forms (O(N) and O(E)); a ``topology`` needs the offsets: use
        ``Scenario.neighbours``, which answers for every form from the graph built once."""
        if self.adjacency is not None:
            return [j for j, a in enumerate(self.adjacency[i]) if a > 0]
        if self.edges is not None:
            return sorted({(b if a == i + 1 else a) - 1 for a, b, _ in self.edges if i + 1 in (a, b) and a != b})
        raise ValueError(f"graph.topology = {self.topology!r} is built from the formation offsets: use Scenario.neighbours")


class GeneratorConfig(Table, frozen=True):
    """``[generator]``: reference generator gains mu1, mu2 > 0 (eqs 16-17)."""

    mu1: Pos = 0.1
    mu2: Pos = 2.0


class EsoConfig(Table, frozen=True):
    """``[eso]``: observer gains beta = [beta1, beta2, beta3] > 0, enabled (eq. 27)."""

    beta: PosVec3 = (15.0, 75.0, 125.0)
    enabled: bool = True


class ControllerConfig(Table, frozen=True):
    """``[controller]``: kp (3,), kd (3,) > 0, desired yaw psi_d rad (eq. 28)."""

    kp: PosVec3 = (4.5, 4.5, 5.4)
    kd: PosVec3 = (5.0, 5.0, 3.0)
    yaw: float = 0.0


class VehicleConfig(Table, frozen=True):
    """``[vehicle]``: optional overrides of :class:`zenswarm.vehicle.params.QuadParams`; ``None`` keeps the default.

    ``radius``: the vehicle's contact radius, m, used by the verdict (obstacle contact when a
    UAV's clearance is below it, UAV-UAV contact below twice it); ``None``: a Crazyflie 2.1's.
    """

    mass: Pos | None = None
    inertia: PosVec3 | None = None
    max_thrust: Pos | None = None
    max_tilt: Pos | None = None
    radius: Pos | None = None


class MissionConfig(Table, frozen=True):
    """``[mission]``: how a flight is judged (:mod:`zenswarm.judge.verdict`).

    slot_tolerance_m: every UAV must end within this distance of its slot q0_goal + h_i, m ...
    settle_window_s: ... for this long at the end of the flight, s.
    stall_speed_m_s, stall_window_s: the leader is stalled (a local minimum of the AAPF) when it
    moves less than stall_speed * stall_window over a window while away from the goal and
    within d0 of an obstacle; the run then ends early.
    divergence_m: a UAV farther than this from its reference q*_i no longer tracks it (it fell, or
    was blown away): it has diverged, and the run ends early.
    """

    slot_tolerance_m: Pos = 0.10
    settle_window_s: Pos = 3.0
    stall_speed_m_s: Pos = 0.01
    stall_window_s: Pos = 5.0
    divergence_m: Pos = 5.0


class DisturbanceConfig(Table, frozen=True):
    """``[disturbance]``: lumped translational disturbance d_p (eq. 1) as an acceleration, m/s^2, ENU.

    d_p(t) = wind + sine_amplitude * sin(2 pi sine_freq_hz t) + gust(t), where gust is a
    first-order Gauss-Markov process with stationary std ``gust_std`` and time constant
    ``gust_tau_s``, driven by the scenario's seeded generator. ``attitude_std`` adds white
    torque noise d_a as an angular acceleration, rad/s^2.
    """

    wind: Vec3 = (0.0, 0.0, 0.0)
    sine_amplitude: Vec3 = (0.0, 0.0, 0.0)
    sine_freq_hz: NonNeg = 0.0
    gust_std: NonNeg = 0.0
    gust_tau_s: Pos = 1.0
    attitude_std: NonNeg = 0.0

    @property
    def active(self) -> bool:
        return bool(any(self.wind) or any(self.sine_amplitude) or self.gust_std > 0 or self.attitude_std > 0)


# ----------------------------------------------------------------------------- the subsystems


class FailsafeConfig(Table, frozen=True):
    """``[failsafe]``: hover_after_s < land_after_s, s of sim time without a fresh command;
    land_speed m/s; hold gains kp (1/s^2), kd (1/s); ground_z m (motors off below it while landing)."""

    hover_after_s: Pos = 0.5
    land_after_s: Pos = 5.0
    land_speed: Pos = 0.3
    kp: Pos = 4.0
    kd: Pos = 3.0
    ground_z: float = 0.03

    def __post_init__(self) -> None:
        if self.land_after_s <= self.hover_after_s:
            raise ScenarioError(
                "failsafe.land_after_s", f"must be > failsafe.hover_after_s ({self.land_after_s} <= {self.hover_after_s})"
            )


class RestartTable(Table, frozen=True):
    """``[restart]``: supervisor backoff (see :class:`zenswarm.compose.policy.RestartPolicy`); present
    means enabled unless ``enabled = false``. Delays s > 0, factor >= 1, max_restarts >= 0."""

    enabled: bool = True
    initial_delay_s: Pos = 0.2
    factor: Annotated[float, Meta(ge=1)] = 2.0
    max_delay_s: Pos = 5.0
    max_restarts: Annotated[int, Meta(ge=0)] = 3


class BurstTable(Table, frozen=True):
    """A Gilbert-Elliott burst-loss model: transition and per-state loss probabilities."""

    p_good_to_bad: Prob
    p_bad_to_good: Prob
    loss_good: Prob = 0.0
    loss_bad: Prob = 1.0

    def __post_init__(self) -> None:
        if self.p_good_to_bad + self.p_bad_to_good <= 0.0:
            raise ValueError("@p_bad_to_good: p_good_to_bad and p_bad_to_good cannot both be 0")


class FadeTable(Table, frozen=True):
    """A logistic fall-off of delivery with distance (:class:`zenswarm.link.radio.RadioModel`): its
    50 % range ``r50`` and ``width`` (distances such as ``"1.2m"`` or metres, > 0)."""

    r50: str | float
    width: str | float


class PartitionTable(Table, frozen=True):
    """A partition as a table: target (``agent:2`` or ``agent:1->agent:2``), start, end (durations;
    end may be ``inf`` or ``end``)."""

    target: str
    start: Duration
    end: Duration


class LinkFaultsTable(Table, frozen=True):
    """One ``[[faults.links]]`` entry: src, dst (process names or globs), kind (``ref``,
    ``leader``, ``state``, ``cmd`` or ``*``); omitted fields inherit the ``[faults]`` values;
    ``burst = false`` turns an inherited burst off, ``capacity = false`` an inherited capacity
    (:mod:`zenswarm.link.queue`)."""

    src: str = "*"
    dst: str = "*"
    kind: str = "*"
    delay: Duration | None = None
    jitter: Duration | None = None
    loss: Prob | None = None
    burst: BurstTable | bool | None = None
    range: str | float | None = None
    fade: FadeTable | bool | None = None
    capacity: str | float | bool | None = None
    queue: str | int | None = None
    medium: str | None = None


class FaultsTable(Table, frozen=True):
    """``[faults]``: link faults (see :func:`zenswarm.link.config.plan_from_scenario` and docs/faults.md);
    capacity, queue, medium: :mod:`zenswarm.link.queue`; trace: a CSV file (:mod:`zenswarm.link.trace`),
    relative to the scenario file; hold: the hold horizon of the references (a duration, e.g.
    ``"0.5s"``: a neighbour or leader last heard longer ago is left out of eqs (16)-(17))."""

    delay: Duration | None = None
    jitter: Duration | None = None
    loss: Prob | None = None
    burst: BurstTable | bool | None = None
    range: str | float | None = None
    fade: FadeTable | bool | None = None
    partitions: tuple[str | PartitionTable, ...] = ()
    links: tuple[LinkFaultsTable, ...] = ()
    capacity: str | float | bool | None = None
    queue: str | int | None = None
    medium: str | None = None
    trace: str | None = None
    hold: Duration | None = None


class MavlinkTable(Table, frozen=True):
    """``[mavlink]``: the MAVLink bridge and simulated vehicles (see
    :func:`zenswarm.vehicle.autopilot.mavlink_settings` for every key; ``None``: the derived default)."""

    connections: tuple[Annotated[str, Meta(min_length=1)], ...] | None = None
    sysids: tuple[Annotated[int, Meta(ge=1, le=254)], ...] | None = None
    origins: tuple[Vec3, ...] | None = None
    host: Annotated[str, Meta(min_length=1)] = "127.0.0.1"
    base_port: Annotated[int, Meta(ge=1, le=65535)] = 14540
    autopilot: Literal["auto", "px4", "ardupilot"] = "auto"
    setpoint: Literal["attitude", "position"] = "attitude"
    rate_hz: Annotated[float, Meta(ge=20)] | None = None
    hover_throttle: Annotated[float, Meta(gt=0, lt=1)] | None = None
    takeoff: bool = True
    takeoff_tolerance_m: Pos = 0.08
    takeoff_timeout_s: Pos = 30.0
    link_timeout_s: Pos = 0.5
    params_timeout_s: Pos = 5.0
    stream_s: NonNeg = 1.0
    cmd_timeout_s: Pos = 0.5
    land_timeout_s: NonNeg = 15.0
    start_timeout_s: NonNeg = 60.0
    reengage: bool = True
    source_system: Annotated[int, Meta(ge=1, le=255)] = 245
    telemetry_hz: Annotated[float, Meta(gt=0, le=1000)] = 50.0
    request_telemetry: bool = True
    offboard_loss_s: Pos = 1.0
    failsafe_land_s: NonNeg = 5.0
    ground_z: float = 0.0


class CrazyflieTable(Table, frozen=True):
    """``[crazyflie]``: the Crazyflie bridge (see
    :func:`zenswarm.vehicle.crazyflie_settings.crazyflie_settings` for every key; ``None``: the derived default)."""

    uris: tuple[Annotated[str, Meta(min_length=1)], ...] | None = None
    host: Annotated[str, Meta(min_length=1)] = "127.0.0.1"
    base_port: Annotated[int, Meta(ge=1, le=65535)] = 19850
    rate_hz: Annotated[float, Meta(ge=10, le=500)] | None = None
    takeoff: bool = True
    takeoff_duration_s: Pos = 2.0
    takeoff_tolerance_m: Pos = 0.08
    takeoff_timeout_s: Pos = 15.0
    connect_timeout_s: Pos = 15.0
    link_timeout_s: Pos = 0.5
    cmd_timeout_s: Pos = 0.5
    land_duration_s: Pos = 2.0
    land_timeout_s: NonNeg = 10.0
    start_timeout_s: NonNeg = 60.0
    yaw_gain: Pos = 4.0
    positioning: Literal["onboard", "extpos"] = "onboard"


# ----------------------------------------------------------------------------- the document


class ScenarioFile(Table, frozen=True, kw_only=True):
    """A whole scenario file; sections absent from the file take their defaults (subsystem
    tables: None). The shapes that depend on N (graph) are checked here."""

    scenario: ScenarioMeta = field(default_factory=ScenarioMeta)
    timing: Timing = field(default_factory=Timing)
    leader: LeaderConfig
    obstacles: tuple[Obstacle, ...]
    formation: FormationConfig
    graph: GraphConfig
    generator: GeneratorConfig = field(default_factory=GeneratorConfig)
    eso: EsoConfig = field(default_factory=EsoConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    agents: AgentsConfig = field(default_factory=AgentsConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)
    faults: FaultsTable | None = None
    failsafe: FailsafeConfig | None = None
    restart: RestartTable | None = None
    mavlink: MavlinkTable | None = None
    crazyflie: CrazyflieTable | None = None

    def __post_init__(self) -> None:
        n = len(self.formation.offsets)
        g = self.graph
        if g.adjacency is not None:
            if len(g.adjacency) != n:
                raise ScenarioError("graph.adjacency", f"expected {n} rows, got {len(g.adjacency)}")
            for r, row in enumerate(g.adjacency):
                if len(row) != n:
                    raise ScenarioError(f"graph.adjacency[{r}]", f"expected a list of length {n}, got {len(row)}")
        if len(g.pinning) != n:
            raise ScenarioError("graph.pinning", f"expected a list of length {n}, got {len(g.pinning)}")


# ----------------------------------------------------------------------------- conversion

T = TypeVar("T")

_TOKEN = re.compile(r"\.([^.\[]+)|\[(\d+)\]")
_WORDS = (("`float`", "a number"), ("`int`", "an integer"), ("`bool`", "true or false"),
          ("`array`", "a list"), ("`object`", "a table"), ("`str`", "a string"))


def _check_finite(x: Any, path: str) -> None:
    """Refuse NaN, +-inf and integers too large for a float anywhere in ``x`` (TOML allows them)."""
    if isinstance(x, dict):
        for k, v in x.items():
            _check_finite(v, f"{path}.{k}" if path else str(k))
    elif isinstance(x, (list, tuple)):
        for k, v in enumerate(x):
            _check_finite(v, f"{path}[{k}]")
    elif isinstance(x, float) and not math.isfinite(x):
        raise ScenarioError(path, f"must be finite, got {x!r}")
    elif isinstance(x, int) and not isinstance(x, bool) and abs(x) > 2**1023:
        try:
            float(x)
        except OverflowError:
            raise ScenarioError(path, f"must be finite, got an integer too large for a float ({len(str(x))} digits)") from None


def _tokens(path: str) -> list[str | int]:
    return [m.group(1) if m.group(1) is not None else int(m.group(2)) for m in _TOKEN.finditer(path)]


def _value_at(obj: Any, tokens: list[str | int]) -> tuple[bool, Any]:
    for t in tokens:
        try:
            obj = obj[t]
        except (KeyError, IndexError, TypeError):
            return False, None
    return True, obj


def _type_at(t: Any, tokens: list[str | int]) -> Any:
    """The msgspec type info at ``tokens`` below ``t`` (Structs through unions and lists)."""
    from msgspec import inspect as mi

    for tok in [*tokens, None]:
        while isinstance(t, mi.UnionType):  # the table member of an optional table
            t = next((u for u in t.types if isinstance(u, mi.StructType)), t.types[0])
        if tok is None:
            return t
        if isinstance(t, mi.StructType) and isinstance(tok, str):
            t = next((f.type for f in t.fields if f.encode_name == tok), None)
        elif isinstance(t, (mi.ListType, mi.VarTupleType)):
            t = t.item_type
        elif isinstance(t, mi.TupleType) and isinstance(tok, int) and tok < len(t.item_types):
            t = t.item_types[tok]
        else:
            return None
    return t


def _error(e: msgspec.ValidationError, obj: Any, typ: type, prefix: str) -> ScenarioError:
    """msgspec's ``<message> - at `$.a[0].b``` as ``ScenarioError("prefix.a[0].b", message)``."""
    from msgspec import inspect as mi

    msg, _, at = str(e).partition(" - at `")
    tokens = _tokens(at.rstrip("`").removeprefix("$"))
    where = "".join(f"[{t}]" if isinstance(t, int) else f".{t}" for t in tokens)
    path = (prefix + where).lstrip(".")

    def join(key: str) -> str:
        return f"{path}.{key}" if path else key

    if m := re.fullmatch(r"Object contains unknown field `(.+)`", msg):
        st = _type_at(mi.type_info(typ), tokens)
        names = sorted(f.encode_name for f in st.fields) if isinstance(st, mi.StructType) else []
        allowed = ", ".join(names) if names else "none: this table takes no keys"
        return ScenarioError(join(m.group(1)), f"unknown key (allowed: {allowed})")
    if m := re.fullmatch(r"Object missing required field `(.+)`", msg):
        return ScenarioError(join(m.group(1)), "missing required key")
    if m := re.fullmatch(r"@(\w+): (.*)", msg, re.S):  # a __post_init__ check naming its key
        return ScenarioError(join(m.group(1)), m.group(2))
    found, raw = _value_at(obj, tokens)
    if msg.startswith("Invalid enum value"):
        lit = _type_at(mi.type_info(typ), tokens)
        choices = ", ".join(map(str, getattr(lit, "values", ())))
        return ScenarioError(path, f"expected one of {choices}, got {raw!r}")
    head, got, tail = msg.partition(", got ")
    for word, plain in _WORDS:
        head = head.replace(word, plain)
    tail = tail.replace("`object`", "a table").replace("`array`", "a list").replace("`", "")
    msg = "e" + head[1:] + got + tail if head.startswith("E") else msg
    if found and not isinstance(raw, (dict, list, tuple)):
        msg += f" {raw!r}" if ", got " in msg else f", got {raw!r}"
    return ScenarioError(path, msg)


def convert(obj: Any, typ: type[T], prefix: str = "") -> T:
    """``obj`` (a parsed TOML document or table: dicts, lists, scalars) as ``typ``, validated.

    prefix: the dotted path of ``obj`` in the file ("" for the document, ``mavlink`` for the
    table). Raises :class:`ScenarioError` naming the field."""
    _check_finite(obj, prefix)
    try:
        return msgspec.convert(obj, typ)
    except msgspec.ValidationError as e:
        raise _error(e, obj, typ, prefix) from None


def to_builtins(table: Table, omit_defaults: bool = False) -> dict[str, Any]:
    """A table back as a TOML-ready dict (tuples as lists); ``omit_defaults``: only the keys set."""
    return {
        f.encode_name: _plain(msgspec.to_builtins(getattr(table, f.name)))
        for f in msgspec.structs.fields(table)
        if not omit_defaults or f.required or getattr(table, f.name) != f.default
    }


def _plain(x: Any) -> Any:
    """Tuples as lists, recursively (TOML and msgpack have arrays only)."""
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    return x


class ScenarioTables(Protocol):
    """What the base's packages below the scenario (the link model, :mod:`zenswarm.link`; the
    autopilot facts, :mod:`zenswarm.vehicle.autopilot`) read of a validated scenario: its tables,
    typed here. :class:`zenswarm.scenario.config.Scenario` is one; they never import it, so the
    scenario package may use them (it validates ``[faults]`` and ``[mavlink]`` on load)."""

    @property
    def n(self) -> int:
        """Number of follower UAVs N."""
        ...

    @property
    def seed(self) -> int: ...

    @property
    def timing(self) -> Timing: ...

    @property
    def graph(self) -> GraphConfig: ...

    def neighbours(self, i: int) -> list[int]:
        """0-based neighbours j (a_ij > 0) of 0-based UAV i, increasing (whatever form ``[graph]`` has)."""
        ...

    @property
    def faults(self) -> FaultsTable | None: ...

    @property
    def mavlink(self) -> MavlinkTable | None: ...

    @property
    def crazyflie(self) -> CrazyflieTable | None: ...

"""Scenario configuration: one TOML file loaded into frozen dataclasses and validated on load.

Every error is a :class:`zenswarm.errors.ScenarioError` whose ``field`` names the offending key as
a dotted path (``leader.goal``, ``graph.adjacency``, ``obstacles[1].radius``). Units are SI
throughout; positions are in the inertial ENU frame (z up), as in the paper.

The sections and their meaning (see ``compose/scenarios/paper_example1.toml`` for a full file):

``[scenario]``   name, description, seed
``[timing]``     control_rate_hz, physics_rate_hz, time_limit_s, settle_time_s, goal_tolerance_m
``[leader]``     start, goal, k_att, k_rep_min, k_rep_max, d0, adaptive, k_rep_fixed, speed_limit
``[[obstacles]]`` center (base centre), radius, height: cylinder capped by a hemisphere (Remark 1)
``[formation]``  offsets h_i (N, 3), initial_positions q_i(0) (N, 3)
``[graph]``      adjacency A (N, N) symmetric, pinning b (N,)
``[generator]``  mu1, mu2 (eqs 16-17)
``[eso]``        beta = [beta1, beta2, beta3], enabled (eq. 27)
``[controller]`` kp (3,), kd (3,), yaw (eq. 28 and the inversion after it)
``[vehicle]``    optional overrides of the Crazyflie 2.1 parameters (see :mod:`plant.params`), and
                 radius (the contact radius the verdict uses; default :data:`CRAZYFLIE_RADIUS_M`)
``[mission]``    how the flight is judged (:mod:`zenswarm.verdict`): slot_tolerance_m,
                 settle_window_s, stall_speed_m_s, stall_window_s, divergence_m
``[disturbance]`` wind, sine_amplitude, sine_freq_hz, gust_std, gust_tau_s (accelerations, m/s^2)

Bounds, so that a valid scenario can be run (``zenswarm scenario check``, ``sim`` and ``up``
agree, all three load through here): ``scenario.seed`` in [0, 2**63 - 1]; at most
:data:`MAX_CONTROL_TICKS` (10 million) control ticks and at least one; at most
:data:`MAX_SUBSTEPS` (1000) physics sub-steps per tick; control rate at most 1 MHz; at most
:data:`MAX_UAV_TICKS` (50 million) UAV-ticks; the sim time within the wire's 10 days.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ScenarioError
from .geometry import obstacle_clearance
from .wire import MAX_T_NS

__all__ = [
    "Obstacle",
    "Timing",
    "LeaderConfig",
    "GraphConfig",
    "GeneratorConfig",
    "EsoConfig",
    "ControllerConfig",
    "VehicleConfig",
    "DisturbanceConfig",
    "MissionConfig",
    "CRAZYFLIE_RADIUS_M",
    "Scenario",
    "FailsafeConfig",
    "failsafe_config",
    "load_scenario",
    "scenario_from_dict",
    "scenario_to_dict",
    "formation_radius",
    "MAX_SEED",
    "MAX_CONTROL_TICKS",
    "MAX_SUBSTEPS",
    "MAX_CONTROL_RATE_HZ",
    "MAX_UAV_TICKS",
    "check_seed",
]

# ----------------------------------------------------------------------------- bounds
# Bounds that keep a valid scenario runnable: every one of them is checked on load, so
# `zenswarm scenario check`, `zenswarm sim` and `zenswarm up` agree on what is valid.

MAX_SEED = 2**63 - 1
"""Largest ``scenario.seed`` (and ``--seed``): the seed travels in the mission message and the
recording's metadata as a signed 64-bit integer."""

MAX_CONTROL_TICKS = 10_000_000
"""Most control ticks in a mission (``time_limit_s * control_rate_hz``): 27.8 h at 100 Hz."""

MAX_SUBSTEPS = 1000
"""Most physics sub-steps per control tick (``physics_rate_hz / control_rate_hz``)."""

MAX_CONTROL_RATE_HZ = 1e6
"""Fastest control rate: a tick of at least 1 us (sim time travels as integer nanoseconds)."""

MAX_UAV_TICKS = 50_000_000
"""Most UAV-ticks (``N * ticks``): the flight's time series, about 180 bytes per UAV and tick,
is held in memory (9 GB at this bound)."""


@dataclass(frozen=True)
class Obstacle:
    """Vertical cylinder capped by an upper hemisphere (paper, Remark 1).

    center: (3,) m, centre of the cylinder base c = [x_c, y_c, z_c]; radius r_o > 0 m;
    height h_o > 0 m (cylinder part; the cap adds r_o above it).
    """

    center: tuple[float, float, float]
    radius: float
    height: float


@dataclass(frozen=True)
class Timing:
    control_rate_hz: float = 100.0
    physics_rate_hz: float = 1000.0
    time_limit_s: float = 70.0
    settle_time_s: float = 30.0
    goal_tolerance_m: float = 0.05

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


@dataclass(frozen=True)
class LeaderConfig:
    """Virtual leader and AAPF parameters, eqs 8-15."""

    start: tuple[float, float, float]
    goal: tuple[float, float, float]
    k_att: float
    k_rep_min: float
    k_rep_max: float
    d0: float
    adaptive: bool = True
    k_rep_fixed: float = 1.0
    speed_limit: float = 0.0  # m/s; 0 means off (fidelity to the paper)


@dataclass(frozen=True)
class GraphConfig:
    """Communication graph among followers: adjacency A (N, N), pinning b (N,)."""

    adjacency: tuple[tuple[float, ...], ...]
    pinning: tuple[float, ...]

    def neighbours(self, i: int) -> list[int]:
        """0-based indices j with a_ij > 0 for 0-based agent index i."""
        return [j for j, a in enumerate(self.adjacency[i]) if a > 0]


@dataclass(frozen=True)
class GeneratorConfig:
    mu1: float = 0.1
    mu2: float = 2.0


@dataclass(frozen=True)
class EsoConfig:
    beta: tuple[float, float, float] = (15.0, 75.0, 125.0)
    enabled: bool = True


@dataclass(frozen=True)
class ControllerConfig:
    kp: tuple[float, float, float] = (4.5, 4.5, 5.4)
    kd: tuple[float, float, float] = (5.0, 5.0, 3.0)
    yaw: float = 0.0  # desired yaw psi_d, rad


CRAZYFLIE_RADIUS_M = 0.0397 + 0.0231
"""Contact radius of a Crazyflie 2.1, m: motor arm 0.0397 m plus propeller radius 0.0231 m
(gym-pybullet-drones ``cf2x.urdf``: arm="0.0397", prop_radius="2.31348e-2"), i.e. the sphere that
holds the propeller discs; the datasheet's footprint is 92 x 92 mm (motor to motor)."""


@dataclass(frozen=True)
class VehicleConfig:
    """Optional overrides of :class:`plant.params.QuadParams`; ``None`` keeps the default.

    ``radius``: the vehicle's contact radius, m, used by the verdict (obstacle contact when a
    UAV's clearance is below it, UAV-UAV contact below twice it); ``None``: a Crazyflie 2.1's.
    """

    mass: float | None = None
    inertia: tuple[float, float, float] | None = None
    max_thrust: float | None = None
    max_tilt: float | None = None
    radius: float | None = None


@dataclass(frozen=True)
class MissionConfig:
    """How a flight is judged (:mod:`zenswarm.verdict`).

    slot_tolerance_m: every UAV must end within this distance of its slot q0_goal + h_i, m ...
    settle_window_s: ... for this long at the end of the flight, s.
    stall_speed_m_s, stall_window_s: the leader is stalled (a local minimum of the AAPF) when it
    moves less than stall_speed * stall_window over a window while away from the goal and
    within d0 of an obstacle; the run then ends early.
    divergence_m: a UAV farther than this from its reference q*_i no longer tracks it (it fell, or
    was blown away): it has diverged, and the run ends early.
    """

    slot_tolerance_m: float = 0.10
    settle_window_s: float = 3.0
    stall_speed_m_s: float = 0.01
    stall_window_s: float = 5.0
    divergence_m: float = 5.0


@dataclass(frozen=True)
class DisturbanceConfig:
    """Lumped translational disturbance d_p (eq. 1) as an acceleration, m/s^2, ENU.

    d_p(t) = wind + sine_amplitude * sin(2 pi sine_freq_hz t) + gust(t), where gust is a
    first-order Gauss-Markov process with stationary std ``gust_std`` and time constant
    ``gust_tau_s``, driven by the scenario's seeded generator. ``attitude_std`` adds white
    torque noise d_a as an angular acceleration, rad/s^2.
    """

    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sine_amplitude: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sine_freq_hz: float = 0.0
    gust_std: float = 0.0
    gust_tau_s: float = 1.0
    attitude_std: float = 0.0

    @property
    def active(self) -> bool:
        return bool(
            any(self.wind) or any(self.sine_amplitude) or self.gust_std > 0 or self.attitude_std > 0
        )


@dataclass(frozen=True)
class Scenario:
    name: str
    timing: Timing
    leader: LeaderConfig
    obstacles: tuple[Obstacle, ...]
    offsets: tuple[tuple[float, float, float], ...]
    initial_positions: tuple[tuple[float, float, float], ...]
    graph: GraphConfig
    generator: GeneratorConfig = field(default_factory=GeneratorConfig)
    eso: EsoConfig = field(default_factory=EsoConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)
    description: str = ""
    seed: int = 0
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def n(self) -> int:
        """Number of follower UAVs N."""
        return len(self.offsets)

    @property
    def vehicle_radius(self) -> float:
        """The UAVs' contact radius, m (``vehicle.radius`` or a Crazyflie 2.1's)."""
        return CRAZYFLIE_RADIUS_M if self.vehicle.radius is None else self.vehicle.radius

    @property
    def r_f(self) -> float:
        """Formation-enclosing sphere radius r_f = max_i ||h_i||, m."""
        return formation_radius(self.offsets)

    def with_changes(self, **changes: Any) -> "Scenario":
        """A copy with top-level fields replaced (validated again)."""
        new = replace(self, **changes)
        validate(new)
        return new


def formation_radius(offsets: Any) -> float:
    """r_f = max_i ||h_i||_2 for offsets of shape (N, 3), m."""
    h = np.asarray(offsets, dtype=float)
    return float(np.max(np.linalg.norm(h, axis=1))) if len(h) else 0.0


# ----------------------------------------------------------------------------- parsing helpers


def check_seed(value: Any, field: str = "scenario.seed") -> int:
    """``value`` as a seed: an integer in [0, :data:`MAX_SEED`]; else :class:`ScenarioError`
    naming ``field`` (``scenario.seed``, ``--seed``). The one check of every seed zenswarm takes."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ScenarioError(field, f"expected a non-negative integer, got {value!r}")
    v = int(value)
    if not 0 <= v <= MAX_SEED:
        raise ScenarioError(field, f"expected a non-negative integer <= 2**63 - 1 ({MAX_SEED}), got {v}")
    return v


def _finite(path: str, x: Any) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise ScenarioError(path, f"expected a number, got {type(x).__name__} {x!r}")
    try:
        v = float(x)
    except OverflowError:  # TOML integers are unbounded in tomllib; float(10**400) overflows
        raise ScenarioError(path, f"must be finite, got an integer too large for a float ({len(str(x))} digits)") from None
    if not math.isfinite(v):
        raise ScenarioError(path, f"must be finite, got {x!r}")
    return v


def _positive(path: str, x: Any) -> float:
    v = _finite(path, x)
    if v <= 0:
        raise ScenarioError(path, f"must be > 0, got {v}")
    return v


def _nonneg(path: str, x: Any) -> float:
    v = _finite(path, x)
    if v < 0:
        raise ScenarioError(path, f"must be >= 0, got {v}")
    return v


def _vec(path: str, x: Any, n: int = 3) -> tuple[float, ...]:
    if not isinstance(x, (list, tuple)):
        raise ScenarioError(path, f"expected a list of {n} numbers, got {type(x).__name__}")
    if len(x) != n:
        raise ScenarioError(path, f"expected {n} numbers, got {len(x)}")
    return tuple(_finite(f"{path}[{k}]", v) for k, v in enumerate(x))


def _matrix(path: str, x: Any, rows: int | None, cols: int) -> tuple[tuple[float, ...], ...]:
    if not isinstance(x, (list, tuple)):
        raise ScenarioError(path, f"expected a list of rows, got {type(x).__name__}")
    if rows is not None and len(x) != rows:
        raise ScenarioError(path, f"expected {rows} rows, got {len(x)}")
    return tuple(_vec(f"{path}[{r}]", row, cols) for r, row in enumerate(x))


def _bool(path: str, x: Any) -> bool:
    if not isinstance(x, bool):
        raise ScenarioError(path, f"expected true or false, got {x!r}")
    return x


def _check_keys(path: str, table: Any, allowed: set[str], required: set[str] = frozenset()) -> dict:
    if not isinstance(table, dict):
        raise ScenarioError(path, f"expected a table, got {type(table).__name__}")
    for k in table:
        if k not in allowed:
            raise ScenarioError(f"{path}.{k}" if path else k, f"unknown key (allowed: {', '.join(sorted(allowed))})")
    for k in required:
        if k not in table:
            raise ScenarioError(f"{path}.{k}" if path else k, "missing required key")
    return table


_SECTIONS = {
    "scenario",
    "timing",
    "leader",
    "obstacles",
    "formation",
    "graph",
    "generator",
    "eso",
    "controller",
    "vehicle",
    "disturbance",
    "mission",
}

# Sections that later subsystems own; they are parsed by those subsystems and kept verbatim in
# ``Scenario.extra`` (still validated there). Registered here so unknown keys stay an error.
EXTRA_SECTIONS: set[str] = {"faults", "failsafe", "restart", "mavlink", "network"}


def scenario_from_dict(d: dict[str, Any]) -> Scenario:
    """Build and validate a :class:`Scenario` from a parsed TOML document."""
    _check_keys("", d, _SECTIONS | EXTRA_SECTIONS, {"leader", "obstacles", "formation", "graph"})

    sc = _check_keys("scenario", d.get("scenario", {}), {"name", "description", "seed"})
    name = sc.get("name", "scenario")
    if not isinstance(name, str) or not name:
        raise ScenarioError("scenario.name", "expected a non-empty string")
    desc = sc.get("description", "")
    if not isinstance(desc, str):
        raise ScenarioError("scenario.description", "expected a string")
    seed = check_seed(sc.get("seed", 0), "scenario.seed")

    t = _check_keys(
        "timing",
        d.get("timing", {}),
        {f.name for f in fields(Timing)},
    )
    timing = Timing(**{k: _positive(f"timing.{k}", v) for k, v in t.items()})

    ld = _check_keys(
        "leader",
        d["leader"],
        {f.name for f in fields(LeaderConfig)},
        {"start", "goal", "k_att", "k_rep_min", "k_rep_max", "d0"},
    )
    leader = LeaderConfig(
        start=_vec("leader.start", ld["start"]),
        goal=_vec("leader.goal", ld["goal"]),
        k_att=_positive("leader.k_att", ld["k_att"]),
        k_rep_min=_positive("leader.k_rep_min", ld["k_rep_min"]),
        k_rep_max=_positive("leader.k_rep_max", ld["k_rep_max"]),
        d0=_positive("leader.d0", ld["d0"]),
        adaptive=_bool("leader.adaptive", ld.get("adaptive", True)),
        k_rep_fixed=_positive("leader.k_rep_fixed", ld.get("k_rep_fixed", 1.0)),
        speed_limit=_nonneg("leader.speed_limit", ld.get("speed_limit", 0.0)),
    )

    obs_raw = d["obstacles"]
    if not isinstance(obs_raw, list):
        raise ScenarioError("obstacles", "expected an array of tables ([[obstacles]])")
    obstacles = []
    for k, o in enumerate(obs_raw):
        p = f"obstacles[{k}]"
        _check_keys(p, o, {"center", "radius", "height"}, {"center", "radius", "height"})
        obstacles.append(
            Obstacle(
                center=_vec(f"{p}.center", o["center"]),
                radius=_positive(f"{p}.radius", o["radius"]),
                height=_positive(f"{p}.height", o["height"]),
            )
        )

    fm = _check_keys("formation", d["formation"], {"offsets", "initial_positions"}, {"offsets", "initial_positions"})
    offsets = _matrix("formation.offsets", fm["offsets"], None, 3)
    n = len(offsets)
    if n == 0:
        raise ScenarioError("formation.offsets", "at least one UAV is required")
    initial = _matrix("formation.initial_positions", fm["initial_positions"], n, 3)

    gr = _check_keys("graph", d["graph"], {"adjacency", "pinning"}, {"adjacency", "pinning"})
    graph = GraphConfig(
        adjacency=_matrix("graph.adjacency", gr["adjacency"], n, n),
        pinning=_vec("graph.pinning", gr["pinning"], n),
    )

    g = _check_keys("generator", d.get("generator", {}), {"mu1", "mu2"})
    generator = GeneratorConfig(**{k: _positive(f"generator.{k}", v) for k, v in g.items()})

    e = _check_keys("eso", d.get("eso", {}), {"beta", "enabled"})
    eso = EsoConfig(
        beta=tuple(_positive(f"eso.beta[{k}]", v) for k, v in enumerate(_vec("eso.beta", e.get("beta", [15.0, 75.0, 125.0])))),
        enabled=_bool("eso.enabled", e.get("enabled", True)),
    )

    c = _check_keys("controller", d.get("controller", {}), {"kp", "kd", "yaw"})
    controller = ControllerConfig(
        kp=tuple(_positive(f"controller.kp[{k}]", v) for k, v in enumerate(_vec("controller.kp", c.get("kp", [4.5, 4.5, 5.4])))),
        kd=tuple(_positive(f"controller.kd[{k}]", v) for k, v in enumerate(_vec("controller.kd", c.get("kd", [5.0, 5.0, 3.0])))),
        yaw=_finite("controller.yaw", c.get("yaw", 0.0)),
    )

    vh = _check_keys("vehicle", d.get("vehicle", {}), {f.name for f in fields(VehicleConfig)})
    vehicle = VehicleConfig(
        mass=_positive("vehicle.mass", vh["mass"]) if "mass" in vh else None,
        inertia=tuple(_positive(f"vehicle.inertia[{k}]", v) for k, v in enumerate(_vec("vehicle.inertia", vh["inertia"]))) if "inertia" in vh else None,
        max_thrust=_positive("vehicle.max_thrust", vh["max_thrust"]) if "max_thrust" in vh else None,
        max_tilt=_positive("vehicle.max_tilt", vh["max_tilt"]) if "max_tilt" in vh else None,
        radius=_positive("vehicle.radius", vh["radius"]) if "radius" in vh else None,
    )

    ms = _check_keys("mission", d.get("mission", {}), {f.name for f in fields(MissionConfig)})
    mission = MissionConfig(**{k: _positive(f"mission.{k}", v) for k, v in ms.items()})

    ds = _check_keys("disturbance", d.get("disturbance", {}), {f.name for f in fields(DisturbanceConfig)})
    disturbance = DisturbanceConfig(
        wind=_vec("disturbance.wind", ds.get("wind", [0.0, 0.0, 0.0])),
        sine_amplitude=_vec("disturbance.sine_amplitude", ds.get("sine_amplitude", [0.0, 0.0, 0.0])),
        sine_freq_hz=_nonneg("disturbance.sine_freq_hz", ds.get("sine_freq_hz", 0.0)),
        gust_std=_nonneg("disturbance.gust_std", ds.get("gust_std", 0.0)),
        gust_tau_s=_positive("disturbance.gust_tau_s", ds.get("gust_tau_s", 1.0)),
        attitude_std=_nonneg("disturbance.attitude_std", ds.get("attitude_std", 0.0)),
    )

    extra = {k: d[k] for k in EXTRA_SECTIONS if k in d}
    for k, v in extra.items():
        if not isinstance(v, dict):
            raise ScenarioError(k, f"expected a table, got {type(v).__name__}")

    scen = Scenario(
        name=name,
        description=desc,
        seed=seed,
        timing=timing,
        leader=leader,
        obstacles=tuple(obstacles),
        offsets=offsets,
        initial_positions=initial,
        graph=graph,
        generator=generator,
        eso=eso,
        controller=controller,
        vehicle=vehicle,
        disturbance=disturbance,
        mission=mission,
        extra=extra,
    )
    validate(scen)
    return scen


def _validate_timing(s: Scenario) -> None:
    """The rates and the time limit fit the bounds above (a run that could not allocate or whose
    sim time would not fit the wire is refused on load, naming the field)."""
    tm = s.timing
    check_seed(s.seed, "scenario.seed")
    if tm.control_rate_hz > MAX_CONTROL_RATE_HZ:
        raise ScenarioError("timing.control_rate_hz", f"must be <= {MAX_CONTROL_RATE_HZ:g} Hz, got {tm.control_rate_hz:g}")
    ratio = tm.physics_rate_hz / tm.control_rate_hz
    if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
        raise ScenarioError(
            "timing.physics_rate_hz",
            f"must be a whole multiple of timing.control_rate_hz ({tm.physics_rate_hz} / {tm.control_rate_hz} = {ratio})",
        )
    if round(ratio) > MAX_SUBSTEPS:
        raise ScenarioError(
            "timing.physics_rate_hz",
            f"at most {MAX_SUBSTEPS} physics sub-steps per control tick, got {tm.physics_rate_hz:g} / "
            f"{tm.control_rate_hz:g} = {round(ratio)}",
        )
    ticks = tm.time_limit_s * tm.control_rate_hz  # a float: never an absurd int or array first
    if ticks > MAX_CONTROL_TICKS:
        raise ScenarioError(
            "timing.time_limit_s",
            f"{tm.time_limit_s:g} s at {tm.control_rate_hz:g} Hz is {ticks:.3g} control ticks; at most "
            f"{MAX_CONTROL_TICKS:,} ({MAX_CONTROL_TICKS / tm.control_rate_hz:g} s at this rate)",
        )
    if tm.n_ticks < 1:
        raise ScenarioError(
            "timing.time_limit_s", f"{tm.time_limit_s:g} s is less than one control tick ({tm.dt:g} s)"
        )
    if tm.n_ticks * s.n > MAX_UAV_TICKS:
        raise ScenarioError(
            "timing.time_limit_s",
            f"{s.n} UAVs x {tm.n_ticks:,} ticks is more than {MAX_UAV_TICKS:,} UAV-ticks (the flight's time series "
            f"is held in memory); at most {MAX_UAV_TICKS // s.n / tm.control_rate_hz:g} s with {s.n} UAVs at this rate",
        )
    # the leader publishes a few ticks ahead of the plant; every sim time must fit the wire's bound
    if (tm.n_ticks + 16) * tm.dt > MAX_T_NS / 1e9:
        raise ScenarioError(
            "timing.time_limit_s",
            f"{tm.time_limit_s:g} s of sim time (plus 16 ticks of {tm.dt:g} s) exceeds the wire's bound of "
            f"{MAX_T_NS / 1e9:g} s (10 days)",
        )


def validate(s: Scenario) -> None:
    """Cross-field checks; raises :class:`ScenarioError` naming the field."""
    _validate_timing(s)
    if s.leader.k_rep_max < s.leader.k_rep_min:
        raise ScenarioError("leader.k_rep_max", f"must be >= leader.k_rep_min ({s.leader.k_rep_max} < {s.leader.k_rep_min})")

    A = np.asarray(s.graph.adjacency, dtype=float)
    b = np.asarray(s.graph.pinning, dtype=float)
    n = s.n
    if np.any(A < 0):
        i, j = np.argwhere(A < 0)[0]
        raise ScenarioError(f"graph.adjacency[{i}][{j}]", "weights must be >= 0")
    if not np.array_equal(A, A.T):
        i, j = np.argwhere(A != A.T)[0]
        raise ScenarioError(
            "graph.adjacency", f"must be symmetric (undirected graph): a[{i}][{j}]={A[i, j]} but a[{j}][{i}]={A[j, i]}"
        )
    if np.any(np.diag(A) != 0):
        i = int(np.flatnonzero(np.diag(A))[0])
        raise ScenarioError(f"graph.adjacency[{i}][{i}]", "diagonal must be 0 (no self loops)")
    if np.any(b < 0):
        raise ScenarioError("graph.pinning", "weights must be >= 0")
    M = np.diag(A.sum(axis=1)) - A + np.diag(b)
    lam_min = float(np.min(np.linalg.eigvalsh(M))) if n else 0.0
    if lam_min <= 1e-12:
        raise ScenarioError(
            "graph.pinning",
            "the leader reaches no spanning tree: M = L + B is not positive definite "
            f"(smallest eigenvalue {lam_min:.3g}); pin at least one UAV in every connected component",
        )

    # Start and goal must be outside every obstacle inflated by r_f (cylinder + cap surfaces).


    r_f = s.r_f
    for key, p in (("leader.start", s.leader.start), ("leader.goal", s.leader.goal)):
        for k, ob in enumerate(s.obstacles):
            c = float(obstacle_clearance(np.asarray(p, dtype=float), ob))
            if c - r_f <= 0:
                raise ScenarioError(
                    key,
                    f"lies inside obstacles[{k}] inflated by the formation radius r_f={r_f:.3f} m "
                    f"(clearance to the surface {c:.3f} m)",
                )
    _validate_extra(s)


def _validate_extra(s: Scenario) -> None:
    """Sections owned by subsystems are validated on load too, so errors show up at once."""
    if "faults" in s.extra:
        from .faults import plan_from_scenario

        plan_from_scenario(s.extra["faults"], s.seed, s.n)
    if "failsafe" in s.extra:
        failsafe_config(s.extra["failsafe"])
    if "restart" in s.extra:
        from .policy import restart_policy

        restart_policy(s.extra["restart"])


@dataclass(frozen=True)
class FailsafeConfig:
    """hover_after_s < land_after_s, s of sim time without a fresh command; land_speed m/s;
    hold gains kp (1/s^2), kd (1/s); ground_z m (motors off below it while landing)."""

    hover_after_s: float = 0.5
    land_after_s: float = 5.0
    land_speed: float = 0.3
    kp: float = 4.0
    kd: float = 3.0
    ground_z: float = 0.03


def failsafe_config(section: dict[str, Any] | None) -> FailsafeConfig:
    """Parse the scenario's ``[failsafe]`` table (``Scenario.extra``); errors name the field."""
    if section is None:
        return FailsafeConfig()
    allowed = set(FailsafeConfig.__dataclass_fields__)
    vals: dict[str, float] = {}
    for k, v in section.items():
        if k not in allowed:
            raise ScenarioError(f"failsafe.{k}", f"unknown key (allowed: {', '.join(sorted(allowed))})")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ScenarioError(f"failsafe.{k}", f"expected a finite number, got {v!r}")
        if k != "ground_z" and v <= 0:
            raise ScenarioError(f"failsafe.{k}", f"must be > 0, got {v}")
        vals[k] = float(v)
    cfg = FailsafeConfig(**vals)
    if cfg.land_after_s <= cfg.hover_after_s:
        raise ScenarioError("failsafe.land_after_s", f"must be > failsafe.hover_after_s ({cfg.land_after_s} <= {cfg.hover_after_s})")
    return cfg


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file.

    Raises :class:`ScenarioError` (field ``file``) when the file is missing or not valid TOML.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise ScenarioError("file", f"scenario file not found: {p}") from None
    except OSError as e:
        raise ScenarioError("file", f"cannot read {p}: {e}") from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ScenarioError("file", f"{p} is not valid TOML: {e}") from None
    return scenario_from_dict(doc)


def scenario_to_dict(s: Scenario) -> dict[str, Any]:
    """The inverse of :func:`scenario_from_dict` (for the mission message and MCAP metadata)."""
    veh = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(s.vehicle).items() if v is not None}
    d: dict[str, Any] = {
        "scenario": {"name": s.name, "description": s.description, "seed": s.seed},
        "timing": dict(vars(s.timing)),
        "leader": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(s.leader).items()},
        "obstacles": [{"center": list(o.center), "radius": o.radius, "height": o.height} for o in s.obstacles],
        "formation": {"offsets": [list(h) for h in s.offsets], "initial_positions": [list(q) for q in s.initial_positions]},
        "graph": {"adjacency": [list(r) for r in s.graph.adjacency], "pinning": list(s.graph.pinning)},
        "generator": dict(vars(s.generator)),
        "eso": {"beta": list(s.eso.beta), "enabled": s.eso.enabled},
        "controller": {"kp": list(s.controller.kp), "kd": list(s.controller.kd), "yaw": s.controller.yaw},
        "disturbance": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(s.disturbance).items()},
        "mission": dict(vars(s.mission)),
    }
    if veh:
        d["vehicle"] = veh
    d.update({k: v for k, v in s.extra.items()})
    return d

"""Scenario configuration: one TOML file loaded into a frozen :class:`Scenario` and validated on load.

The format is declared once, as typed msgspec Structs, in :mod:`zenswarm.schema` (re-exported
here): the schema rejects unknown sections and keys and checks types and ranges; this module adds
the checks that need the whole scenario (graph Lemma 1, start/goal clearance, run-size bounds, the
subsystems' tables against N).

Every error is a :class:`zenswarm.errors.ScenarioError` whose ``field`` names the offending key as
a dotted path (``leader.goal``, ``graph.adjacency``, ``obstacles[1].radius``). Units are SI
throughout; positions are in the inertial ENU frame (z up), as in the paper.

The sections and their meaning (see ``compose/scenarios/paper_example1.toml`` for a full file):

``[scenario]``   name, description, seed
``[timing]``     control_rate_hz, physics_rate_hz, time_limit_s, settle_time_s, goal_tolerance_m
``[leader]``     start, goal, k_att, k_rep_min, k_rep_max, d0, adaptive, k_rep_fixed, speed_limit,
                 planner (plug-in name, :mod:`zenswarm.scenario.plugins`) and ``[leader.params]`` (its parameters)
``[[obstacles]]`` center (base centre), radius, height: cylinder capped by a hemisphere (Remark 1)
``[formation]``  offsets h_i (N, 3), initial_positions q_i(0) (N, 3)
``[graph]``      the graph A as adjacency (N, N) symmetric, or edges [[i, j, a_ij], ...], or a topology
                 by name (ring, star, complete, knn with k); pinning b (N,) (:mod:`zenswarm.scenario.graph`)
``[generator]``  mu1, mu2 (eqs 16-17)
``[eso]``        beta = [beta1, beta2, beta3], enabled (eq. 27)
``[controller]`` kp (3,), kd (3,), yaw (eq. 28 and the inversion after it)
``[agents]``     controller (plug-in name, default ``paper``) and ``[agents.params]`` (its parameters)
``[plant]``      model (plant model plug-in name, default ``quadrotor``) and ``[plant.params]`` (its parameters)
``[vehicle]``    optional overrides of the Crazyflie 2.1 parameters (see :mod:`zenswarm.vehicle.params`), and
                 radius (the contact radius the verdict uses; default :data:`CRAZYFLIE_RADIUS_M`)
``[mission]``    how the flight is judged (:mod:`zenswarm.judge.verdict`): slot_tolerance_m,
                 settle_window_s, stall_speed_m_s, stall_window_s, divergence_m
``[disturbance]`` wind, sine_amplitude, sine_freq_hz, gust_std, gust_tau_s (accelerations, m/s^2)
``[faults]``     link faults (``Scenario.faults``, :func:`zenswarm.link.config.plan_from_scenario`)
``[failsafe]``   the plant's command-loss failsafe (``Scenario.failsafe``, :func:`failsafe_config`)
``[restart]``    the supervisor's restart backoff (``Scenario.restart``, :func:`zenswarm.compose.policy.restart_policy`)
``[mavlink]``    MAVLink bridge and vehicles (``Scenario.mavlink``, :func:`zenswarm.vehicle.autopilot.mavlink_settings`)
``[crazyflie]``  Crazyflie bridge (``Scenario.crazyflie``, :func:`zenswarm.vehicle.crazyflie_settings.crazyflie_settings`)

Any other section or key is an error naming it.

Bounds, so that a valid scenario can be run (``zenswarm scenario check``, ``sim`` and ``up``
agree, all three load through here): ``scenario.seed`` in [0, 2**63 - 1]; at most
:data:`MAX_CONTROL_TICKS` (10 million) control ticks and at least one; at most
:data:`MAX_SUBSTEPS` (1000) physics sub-steps per tick; control rate at most 1 MHz; at most
:data:`MAX_UAV_TICKS` (50 million) UAV-ticks; the sim time within the wire's 10 days.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from zenswarm.bus.wire import MAX_T_NS
from zenswarm.errors import ScenarioError
from zenswarm.scenario.graph import CommGraph
from zenswarm.schema import (
    MAX_SEED,
    AgentsConfig,
    ControllerConfig,
    CrazyflieTable,
    DisturbanceConfig,
    EsoConfig,
    FailsafeConfig,
    FaultsTable,
    GeneratorConfig,
    GraphConfig,
    LeaderConfig,
    MavlinkTable,
    MissionConfig,
    Obstacle,
    PlantConfig,
    RestartTable,
    ScenarioFile,
    Timing,
    VehicleConfig,
    check_seed,
    convert,
    to_builtins,
)
from zenswarm.vehicle.geometry import obstacle_clearance

__all__ = [
    "Obstacle",
    "Timing",
    "LeaderConfig",
    "GraphConfig",
    "GeneratorConfig",
    "EsoConfig",
    "eso_spectral_radius",
    "ControllerConfig",
    "AgentsConfig",
    "PlantConfig",
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

MAX_CONTROL_TICKS = 10_000_000
"""Most control ticks in a mission (``time_limit_s * control_rate_hz``): 27.8 h at 100 Hz."""

MAX_SUBSTEPS = 1000
"""Most physics sub-steps per control tick (``physics_rate_hz / control_rate_hz``)."""

MAX_CONTROL_RATE_HZ = 1e6
"""Fastest control rate: a tick of at least 1 us (sim time travels as integer nanoseconds)."""

MAX_UAV_TICKS = 50_000_000
"""Most UAV-ticks (``N * ticks``): the flight's time series, about 180 bytes per UAV and tick,
is held in memory (9 GB at this bound)."""


CRAZYFLIE_RADIUS_M = 0.0397 + 0.0231
"""Contact radius of a Crazyflie 2.1, m: motor arm 0.0397 m plus propeller radius 0.0231 m
(gym-pybullet-drones ``cf2x.urdf``: arm="0.0397", prop_radius="2.31348e-2"), i.e. the sphere that
holds the propeller discs; the datasheet's footprint is 92 x 92 mm (motor to motor)."""


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
    agents: AgentsConfig = field(default_factory=AgentsConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)
    mission: MissionConfig = field(default_factory=MissionConfig)
    description: str = ""
    seed: int = 0
    faults: FaultsTable | None = None
    failsafe: FailsafeConfig | None = None
    restart: RestartTable | None = None
    mavlink: MavlinkTable | None = None
    crazyflie: CrazyflieTable | None = None

    @property
    def n(self) -> int:
        """Number of follower UAVs N."""
        return len(self.offsets)

    @cached_property
    def comm_graph(self) -> CommGraph:
        """The graph A and pinning b as neighbour lists (:class:`zenswarm.scenario.graph.CommGraph`),
        built and checked once per scenario from whichever form ``[graph]`` has: O(N + E) for
        ``edges`` and the topologies but knn's distances, O(N^2) for a dense ``adjacency``.
        Raises ScenarioError naming the field (on load: :func:`validate` builds it)."""
        g = self.graph
        if g.adjacency is not None:
            cg = CommGraph.from_dense(g.adjacency, g.pinning)
        elif g.edges is not None:
            cg = CommGraph.from_edges(g.edges, self.n, g.pinning)
        else:
            assert g.topology is not None, "the schema requires one form"
            cg = CommGraph.from_topology(g.topology, g.k, self.offsets_array, g.pinning)
        cg.check_pinning()
        return cg

    @cached_property
    def offsets_array(self) -> np.ndarray:
        """Formation offsets h (N, 3) m as one read-only float64 array (built once)."""
        h = np.array(self.offsets, dtype=float).reshape(-1, 3)
        h.setflags(write=False)
        return h

    def neighbours(self, i: int) -> list[int]:
        """0-based neighbours j (a_ij > 0) of 0-based UAV i, increasing."""
        return self.comm_graph.neighbours(i)

    @property
    def vehicle_radius(self) -> float:
        """The UAVs' contact radius, m (``vehicle.radius`` or a Crazyflie 2.1's)."""
        return CRAZYFLIE_RADIUS_M if self.vehicle.radius is None else self.vehicle.radius

    @property
    def r_f(self) -> float:
        """Formation-enclosing sphere radius r_f = max_i ||h_i||, m."""
        return formation_radius(self.offsets)

    def with_changes(self, **changes: Any) -> Scenario:
        """A copy with top-level fields replaced (validated again)."""
        new = replace(self, **changes)
        validate(new)
        return new


def formation_radius(offsets: Any) -> float:
    """r_f = max_i ||h_i||_2 for offsets of shape (N, 3), m."""
    h = np.asarray(offsets, dtype=float)
    return float(np.max(np.linalg.norm(h, axis=1))) if len(h) else 0.0


# ----------------------------------------------------------------------------- parsing




def scenario_from_dict(d: dict[str, Any]) -> Scenario:
    """Build and validate a :class:`Scenario` from a parsed TOML document (the schema of
    :mod:`zenswarm.schema`, then the cross-field checks of :func:`validate`)."""
    doc = convert(d, ScenarioFile)
    scen = Scenario(
        name=doc.scenario.name,
        description=doc.scenario.description,
        seed=doc.scenario.seed,
        timing=doc.timing,
        leader=doc.leader,
        obstacles=doc.obstacles,
        offsets=doc.formation.offsets,
        initial_positions=doc.formation.initial_positions,
        graph=doc.graph,
        generator=doc.generator,
        eso=doc.eso,
        controller=doc.controller,
        agents=doc.agents,
        plant=doc.plant,
        vehicle=doc.vehicle,
        disturbance=doc.disturbance,
        mission=doc.mission,
        faults=doc.faults,
        failsafe=doc.failsafe,
        restart=doc.restart,
        mavlink=doc.mavlink,
        crazyflie=doc.crazyflie,
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


def eso_spectral_radius(beta: Any, dt: float) -> float:
    """Spectral radius of the observer's discrete error dynamics, eq. (27) as
    :func:`zenswarm.agents.eso.eso_step` steps it (explicit Euler every control period ``dt``, s):
    per axis the estimation error e = (q - q_hat, v - v_hat, d - d_hat) follows
    e_{k+1} = (I + dt A_e) e_k (plus the terms of the true state's own change), A_e = [[-b1, 1, 0],
    [-b2, 0, 1], [-b3, 0, 0]] (the per-axis block of eq. 31). The observer converges iff every
    eigenvalue of I + dt A_e lies inside the unit circle (the radius < 1); then it does for every
    shorter step too (a realtime agent's sub-steps), the Euler disc being convex."""
    b1, b2, b3 = (float(x) for x in beta)
    a_e = np.array([[-b1, 1.0, 0.0], [-b2, 0.0, 1.0], [-b3, 0.0, 0.0]])
    return float(np.max(np.abs(np.linalg.eigvals(np.eye(3) + dt * a_e))))


def _validate_eso(s: Scenario) -> None:
    """``[eso] beta`` must make the discrete observer stable at the control rate
    (:func:`eso_spectral_radius` < 1): gains that cannot converge at the scenario's rate are bad
    input (they would overflow in the first second and end as a non-finite command), not a
    flight to judge."""
    dt = s.timing.dt
    with np.errstate(all="ignore"):
        rho = eso_spectral_radius(s.eso.beta, dt)
    if not rho < 1.0:  # also NaN
        beta = ", ".join(f"{float(b):g}" for b in s.eso.beta)
        raise ScenarioError(
            "eso.beta",
            f"[{beta}] makes the observer (eq. 27, explicit Euler every control tick, dt = {dt:g} s) diverge: the "
            f"eigenvalues of its discrete error dynamics I + dt*A_e must lie inside the unit circle (spectral radius "
            f"< 1), got {rho:.4g}. With bandwidth gains beta = (3w, 3w^2, w^3) (A_e's eigenvalues all at -w) the bound "
            f"is w < 2/dt = {2.0 / dt:g} rad/s; or raise timing.control_rate_hz",
        )


def validate(s: Scenario) -> None:
    """Cross-field checks; raises :class:`ScenarioError` naming the field."""
    _validate_timing(s)
    _validate_eso(s)
    if s.leader.k_rep_max < s.leader.k_rep_min:
        raise ScenarioError("leader.k_rep_max", f"must be >= leader.k_rep_min ({s.leader.k_rep_max} < {s.leader.k_rep_min})")

    s.comm_graph  # noqa: B018 -- builds the graph and checks it (forms, entries, Lemma 1), O(N + E)

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
    """The subsystems' tables are checked against the scenario on load too (durations and process
    names of ``[faults]``, the per-UAV lists of ``[mavlink]``), so errors show up at once."""
    if s.faults is not None:
        from zenswarm.link import plan_from_scenario

        plan_from_scenario(s.faults, s.seed, s.n)
    if s.mavlink is not None:
        from zenswarm.vehicle.autopilot import mavlink_settings

        mavlink_settings(s)
    if s.crazyflie is not None:
        from zenswarm.vehicle.crazyflie_settings import crazyflie_settings

        crazyflie_settings(s)


def failsafe_config(section: FailsafeConfig | dict[str, Any] | None) -> FailsafeConfig:
    """The scenario's ``[failsafe]`` table (``Scenario.failsafe``, or a dict validated by the
    schema; None: the defaults); errors name the field."""
    if section is None:
        return FailsafeConfig()
    if isinstance(section, FailsafeConfig):
        return section
    return convert(section, FailsafeConfig, "failsafe")


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file.

    A relative ``[faults] trace`` path is made relative to the scenario file's directory.
    Raises :class:`ScenarioError` (field ``file``) when the file is missing or not valid TOML.
    """
    return scenario_of_document(read_document(path), path)


def read_document(path: str | Path) -> dict[str, Any]:
    """A scenario file parsed as TOML (not validated: :func:`scenario_of_document`); ScenarioError
    (field ``file``) when it is missing or not valid TOML."""
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
    return doc


def scenario_of_document(doc: dict[str, Any], path: str | Path) -> Scenario:
    """The validated scenario of a document :func:`read_document` read from ``path`` (a relative
    ``[faults] trace`` made relative to the file's directory)."""
    return trace_beside(scenario_from_dict(doc), path)


def trace_in(trace: str, directory: str | Path) -> str:
    """The rule for a ``[faults] trace`` path: a relative one is taken in ``directory`` (the
    scenario file's; made absolute, so it reads the same from any working directory or worker);
    an absolute one as it is."""
    return trace if Path(trace).is_absolute() else str(Path(directory).absolute() / trace)


def document_trace_beside(doc: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """A scenario document (as :func:`read_document` gives it; changed in place and returned) with
    a relative ``faults.trace`` made relative to the directory of the scenario file at ``path``:
    the document of :func:`trace_beside`'s scenario, for a copy of it written elsewhere."""
    faults = doc.get("faults")
    if isinstance(faults, dict) and isinstance(faults.get("trace"), str):
        faults["trace"] = trace_in(faults["trace"], Path(path).parent)
    return doc


def trace_beside(sc: Scenario, path: str | Path) -> Scenario:
    """``sc`` with a relative ``[faults] trace`` made relative to the directory of the scenario
    file at ``path`` (where its author wrote it from); an absolute one, or none, as it is."""
    if sc.faults is None or sc.faults.trace is None or Path(sc.faults.trace).is_absolute():
        return sc
    return replace(sc, faults=msgspec.structs.replace(sc.faults, trace=trace_in(sc.faults.trace, Path(path).parent)))


def scenario_to_dict(s: Scenario) -> dict[str, Any]:
    """The inverse of :func:`scenario_from_dict` (for the mission message and MCAP metadata):
    every key of the flight's tables; of ``[vehicle]`` and the subsystems' tables only the keys set."""
    d: dict[str, Any] = {
        "scenario": {"name": s.name, "description": s.description, "seed": s.seed},
        "timing": to_builtins(s.timing),
        "leader": {k: v for k, v in to_builtins(s.leader).items() if not (k in ("planner", "params") and not v)},
        "obstacles": [to_builtins(o) for o in s.obstacles],
        "formation": {"offsets": [list(h) for h in s.offsets], "initial_positions": [list(q) for q in s.initial_positions]},
        "graph": to_builtins(s.graph, omit_defaults=True),  # the form the file has (a sparse one stays sparse)
        "generator": to_builtins(s.generator),
        "eso": to_builtins(s.eso),
        "controller": to_builtins(s.controller),
        "disturbance": to_builtins(s.disturbance),
        "mission": to_builtins(s.mission),
    }
    agents = to_builtins(s.agents, omit_defaults=True)
    if agents:
        d["agents"] = agents
    plant = {k: v for k, v in to_builtins(s.plant, omit_defaults=True).items() if not (k == "params" and not v)}
    if plant:  # the default model without parameters is not written (scenarios as before plant models)
        d["plant"] = plant
    veh = {k: v for k, v in to_builtins(s.vehicle).items() if v is not None}
    if veh:
        d["vehicle"] = veh
    for name in ("faults", "failsafe", "restart", "mavlink", "crazyflie"):
        table = getattr(s, name)
        if table is not None:
            d[name] = to_builtins(table, omit_defaults=True)
    return d

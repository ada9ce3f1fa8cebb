"""Generate valid scenario files: N UAVs, a formation shape, a topology, pinning and obstacles.

:func:`generate_scenario` returns a TOML-ready ``dict`` with the same structure as
``compose/scenarios/paper_example1.toml``; :func:`to_toml` writes it as TOML text (no external
dependency) so that ``tomllib.loads(to_toml(d)) == d``. The command ``zenswarm scenario generate`` is
:mod:`zenswarm.compose.scenario_generate`.

Geometry (SI units, inertial ENU frame, z up, as in the paper):

* Formation offsets h_i (N, 3) m lie in the horizontal plane, centred on the virtual leader (their
  mean is 0) and with ``spacing`` m between neighbouring UAVs (the smallest pairwise distance):

  - ``circle``: a regular N-gon of circumradius spacing / (2 sin(pi / N)) (chord = spacing);
  - ``v``: a V (chevron) pointing along +x with arms at +-30 deg from -x, ``spacing`` along each
    arm (with 30 deg the first two arm points are also ``spacing`` apart);
  - ``grid``: ceil(sqrt(N)) columns, rows filled in order, ``spacing`` in x and y.

* The virtual leader starts at ``START`` = [0, 0, 0.4] m (the paper's start) and flies a distance
  L = max(3 m, 6 r_f + 1 m) along the paper's start-goal heading (about 30 deg) to a goal 0.2 m
  higher, so bigger formations get proportionally more room.
* Initial positions q_i(0) = start + h_i + jitter, jitter ~ N(0, (0.05 spacing)^2) per axis, clipped
  to +-0.1 spacing, so no two UAVs start closer than about 0.65 spacing.
* Obstacles are capped cylinders standing on the ground (z_c = 0) with radius 0.10-0.25 m and
  cylinder height 0.3-1.0 m (the paper's obstacles are 0.14/0.225 m and 0.4/1 m), centred on the
  start-goal segment (10-90 % of the way) within +-(r_f + 0.5 m) of it. Start and goal keep a
  clearance larger than r_f + d0 (+ the jitter bound at the start) from every obstacle, and any
  two obstacles keep a horizontal gap of at least ``OBSTACLE_GAP`` m.

Randomness: one ``numpy.random.SeedSequence(seed)`` spawns independent generators for the jitter,
the random pinning and the obstacles, so the same arguments always give the same dict, and e.g.
changing ``n_obstacles`` does not move the UAVs.
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np

from zenswarm.errors import ScenarioError
from zenswarm.scenario.config import Obstacle, check_seed, scenario_from_dict
from zenswarm.scenario.graph import TOPOLOGIES, components, topology_neighbours
from zenswarm.vehicle.geometry import obstacle_clearance

__all__ = [
    "SHAPES",
    "TOPOLOGIES",
    "PINNINGS",
    "START",
    "OBSTACLE_GAP",
    "formation_offsets",
    "adjacency_matrix",
    "pinning_vector",
    "connected_components",
    "generate_scenario",
    "to_toml",
]

SHAPES: tuple[str, ...] = ("circle", "v", "grid")
PINNINGS: tuple[str, ...] = ("first", "all", "random")

START: tuple[float, float, float] = (0.0, 0.0, 0.4)
"""Virtual leader start, m (the paper's)."""

GOAL_HEADING_RAD: float = math.atan2(1.4, 2.4)
"""Horizontal start-to-goal heading, rad (the paper's, about 30.3 deg)."""

GOAL_RISE_M: float = 0.2
"""Goal height above the start, m (the paper's: 0.6 - 0.4)."""

OBSTACLE_GAP: float = 0.05
"""Smallest horizontal gap between two obstacle surfaces, m."""

OBSTACLE_RADIUS_RANGE: tuple[float, float] = (0.10, 0.25)
OBSTACLE_HEIGHT_RANGE: tuple[float, float] = (0.3, 1.0)
OBSTACLE_TRIES: int = 1000
"""Candidate draws per obstacle before a layout attempt is abandoned."""
OBSTACLE_LAYOUTS: int = 3
"""Whole-layout attempts before :func:`generate_scenario` gives up."""

RANDOM_PIN_PROBABILITY: float = 0.3
"""Per-UAV pinning probability for ``pinning="random"`` (then at least one per component)."""

# The paper's gains (section Experiments; d0 of example 1) and the example files' timing.
PAPER_LEADER: dict[str, Any] = {"k_att": 0.1, "k_rep_min": 0.05, "k_rep_max": 0.3, "d0": 0.12}
PAPER_GENERATOR: dict[str, Any] = {"mu1": 0.1, "mu2": 2.0}
PAPER_ESO: dict[str, Any] = {"beta": [15.0, 75.0, 125.0], "enabled": True}
PAPER_CONTROLLER: dict[str, Any] = {"kp": [4.5, 4.5, 5.4], "kd": [5.0, 5.0, 3.0], "yaw": 0.0}
GOAL_TOLERANCE_M: float = 0.05

_DIGITS = 6  # generated coordinates are rounded to 1 um so the files stay readable


def _r(x: float, digits: int = _DIGITS) -> float:
    """Round to ``digits`` decimals and turn -0.0 into 0.0 (plain Python float)."""
    return float(round(float(x), digits)) + 0.0


# ----------------------------------------------------------------------------- formation


def formation_offsets(n: int, shape: str = "circle", spacing: float = 0.3) -> np.ndarray:
    """Formation offsets h_i, shape (n, 3), m, in the horizontal plane with mean 0.

    The smallest distance between two offsets equals ``spacing`` (m) for n >= 2 (up to the 1 um
    rounding); n = 1 gives the single offset 0. See the module docstring for the shapes.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if not spacing > 0 or not math.isfinite(spacing):
        raise ValueError(f"spacing must be a finite number > 0 m, got {spacing}")
    if shape not in SHAPES:
        raise ValueError(f"unknown shape {shape!r} (choose from {', '.join(SHAPES)})")
    h = np.zeros((n, 3))
    if n == 1:
        return h
    if shape == "circle":
        radius = spacing / (2.0 * math.sin(math.pi / n))
        ang = 2.0 * math.pi * np.arange(n) / n
        h[:, 0] = radius * np.cos(ang)
        h[:, 1] = radius * np.sin(ang)
    elif shape == "v":
        half = math.radians(30.0)
        for i in range(1, n):
            j = (i + 1) // 2  # position along the arm
            side = 1.0 if i % 2 else -1.0  # odd: left (+y), even: right (-y)
            h[i, 0] = -j * spacing * math.cos(half)
            h[i, 1] = side * j * spacing * math.sin(half)
    else:  # grid
        cols = math.ceil(math.sqrt(n))
        idx = np.arange(n)
        h[:, 0] = -(idx // cols) * spacing  # rows go back along -x
        h[:, 1] = (idx % cols) * spacing
    h[:, :2] -= h[:, :2].mean(axis=0)
    rounded: np.ndarray = np.vectorize(_r)(h)
    return rounded


# ----------------------------------------------------------------------------- graph


def connected_components(adjacency: np.ndarray) -> list[list[int]]:
    """Connected components of the undirected graph with adjacency (N, N) (a_ij > 0 = edge).

    Returns lists of 0-based node indices, each sorted, ordered by their smallest node.
    """
    A = np.asarray(adjacency, dtype=float)
    n = A.shape[0]
    seen = np.zeros(n, dtype=bool)
    comps: list[list[int]] = []
    for root in range(n):
        if seen[root]:
            continue
        stack, comp = [root], []
        seen[root] = True
        while stack:  # bounded: each node is pushed once
            i = stack.pop()
            comp.append(i)
            for j in np.flatnonzero(A[i] > 0):
                if not seen[j]:
                    seen[j] = True
                    stack.append(int(j))
        comps.append(sorted(comp))
    return comps


def adjacency_matrix(offsets: np.ndarray, topology: str = "ring", k: int = 2) -> np.ndarray:
    """Symmetric 0/1 adjacency A (N, N) of a connected graph, zero diagonal: the dense form of
    what a scenario's ``[graph] topology`` names, built from its neighbour lists
    (:func:`zenswarm.scenario.graph.topology_neighbours`, which says how each topology is made;
    ValueError for an unknown topology or a bad k). offsets: (N, 3) m.
    """
    nbr = topology_neighbours(offsets, topology, k)
    A = np.zeros((len(nbr), len(nbr)))
    for i, row in enumerate(nbr):
        A[i, row] = 1.0
    return A


def pinning_vector(adjacency: np.ndarray, pinning: str = "first", rng: np.random.Generator | None = None) -> np.ndarray:
    """Pinning gains b (N,) in {0, 1} such that M = L + B is positive definite (Lemma 1).

    ``first``: UAV 1 (and, should the graph be disconnected, the first UAV of every other
    component); ``all``: every UAV; ``random``: each UAV with probability
    ``RANDOM_PIN_PROBABILITY`` using ``rng``, then one random UAV of every component left without
    a pinned UAV. In every case each connected component has a pinned
    UAV, which is exactly the condition for M to be positive definite.
    """
    A = np.asarray(adjacency, dtype=float)
    return _pinning(connected_components(A), A.shape[0], pinning, rng)


def _pinning(comps: list[list[int]], n: int, pinning: str, rng: np.random.Generator | None) -> np.ndarray:
    """:func:`pinning_vector` from the graph's connected components (sorted lists of 0-based
    nodes, ordered by their smallest node)."""
    if pinning not in PINNINGS:
        raise ValueError(f"unknown pinning {pinning!r} (choose from {', '.join(PINNINGS)})")
    b = np.zeros(n)
    if pinning == "first":
        b[0] = 1.0
    elif pinning == "all":
        b[:] = 1.0
    else:
        if rng is None:
            raise ValueError("pinning='random' needs a numpy Generator rng")
        b[rng.random(n) < RANDOM_PIN_PROBABILITY] = 1.0
    for comp in comps:
        if not np.any(b[comp] > 0):
            pick = comp[0] if pinning != "random" else int(comp[int(rng.integers(len(comp)))])  # type: ignore[union-attr]
            b[pick] = 1.0
    return b


# ----------------------------------------------------------------------------- obstacles


def _clearance(p: np.ndarray, center: np.ndarray, radius: float, height: float) -> float:
    """Signed distance from p (3,) to a capped cylinder's surface, m (zenswarm.vehicle.geometry.obstacle_clearance)."""
    return float(obstacle_clearance(p, Obstacle(center=tuple(center), radius=radius, height=height)))


def _place_obstacles(
    n_obstacles: int,
    start: np.ndarray,
    goal: np.ndarray,
    keep_start: float,
    keep_goal: float,
    lateral: float,
    rng: np.random.Generator,
) -> list[dict[str, Any]]:
    """Rejection-sample ``n_obstacles`` non-overlapping capped cylinders near the start-goal segment.

    keep_start, keep_goal: required clearance (m) of start and goal from every obstacle surface.
    lateral: half-width (m) of the band around the segment where centres are drawn.
    Bounded: OBSTACLE_TRIES draws per obstacle, OBSTACLE_LAYOUTS layouts; raises ScenarioError
    (field ``obstacles``) when no layout fits.
    """
    seg = goal[:2] - start[:2]
    length = float(np.linalg.norm(seg))
    along = seg / length
    perp = np.array([-along[1], along[0]])
    for _layout in range(OBSTACLE_LAYOUTS):
        centers = np.zeros((0, 2))
        radii = np.zeros(0)
        out: list[dict[str, Any]] = []
        for _ in range(n_obstacles):
            for _try in range(OBSTACLE_TRIES):
                t = rng.uniform(0.1, 0.9)
                s = rng.uniform(-lateral, lateral)
                xy = start[:2] + t * seg + s * perp
                c = np.array([_r(xy[0], 3), _r(xy[1], 3), 0.0])
                r = _r(rng.uniform(*OBSTACLE_RADIUS_RANGE), 3)
                hgt = _r(rng.uniform(*OBSTACLE_HEIGHT_RANGE), 3)
                if _clearance(start, c, r, hgt) <= keep_start or _clearance(goal, c, r, hgt) <= keep_goal:
                    continue
                if len(radii) and np.any(np.hypot(*(centers - c[:2]).T) < radii + r + OBSTACLE_GAP):
                    continue
                centers = np.vstack([centers, c[:2]])
                radii = np.append(radii, r)
                out.append({"center": [float(v) for v in c], "radius": r, "height": hgt})
                break
            else:
                break  # this layout is stuck; start a new one
        if len(out) == n_obstacles:
            return out
    raise ScenarioError(
        "obstacles",
        f"cannot place {n_obstacles} non-overlapping obstacles between start and goal "
        f"({length:.2f} m apart, band +-{lateral:.2f} m) keeping start and goal clear by "
        f"r_f + d0; tried {OBSTACLE_LAYOUTS} layouts of up to {OBSTACLE_TRIES} draws per obstacle. "
        "Use fewer obstacles or a smaller formation.",
    )


# ----------------------------------------------------------------------------- scenario


def _check_args(n: int, shape: str, topology: str, pinning: str, n_obstacles: int, seed: int) -> None:
    """ValueError naming the bad argument of :func:`generate_scenario`."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    try:
        check_seed(seed, "seed")
    except ScenarioError as e:
        raise ValueError(f"seed must be {e.message.removeprefix('expected ')}") from None
    if isinstance(n_obstacles, bool) or not isinstance(n_obstacles, int) or n_obstacles < 0:
        raise ValueError(f"n_obstacles must be an integer >= 0, got {n_obstacles!r}")
    if shape not in SHAPES:
        raise ValueError(f"unknown shape {shape!r} (choose from {', '.join(SHAPES)})")
    if topology not in TOPOLOGIES:
        raise ValueError(f"unknown topology {topology!r} (choose from {', '.join(TOPOLOGIES)})")
    if pinning not in PINNINGS:
        raise ValueError(f"unknown pinning {pinning!r} (choose from {', '.join(PINNINGS)})")


def generate_scenario(
    n: int,
    shape: str = "circle",
    topology: str = "ring",
    k: int = 2,
    pinning: str = "first",
    n_obstacles: int = 0,
    seed: int = 0,
    spacing: float = 0.3,
    name: str | None = None,
    time_limit_s: float | None = None,
) -> dict[str, Any]:
    """A valid scenario as a TOML-ready dict (the structure of ``paper_example1.toml``).

    n: number of follower UAVs N >= 1. shape: ``circle`` | ``v`` | ``grid``. topology: ``ring`` |
    ``star`` | ``complete`` | ``knn`` (k nearest neighbours, k >= 1). pinning: ``first`` | ``all``
    | ``random``. n_obstacles: capped cylinders to place (>= 0). seed: non-negative integer; also
    stored as ``scenario.seed``. spacing: distance between neighbouring UAVs in the formation, m.
    name: ``scenario.name`` (default ``gen_<shape>_<topology>_n<N>_s<seed>``). time_limit_s:
    mission time limit, s (default: 1.5 x the attractive-field time to reach the goal tolerance,
    ln(L / 0.05 m) / K_att, plus 10 s, rounded up to 5 s and at least 70 s).

    Gains are the paper's (d0 of example 1); rates and tolerances those of the example files.
    The result is checked by building it with :func:`zenswarm.scenario.config.scenario_from_dict`, so it
    is always valid; ValueError for bad arguments, ScenarioError when the obstacles do not fit.
    """
    _check_args(n, shape, topology, pinning, n_obstacles, seed)

    rng_jitter, rng_pin, rng_obs = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))

    h = formation_offsets(n, shape, spacing)
    r_f = float(np.max(np.linalg.norm(h, axis=1)))
    d0 = PAPER_LEADER["d0"]

    start, goal = _start_goal(r_f)

    jitter_bound = 0.1 * spacing
    jitter = np.clip(rng_jitter.normal(0.0, 0.05 * spacing, size=(n, 3)), -jitter_bound, jitter_bound)
    q0 = np.vectorize(_r)(start + h + jitter)

    nbr = topology_neighbours(h, topology, k)  # the graph the file names, as the scenario builds it
    b = _pinning(components(nbr), n, pinning, rng_pin)

    obstacles = _place_obstacles(
        n_obstacles,
        start,
        goal,
        keep_start=r_f + d0 + math.sqrt(3.0) * jitter_bound,
        keep_goal=r_f + d0,
        lateral=r_f + 0.5,
        rng=rng_obs,
    )

    if time_limit_s is None:
        t_goal = math.log(float(np.linalg.norm(goal - start)) / GOAL_TOLERANCE_M) / PAPER_LEADER["k_att"]
        time_limit_s = max(70.0, 5.0 * math.ceil((1.5 * t_goal + 10.0) / 5.0))

    if name is None:
        name = f"gen_{shape}_{topology}_n{n}_s{seed}"
    topo_desc = f"knn (k={k})" if topology == "knn" else topology
    description = (
        f"generated: {n} UAV{'s' if n != 1 else ''}, {shape} formation (spacing {spacing:g} m), {topo_desc} graph, "
        f"pinning {pinning} ({int(b.sum())} pinned), {n_obstacles} obstacles, seed {seed}"
    )
    graph = {  # by name: a few bytes at any N (the dense matrix was N^2 numbers)
        "topology": topology,
        **({"k": int(k)} if topology == "knn" else {}),
        "pinning": [float(v) for v in b],
    }
    d = _document({"name": name, "description": description, "seed": seed}, float(time_limit_s), start, goal, obstacles, h, q0, graph)
    scenario_from_dict(d)  # always valid: raises ScenarioError naming the field otherwise
    return d


def _start_goal(r_f: float) -> tuple[np.ndarray, np.ndarray]:
    """The leader's start and goal, m, ENU: the goal at GOAL_HEADING_RAD, GOAL_RISE_M up, 6 formation
    radii r_f (m) + 1 m away (at least 3 m), rounded to mm."""
    start = np.array(START, dtype=float)
    length = max(3.0, 6.0 * r_f + 1.0)
    goal = start + np.array(
        [length * math.cos(GOAL_HEADING_RAD), length * math.sin(GOAL_HEADING_RAD), GOAL_RISE_M]
    )
    goal = np.array([_r(v, 3) for v in goal])
    return start, goal


def _document(
    scenario: dict[str, Any], time_limit_s: float, start: np.ndarray, goal: np.ndarray, obstacles: list[dict[str, Any]],
    h: np.ndarray, q0: np.ndarray, graph: dict[str, Any],
) -> dict[str, Any]:
    """The scenario document of :func:`generate_scenario` from its parts (the paper's gains, the
    example files' rates and tolerances)."""
    d: dict[str, Any] = {
        "scenario": scenario,
        "timing": {
            "control_rate_hz": 100.0,
            "physics_rate_hz": 1000.0,
            "time_limit_s": time_limit_s,
            "settle_time_s": 30.0,
            "goal_tolerance_m": GOAL_TOLERANCE_M,
        },
        "leader": {
            "start": [float(v) for v in start],
            "goal": [float(v) for v in goal],
            **PAPER_LEADER,
            "adaptive": True,
            "k_rep_fixed": 1.0,
            "speed_limit": 0.0,
        },
        "obstacles": obstacles,
        "formation": {
            "offsets": [[float(v) for v in row] for row in h],
            "initial_positions": [[float(v) for v in row] for row in q0],
        },
        "graph": graph,
        "generator": dict(PAPER_GENERATOR),
        "eso": {"beta": list(PAPER_ESO["beta"]), "enabled": PAPER_ESO["enabled"]},
        "controller": {"kp": list(PAPER_CONTROLLER["kp"]), "kd": list(PAPER_CONTROLLER["kd"]), "yaw": PAPER_CONTROLLER["yaw"]},
    }
    return d


# ----------------------------------------------------------------------------- TOML writer

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _key(k: Any) -> str:
    if not isinstance(k, str):
        raise TypeError(f"TOML keys must be strings, got {type(k).__name__} {k!r}")
    return k if _BARE_KEY.fullmatch(k) else _string(k)


def _string(s: str) -> str:
    out = []
    for ch in s:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list) and len(v) > 0 and all(isinstance(x, dict) for x in v)


def _number(v: Any) -> str:
    """A TOML integer or float (nan, inf, -inf; else the shortest round-trip form)."""
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    x = float(v)
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return repr(x)  # shortest round-trip form; always has '.', 'e', or is handled above


def _value(v: Any, indent: str = "") -> str:
    """One TOML value. Lists of lists are written one row per line."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer, float, np.floating)):
        return _number(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + " }" if v else "{}"
    if isinstance(v, (list, tuple)):
        if v and all(isinstance(x, (list, tuple)) for x in v):
            inner = indent + "    "
            rows = "".join(f"{inner}{_value(x, inner)},\n" for x in v)
            return "[\n" + rows + indent + "]"
        return "[" + ", ".join(_value(x, indent) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} {v!r} as TOML")


def _table(d: dict[str, Any], path: list[str], lines: list[str]) -> None:
    for k, v in d.items():
        if not isinstance(v, dict) and not _is_table_array(v):
            lines.append(f"{_key(k)} = {_value(v)}")
    for k, v in d.items():
        sub = path + [_key(k)]
        if isinstance(v, dict):
            lines.append("")
            lines.append(f"[{'.'.join(sub)}]")
            _table(v, sub, lines)
        elif _is_table_array(v):
            for item in v:
                lines.append("")
                lines.append(f"[[{'.'.join(sub)}]]")
                _table(item, sub, lines)


def to_toml(d: dict[str, Any]) -> str:
    """TOML text for a nested dict so that ``tomllib.loads(to_toml(d)) == d``.

    Supported: tables (dicts, string keys), arrays of tables (non-empty lists of dicts), strings,
    booleans, ints, floats (including nan and inf), and (nested) lists of these; dicts inside
    inline arrays become inline tables. Tuples are written as arrays (so they read back as
    lists). Raises TypeError for anything else (e.g. datetimes, None).
    """
    if not isinstance(d, dict):
        raise TypeError(f"expected a dict, got {type(d).__name__}")
    lines: list[str] = []
    _table(d, [], lines)
    text = "\n".join(lines).lstrip("\n")
    return text + "\n" if text else ""

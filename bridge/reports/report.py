"""``zenswarm report``: the flight report, from an MCAP recording alone (or a simulator time series).

From a recording (``zenswarm report FILE.mcap --out DIR``) the scenario comes from the file's
``zenswarm`` metadata record, the flight's :class:`zenswarm.judge.metrics.TimeSeries` is rebuilt from the
recorded samples by the supervisor's :class:`zenswarm.process.collector.Collector` (the same code that
builds it live, so a lockstep recording gives the run's own series), and the results by
:func:`zenswarm.judge.metrics.compute_results` (so ``results.json`` matches the run's own on every field
of :data:`zenswarm.judge.metrics.FLIGHT_FIELDS`; ``wall_time_s`` is null, the recording does not know the
run's compute time). Figures (PNG, matplotlib Agg, no display needed), after the paper's Figs 4-8:

``trajectories_3d.png``  3D trajectories of the virtual leader and the UAVs, obstacles as cylinders
                         with hemispherical caps, start/goal markers (Fig. 4); beside it a top view
                         with formation snapshots and the leader's enclosing circle r_f.
``formation_errors.png`` generator formation errors q*_i - q0 - h_i and v*_i - v0, per axis and UAV,
                         eqs (16)-(17) (Figs 5 and 7): the paper's analysis.
``formation_errors_vehicles.png`` the vehicles' formation errors q_i - q0 - h_i and v_i - v0: where
                         the UAVs really are (the verdict's ``max_formation_error_m``).
``tracking_errors.png``  tracking errors q*_i - q_i and v*_i - v_i, eq. (28) (Figs 6 and 8).
``clearance.png``        each UAV's distance to the nearest obstacle surface (capped cylinder) against
                         the vehicle radius (contact), and the leader sphere's clearance d_obs(q0)
                         against the threshold d0.
``commands.png``         per UAV, what the vehicle was asked and did: the commanded collective
                         thrust against the thrust its measured motion implies, m ||dv/dt + g e_z||
                         (drag and disturbances included), and the commanded roll, pitch, yaw
                         (``rpy_cmd``) against the measured attitude (``rpy``).
``plant.png``            flights whose plant model records internal signals only
                         (:attr:`zenswarm.plant.api.PlantModel.records`, ``plant.<name>`` in the
                         series, e.g. the built-in's rotor thrusts and torque): one row per signal,
                         its components over time for the first UAVs, with its unit.
``links.png``            messages per key in the recording (and how many the report's decoder
                         rejected), and the drop/reject/timeout counters each process reported in
                         its last ``diag`` message (recordings only).
``effective_graph.png``  runs with a radio model, a capacity queue or a link trace only: the
                         effective communication graph over time (connected components per tick,
                         where the leader-rooted spanning tree of Lemma 1 held, each ref/leader
                         link up/down per tick as a raster), each link's delivery ratio and the
                         histogram of the delivered messages' delays; recomputed from the fault
                         plan (scenario ``[faults]`` + the recorded fault flags) and the series,
                         as ``results.json``'s ``effective_graph``.

``zenswarm report --series RUN/timeseries.npz --scenario SCENARIO.toml --out DIR`` plots the
output of ``zenswarm sim`` (or of ``zenswarm up``) the same way, without ``links.png`` and without
rewriting the run's ``results.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, NamedTuple

import numpy as np

from zenswarm.bridge.args import FIGURE_FORMATS, figure_formats
from zenswarm.bus import wire
from zenswarm.errors import RecordingError, ScenarioError, ZenswarmError, run_command
from zenswarm.judge.metrics import TimeSeries, compute_results
from zenswarm.link import FaultPlan, graph_series, plan_for
from zenswarm.process.paths import check_output_dir
from zenswarm.scenario.config import Scenario, load_scenario
from zenswarm.vehicle.geometry import d_obs_many, obstacle_clearance_many

__all__ = [
    "METADATA_NAME",
    "FIGURES",
    "RecordedMessage",
    "Recording",
    "Flight",
    "load_recording",
    "flight_from_recording",
    "report_recording",
    "report_from_series",
    "plot_effective_graph",
    "network_plan",
    "recorded_fault_plan",
    "add_parsers",
]

METADATA_NAME = "zenswarm"
"""Name of the MCAP metadata record the recorder writes (keys scenario_json, swarm, mode)."""

FIGURES = (
    "trajectories_3d.png",
    "formation_errors.png",
    "formation_errors_vehicles.png",
    "tracking_errors.png",
    "clearance.png",
    "commands.png",
    "plant.png",
    "links.png",
)
"""Figures of a report from a recording (``links.png`` only from a recording, ``plant.png`` only
when the plant model records signals: the built-in ``quadrotor`` and ``rotorpy`` do)."""

_DPI = 120

VIEW_3D = (24.0, -125.0)
"""Elevation and azimuth (degrees, matplotlib's ``view_init``) of the 3D trajectories figure."""


def _save(fig: Any, path: Path, formats: Sequence[str] = ("png",)) -> list[Path]:
    """Write ``fig`` as ``path`` with each suffix of ``formats`` (the first is the figure's own
    path's); returns the files written."""
    out = []
    for fmt in formats:
        f = path.with_suffix("." + fmt)
        fig.savefig(f, dpi=_DPI)
        out.append(f)
    return out
_STYLES = ("-", "--", "-.", ":")
"""Line styles by UAV, so curves that coincide (symmetric UAVs) stay visible."""


# =========================================================================== reading a recording


class RecordedMessage(NamedTuple):
    """One recorded sample. log_time: receive wall time, ns; publish_time: sender's sim time, ns."""

    topic: str
    log_time: int
    publish_time: int
    data: bytes
    encoding: str


@dataclass
class Recording:
    """An MCAP recording of a swarm, loaded whole (messages in file order).

    metadata: the ``zenswarm`` metadata record(s), merged; scenario from its ``scenario_json``;
    swarm and mode (``lockstep``, ``realtime``; anything else counts as lockstep) from it too.
    truncated: the damage met while reading (file cut short, chunk failing its CRC), None for a
    complete, intact file. notes: what a reader must be told (:meth:`zenswarm.bridge.recording.mcapio.Recording.notes`:
    truncated or damaged, oversize payloads the recorder did not record).
    """

    path: Path
    metadata: dict[str, str]
    scenario: Scenario
    swarm: str
    mode: str
    messages: list[RecordedMessage]
    truncated: str | None = None
    other_metadata: list[tuple[str, dict[str, str]]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def realtime(self) -> bool:
        return self.mode == "realtime"


def load_recording(path: str | Path) -> Recording:
    """Load a recording and the scenario it carries (read by :func:`zenswarm.bridge.recording.mcapio.read_recording`,
    leniently: a truncated file or a corrupted chunk costs only what is unreadable, and
    :attr:`Recording.truncated` says what happened).

    Raises :class:`RecordingError` naming the file when it is missing, not an MCAP file, has no
    ``zenswarm`` metadata record, or its scenario is missing or invalid.
    """
    from zenswarm.bridge.recording import mcapio

    p = Path(path)
    r = mcapio.read_recording(p, strict=False)
    meta = r.metadata.get(METADATA_NAME)
    if not meta:
        raise RecordingError(
            f"{p}: no '{METADATA_NAME}' metadata record: not a zenswarm recording "
            "(the recorder writes the scenario, swarm name and mode there)"
        )
    scenario = r.load_scenario()
    messages = [
        RecordedMessage(ch.topic, m.log_time, m.publish_time, bytes(m.data), ch.message_encoding) for ch, m in r.raw_messages()
    ]
    problems = ([r.summary_problem] if r.summary_problem else []) + [x for x in r.problems if x != r.summary_problem]
    swarm = meta.get("swarm") or _guess_swarm(messages)
    if swarm is None:
        raise RecordingError(f"{p}: no swarm name in the metadata and no swarm key among the messages")
    try:
        wire.validate_swarm_name(swarm)
    except wire.InvalidKeyError as e:
        raise RecordingError(f"{p}: {e}") from None
    mode = meta.get("mode") or "lockstep"
    others = [(name, dict(d)) for name, d in r.metadata.items() if name != METADATA_NAME]
    return Recording(p, dict(meta), scenario, swarm, mode, messages, "; ".join(problems) or None, others, r.notes())


def _guess_swarm(messages: Sequence[RecordedMessage]) -> str | None:
    for m in messages:
        parts = m.topic.split("/")
        if len(parts) >= 3 and parts[0] == "swarm":
            return parts[1]
    return None


# =========================================================================== the flight


@dataclass
class Flight:
    """What a report needs: the series, and (from a recording) the bus statistics."""

    series: TimeSeries
    scenario: Scenario
    message_counts: dict[str, int] = field(default_factory=dict)
    decoder_rejects: dict[str, int] = field(default_factory=dict)
    decoder_counters: dict[str, int] = field(default_factory=dict)
    diagnostics: dict[str, dict[str, Any]] = field(default_factory=dict)
    mode: str = "lockstep"
    swarm: str | None = None


def _last_data_tick(ts: TimeSeries) -> int:
    """Index of the last tick that holds any sample (-1 if none)."""
    T = len(ts.t)
    if T == 0:
        return -1
    have = np.zeros(T, dtype=bool)
    for a in (ts.q0, ts.qref, ts.q, ts.u):
        have |= np.isfinite(a.reshape(T, -1)).any(axis=1)
    idx = np.flatnonzero(have)
    return int(idx[-1]) if len(idx) else -1


def flight_from_recording(rec: Recording) -> Flight:
    """Rebuild the flight's time series from the recorded samples with the supervisor's Collector.

    The series runs to the last tick that has any sample (the whole time limit for a complete
    run); realtime recordings are forward-filled over gaps, exactly as ``zenswarm up --realtime``
    does. Raises RecordingError when no sample of the swarm is in the file.
    """
    from zenswarm.process.collector import Collector

    keys = wire.Keys(rec.swarm)
    col = Collector(rec.scenario, keys)
    counts: dict[str, int] = {}
    for m in rec.messages:
        counts[m.topic] = counts.get(m.topic, 0) + 1
        if m.encoding == "msgpack":
            col.on_sample(m.topic, m.data)
    raw = col.series(None, fill=False)
    last = _last_data_tick(raw)
    if last < 0:
        raise RecordingError(f"{rec.path}: no flight data (leader/ref, uav/*/state|ref|cmd) of swarm '{rec.swarm}'")
    ts = col.series(last + 1, fill=rec.realtime)
    return Flight(
        series=ts,
        scenario=rec.scenario,
        message_counts=counts,
        decoder_rejects=dict(col.decoder.rejects),
        decoder_counters=col.decoder.counters(),
        diagnostics={k: dict(v) for k, v in col.diag.items()},
        mode=rec.mode,
        swarm=rec.swarm,
    )


# =========================================================================== figures


def _figure(figsize: tuple[float, float], layout: Literal["constrained", "compressed", "tight"] | None = None, **adjust: float):
    """A figure without pyplot (no global state, Agg canvas). Fixed margins (``adjust``, as for
    ``subplots_adjust``) unless a layout engine is asked for: constrained layout costs seconds."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout=layout)
    if adjust:
        fig.subplots_adjust(**adjust)
    return fig


def _uav_colors(n: int) -> list:
    from matplotlib import colormaps

    cmap = colormaps["tab10"] if n <= 10 else colormaps["turbo"]
    if n <= 10:
        return [cmap(i) for i in range(n)]
    return [cmap(0.05 + 0.9 * i / max(1, n - 1)) for i in range(n)]


def _cylinder_mesh(ob: Any, nth: int = 40, nz: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    xc, yc, zc = ob.center
    th = np.linspace(0.0, 2.0 * math.pi, nth)
    z = np.linspace(zc, zc + ob.height, nz)
    TH, Z = np.meshgrid(th, z)
    return xc + ob.radius * np.cos(TH), yc + ob.radius * np.sin(TH), Z


def _cap_mesh(ob: Any, nth: int = 40, nphi: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Upper hemisphere of radius r_o on top of the cylinder (Remark 1)."""
    xc, yc, zc = ob.center
    th = np.linspace(0.0, 2.0 * math.pi, nth)
    ph = np.linspace(0.0, 0.5 * math.pi, nphi)  # polar angle from +z
    TH, PH = np.meshgrid(th, ph)
    r = ob.radius
    return xc + r * np.sin(PH) * np.cos(TH), yc + r * np.sin(PH) * np.sin(TH), zc + ob.height + r * np.cos(PH)


def _finite_rows(a: np.ndarray) -> np.ndarray:
    """Rows of an (T, 3) array with every element finite."""
    return a[np.all(np.isfinite(a), axis=-1)]


GOAL_MS = 13.0
"""The goal's star in the top view, points."""


def hidden_behind_obstacles(p: np.ndarray, sc: Scenario, elev: float, azim: float) -> np.ndarray:
    """Which points of ``p`` (T, 3) m a viewer looking from elevation ``elev`` and azimuth
    ``azim`` (degrees, matplotlib's ``view_init``; orthographic) sees behind an obstacle of
    ``sc``: farther than the obstacle's axis and inside its outline (the cylinder and its cap
    seen from there), (T,) bool; rows with a NaN are False."""
    e, a = math.radians(elev), math.radians(azim)
    eye = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])  # towards the viewer
    right = np.array([-math.sin(a), math.cos(a), 0.0])
    up = np.cross(eye, right)
    out = np.zeros(len(p), dtype=bool)
    for ob in sc.obstacles:
        d = p - np.asarray(ob.center, dtype=float)
        r, h = ob.radius, ob.height
        lateral, height, depth = d @ right, d @ up, d @ eye
        lo = -r * math.sin(e)  # the base's ellipse, its near edge
        hi = h * math.cos(e) + r  # the cap's top
        out |= (np.abs(lateral) <= r) & (height >= lo) & (height <= hi) & (depth < 0.0)
    return out & np.all(np.isfinite(p), axis=-1)


def plot_trajectories(ts: TimeSeries, sc: Scenario, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """3D trajectories (paper Fig. 4) plus a top view with formation snapshots."""
    n = ts.q.shape[1]
    colors = _uav_colors(n)
    fig = _figure((13.0, 6.2))
    gs = fig.add_gridspec(1, 2, width_ratios=[1.35, 1.0], left=0.0, right=0.98, bottom=0.08, top=0.9, wspace=0.12)
    ax = fig.add_subplot(gs[0, 0], projection="3d")
    top = fig.add_subplot(gs[0, 1])
    _trajectories_3d(ax, ts, sc, colors)
    _trajectories_top(top, ts, sc, colors)
    fig.suptitle(f"{sc.name}: trajectories of the virtual leader and {n} UAVs")
    return _save(fig, path, formats)[0]


def _trajectories_3d(ax: Any, ts: TimeSeries, sc: Scenario, colors: Sequence[Any]) -> None:
    """The 3D view of :func:`plot_trajectories`: obstacles, paths, starts and ends, to scale."""
    n = ts.q.shape[1]
    pts = [_finite_rows(ts.q0)] + [_finite_rows(ts.q[:, i]) for i in range(n)]
    pts.append(np.asarray([sc.leader.start, sc.leader.goal], dtype=float))
    for ob in sc.obstacles:
        xc, yc, zc = ob.center
        r = ob.radius
        pts.append(np.array([[xc - r, yc - r, zc], [xc + r, yc + r, zc + ob.height + r]]))
    allp = np.vstack([p for p in pts if len(p)])
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    span = np.maximum(hi - lo, 1e-3)
    pad = 0.06 * span.max()
    lo, hi = lo - pad, hi + pad
    lo[2] = min(lo[2], 0.0)  # show the ground
    aspect = hi - lo  # to scale: one metre is as long on x, y and z

    # Drawn in a fixed order (mplot3d sorts artists by their mean depth, which puts whole paths
    # over or under whole obstacles): obstacles (translucent) at zorder 2; each path's parts
    # hidden behind an obstacle from this view under them (zorder 1), the rest over them (3).
    ax.computed_zorder = False
    for ob in sc.obstacles:
        ax.plot_surface(*_cylinder_mesh(ob), color="0.55", alpha=0.4, linewidth=0, shade=True, zorder=2)
        ax.plot_surface(*_cap_mesh(ob), color="0.55", alpha=0.4, linewidth=0, shade=True, zorder=2)
    q0 = ts.q0

    def path3d(p: np.ndarray, **kw: Any) -> None:
        hidden = hidden_behind_obstacles(p, sc, *VIEW_3D)
        front, back = p.copy(), p.copy()
        front[hidden] = np.nan  # a segment is drawn where both its ends are
        back[~hidden] = np.nan
        ax.plot(front[:, 0], front[:, 1], front[:, 2], zorder=3, **kw)
        kw.pop("label", None)
        ax.plot(back[:, 0], back[:, 1], back[:, 2], zorder=1, **kw)

    path3d(q0, color="k", ls="--", lw=1.4, label="virtual leader $q_0$")
    for i in range(n):
        qi = ts.q[:, i]
        path3d(qi, color=colors[i], lw=1.5, label=f"UAV {i + 1}")
        f = _finite_rows(qi)
        if len(f):
            ax.scatter(*f[0], color=colors[i], marker="o", s=22, depthshade=False, zorder=4)
            ax.scatter(*f[-1], color=colors[i], marker="^", s=30, depthshade=False, zorder=4)
    st, gl = np.asarray(sc.leader.start, float), np.asarray(sc.leader.goal, float)
    ax.scatter(*st, color="k", marker="s", s=40, depthshade=False, label="start", zorder=4)
    ax.scatter(*gl, color="tab:green", marker="*", s=160, depthshade=False, label="goal", zorder=4)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(aspect))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.zaxis.set_rotate_label(False)
    ax.set_zlabel("z [m]", rotation=90)
    ax.view_init(elev=VIEW_3D[0], azim=VIEW_3D[1])
    ax.set_title("3D trajectories to scale (o start, ^ end)")
    ax.legend(loc="upper left", fontsize=8)


def _trajectories_top(top: Any, ts: TimeSeries, sc: Scenario, colors: Sequence[Any]) -> None:
    """The top view of :func:`plot_trajectories`: obstacles, paths, formation snapshots with the
    enclosing circle r_f."""
    from matplotlib.patches import Circle

    n = ts.q.shape[1]
    q0 = ts.q0
    st, gl = np.asarray(sc.leader.start, float), np.asarray(sc.leader.goal, float)
    for k, ob in enumerate(sc.obstacles):
        xc, yc, _ = ob.center
        top.add_patch(Circle((xc, yc), ob.radius, color="0.55", alpha=0.5))
        top.annotate(f"obs {k + 1}\nh={ob.height:g}+{ob.radius:g} m", (xc, yc), ha="center", va="center", fontsize=7)
    top.plot(q0[:, 0], q0[:, 1], color="k", ls="--", lw=1.2, label="$q_0$")
    for i in range(n):
        top.plot(ts.q[:, i, 0], ts.q[:, i, 1], color=colors[i], lw=1.3, label=f"UAV {i + 1}")
    T = len(ts.t)
    good = np.flatnonzero(np.all(np.isfinite(ts.q.reshape(T, -1)), axis=1) & np.all(np.isfinite(q0), axis=1))
    if len(good):
        snaps = _snapshot_ticks(q0, good, 7)
        for k in snaps:
            poly = np.vstack([ts.q[k], ts.q[k][:1]]) if n > 2 else ts.q[k]
            top.plot(poly[:, 0], poly[:, 1], color="0.3", lw=0.7, alpha=0.7)
            top.add_patch(Circle((q0[k, 0], q0[k, 1]), sc.r_f, fill=False, ls=":", lw=0.8, color="0.4"))
            near_goal = np.hypot(*(q0[k, :2] - gl[:2])) < sc.r_f
            # beside the goal's star (13 pt wide), not on it: under it, right of it
            xytext = (9, -17) if near_goal else (3, -9)
            top.annotate(
                f"{ts.t[k]:.1f} s", (q0[k, 0], q0[k, 1]), fontsize=7, color="0.25", xytext=xytext, textcoords="offset points"
            )
    top.plot(*st[:2], "ks", ms=6)
    top.plot(*gl[:2], "*", color="tab:green", ms=GOAL_MS)
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title(f"top view: formation snapshots, enclosing circle $r_f$={sc.r_f:.3f} m")
    top.grid(True, alpha=0.3)
    top.legend(loc="best", fontsize=8)


def _snapshot_ticks(q0: np.ndarray, good: np.ndarray, count: int) -> np.ndarray:
    """``count`` ticks among ``good`` evenly spaced along the leader's path length (so the
    snapshots do not pile up where the leader hovers at the goal)."""
    p = q0[good]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
    if s[-1] <= 1e-9:
        return good[:1]
    idx = np.searchsorted(s, np.linspace(0.0, s[-1] * 0.999, count))
    return good[np.unique(np.clip(idx, 0, len(good) - 1))]


def _plot_error_grid(
    t: np.ndarray, pos: np.ndarray, vel: np.ndarray, path: Path, title: str, plabel: str, vlabel: str,
    settle_s: float | None = None, formats: Sequence[str] = ("png",),
) -> Path:
    """2 x 3 grid: position (top) and velocity (bottom) error components, one line per UAV."""
    n = pos.shape[1]
    colors = _uav_colors(n)
    fig = _figure((13.0, 6.4), left=0.06, right=0.985, bottom=0.08, top=0.88, wspace=0.24, hspace=0.3)
    axes = fig.subplots(2, 3, sharex=True)
    for row, (err, lab, unit) in enumerate(((pos, plabel, "m"), (vel, vlabel, "m/s"))):
        for c, axis in enumerate("xyz"):
            ax = axes[row, c]
            for i in range(n):
                ax.plot(t, err[:, i, c], color=colors[i], ls=_STYLES[i % len(_STYLES)], lw=1.1, label=f"UAV {i + 1}")
            ax.axhline(0.0, color="0.5", lw=0.6)
            if settle_s is not None:
                ax.axvline(settle_s, color="tab:purple", ls="--", lw=0.9, label=f"settle time {settle_s:g} s")
            ax.set_title(f"{lab}, {axis} [{unit}]", fontsize=10)
            ax.grid(True, alpha=0.3)
            ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3), useMathText=True)
            if row == 1:
                ax.set_xlabel("t [s]")
    axes[0, 0].legend(fontsize=8, loc="best")
    if settle_s is not None:
        title += f"\n(dashed: the settle time {settle_s:g} s, after which the verdict takes the maximum formation error)"
    fig.suptitle(title, fontsize=11)
    return _save(fig, path, formats)[0]


def plot_formation_errors(ts: TimeSeries, sc: Scenario, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """Generator formation errors q*_i - q0 - h_i and v*_i - v0 (eqs 16-17; paper Figs 5 and 7)."""
    h = np.asarray(sc.offsets, dtype=float)
    ep = ts.qref - ts.q0[:, None, :] - h[None]
    ev = ts.vref - ts.v0[:, None, :]
    return _plot_error_grid(
        ts.t,
        ep,
        ev,
        path,
        f"{sc.name}: formation errors of the reference generator, eqs (16)-(17)",
        r"$q^*_i - q_0 - h_i$",
        r"$v^*_i - v_0$",
        settle_s=sc.timing.settle_time_s,
        formats=formats,
    )


def plot_vehicle_formation_errors(ts: TimeSeries, sc: Scenario, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """The vehicles' formation errors q_i - q0 - h_i and v_i - v0: where the UAVs really are
    against their places in the formation (what the verdict's max_formation_error_m measures)."""
    h = np.asarray(sc.offsets, dtype=float)
    return _plot_error_grid(
        ts.t,
        ts.q - ts.q0[:, None, :] - h[None],
        ts.v - ts.v0[:, None, :],
        path,
        f"{sc.name}: formation errors of the vehicles (measured states)",
        r"$q_i - q_0 - h_i$",
        r"$v_i - v_0$",
        settle_s=sc.timing.settle_time_s,
        formats=formats,
    )


def plot_tracking_errors(ts: TimeSeries, sc: Scenario, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """Tracking errors q*_i - q_i and v*_i - v_i (composite controller, eq. 28; paper Figs 6 and 8)."""
    return _plot_error_grid(
        ts.t,
        ts.qref - ts.q,
        ts.vref - ts.v,
        path,
        f"{sc.name}: trajectory tracking errors under the composite controller, eq. (28)",
        r"$q^*_i - q_i$",
        r"$v^*_i - v_i$",
        settle_s=sc.timing.settle_time_s,
        formats=formats,
    )


def leader_d_obs(q0: np.ndarray, sc: Scenario) -> np.ndarray:
    """min over obstacles of the sphere clearance d_obs(q0) = ||q0 - q_obs(q0)|| - r_o - r_f, (T,) m."""
    out = np.full(len(q0), np.inf)
    for ob in sc.obstacles:
        out = np.fmin(out, d_obs_many(q0, ob, sc.r_f))
    out[~np.isfinite(q0).all(axis=1)] = np.nan
    return out


def uav_clearance(q: np.ndarray, sc: Scenario) -> np.ndarray:
    """Each UAV's distance to the nearest obstacle surface, (T, N) m (negative inside)."""
    c = np.full(q.shape[:-1], np.inf)
    for ob in sc.obstacles:
        c = np.fmin(c, obstacle_clearance_many(q, ob))
    return c


def plot_clearance(ts: TimeSeries, sc: Scenario, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """UAV clearance to the nearest obstacle, and the leader sphere's d_obs against d0."""
    n = ts.q.shape[1]
    colors = _uav_colors(n)
    fig = _figure((11.0, 6.6), left=0.08, right=0.98, bottom=0.08, top=0.9, hspace=0.2)
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    if not sc.obstacles:
        for ax in (ax1, ax2):
            ax.text(0.5, 0.5, "no obstacles in this scenario", ha="center", va="center", transform=ax.transAxes)
    else:
        c = uav_clearance(ts.q, sc)
        for i in range(n):
            ax1.plot(ts.t, c[:, i], color=colors[i], lw=1.2, label=f"UAV {i + 1}")
        r = sc.vehicle_radius
        ax1.axhline(r, color="tab:red", lw=1.0, ls="--", label=f"contact: clearance = vehicle radius {r:.4f} m")
        ax1.axhline(0.0, color="0.5", lw=0.8, ls=":", label="surface")
        if np.isfinite(c).any():
            kc, ic = np.unravel_index(np.nanargmin(c), c.shape)  # tick and UAV of the closest approach
            ax1.plot(ts.t[kc], c[kc, ic], "v", color="tab:red", ms=7)
            label = f"min {c[kc, ic]:.3f} m (UAV {ic + 1}, t={ts.t[kc]:.2f} s)"
            ax1.annotate(label, (ts.t[kc], c[kc, ic]), xytext=(6, 10), textcoords="offset points", fontsize=8)
        ax1.set_ylabel("clearance [m]")
        ax1.set_title("UAV distance to the nearest obstacle surface (cylinder + hemispherical cap)", fontsize=10)
        ax1.set_ylim(bottom=min(-0.02, float(np.nanmin(c)) - 0.02) if np.isfinite(c).any() else None)
        d = leader_d_obs(ts.q0, sc)
        ax2.plot(ts.t, d, color="k", lw=1.3, label=r"$d_{obs}(q_0)$ (sphere of radius $r_f$)")
        ax2.axhline(sc.leader.d0, color="tab:orange", ls="--", lw=1.0, label=f"$d_0$ = {sc.leader.d0:g} m (avoidance threshold)")
        ax2.axhline(0.0, color="tab:red", ls="--", lw=1.0, label="sphere touches obstacle")
        if np.isfinite(d).any():
            kd = int(np.nanargmin(d))
            ax2.plot(ts.t[kd], d[kd], "v", color="tab:red", ms=7)
            label = f"min {d[kd]:.3f} m at t={ts.t[kd]:.2f} s"
            ax2.annotate(label, (ts.t[kd], d[kd]), xytext=(6, 10), textcoords="offset points", fontsize=8)
            hi = float(np.nanmax(d[np.isfinite(d)]))
            ax2.set_ylim(min(-0.02, float(np.nanmin(d)) - 0.02), max(4.0 * sc.leader.d0, min(hi, 8.0 * sc.leader.d0)))
        ax2.set_ylabel("clearance [m]")
        ax2.set_title(f"virtual leader: formation-sphere clearance $d_{{obs}}$, $r_f$={sc.r_f:.3f} m", fontsize=10)
        for ax in (ax1, ax2):
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8, loc="upper right")
    ax2.set_xlabel("t [s]")
    fig.suptitle(f"{sc.name}: obstacle clearance")
    return _save(fig, path, formats)[0]


COMMAND_UAVS = 6
"""``commands.png`` shows the first this many UAVs (a row each)."""


def plot_commands(ts: TimeSeries, sc: Scenario, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """Per UAV (rows, the first :data:`COMMAND_UAVS`): the commanded collective thrust (N) against
    the thrust the measured motion implies, m ||dv/dt + g e_z|| (dv/dt by central differences of
    the sampled velocity; drag and disturbances included), and the commanded roll, pitch and yaw
    (``rpy_cmd``, the inversion after eq. 28) against the measured attitude (``rpy``), degrees."""
    from zenswarm.vehicle.params import QuadParams

    qp = QuadParams.from_vehicle(sc.vehicle)
    n = min(ts.q.shape[1], COMMAND_UAVS)
    colors = _uav_colors(ts.q.shape[1])
    fig = _figure((14.0, 2.3 * n + 1.2), left=0.07, right=0.99, bottom=0.5 / (2.3 * n + 1.2), top=1 - 0.75 / (2.3 * n + 1.2),
                  wspace=0.25, hspace=0.35)  # fmt: skip
    axes = np.atleast_2d(fig.subplots(n, 4, sharex=True))
    t = ts.t
    if len(t) > 1:
        acc = np.gradient(ts.v, t, axis=0)
    else:
        acc = np.zeros_like(ts.v)
    implied = qp.mass * np.linalg.norm(acc + np.array([0.0, 0.0, qp.g]), axis=2)
    for i in range(n):
        ax = axes[i, 0]
        ax.plot(t, ts.thrust[:, i], color=colors[i], lw=1.2, label="commanded")
        ax.plot(t, implied[:, i], color="k", lw=0.8, alpha=0.7, label=r"implied: $m\|\dot v + g e_z\|$")
        ax.axhline(qp.mass * qp.g, color="0.5", lw=0.6, ls=":")
        ax.set_ylabel(f"UAV {i + 1}\nthrust [N]")
        for c, name in enumerate(("roll", "pitch", "yaw")):
            ax = axes[i, c + 1]
            ax.plot(t, np.degrees(ts.rpy_cmd[:, i, c]), color=colors[i], lw=1.2, label="commanded")
            ax.plot(t, np.degrees(ts.rpy[:, i, c]), color="k", lw=0.8, alpha=0.7, label="measured")
            if i == 0:
                ax.set_title(f"{name} [deg]", fontsize=10)
        if i == 0:
            axes[0, 0].set_title("collective thrust [N] (dotted: m g)", fontsize=10)
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    axes[0, 0].legend(fontsize=7, loc="best")
    axes[0, 1].legend(fontsize=7, loc="best")
    more = f" (the first {n} of {ts.q.shape[1]} UAVs)" if ts.q.shape[1] > n else ""
    fig.suptitle(f"{sc.name}: commanded against achieved thrust and attitude{more}")
    return _save(fig, path, formats)[0]


PLANT_UAVS = 3
"""``plant.png`` shows the first this many UAVs (a column each)."""

PLANT_SIGNALS = 8
"""``plant.png`` shows the first this many recorded signals (a row each)."""


def plot_plant_records(ts: TimeSeries, sc: Scenario, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """What the plant model recorded (``ts.plant``): a row per signal (the first
    :data:`PLANT_SIGNALS`), a column per UAV (the first :data:`PLANT_UAVS`), each component of the
    signal over time, labelled with the model's declared unit when the model can be loaded here."""
    from zenswarm.scenario.plugins import plant_records

    try:
        units = {n: s.unit for n, s in plant_records(sc).items()}
    except Exception:  # noqa: BLE001 - a plug-in not installed where the report is made: no units
        units = {}
    names = list(ts.plant)[:PLANT_SIGNALS]
    n_uav = ts.q.shape[1]
    cols = min(n_uav, PLANT_UAVS)
    h = 2.2 * len(names) + 1.2
    fig = _figure((4.6 * cols + 1.0, h), left=0.09, right=0.98, bottom=0.5 / h, top=1 - 0.75 / h, wspace=0.25, hspace=0.4)
    axes = np.atleast_2d(np.asarray(fig.subplots(len(names), cols, sharex=True, squeeze=False)))
    for r, name in enumerate(names):
        a = ts.plant[name]
        flat = a.reshape(a.shape[0], a.shape[1], -1)
        for i in range(cols):
            ax = axes[r, i]
            for c in range(flat.shape[2]):
                ax.plot(ts.t, flat[:, i, c], lw=1.0, label=f"[{c}]" if flat.shape[2] > 1 else None)
            if r == 0:
                ax.set_title(f"UAV {i + 1}", fontsize=10)
            if i == 0:
                unit = units.get(name)
                ax.set_ylabel(f"{name}" + (f" [{unit}]" if unit else ""))
            if i == cols - 1 and flat.shape[2] > 1:
                ax.legend(fontsize=7, loc="best")
            ax.grid(True, alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    more = f" (the first {cols} of {n_uav} UAVs)" if n_uav > cols else ""
    fig.suptitle(f"{sc.name}: what the plant model {sc.plant.model!r} recorded{more}")
    return _save(fig, path, formats)[0]


_FAULT_RE = re.compile(r"drop|reject|timeout|late|lost|loss|stale|held|miss|undecodable|error", re.IGNORECASE)


def _short_key(topic: str, swarm: str | None) -> str:
    prefix = f"swarm/{swarm}/" if swarm else None
    return topic[len(prefix) :] if prefix and topic.startswith(prefix) else topic


def _fault_counters(fl: Flight) -> list[tuple[str, float]]:
    """``(label, count)`` of every fault counter of the processes' last diag messages (see
    :func:`plot_links`), then the report decoder's rejects per key."""
    faults: list[tuple[str, float]] = []
    for proc in sorted(fl.diagnostics, key=_proc_order):
        for name, val in sorted(fl.diagnostics[proc].items()):
            if isinstance(val, (int, float)) and _FAULT_RE.search(name):
                faults.append((f"{proc}: {name}", float(val)))
    for key, nrej in sorted(fl.decoder_rejects.items()):
        faults.append((f"report decoder: {_short_key(key, fl.swarm)}", float(nrej)))
    return faults


def _plot_key_counts(ax: Any, fl: Flight, keys: list[str]) -> None:
    """Messages recorded per key (red: some rejected by the report's decoder)."""
    y = np.arange(len(keys))
    counts = np.array([fl.message_counts[k] for k in keys], dtype=float)
    rej = np.array([fl.decoder_rejects.get(k, 0) for k in keys], dtype=float)
    ax.barh(y, counts, color=["tab:red" if r else "tab:blue" for r in rej])
    ax.set_yticks(y, [_short_key(k, fl.swarm) for k in keys], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("messages recorded")
    ax.set_xlim(0, max(1.0, float(counts.max(initial=0.0))) * 1.3)
    nrej = int(rej.sum())
    ax.set_title(
        f"messages per key: {int(counts.sum())} recorded" + (f", {nrej} rejected by the decoder (red)" if nrej else ", none rejected"),
        fontsize=10,
    )
    for yy, c, r in zip(y, counts, rej, strict=True):
        text = f"{int(c)}" + (f"  ({int(r)} rejected)" if r else "")
        ax.annotate(text, (c, yy), xytext=(2, 0), textcoords="offset points", va="center", fontsize=7, color="tab:red" if r else "black")
    ax.grid(True, axis="x", alpha=0.3)


def _plot_fault_counters(ax: Any, faults: list[tuple[str, float]]) -> None:
    """The nonzero fault counters as bars; the ones at zero named in one line, not drawn."""
    nonzero = [(lab, v) for lab, v in faults if v != 0]
    zero = len(faults) - len(nonzero)
    if nonzero:
        yf = np.arange(len(nonzero))
        vals = np.array([v for _, v in nonzero])
        ax.barh(yf, vals, color="tab:red")
        ax.set_yticks(yf, [lab for lab, _ in nonzero], fontsize=8)
        ax.invert_yaxis()
        for yy, v in zip(yf, vals, strict=True):
            ax.annotate(f"{v:g}", (v, yy), xytext=(2, 0), textcoords="offset points", va="center", fontsize=7)
        ax.set_xlim(0, max(1.0, float(vals.max()) * 1.15))
        ax.set_title(f"drop / reject / timeout counters: {len(nonzero)} of {len(faults)} nonzero", fontsize=10)
        ax.set_xlabel("count (last diag message of each process)")
        ax.grid(True, axis="x", alpha=0.3)
    else:
        text = (
            f"all {zero} drop / reject / timeout counters are zero\n(last diag message of each process)"
            if faults
            else "no diag messages with drop/reject counters\nin this recording"
        )
        ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, fontsize=9)
        ax.set_title("drop / reject / timeout counters", fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    if nonzero and zero:
        ax.text(1.0, -0.12, f"{zero} more counters at zero, not drawn", transform=ax.transAxes, ha="right", va="top", fontsize=7)


def plot_links(fl: Flight, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """Messages per key, the report decoder's rejects per key, and each process's nonzero fault
    counters (those at zero are counted in one line, not drawn: they would take half the figure).

    Fault counters are every numeric counter of a process's last diag message whose name says
    drop, reject, timeout, late, lost/loss, stale, held, miss, undecodable or error; per-link counters (their name
    names the link or key) show up as their own bars.
    """
    keys = sorted(fl.message_counts, key=lambda k: (_short_key(k, fl.swarm).split("/")[0], _key_order(k), k))
    faults = _fault_counters(fl)
    nonzero = sum(1 for _, v in faults if v != 0)
    nrows = max(len(keys), nonzero, 1)
    fig = _figure((12.0, max(3.0, 0.2 * nrows + 1.3)), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, width_ratios=(1.3, 1.0))
    _plot_key_counts(ax1, fl, keys)
    _plot_fault_counters(ax2, faults)
    fig.suptitle(f"bus traffic of swarm '{fl.swarm}' ({fl.mode})")
    return _save(fig, path, formats)[0]


def _key_order(topic: str) -> int:
    m = re.search(r"/uav/(\d+)/", topic)
    return int(m.group(1)) if m else 0


def _proc_order(proc: str) -> tuple[int, int, str]:
    m = re.fullmatch(r"agent:(\d+)", proc)
    if m:
        return (1, int(m.group(1)), proc)
    return (0 if proc in ("plant", "leader") else 2, 0, proc)


# =========================================================================== effective graph


def network_plan(sc: Scenario, faults: FaultPlan | None) -> FaultPlan | None:
    """``faults`` if the run has a radio model, a capacity queue or a trace (the faults that make
    the effective graph worth a figure), else None."""
    if faults is None:
        return None
    return faults if (faults.radio_active or faults.queues is not None or faults.trace is not None) else None


def recorded_fault_plan(rec: Recording) -> FaultPlan | None:
    """The link-fault plan of a recorded run: the scenario's ``[faults]`` table plus the fault
    flags the recorder was given (metadata ``fault_args``, as ``replay --verify`` reads them)."""
    from zenswarm.bridge.args import add_fault_args, link_faults

    p = argparse.ArgumentParser(add_help=False)
    add_fault_args(p)
    try:
        words = json.loads(rec.metadata.get("fault_args", "[]"))
        return link_faults(p.parse_args([str(w) for w in words])).plan(rec.scenario)
    except (ValueError, SystemExit, ZenswarmError) as e:
        raise RecordingError(f"{rec.path}: metadata fault_args unusable ({e})") from None


def plot_effective_graph(ts: TimeSeries, sc: Scenario, faults: FaultPlan, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """The effective communication graph over time (:func:`zenswarm.link.swarm.graph_series`,
    recomputed from the fault plan and the flown series, as ``results.json``'s ``effective_graph``):
    the connected components per tick with the ticks where the leader-rooted spanning tree of
    Lemma 1 held, each ref/leader link up or down per tick (raster), each link's delivery ratio
    (ticks >= 1: the start-up exchange is never faulted) and the histogram of the delivered
    messages' delays (queue wait + serialization + delay/jitter or trace), in ms."""
    nbrs = [sc.neighbours(i) for i in range(sc.n)]
    pinned = [float(b) > 0 for b in sc.graph.pinning]
    T = _last_data_tick(ts) + 1
    gs = graph_series(faults, nbrs, pinned, ts.q[:T], ts.q0[:T], sc.timing.dt)
    t = np.arange(T) * sc.timing.dt
    links = gs.links
    nl = len(links)
    fig = _figure((13.0, max(6.5, 0.13 * nl + 4.0)), layout="constrained")
    gsp = fig.add_gridspec(2, 2, width_ratios=(2.2, 1.0), height_ratios=(1.0, max(1.5, 0.05 * nl + 1.0)))
    ax_c = fig.add_subplot(gsp[0, 0])
    ax_r = fig.add_subplot(gsp[1, 0], sharex=ax_c)
    ax_h = fig.add_subplot(gsp[0, 1])
    ax_d = fig.add_subplot(gsp[1, 1])

    ax_c.step(t, gs.components, where="post", color="tab:blue", label="connected components")
    held = gs.tree.astype(float)
    ax_c.fill_between(t, 0, held * 0.5, step="post", color="tab:green", alpha=0.3, label="spanning tree from the leader held")
    ax_c.set_ylim(0, max(2, int(gs.components.max(initial=1))) + 0.5)
    ax_c.set_ylabel("components")
    frac = float(np.mean(gs.tree)) if T else 0.0
    cmax = int(gs.components.max(initial=0))
    ax_c.set_title(f"effective graph: up to {cmax} components, spanning tree {100 * frac:.1f} % of ticks", fontsize=10)
    ax_c.legend(fontsize=8, loc="upper right")
    ax_c.grid(True, alpha=0.3)

    if nl:
        up = np.array([ls.up for ls in links], dtype=float)
        ax_r.imshow(up, aspect="auto", interpolation="nearest", cmap="RdYlGn", vmin=0, vmax=1,
                    extent=(0.0, T * sc.timing.dt, nl - 0.5, -0.5))  # fmt: skip
        ax_r.set_yticks(np.arange(nl), [ls.name for ls in links], fontsize=6 if nl > 20 else 8)
    ax_r.set_xlabel("t (s)")
    ax_r.set_title("links up (green) / down (red), per tick", fontsize=10)

    ratio = np.array([float(np.mean(ls.up[1:])) if T > 1 else 1.0 for ls in links])
    y = np.arange(nl)
    ax_d.barh(y, ratio, color=["tab:red" if r < 1.0 else "tab:green" for r in ratio])
    ax_d.set_yticks(y, [ls.name for ls in links], fontsize=6 if nl > 20 else 8)
    ax_d.invert_yaxis()
    ax_d.set_xlim(0, 1.05)
    ax_d.set_xlabel("delivery ratio (ticks >= 1)")
    ax_d.set_title(f"per-link delivery: mean {float(ratio.mean()) if nl else 1.0:.3f}", fontsize=10)
    ax_d.grid(True, axis="x", alpha=0.3)

    for kind, color in (("ref", "tab:blue"), ("leader", "tab:orange")):
        d = [ls.delay_s[1:][ls.up[1:]] for ls in links if ls.kind == kind]
        ms = np.concatenate(d) * 1e3 if d else np.zeros(0)
        if ms.size:
            ax_h.hist(ms, bins=40, color=color, alpha=0.6,
                      label=f"{kind}: {ms.size} msgs, mean {ms.mean():.2f} ms, p95 {np.percentile(ms, 95):.2f} ms")  # fmt: skip
    ax_h.set_xlabel("delay of delivered messages (ms)")
    ax_h.set_ylabel("messages")
    ax_h.set_title("latency histogram", fontsize=10)
    if ax_h.get_legend_handles_labels()[0]:
        ax_h.legend(fontsize=7)
    ax_h.grid(True, alpha=0.3)
    fig.suptitle("communication: effective graph, delivery and latency")
    return _save(fig, path, formats)[0]


# =========================================================================== reports


def _written(first: Path, formats: Sequence[str]) -> list[Path]:
    """The files a figure was written as: ``first`` with each suffix of ``formats``."""
    return [first.with_suffix("." + f) for f in formats]


def report_from_series(
    ts: TimeSeries, scenario: Scenario, out_dir: str | Path, faults: FaultPlan | None = None, formats: Sequence[str] = ("png",)
) -> list[Path]:
    """Write the figures that need only the time series (trajectories, formation and tracking
    errors, clearance) into ``out_dir`` (created), each in every format of ``formats``
    (:data:`zenswarm.bridge.args.FIGURE_FORMATS`); returns their paths. With ``faults`` (the run's link-fault plan) that has a
    radio model, a capacity queue or a trace, also ``effective_graph.png`` (:func:`plot_effective_graph`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if len(ts.t) == 0:
        raise ZenswarmError("the time series is empty: nothing to plot")
    fm = tuple(formats) or ("png",)
    firsts = [
        plot_trajectories(ts, scenario, out / "trajectories_3d.png", fm),
        plot_formation_errors(ts, scenario, out / "formation_errors.png", fm),
        plot_vehicle_formation_errors(ts, scenario, out / "formation_errors_vehicles.png", fm),
        plot_tracking_errors(ts, scenario, out / "tracking_errors.png", fm),
        plot_clearance(ts, scenario, out / "clearance.png", fm),
        plot_commands(ts, scenario, out / "commands.png", fm),
    ]
    if ts.plant:
        firsts.append(plot_plant_records(ts, scenario, out / "plant.png", fm))
    net = network_plan(scenario, faults)
    if net is not None:
        firsts.append(plot_effective_graph(ts, scenario, net, out / "effective_graph.png", fm))
    return [f for first in firsts for f in _written(first, fm)]


def results_from_flight(fl: Flight, full_time: bool = False) -> dict[str, Any]:
    """results.json of a recorded flight: compute_results plus the bus statistics. The flight is
    judged up to the tick its outcome was decided (as the run ended there) unless ``full_time``."""
    res = compute_results(fl.series, fl.scenario, wall_time_s=None, early_end=not full_time)
    res["mode"] = fl.mode
    res["swarm"] = fl.swarm
    res["diagnostics"] = fl.diagnostics
    res["decoder_rejects"] = fl.decoder_counters
    res["message_counts"] = dict(sorted(fl.message_counts.items()))
    return res


def report_recording(
    path: str | Path,
    out_dir: str | Path,
    full_time: bool = False,
    warn: Callable[[str], None] | None = None,
    formats: Sequence[str] = ("png",),
) -> list[Path]:
    """The full report of a recording: every figure of :data:`FIGURES` and ``results.json``, and
    ``effective_graph.png`` when the run had a radio model, a capacity queue or a trace (the
    scenario's ``[faults]`` and the fault flags in the recording's metadata).

    full_time: judge every recorded tick, as ``--full-time`` runs do. formats: the figures'
    formats (:data:`zenswarm.bridge.args.FIGURE_FORMATS`), each figure once per format. warn: called with each
    thing the reader must know (:attr:`Recording.notes`): a truncated or damaged recording (then
    also which sim time the report covers), payloads not recorded."""
    rec = load_recording(path)
    fl = flight_from_recording(rec)
    if warn is not None:
        for note in rec.notes:
            warn(note)
        if rec.truncated:
            sc = rec.scenario
            warn(f"the report covers sim time 0 to {len(fl.series.t) * sc.timing.dt:.2f} s of the {sc.timing.time_limit_s:g} s time limit")
    out = Path(out_dir)
    fm = tuple(formats) or ("png",)
    files = report_from_series(fl.series, fl.scenario, out, faults=recorded_fault_plan(rec), formats=fm)
    files += _written(plot_links(fl, out / "links.png", fm), fm)
    res = results_from_flight(fl, full_time=full_time)
    res["recording"] = str(rec.path)
    res["recording_truncated"] = rec.truncated
    rp = out / "results.json"
    rp.write_text(json.dumps(res, indent=2, sort_keys=True, default=str) + "\n")
    files.append(rp)
    return files


# =========================================================================== CLI


def _run_report(args: argparse.Namespace) -> int:
    if (args.recording is None) == (args.series is None):
        args._parser.error("give either a recording FILE or --series NPZ --scenario TOML")
    check_output_dir(args.out, "--out")
    if args.series is not None:
        if args.scenario is None:
            args._parser.error("--series needs --scenario (the scenario the series was flown with)")
        sc = load_scenario(args.scenario)
        try:
            ts = TimeSeries.load(str(args.series))
        except FileNotFoundError:
            raise RecordingError(f"{args.series}: no such time series file") from None
        except (OSError, ValueError, KeyError) as e:
            raise RecordingError(f"{args.series}: not a zenswarm timeseries.npz ({e})") from None
        if ts.q.ndim != 3 or ts.q.shape[1] != sc.n:
            got = ts.q.shape[1] if ts.q.ndim == 3 else "?"
            raise ScenarioError("--scenario", f"{args.scenario} has {sc.n} UAVs but {args.series} has {got}")
        files = report_from_series(ts, sc, args.out, faults=plan_for(sc), formats=args.format)
    else:
        import sys

        def warn(text: str) -> None:
            print(f"report: warning: {args.recording}: {text}", file=sys.stderr, flush=True)

        files = report_recording(args.recording, args.out, full_time=args.full_time, warn=warn, formats=args.format)
    for f in files:
        print(f)
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``zenswarm report`` on the CLI's subparsers."""
    p = sub.add_parser(
        "report",
        help="flight report (figures like the paper's Figs 4-8, results.json) from a recording",
        description=(
            "Write the flight report of a recording into OUT: trajectories_3d.png, "
            "formation_errors.png (generator), formation_errors_vehicles.png, tracking_errors.png, clearance.png, "
            "commands.png (commanded against achieved thrust and attitude), "
            "plant.png (what the plant model recorded, e.g. rotor thrusts), "
            "links.png, effective_graph.png (runs with a radio model, capacity queue or link trace) and results.json "
            "(the same fields as `zenswarm sim`). Works from the MCAP file alone; a "
            "truncated or damaged recording is reported from what can be read, with a warning on stderr (also for "
            "payloads the recorder did not record). With --series, plot a `zenswarm sim` time series instead (no "
            "links.png, no results.json)."
        ),
    )
    p.add_argument("recording", nargs="?", type=Path, metavar="FILE", help="MCAP recording (zenswarm up --record / zenswarm record)")
    p.add_argument("--out", type=Path, required=True, help="output directory (created)")
    p.add_argument("--series", type=Path, metavar="NPZ", help="a timeseries.npz written by zenswarm sim or zenswarm up")
    p.add_argument("--scenario", type=Path, metavar="TOML", help="with --series: the scenario file of that run")
    p.add_argument(
        "--format",
        type=figure_formats,
        default=("png",),
        metavar="FMT[,FMT...]",
        help=f"the figures' formats, comma-separated, of {', '.join(FIGURE_FORMATS)} (default png; e.g. png,svg,pdf: each "
        "figure in each; SVG and PDF are vector, for papers)",
    )
    p.add_argument(
        "--full-time",
        action="store_true",
        help="judge every recorded tick (for runs flown with --full-time); by default the flight is judged up to "
        "the tick its outcome was decided, as the run itself ended there",
    )
    p.set_defaults(func=_run_report, _parser=p)


def main(argv: Sequence[str] | None = None) -> int:
    """Stand-alone entry (``python -m zenswarm.bridge.reports.report ...``): the ``report`` command only
    (``zenswarm`` wires ``report`` and ``export`` through :mod:`zenswarm.bridge.cli`; this module
    does not import :mod:`zenswarm.bridge.views.foxglove`, which imports it)."""

    parser = argparse.ArgumentParser(prog="zenswarm")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parsers(sub)
    args = parser.parse_args(argv)
    return run_command(lambda: args.func(args))


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())

"""The flight report's figures: one function per figure, each drawing a flight's
:class:`zenswarm.judge.metrics.TimeSeries` (or, for ``links.png``, a
:class:`zenswarm.bridge.reports.flight.Flight`) on a matplotlib Figure (Agg canvas, no pyplot, no
display) and writing it in each format asked (PNG, SVG, PDF), after the paper's Figs 4-8. What each
figure shows, and the report that writes them all: :mod:`zenswarm.bridge.reports.report`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from zenswarm.bridge.reports.flight import Flight, last_data_tick
from zenswarm.judge.metrics import TimeSeries
from zenswarm.link import FaultPlan, graph_series
from zenswarm.scenario.config import Scenario
from zenswarm.vehicle.geometry import d_obs_many, obstacle_clearance_many

__all__ = [
    "VIEW_3D",
    "GOAL_MS",
    "COMMAND_UAVS",
    "PLANT_UAVS",
    "PLANT_SIGNALS",
    "hidden_behind_obstacles",
    "leader_d_obs",
    "uav_clearance",
    "plot_trajectories",
    "plot_formation_errors",
    "plot_vehicle_formation_errors",
    "plot_tracking_errors",
    "plot_clearance",
    "plot_commands",
    "plot_plant_records",
    "plot_links",
    "plot_effective_graph",
]

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


def plot_effective_graph(ts: TimeSeries, sc: Scenario, faults: FaultPlan, path: Path, formats: Sequence[str] = ("png",)) -> Path:
    """The effective communication graph over time (:func:`zenswarm.link.swarm.graph_series`,
    recomputed from the fault plan and the flown series, as ``results.json``'s ``effective_graph``):
    the connected components per tick with the ticks where the leader-rooted spanning tree of
    Lemma 1 held, each ref/leader link up or down per tick (raster), each link's delivery ratio
    (ticks >= 1: the start-up exchange is never faulted) and the histogram of the delivered
    messages' delays (queue wait + serialization + delay/jitter or trace), in ms."""
    nbrs = [sc.neighbours(i) for i in range(sc.n)]
    pinned = [float(b) > 0 for b in sc.graph.pinning]
    T = last_data_tick(ts) + 1
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

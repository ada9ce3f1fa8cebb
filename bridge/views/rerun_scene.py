"""The Rerun encoder of the scene (:mod:`zenswarm.bridge.views.scene`, the neutral description of what
the view shows), for the open-source `Rerun <https://rerun.io>`_ viewer (the ``rerun-sdk``
package, extra ``zenswarm[rerun]``):

* ``zenswarm export FILE --rerun OUT.rrd`` (:func:`export_rerun`): a recording Rerun opens
  (``rerun OUT.rrd``, or drop it on the web viewer), from the same frames as
  ``zenswarm export --foxglove``;
* ``zenswarm up ... --live rerun[:PORT]`` and ``zenswarm replay FILE --live rerun[:PORT]``
  (:class:`RerunLiveView`): Rerun's own web viewer and gRPC data server, on loopback, fed as
  the flight goes.

What is logged (entity paths), every frame on the ``sim_time`` timeline (a duration: the wire's
sim time t):

``world``                        view coordinates ENU (right-handed, z up), m; static
``world/<entity>/<kind>``        each entity of :func:`zenswarm.bridge.views.scene.describe` (``obstacle/1``,
                                 ``d0_band/1``, ``goal``, ``start``, ``leader``, ``uav/1``, ``links``,
                                 ``trails``) as archetypes: ``spheres`` (Ellipsoids3D), ``cylinders``
                                 (Cylinders3D), ``cubes`` (Boxes3D), ``arrows`` (Arrows3D), ``labels``
                                 (Points3D with labels), ``lines`` (LineStrips3D); translucent shapes
                                 (alpha < 0.5: the d0 bands, the leader's sphere of radius r_f, the
                                 references q*_i) under ``<kind>_faint`` as a transparent fill with a
                                 wireframe. The obstacles, bands, goal and start are static (logged once);
                                 a part that goes away (an arrow when the UAV stops) is cleared.
``world/frames/<child>``         the poses of :func:`zenswarm.bridge.views.scene.poses` (Transform3D and
                                 its axes): ``leader``, ``uav<i>`` with the measured attitude
``metrics/<name>``               Scalars: :func:`zenswarm.bridge.views.scene.metric_series` of the frame's
                                 figures (``formation_error_m/uav1``, ``clearance_m/uav2``,
                                 ``max_tracking_error_m``, ``link_delivery/<link>``, ...)

Why the web viewer runs as the wheel's ``rerun`` executable: the SDK's in-process servers
(``rr.serve_grpc``, ``rr.serve_web_viewer``, rerun-sdk 0.41) listen on 0.0.0.0, every interface,
with no option to narrow it; the same wheel's ``rerun --serve-web --bind 127.0.0.1`` serves the
same viewer and gRPC server on loopback only. The view logs to it with ``connect_grpc``.
"""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
import urllib.parse
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm.bridge.views.scene import PacedView
from zenswarm.errors import RecordingError, ScenarioError, ZenswarmError

__all__ = [
    "EXTRA",
    "TIMELINE",
    "require_rerun",
    "RerunScene",
    "RerunSummary",
    "export_rerun",
    "RerunServer",
    "RerunLiveView",
]

EXTRA = "zenswarm[rerun]"
"""The extra that installs rerun-sdk: ``pip install 'zenswarm[rerun]'`` (from a checkout ``pip install -e '.[rerun]'``)."""

TIMELINE = "sim_time"
"""The timeline every frame is logged on: the sim time, a duration."""

HOST = "127.0.0.1"

FAINT = 0.5
"""Shapes with alpha below this are drawn as a transparent fill with a wireframe (``<kind>_faint``)."""


QUIET_SDK_LOG = "warn,re_grpc_client=off,re_sdk=off"
"""``RUST_LOG`` of the live view's rerun-sdk (unless the user set one): its gRPC client and
recording stream log a connection severed at the end (a viewer that could not keep up) as errors;
:meth:`RerunLiveView.close` says it in one line instead."""


def require_rerun(flag: str) -> None:
    """Raise :class:`ScenarioError` naming ``flag`` and the extra when rerun-sdk is not installed."""
    quiet = "RUST_LOG" not in os.environ and "rerun" not in sys.modules
    if quiet:  # the SDK reads RUST_LOG once, when first imported
        os.environ["RUST_LOG"] = QUIET_SDK_LOG
    try:
        import rerun  # noqa: F401
    except ImportError:
        raise ScenarioError(
            flag, f"needs the Rerun SDK (rerun-sdk), not installed: pip install '{EXTRA}' (from a checkout: pip install -e '.[rerun]')"
        ) from None
    finally:
        if quiet:
            os.environ.pop("RUST_LOG", None)  # the swarm's processes (Zenoh's logging) do not inherit it


def _u8(c: tuple[float, float, float, float]) -> list[int]:
    return [int(round(255.0 * min(1.0, max(0.0, x)))) for x in c]


def _fill(faint: bool) -> Any:
    from rerun.components import FillMode

    return FillMode.TransparentFillMajorWireframe if faint else FillMode.Solid


def _parts(e: Any) -> dict[str, Any]:
    """The Rerun archetypes of one neutral entity: ``kind`` (path under the entity) -> archetype."""
    import rerun as rr

    out: dict[str, Any] = {}
    for faint in (False, True):
        sfx = "_faint" if faint else ""
        sp = [s for s in e.spheres if (s.color[3] < FAINT) == faint]
        if sp:
            out["spheres" + sfx] = rr.Ellipsoids3D(
                centers=[np.asarray(s.center, dtype=float) for s in sp],
                half_sizes=[[0.5 * s.diameter] * 3 for s in sp],
                colors=[_u8(s.color) for s in sp],
                fill_mode=_fill(faint),
            )
        cy = [c for c in e.cylinders if (c.color[3] < FAINT) == faint]
        if cy:
            out["cylinders" + sfx] = rr.Cylinders3D(
                centers=[np.asarray(c.base, dtype=float) + (0.0, 0.0, 0.5 * c.height) for c in cy],
                lengths=[c.height for c in cy],
                radii=[0.5 * c.diameter for c in cy],
                colors=[_u8(c.color) for c in cy],
                fill_mode=_fill(faint),
            )
    if e.cubes:
        out["cubes"] = rr.Boxes3D(
            centers=[np.asarray(c.center, dtype=float) for c in e.cubes],
            sizes=[[c.size] * 3 for c in e.cubes],
            colors=[_u8(c.color) for c in e.cubes],
            fill_mode=_fill(False),
        )
    if e.arrows:
        out["arrows"] = rr.Arrows3D(
            origins=[np.asarray(a.origin, dtype=float) for a in e.arrows],
            vectors=[np.asarray(a.direction, dtype=float) * (a.length + a.head_length) for a in e.arrows],
            radii=[0.5 * a.shaft_diameter for a in e.arrows],
            colors=[_u8(a.color) for a in e.arrows],
        )
    if e.labels:
        out["labels"] = rr.Points3D(
            [np.asarray(t.position, dtype=float) for t in e.labels],
            labels=[t.text for t in e.labels],
            colors=[_u8(t.color) for t in e.labels],
            radii=rr.Radius.ui_points(1.0),
            show_labels=True,
        )
    if e.lines:
        strips, colors, radii = [], [], []
        for ln in e.lines:
            pts = [np.asarray(p, dtype=float) for p in ln.points]
            segs = [pts] if ln.kind == "strip" else [pts[i : i + 2] for i in range(0, len(pts) - 1, 2)]
            strips += segs
            colors += [_u8(ln.color)] * len(segs)
            radii += [-0.5 * ln.width] * len(segs)  # negative radius: ui points (screen size), as Foxglove's scale-invariant lines
        out["lines"] = rr.LineStrips3D(strips, colors=colors, radii=radii)
    return out


def _escape(name: str) -> str:
    import rerun as rr

    return "/".join(rr.escape_entity_path_part(p) for p in name.split("/"))


def blueprint() -> Any:
    """The default layout: the 3D scene beside plots of the errors, the clearances, the leader's
    d_obs against d0, and link delivery."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="/world", name="scene (ENU, m)"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="/metrics/formation_error_m", name="formation error ||q_i - q0 - h_i||, m"),
                rrb.TimeSeriesView(origin="/metrics/tracking_error_m", name="tracking error ||q*_i - q_i||, m"),
                rrb.TimeSeriesView(origin="/metrics/clearance_m", name="clearance to obstacles, m"),
                rrb.TimeSeriesView(
                    origin="/metrics",
                    contents=["/metrics/leader_d_obs_m", "/metrics/d0_m"],
                    name="virtual leader: d_obs(q0) against d0 (eq. 10), m",
                ),
                rrb.TimeSeriesView(
                    origin="/metrics",
                    contents=["/metrics/link_delivery/**", "/metrics/failsafe_uavs", "/metrics/min_inter_uav_m"],
                    name="links, failsafe, closest pair",
                ),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class RerunScene:
    """Logs frames of scenario ``sc`` on the Rerun recording stream ``rec`` (a file or a gRPC
    server; see the module docstring for what goes where)."""

    def __init__(self, sc: Any, rec: Any) -> None:
        import rerun as rr

        from zenswarm.bridge.views.scene import palette

        self.sc = sc
        self.rec = rec
        self.colors = palette(sc.n)
        self._logged: set[str] = set()  # the non-static parts logged so far
        self._static_done = False
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for i, col in enumerate(self.colors):  # each UAV's plots in its colour in the scene
            for fig in ("formation_error_m", "tracking_error_m", "clearance_m"):
                rec.log(f"metrics/{fig}/uav{i + 1}", rr.SeriesLines(colors=[_u8((*col, 1.0))], names=[f"uav {i + 1}"]), static=True)
        rec.log("metrics/leader_d_obs_m", rr.SeriesLines(colors=[[20, 20, 20]], names=["d_obs(q0)"], widths=[2.0]), static=True)
        rec.log("metrics/d0_m", rr.SeriesLines(colors=[_u8((0.95, 0.55, 0.15, 1.0))], names=["d0"]), static=True)
        self.frames = 0

    def put(self, f: Any, diag: dict[str, dict[str, Any]]) -> None:
        """Log frame ``f`` (:class:`zenswarm.bridge.views.scene.Frame`) at its sim time, with the figures
        of ``diag`` (process -> its newest diagnostics)."""
        import rerun as rr

        from zenswarm.bridge.views.scene import describe, metric_series, metrics, poses

        rec = self.rec
        rec.set_time(TIMELINE, duration=np.timedelta64(int(f.t_ns), "ns"))
        now: set[str] = set()
        for e in describe(f, self.sc, self.colors):
            if e.static and self._static_done:
                continue
            for kind, arch in _parts(e).items():
                path = f"world/{_escape(e.id)}/{kind}"
                rec.log(path, arch, static=e.static)
                if not e.static:
                    now.add(path)
        self._static_done = True
        for path in sorted(self._logged - now):  # gone since the last frame
            rec.log(path, rr.Clear(recursive=False))
        self._logged = now
        for p in poses(f):
            rec.log(
                f"world/frames/{_escape(p.child)}",
                rr.Transform3D(translation=np.asarray(p.position, dtype=float), quaternion=rr.Quaternion(xyzw=list(p.rotation))),
                rr.TransformAxes3D(0.1),
            )
        for name, value in metric_series(metrics(f, self.sc, diag)).items():
            rec.log(f"metrics/{_escape(name)}", rr.Scalars(value))
        self.frames += 1


# =========================================================================== export


@dataclass
class RerunSummary:
    """What :func:`export_rerun` wrote."""

    out: Path
    frames: int = 0
    entities: set[str] = field(default_factory=set)


def export_rerun(recording: str | Path, out: str | Path, *, scene_hz: float = 20.0, trail_s: float = 10.0) -> RerunSummary:
    """Write ``out`` (.rrd), the flight of ``recording`` (MCAP) as Rerun sees it: the frames of
    ``zenswarm export --foxglove`` (``scene_hz`` frames per second of sim time, trails of
    ``trail_s`` s), each with the diagnostics recorded up to its time. Written next to ``out``
    and renamed into place when complete. Raises RecordingError for an unusable input."""
    import rerun as rr

    from zenswarm.bridge.reports.flight import flight_from_recording, load_recording
    from zenswarm.bridge.views.foxglove import ExportSummary, _json_items, interleave, scene_frames
    from zenswarm.bridge.views.scene import frame_from_series
    from zenswarm.bus import wire

    if not scene_hz > 0 or not math.isfinite(scene_hz):
        raise ZenswarmError(f"--scene-hz must be a positive number, got {scene_hz}")
    if not trail_s >= 0 or not math.isfinite(trail_s):
        raise ZenswarmError(f"--trail-s must be >= 0, got {trail_s}")
    rec_in = load_recording(recording)
    out = Path(out)
    items, _ = _json_items(rec_in, wire.Keys(rec_in.swarm), ExportSummary(out), frozenset({"diag"}))  # the figures need the diagnostics
    items.sort(key=lambda it: (it[0], it[1]))
    try:
        ts = flight_from_recording(rec_in).series
    except RecordingError as e:
        raise RecordingError(f"{recording}: no flight to show in Rerun ({e})") from None
    frames, stride, trail_ticks = scene_frames(ts, rec_in.scenario, scene_hz, trail_s)
    summary = RerunSummary(out)
    tmp = out.with_name(out.name + ".part")
    out.parent.mkdir(parents=True, exist_ok=True)
    stream = rr.RecordingStream("zenswarm", recording_id=f"{rec_in.swarm}:{Path(recording).name}")
    stream.set_log_time_enabled(False)  # one timeline, sim_time: the file does not depend on when it was written
    stream.save(tmp, default_blueprint=blueprint())
    try:
        stream.send_recording_name(f"{rec_in.scenario.name} ({Path(recording).name})")
        scene = RerunScene(rec_in.scenario, stream)

        def put_frame(j: int, diag: dict[str, dict[str, Any]]) -> None:
            scene.put(frame_from_series(ts, frames[j][1], trail_ticks, stride), diag)

        interleave(items, [t for t, _ in frames], put_frame, lambda *_: None)
        summary.frames = scene.frames
        summary.entities = set(scene._logged)
        stream.flush()
    except BaseException:
        stream.disconnect()
        tmp.unlink(missing_ok=True)  # no half file left behind
        raise
    stream.disconnect()
    os.replace(tmp, out)
    return summary


# =========================================================================== live


def _pdeathsig() -> None:  # in the child between fork and exec: die with the process that started it
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


_GRPC_RE = re.compile(r"Listening for gRPC connections on [0-9.]+:(\d+)")
_WEB_RE = re.compile(r"Hosting a web-viewer at http://[0-9.]+:(\d+)")


def _rerun_executable() -> list[str]:
    """The wheel's ``rerun`` executable (rerun_cli), run as ``python -m rerun_cli`` when not on disk."""
    import importlib.util

    spec = importlib.util.find_spec("rerun_cli")
    exe = Path(spec.origin).parent / "rerun" if spec is not None and spec.origin else None
    return [str(exe)] if exe is not None and exe.is_file() else [sys.executable, "-m", "rerun_cli"]


class RerunServer:
    """Rerun's web viewer on ``http://127.0.0.1:web_port`` and its gRPC data server on
    ``grpc_port`` (0: any free port), both loopback only: the rerun-sdk wheel's ``rerun
    --serve-web --bind 127.0.0.1`` as a child process (dies with this one). Started at
    construction; a port in use (or a viewer that does not start) raises :class:`ScenarioError`
    naming ``flag``. :attr:`url` is what to open in a browser, :attr:`grpc_url` what the
    SDK (and the native viewer, ``rerun --connect URL``) connects to."""

    def __init__(self, web_port: int, grpc_port: int = 0, *, flag: str = "--live", timeout_s: float = 20.0) -> None:
        cmd = _rerun_executable() + [
            "--serve-web", "--bind", HOST, "--port", str(grpc_port), "--web-viewer-port", str(web_port),
            "--server-memory-limit", "25%",
        ]
        env = dict(os.environ, RUST_LOG="info")  # it says its ports at level info
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True,
            start_new_session=True, preexec_fn=_pdeathsig, env=env,
        )
        self.log: deque[str] = deque(maxlen=200)
        ports: dict[str, int] = {}
        ready = threading.Event()

        def pump() -> None:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                self.log.append(line.rstrip())
                for key, rx in (("grpc", _GRPC_RE), ("web", _WEB_RE)):
                    m = rx.search(line)
                    if m:
                        ports[key] = int(m.group(1))
                if len(ports) == 2:
                    ready.set()
            ready.set()  # it ended

        self._reader = threading.Thread(target=pump, name="rerun-viewer-log", daemon=True)
        self._reader.start()
        if not ready.wait(timeout_s) or len(ports) < 2:
            self.close()
            tail = " | ".join(line for line in list(self.log)[-4:] if line)
            raise ScenarioError(flag, f"Rerun's web viewer did not start on {HOST}:{web_port}: {_plain(tail) or 'no output'}")
        self.web_port, self.grpc_port = ports["web"], ports["grpc"]
        self.grpc_url = f"rerun+http://{HOST}:{self.grpc_port}/proxy"
        self.url = f"http://{HOST}:{self.web_port}/?url={urllib.parse.quote(self.grpc_url, safe='')}"

    def close(self) -> None:
        """Stop the viewer's process (SIGINT, then SIGKILL after 5 s)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        self._reader.join(timeout=5.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def _plain(text: str) -> str:
    return _ANSI.sub("", text)


CLOSE_FLUSH_S = 5.0
"""How long :meth:`RerunLiveView.close` waits for the logged frames to reach Rerun's server."""

LIVE_FLUSH_TICK_S = 0.5
"""The live view's Rerun batcher sends what was logged every this many wall seconds (rerun-sdk's
default for a network sink is 8 ms: each frame's every entity then went out as a chunk of its
own, about 40 chunks per frame; with 0.5 s about 5 frames share one chunk per entity, 4x fewer
bytes: BENCHMARKS.md, "Live view in Rerun")."""


def live_batcher() -> Any:
    """The ``rr.ChunkBatcherConfig`` of the live view's recording stream (:data:`LIVE_FLUSH_TICK_S`)."""
    import rerun as rr

    return rr.ChunkBatcherConfig(flush_tick=LIVE_FLUSH_TICK_S)


def _stderr(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


class RerunLiveView(PacedView):
    """The live view in Rerun: :class:`RerunServer` on ``port`` (the web viewer's; 0: any free)
    fed with the frames of swarm ``swarm`` flying ``sc`` (:class:`zenswarm.bridge.views.scene.LatestFrames`),
    at most ``hz`` per wall second. The same interface as :class:`zenswarm.bridge.views.live.LiveView`
    (:meth:`feed`, :meth:`maybe_publish`, :meth:`publish`, :meth:`close`, :meth:`how_to_open`)."""

    viewer = "rerun"

    def __init__(
        self, sc: Any, swarm: str, port: int, *, flag: str = "--live", hz: float = 10.0, trail_s: float = 10.0,
        warn: Callable[[str], None] = _stderr,
    ) -> None:
        require_rerun(flag)
        import rerun as rr

        super().__init__(sc, swarm, hz, trail_s)
        self.server = RerunServer(port, flag=flag)
        self.url = self.server.url
        self.port = self.server.web_port
        self.rec = rr.RecordingStream("zenswarm", recording_id=f"{swarm}:{time.time_ns()}", batcher_config=live_batcher())
        self.warn = warn
        self.rec.connect_grpc(self.server.grpc_url, default_blueprint=blueprint())
        self.rec.send_recording_name(f"{sc.name} (swarm {swarm}, live)")
        self.scene = RerunScene(sc, self.rec)

    def how_to_open(self) -> str:
        """The line the commands print: where the view is and how to open it."""
        return (
            f"live view (Rerun) on {self.url} : open it in a browser (the native viewer: rerun --connect {self.server.grpc_url})"
        )

    def publish(self) -> bool:
        """Log a frame of the newest messages (False: no state yet, or none newer than the last frame)."""
        got = self.latest.frame()
        if got is None:
            return False
        self.scene.put(*got)
        self.frames += 1
        return True

    def close(self, timeout_s: float = CLOSE_FLUSH_S) -> None:
        """Send what is logged and disconnect (waiting ``timeout_s`` for each at most), then stop
        the viewer's process (a browser showing it keeps what it received). Never raises and
        never changes the flight's outcome: if not everything went out in time (a browser
        reading slowly holds the server back), says so in one line (:attr:`warn`), stops the
        viewer and lets the rest go."""
        problem = ""
        done: threading.Thread | None = None
        try:
            try:
                self.rec.flush(timeout_sec=timeout_s)
            except RuntimeError as e:  # rerun-sdk: "Flush timed out - not all log messages were sent"
                problem = _plain(str(e)).strip().rstrip(".") or type(e).__name__
            if not problem:
                done = threading.Thread(target=self.rec.disconnect, name="rerun-disconnect", daemon=True)
                done.start()
                done.join(timeout_s)
                if done.is_alive():
                    problem = "the viewer's server did not take the last frames"
            if problem:
                self.warn(
                    f"live view (Rerun): not everything reached the viewer ({problem} within {timeout_s:g} s; "
                    f"{self.frames} frames logged); the viewer stops now"
                )
                self.server.close()  # the connection goes with it: the SDK stops waiting
                if done is None:
                    done = threading.Thread(target=self.rec.disconnect, name="rerun-disconnect", daemon=True)
                    done.start()
                done.join(timeout_s)
        except Exception as e:  # noqa: BLE001 -- a view never changes the mission's exit status
            self.warn(f"live view (Rerun): closing it failed: {e}")
        finally:
            self.server.close()

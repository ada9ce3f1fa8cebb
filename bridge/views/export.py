"""``zenswarm export``: a recording for a viewer. ``--foxglove FILE --out OUT.mcap`` (or ``FILE
--out OUT.mcap``): an MCAP file for Foxglove (:mod:`zenswarm.bridge.views.foxglove`); ``FILE --rerun
OUT.rrd``: a Rerun recording (:mod:`zenswarm.bridge.views.rerun_scene`, extra ``zenswarm[rerun]``);
both at once. Every flag is checked before either is written (exit 2 naming it)."""

from __future__ import annotations

import argparse
from pathlib import Path

from zenswarm.bridge.views.foxglove import SCENE_TOPIC, TF_TOPIC, export_foxglove

__all__ = ["add_parsers"]



def _not_the_source(source: str, out: str, flag: str) -> None:
    """An output path that is the recording being read would overwrite it before it is read
    through: :class:`ScenarioError` naming ``flag`` (exit 2), nothing written."""
    import os

    from zenswarm.errors import ScenarioError

    if os.path.exists(source) and os.path.exists(out) and os.path.samefile(source, out):
        raise ScenarioError(flag, f"{out} is the recording being exported ({source}): write to another file")


def _run_export(args: argparse.Namespace) -> int:
    from zenswarm.errors import ScenarioError
    from zenswarm.process.paths import check_output_file

    if args.recording is not None and args.foxglove is not None:
        raise ScenarioError("--foxglove", f"one recording at a time: {args.recording} (positional) or --foxglove {args.foxglove}, not both")
    source = args.foxglove if args.foxglove is not None else args.recording
    if source is None:
        raise ScenarioError(
            "FILE", "name the recording to export: zenswarm export FILE --rerun OUT.rrd, or --foxglove FILE --out OUT.mcap"
        )
    if args.foxglove is not None and args.out is None:
        raise ScenarioError("--out", "--foxglove FILE writes OUT.mcap: give --out OUT.mcap")
    if args.out is None and args.rerun is None:
        raise ScenarioError("--out", "nothing to write: --out OUT.mcap (Foxglove) and/or --rerun OUT.rrd (Rerun)")
    if args.out is not None:
        check_output_file(args.out, "--out")
        _not_the_source(source, args.out, "--out")
    if args.rerun is not None:
        from zenswarm.bridge.views.rerun_scene import require_rerun

        require_rerun("--rerun")
        check_output_file(args.rerun, "--rerun")
        _not_the_source(source, args.rerun, "--rerun")
        if args.out is not None and Path(args.out).resolve() == Path(args.rerun).resolve():
            raise ScenarioError("--rerun", f"{args.rerun} is also --out")
    if args.out is not None:
        s = export_foxglove(source, args.out, scene_hz=args.scene_hz, trail_s=args.trail_s)
        skipped = ", ".join(f"{n} {why}" for why, n in sorted(s.skipped.items())) or "none"
        print(
            f"{s.out}: {s.messages} recorded messages on {len(s.topics) - (2 if s.scene_frames else 0)} JSON channels, "
            f"{s.scene_frames} scene frames on {SCENE_TOPIC} and {TF_TOPIC}; skipped: {skipped}"
        )
        print(s.out)
    if args.rerun is not None:
        from zenswarm.bridge.views.rerun_scene import export_rerun

        r = export_rerun(source, args.rerun, scene_hz=args.scene_hz, trail_s=args.trail_s)
        print(f"{r.out}: {r.frames} frames for Rerun on the sim_time timeline (open it: rerun {r.out})")
        print(r.out)
    return 0


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``zenswarm export`` on the CLI's subparsers."""
    p = sub.add_parser(
        "export",
        help="export a recording for viewers (--foxglove ... --out: MCAP for Foxglove; --rerun: .rrd for Rerun)",
        description=(
            "Export a recording. --foxglove FILE --out OUT.mcap (or FILE --out OUT.mcap) writes an MCAP "
            "file Foxglove opens without plugins: every recorded message as JSON with a JSON Schema per "
            "message kind (topics are the Zenoh keys), plus a 3D scene on /scene (foxglove.SceneUpdate: "
            "obstacles, UAVs, trails, the virtual leader and its enclosing sphere) and /tf "
            "(foxglove.FrameTransforms), timed in sim time. FILE --rerun OUT.rrd writes the same scene "
            "and the errors, clearances and link health as time series for Rerun (rerun OUT.rrd), on "
            "the sim_time timeline (needs zenswarm[rerun]). Both at once: FILE --out OUT.mcap --rerun OUT.rrd."
        ),
    )
    p.add_argument("recording", nargs="?", type=Path, metavar="FILE", help="the MCAP recording to export")
    p.add_argument("--foxglove", type=Path, metavar="FILE", help="the MCAP recording to export for Foxglove (then --out is needed)")
    p.add_argument("--out", type=Path, metavar="OUT.mcap", help="output MCAP file for Foxglove (replaced if present)")
    p.add_argument("--rerun", type=Path, metavar="OUT.rrd", help="output Rerun recording (replaced if present; needs zenswarm[rerun])")
    p.add_argument("--scene-hz", type=float, default=20.0, help="rate of the scene's frames in sim time (default 20)")
    p.add_argument("--trail-s", type=float, default=10.0, help="length of the trails, s of sim time (default 10)")
    p.set_defaults(func=_run_export)

"""The flight report of ``zenswarm up --record FILE --report``: written from the recording alone
once the flight's results are (:func:`report_hook`, the end hook the front door attaches to the
supervisor), partial if the recorder died."""

from __future__ import annotations

from collections.abc import Sequence

from zenswarm.compose.hooks import EndHook, FlightEnd
from zenswarm.errors import ZenswarmError

__all__ = ["report_hook"]


def report_hook(formats: Sequence[str], *, full_time: bool) -> EndHook:
    """The end hook writing the report into OUT/report, its figures in ``formats``; ``full_time``:
    every recorded tick judged (``--full-time``). A report that fails is said, never an exit status."""

    def report(end: FlightEnd) -> None:
        if end.recording is None:
            return
        loss = end.recording_loss
        if loss is not None:
            end.say(f"report: warning: the recorder died at sim time {loss['died_at_sim_time_s']:.2f} s: "
                    "the report is partial, from what was recorded before")  # fmt: skip
        try:
            from zenswarm.bridge.reports.report import report_recording

            written = report_recording(
                end.recording, end.out / "report", full_time=full_time, warn=lambda text: end.say(f"report: warning: {text}"),
                formats=formats,
            )  # fmt: skip
        except ZenswarmError as e:
            end.say(f"report failed: {e}")
            return
        end.say(f"report: {len(written)} files in {end.out / 'report'}")

    return report

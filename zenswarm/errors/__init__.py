"""The project's one exception hierarchy, the exit statuses, and the wrapper that turns one into
the other at a command line (:func:`run_command`)."""

from __future__ import annotations

import sys
from collections.abc import Callable


class ZenswarmError(Exception):
    """Base class of every error zenswarm raises on purpose."""


class ScenarioError(ZenswarmError):
    """A scenario file or value is invalid. ``field`` names the offending field (dotted path)."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")


class DecodeError(ZenswarmError):
    """A payload on the bus could not be decoded or failed validation."""


class ProcessFailure(ZenswarmError):
    """A swarm process died or the mission failed."""


class RecordingError(ZenswarmError):
    """An MCAP recording is missing, truncated or corrupted."""


class CampaignError(ZenswarmError):
    """A campaign directory (``zenswarm sweep --out DIR``) is missing, unreadable or malformed."""


EXIT_OK, EXIT_MISSION_FAILED, EXIT_PROCESS_FAILED = 0, 1, 3
"""Exit statuses of a flight (``zenswarm sim``, ``zenswarm up``): the mission succeeded, it
failed (goal not reached, a collision), a process died for good (``zenswarm up``)."""

EXIT_BAD_INPUT = 2
"""Exit status of a command refused before any work: a :class:`ZenswarmError` (bad input, a busy
port, a missing file, ...), said on stderr."""

EXIT_INTERRUPTED = 130
"""Exit status of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it)."""

EXIT_BROKEN_PIPE = 141
"""Exit status of a command whose standard output was closed by its reader (``zenswarm info F |
head``): 128 + SIGPIPE, as a shell reports a program the closed pipe stopped; nothing more is
printed, no traceback."""

EXIT_PLUGIN_FAILED = 4
"""Exit status of ``zenswarm sim``, ``zenswarm up`` and a swarm process when a plug-in failed
(:class:`PluginFailure`): distinct from 1 (the mission failed) and 3 (a process died)."""


class PluginFailure(ZenswarmError):
    """A plug-in (a controller, a planner or a plant model) misbehaved at its boundary: it raised,
    or returned a non-finite or wrongly shaped value. Caught where the runner calls the plug-in
    (:class:`zenswarm.scenario.plugins.Boundary`) and turned into the failure ``plugin_error`` of the
    verdict, at the sim time ``tick * dt`` it happened, by the simulator and the swarm alike.

    kind: ``controller``, ``planner`` or ``plant``. plugin: the name it was selected by.
    process: the swarm process that runs it (``agent:2``, ``leader``, ``plant``). uavs: the UAVs
    concerned, 1-based. tick: the control tick whose value it failed to give. stage: where in
    that tick (:data:`zenswarm.scenario.plugins.STAGES`: the failures of a run are those of its first
    (tick, stage)). call: the method (``step``, ``share``, ``ref``, ...). field: the bad output
    field (``thrust``, ``rpy``, ``q0``, ...; None when it raised). detail: what was wrong.
    """

    def __init__(
        self, kind: str, plugin: str, process: str, uavs: tuple[int, ...], tick: int, stage: int, call: str,
        detail: str, field: str | None = None,
    ) -> None:
        self.kind = kind
        self.plugin = plugin
        self.process = process
        self.uavs = tuple(int(u) for u in uavs)
        self.tick = int(tick)
        self.stage = int(stage)
        self.call = call
        self.detail = detail
        self.field = field
        super().__init__(f"{kind} {plugin!r} of {process} failed at tick {tick} in {call}(): {detail}")

    @property
    def order(self) -> tuple[int, int]:
        """(tick, stage): the failures of a run are those with the smallest."""
        return (self.tick, self.stage)

    def failure(self, dt: float) -> dict[str, object]:
        """The ``plugin_error`` failure of a results dict (dt: the control tick, s)."""
        return {
            "cause": "plugin_error", "t_s": self.tick * dt, "uavs": list(self.uavs), "detail": self.args[0],
            "plugin": self.plugin, "kind": self.kind, "process": self.process, "tick": self.tick, "stage": self.stage,
            "call": self.call, "field": self.field,
        }

    def to_dict(self) -> dict[str, object]:
        """The fields, as a process reports them to its supervisor (:meth:`from_dict` reads them)."""
        return {
            "kind": self.kind, "plugin": self.plugin, "process": self.process, "uavs": list(self.uavs), "tick": self.tick,
            "stage": self.stage, "call": self.call, "detail": self.detail, "field": self.field,
        }

    @classmethod
    def from_dict(cls, d: dict[str, object]) -> PluginFailure:
        uavs = d.get("uavs") or ()
        assert isinstance(uavs, (list, tuple))
        field = d.get("field")
        return cls(
            str(d["kind"]), str(d["plugin"]), str(d["process"]), tuple(int(u) for u in uavs), int(str(d["tick"])),
            int(str(d["stage"])), str(d["call"]), str(d["detail"]), None if field is None else str(field),
        )


def run_command(body: Callable[[], int | None], label: str = "zenswarm") -> int:
    """Run a command's ``body`` and return its exit status (None: 0). A :class:`ZenswarmError` is
    printed as ``label: error: ...`` on stderr, exit :data:`EXIT_BAD_INPUT`; Ctrl-C as ``label:
    interrupted``, exit :data:`EXIT_INTERRUPTED`; standard output closed by its reader (``| head``):
    silence, exit :data:`EXIT_BROKEN_PIPE`. The command lines' one wrapper (``zenswarm
    sweep``, ``python -m zenswarm.bridge.reports.report``, ...)."""
    try:
        return int(body() or 0)
    except ZenswarmError as e:
        print(f"{label}: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{label}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # the reader of standard output went away (``| head``): stop quietly; what is still
        # buffered goes nowhere, so the interpreter's last flush at exit does not fail again
        import os

        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):  # no file descriptor behind sys.stdout
            pass
        return EXIT_BROKEN_PIPE

"""zenswarm: hierarchical distributed formation flight for quadrotor swarms over Zenoh.

The package's folders are its layers (docs/architecture.md): the front door here (``zenswarm``
the command, :mod:`zenswarm.api`, :mod:`zenswarm.sweep`, the pytest plugin); the edges
(:mod:`zenswarm.compose`, :mod:`zenswarm.bridge`); the roles (:mod:`zenswarm.agents`,
:mod:`zenswarm.leader`, :mod:`zenswarm.plant`); and the base by concern: :mod:`zenswarm.process`,
:mod:`zenswarm.campaign`, :mod:`zenswarm.scenario`, :mod:`zenswarm.judge`, :mod:`zenswarm.link`,
:mod:`zenswarm.vehicle`, :mod:`zenswarm.bus`, :mod:`zenswarm.schema`, :mod:`zenswarm.errors`.

This module holds the version and nothing that imports a layer: importing any part of zenswarm
runs it. The base's modules had other names before 0.2 (``zenswarm.config``, ``zenswarm.faults``,
...), and the bridge's before its folders (``zenswarm.bridge.mavlink``, ...); :data:`MOVED` maps
each to its new name, and importing an old name gives the module under its new name with a
:class:`DeprecationWarning` (no second copy of a module is ever made).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from types import ModuleType

__version__ = "0.1.0"

MOVED: dict[str, str] = {
    "zenswarm.wire": "zenswarm.bus.wire",
    "zenswarm.geometry": "zenswarm.vehicle.geometry",
    "zenswarm.frames": "zenswarm.vehicle.frames",
    "zenswarm.inversion": "zenswarm.vehicle.inversion",
    "zenswarm.params": "zenswarm.vehicle.params",
    "zenswarm.autopilot": "zenswarm.vehicle.autopilot",
    "zenswarm.faults": "zenswarm.link.faults",
    "zenswarm.linkqueue": "zenswarm.link.queue",
    "zenswarm.linktrace": "zenswarm.link.trace",
    "zenswarm.radio": "zenswarm.link.radio",
    "zenswarm.linkfaults": "zenswarm.link.swarm",
    "zenswarm.config": "zenswarm.scenario.config",
    "zenswarm.overrides": "zenswarm.scenario.overrides",
    "zenswarm.generate": "zenswarm.scenario.generate",
    "zenswarm.plugins": "zenswarm.scenario.plugins",
    "zenswarm.verdict": "zenswarm.judge.verdict",
    "zenswarm.metrics": "zenswarm.judge.metrics",
    "zenswarm.runtime": "zenswarm.process.runtime",
    "zenswarm.security": "zenswarm.process.security",
    "zenswarm.collector": "zenswarm.process.collector",
    "zenswarm.rtsched": "zenswarm.process.rtsched",
    "zenswarm.paths": "zenswarm.process.paths",
    "zenswarm.delaymargin": "zenswarm.campaign.delaymargin",
    "zenswarm.policy": "zenswarm.compose.policy",
    # the bridge's modules before its folders (issue 44); zenswarm.bridge.replay is now the folder
    # (its module: zenswarm.bridge.replay.replay)
    "zenswarm.bridge.mcapio": "zenswarm.bridge.recording.mcapio",
    "zenswarm.bridge.recorder": "zenswarm.bridge.recording.recorder",
    "zenswarm.bridge.info": "zenswarm.bridge.recording.info",
    "zenswarm.bridge.playback": "zenswarm.bridge.replay.playback",
    "zenswarm.bridge.report": "zenswarm.bridge.reports.report",
    "zenswarm.bridge.sweep_report": "zenswarm.bridge.reports.sweep_report",
    "zenswarm.bridge.scene": "zenswarm.bridge.views.scene",
    "zenswarm.bridge.foxglove": "zenswarm.bridge.views.foxglove",
    "zenswarm.bridge.foxglove_scene": "zenswarm.bridge.views.foxglove_scene",
    "zenswarm.bridge.rerun_scene": "zenswarm.bridge.views.rerun_scene",
    "zenswarm.bridge.live": "zenswarm.bridge.views.live",
    "zenswarm.bridge.export": "zenswarm.bridge.views.export",
    "zenswarm.bridge.mavlink": "zenswarm.bridge.vehicles.mavlink",
    "zenswarm.bridge.crazyflie": "zenswarm.bridge.vehicles.crazyflie",
}
"""Old module name -> new name (0.1 -> 0.2, issue 29; the bridge's folders, issue 44)."""


class _Moved(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds an old name of :data:`MOVED` and loads it as the module under its new name."""

    def find_spec(self, fullname: str, path: object = None, target: object = None) -> importlib.machinery.ModuleSpec | None:
        return importlib.machinery.ModuleSpec(fullname, self) if fullname in MOVED else None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        new = MOVED[spec.name]
        warnings.warn(f"{spec.name} is now {new}; the old name goes in a later release", DeprecationWarning, stacklevel=2)
        module = importlib.import_module(new)
        spec.loader_state = module.__spec__  # the import system sets __spec__ of what we return
        return module

    def exec_module(self, module: ModuleType) -> None:
        spec = module.__spec__
        if spec is not None and isinstance(spec.loader_state, importlib.machinery.ModuleSpec):
            module.__spec__ = spec.loader_state  # the module's own, back


if not any(isinstance(f, _Moved) for f in sys.meta_path):
    sys.meta_path.append(_Moved())

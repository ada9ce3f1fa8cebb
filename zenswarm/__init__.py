"""zenswarm: hierarchical distributed formation flight for quadrotor swarms over Zenoh.

The package's folders are its layers (docs/architecture.md): the front door here (``zenswarm``
the command, :mod:`zenswarm.api`, :mod:`zenswarm.sweep`, the pytest plugin); the edges
(:mod:`zenswarm.compose`, :mod:`zenswarm.bridge`); the roles (:mod:`zenswarm.agents`,
:mod:`zenswarm.leader`, :mod:`zenswarm.plant`); and the base by concern: :mod:`zenswarm.process`,
:mod:`zenswarm.campaign`, :mod:`zenswarm.scenario`, :mod:`zenswarm.judge`, :mod:`zenswarm.link`,
:mod:`zenswarm.vehicle`, :mod:`zenswarm.bus`, :mod:`zenswarm.schema`, :mod:`zenswarm.errors`.

This module holds the version and nothing that imports a layer: importing any part of zenswarm
runs it. The base's modules had other names before 0.2 (``zenswarm.config``, ``zenswarm.faults``,
...); :data:`MOVED` maps each to its new name, and importing an old name gives the module under
its new name with a :class:`DeprecationWarning` (no second copy of a module is ever made).
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
}
"""Old module name -> new name (0.1 -> 0.2, issue 29)."""


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

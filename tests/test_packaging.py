"""The installed layout: one ``zenswarm`` namespace, nothing else in site-packages.

The repository keeps agents/ leader/ plant/ bridge/ compose/ at the top level; they install as
``zenswarm.agents`` ... ``zenswarm.compose`` (pyproject ``package-dir``). Run from a directory
outside the repository, so only what the installation provides can be imported.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROLES_AND_EDGES = ("agents", "leader", "plant", "bridge", "compose")


def _run(code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("name", ROLES_AND_EDGES)
def test_old_top_level_names_are_not_installed(name: str, tmp_path: Path) -> None:
    out = _run(f"import {name}", tmp_path)
    assert out.returncode != 0 and "ModuleNotFoundError" in out.stderr, f"`import {name}` worked outside the repo"


def test_namespace_packages_come_from_the_repository_folders(tmp_path: Path) -> None:
    code = "import importlib\n" + "".join(
        f"print(importlib.import_module('zenswarm.{n}').__file__)\n" for n in ROLES_AND_EDGES
    )
    out = _run(code, tmp_path)
    assert out.returncode == 0, out.stderr
    files = [Path(line) for line in out.stdout.split()]
    assert [f.parent.name for f in files] == list(ROLES_AND_EDGES)


def test_package_dir_maps_every_folder() -> None:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert cfg["package-dir"] == {"zenswarm": "zenswarm", **{f"zenswarm.{n}": n for n in ROLES_AND_EDGES}}
    # the sub-packages of every folder, at every depth (the base's zenswarm/<name>/, the bridge's
    # bridge/<name>/ and bridge/vehicles/mavlink/) install from it: each must be listed, or a wheel would
    # leave it out while an editable install still finds it
    subs = sorted(
        ".".join((pkg, *d.relative_to(ROOT / folder).parts)) for pkg, folder in cfg["package-dir"].items()
        for d in (ROOT / folder).rglob("*") if d.is_dir() and (d / "__init__.py").is_file()
    )  # fmt: skip
    assert "zenswarm.link" in subs and "zenswarm.bridge.recording" in subs, subs
    assert sorted(cfg["packages"]) == sorted([*cfg["package-dir"], *subs])


def test_builtin_scenarios_ship_with_the_package(tmp_path: Path) -> None:
    out = _run("import zenswarm.compose as c, pathlib; print(pathlib.Path(c.__file__).parent / 'scenarios')", tmp_path)
    assert out.returncode == 0, out.stderr
    assert (Path(out.stdout.strip()) / "paper_example1.toml").is_file()


def test_old_module_names_import_the_moved_modules(tmp_path: Path) -> None:
    """0.1's module names (zenswarm.config, zenswarm.faults, ...) still import: the very module
    under its new name, with a DeprecationWarning naming it (zenswarm.MOVED)."""
    code = """
import importlib, json, sys, warnings
import zenswarm
out = {}
for old, new in zenswarm.MOVED.items():
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        mod = importlib.import_module(old)
    out[old] = [mod is sys.modules[new], mod.__name__, mod.__spec__.name, [str(x.message) for x in w if x.category is DeprecationWarning]]
from zenswarm.faults import FaultPlan
from zenswarm.link import FaultPlan as New
out["same class"] = FaultPlan is New
print(json.dumps(out))
"""
    out = _run(code, tmp_path)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    import zenswarm

    assert res.pop("same class") is True
    assert set(res) == set(zenswarm.MOVED) and len(res) >= 20
    for old, (same, name, spec, warned) in res.items():
        new = zenswarm.MOVED[old]
        assert same and name == new and spec == new, (old, name, spec)
        assert any(new in w for w in warned), (old, warned)

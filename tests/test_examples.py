"""The example plug-in packages outside zenswarm (examples/consensus_controller, a controller, and
examples/lag_plant, a plant model) and a user's test module for the controller
(examples/user_tests/test_consensus.py), as a user would run them.

The example is installed into a fresh virtual environment that sees what this interpreter has
installed (``--system-site-packages``, and this interpreter's own site-packages added by a
``.pth`` file, as zenswarm itself usually lives in a venv): only the examples are installed, from
their directories, without build isolation and without the package index. Then the README's two
commands, ``zenswarm plugins`` and ``zenswarm plugins check`` (the simulator against a short
lockstep ``zenswarm up``, bit for bit), and the user's test file, copied to a directory outside
the repository and run with that environment's pytest.
"""

from __future__ import annotations

import os
import re
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "consensus_controller"
PLANT_EXAMPLE = ROOT / "examples" / "lag_plant"
USER_TESTS = ROOT / "examples" / "user_tests" / "test_consensus.py"

pytestmark = pytest.mark.swarm  # installs a package, starts processes


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PYTHONUNBUFFERED"] = "1"
    return env


@pytest.fixture(scope="module")
def venv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A venv with the examples installed (and nothing else); its bin/ directory."""
    d = tmp_path_factory.mktemp("venv") / "v"
    # --without-pip: no copy of pip bootstrapped into it (ensurepip took several seconds of CPU);
    # the pip that installs the examples below is this interpreter's, found through the .pth
    # file, and installs into this venv (the interpreter running it is the venv's)
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(d)], check=True, timeout=120)
    py = d / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    parents = [p for p in site.getsitepackages() if Path(p).is_dir()]
    (Path(purelib) / "_zenswarm_parent.pth").write_text("".join(f"import site; site.addsitedir({p!r})\n" for p in parents))
    src = tmp_path_factory.mktemp("src")
    builds = [src / ex.name for ex in (EXAMPLE, PLANT_EXAMPLE)]  # copies: the build writes into its source tree
    for ex, build in zip((EXAMPLE, PLANT_EXAMPLE), builds, strict=True):
        shutil.copytree(ex, build, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    cp = subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--no-build-isolation", *map(str, builds)],
                        capture_output=True, text=True, timeout=300, env=_env())
    assert cp.returncode == 0, cp.stdout + cp.stderr
    return d / "bin"


def _run(args: list[str], cwd: Path, timeout: float = 300.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=timeout, env=_env())


def test_readme_two_commands_install_and_fly_paper_example_1(venv: Path, tmp_path: Path) -> None:
    """The README's commands, in that venv: the example flies paper example 1 to success."""
    text = (EXAMPLE / "README.md").read_text()
    block = re.search(r"```sh\n(.*?)```", text, re.S)
    assert block is not None
    install, fly = block.group(1).strip().splitlines()
    assert install == "pip install ./examples/consensus_controller"  # done by the fixture, from a copy
    words = fly.split()
    assert words[:2] == ["zenswarm", "sim"] and "--controller" in words
    words[words.index("--out") + 1] = str(tmp_path / "out")
    cp = _run([str(venv / "python"), "-m", "zenswarm", *words[1:]], cwd=ROOT)
    assert cp.returncode == 0, cp.stdout[-3000:]
    assert "paper_example1: SUCCESS" in cp.stdout
    listed = _run([str(venv / "python"), "-m", "zenswarm", "plugins"], cwd=tmp_path)
    assert re.search(r"consensus\s+example plug-in: first-order consensus", listed.stdout), listed.stdout
    assert "entry point zenswarm.controllers: zenswarm_consensus.controller:ConsensusController" in listed.stdout


def test_conformance_check_passes_sim_equals_lockstep_up(venv: Path, tmp_path: Path) -> None:
    """`zenswarm plugins check consensus`: every check, the short lockstep swarm bit for bit."""
    cp = _run([str(venv / "python"), "-m", "zenswarm", "plugins", "check", "consensus", "--duration", "2"], cwd=tmp_path)
    assert cp.returncode == 0, cp.stdout[-3000:]
    assert re.search(r"PASS\s+sim == swarm\s+2 s of paper_example1, link loss 0.2", cp.stdout), cp.stdout
    assert cp.stdout.rstrip().endswith("result: PASS")


def test_plant_model_package_listed_checked_and_flown(venv: Path, tmp_path: Path) -> None:
    """examples/lag_plant: `zenswarm plugins` lists it under zenswarm.plants, `zenswarm plugins
    check lag` passes every check (the short lockstep swarm bit for bit), and the README's command
    flies paper example 1 on it to success."""
    listed = _run([str(venv / "python"), "-m", "zenswarm", "plugins"], cwd=tmp_path)
    assert "entry point zenswarm.plants: zenswarm_lagplant.model:LagPlant" in listed.stdout, listed.stdout
    cp = _run([str(venv / "python"), "-m", "zenswarm", "plugins", "check", "lag", "--duration", "2"], cwd=tmp_path)
    assert cp.returncode == 0, cp.stdout[-3000:]
    assert re.search(r"plant zenswarm_lagplant.model:LagPlant", cp.stdout), cp.stdout
    assert re.search(r"PASS\s+sim == swarm\s+2 s of paper_example1, link loss 0.2", cp.stdout), cp.stdout
    assert cp.stdout.rstrip().endswith("result: PASS")
    block = re.search(r"```sh\n(.*?)```", (PLANT_EXAMPLE / "README.md").read_text(), re.S)
    assert block is not None
    install, fly = block.group(1).strip().splitlines()
    assert install == "pip install ./examples/lag_plant"  # done by the fixture, from a copy
    words = fly.split()
    assert words[:2] == ["zenswarm", "sim"] and words[words.index("--plant-model") + 1] == "lag"
    words[words.index("--out") + 1] = str(tmp_path / "out")
    cp = _run([str(venv / "python"), "-m", "zenswarm", *words[1:], "--quiet"], cwd=ROOT)
    assert cp.returncode == 0 and "paper_example1: SUCCESS" in cp.stdout, cp.stdout[-3000:]


def test_users_test_module_passes_outside_the_repository(venv: Path, tmp_path: Path) -> None:
    """The user's pytest file, outside the repository, with the public fixtures only: it flies
    the plug-in in process and as processes under link faults and a SIGKILL; nothing is left."""
    work = tmp_path / "mytests"
    work.mkdir()
    shutil.copy(USER_TESTS, work / "test_consensus.py")
    cp = _run([str(venv / "python"), "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_consensus.py"], cwd=work, timeout=600)
    assert cp.returncode == 0, cp.stdout[-4000:]
    assert re.search(r"\b4 passed\b", cp.stdout), cp.stdout[-2000:]

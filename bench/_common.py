"""Shared helpers of the speed benchmarks in bench/ (not a benchmark itself).

* machine description (nproc, CPU model, Python/numpy/zenoh versions, BLAS, load average);
* CPU accounting of a run: our own CPU (this process + reaped children) and the CPU the rest
  of the machine used meanwhile ("background", in cores), from /proc/stat;
* scenario files (paper examples, ``zenswarm scenario generate`` with a time limit);
* running ``zenswarm up`` as a child, sampling its process tree (/proc) while it flies, and
  cleaning up every process it started (by pid, only processes whose command line carries our
  unique swarm name);
* the swarm's process-tree CPU by role over a flight, the message stamps of bench/stamps;
* a benchmark's start (cleanup on signals, temporary directory, machine printed), medians, a
  plain-text table and the JSON report.
"""

from __future__ import annotations

import json
import os
import platform
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
SCEN_DIR = REPO / "compose" / "scenarios"
STAMPS = Path(__file__).resolve().parent / "stamps"
PAPER = {"example1": SCEN_DIR / "paper_example1.toml", "example2": SCEN_DIR / "paper_example2.toml"}
CLK_TCK = os.sysconf("SC_CLK_TCK")
PAGE_KB = os.sysconf("SC_PAGE_SIZE") // 1024

# The README's note: these two variables slow a current numpy; benchmarks drop them for the
# measured command alone (tests and CI keep them). On this machine they are usually unset.
OPENBLAS_VARS = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")


# --------------------------------------------------------------------------- machine
def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "?"


def machine_info() -> dict[str, Any]:
    import numpy as np

    info: dict[str, Any] = {
        "nproc": len(os.sched_getaffinity(0)),
        "cpu_count": os.cpu_count(),
        "cpu_model": cpu_model(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "platform": platform.platform(),
        "loadavg_at_start": list(os.getloadavg()),
        "openblas_env": {k: os.environ[k] for k in OPENBLAS_VARS if k in os.environ},
    }
    try:
        from importlib.metadata import version

        info["zenoh"] = version("eclipse-zenoh")
        info["msgpack"] = version("msgpack")
    except Exception:  # noqa: BLE001
        pass
    try:
        cfg = np.show_config(mode="dicts")
        blas = cfg.get("Build Dependencies", {}).get("blas", {})
        info["numpy_blas"] = f"{blas.get('name', '?')} {blas.get('version', '')}".strip()
    except Exception:  # noqa: BLE001
        pass
    try:
        info["git_commit"] = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10
        ).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
        info["git_dirty"] = bool(dirty)
    except Exception:  # noqa: BLE001
        pass
    return info


def machine_lines(info: dict[str, Any]) -> list[str]:
    la = info.get("loadavg_at_start", [0, 0, 0])
    return [
        f"machine: {info['nproc']} cores, {info['cpu_model']}; Python {info['python']}, numpy {info['numpy']}"
        f" ({info.get('numpy_blas', '?')}), zenoh {info.get('zenoh', '?')}; commit {info.get('git_commit', '?')}"
        f"{' (dirty)' if info.get('git_dirty') else ''}",
        f"load average at start: {la[0]:.2f} {la[1]:.2f} {la[2]:.2f}; OPENBLAS env: {info['openblas_env'] or 'unset'}",
    ]


def bench_env(keep_openblas: bool = False) -> dict[str, str]:
    """Environment for a measured child: the README's OPENBLAS variables dropped (unless kept)."""
    env = dict(os.environ)
    if not keep_openblas:
        for k in OPENBLAS_VARS:
            env.pop(k, None)
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


# --------------------------------------------------------------------------- CPU accounting
def _proc_stat_busy_s() -> float:
    """Seconds of busy CPU (all cores) since boot: user+nice+system+irq+softirq+steal."""
    f = Path("/proc/stat").read_text().split("\n", 1)[0].split()
    user, nice, system, idle, iowait, irq, softirq, steal = (int(x) for x in f[1:9])
    return (user + nice + system + irq + softirq + steal) / CLK_TCK


def _own_cpu_s() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


class CpuWindow:
    """Our CPU and everybody else's over a time window.

    ``own_cpu_s``: this process and its reaped children (and theirs); ``background_cores``: busy CPU
    of the rest of the machine divided by the wall time, i.e. how many cores other jobs took.
    """

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.busy0 = _proc_stat_busy_s()
        self.own0 = _own_cpu_s()
        self.load0 = os.getloadavg()[0]

    def close(self) -> dict[str, float]:
        wall = time.perf_counter() - self.t0
        busy = _proc_stat_busy_s() - self.busy0
        own = _own_cpu_s() - self.own0
        return {
            "window_wall_s": wall,
            "own_cpu_s": own,
            "background_cores": max(0.0, busy - own) / wall if wall > 0 else 0.0,
            "load1_start": self.load0,
            "load1_end": os.getloadavg()[0],
        }


def wait_for_quiet(max_background: float, max_wait_s: float, probe_s: float = 2.0) -> float:
    """Wait (up to ``max_wait_s``) until other jobs use at most ``max_background`` cores; return it."""
    deadline = time.monotonic() + max_wait_s
    while True:
        b0, t0 = _proc_stat_busy_s(), time.monotonic()
        time.sleep(probe_s)
        bg = (_proc_stat_busy_s() - b0) / (time.monotonic() - t0)
        if bg <= max_background or time.monotonic() >= deadline:
            return bg


def quiet_wait(max_background: float, max_wait_s: float = 120.0) -> None:
    """``--quiet-wait CORES``: :func:`wait_for_quiet` when CORES > 0 (0 = don't wait)."""
    if max_background > 0:
        wait_for_quiet(max_background, max_wait_s)


# --------------------------------------------------------------------------- scenarios
def generated_scenario(n: int, out_dir: Path, time_limit: float | None = None, seed: int = 1) -> Path:
    """``zenswarm scenario generate --n N --shape circle --topology knn --k 3 --obstacles 2 --seed 1``."""
    name = f"gen{n}" + (f"_t{time_limit:g}" if time_limit else "")
    out = out_dir / f"{name}.toml"
    argv = [sys.executable, "-m", "zenswarm", "scenario", "generate", "--n", str(n), "--shape", "circle",
            "--topology", "knn", "--k", "3", "--obstacles", "2", "--seed", str(seed), "--out", str(out), "--force"]
    if time_limit:
        argv += ["--time-limit", f"{time_limit:g}"]
    subprocess.run(argv, check=True, capture_output=True, text=True, cwd=REPO)
    return out


def scenario_file(spec: str, out_dir: Path, time_limit: float | None = None) -> tuple[str, Path]:
    """'example1' / 'example2' / 'gen16' (a generated N-UAV scenario) / a path -> (label, file).

    ``time_limit`` shortens generated scenarios (the paper examples keep their own, 70 s)."""
    if spec in PAPER:
        return spec, PAPER[spec]
    m = re.fullmatch(r"gen(\d+)", spec)
    if m:
        n = int(m.group(1))
        return spec, generated_scenario(n, out_dir, time_limit)
    p = Path(spec)
    if not p.exists():
        raise SystemExit(f"scenario {spec!r}: expected example1, example2, gen<N> or an existing file")
    return p.stem, p


def scenario_facts(path: Path) -> dict[str, Any]:
    from zenswarm.scenario.config import load_scenario

    sc = load_scenario(path)
    return {"n_uav": sc.n, "sim_time_s": sc.timing.time_limit_s, "n_ticks": sc.timing.n_ticks,
            "control_rate_hz": sc.timing.control_rate_hz, "physics_rate_hz": 1.0 / (sc.timing.dt / sc.timing.substeps)}


# --------------------------------------------------------------------------- simulator worker
def run_sim_worker(scenario: Path, keep_openblas: bool = False, timeout_s: float = 1800.0) -> dict[str, Any]:
    """Run ``zenswarm.compose.sim.simulate`` on ``scenario`` in a fresh interpreter; return its timings."""
    code = (
        "import json, sys, time\n"
        "from zenswarm.scenario.config import load_scenario\n"
        "from zenswarm.compose.sim import simulate\n"
        "sc = load_scenario(sys.argv[1])\n"
        "c0 = time.process_time(); w0 = time.perf_counter()\n"
        "r = simulate(sc)\n"
        "w = time.perf_counter() - w0; c = time.process_time() - c0\n"
        "print(json.dumps({'wall_s': w, 'cpu_s': c, 'sim_time_s': r.results['sim_time_s'],"
        " 'success': r.results['success'], 'goal_reached': r.results['goal_reached'],"
        " 'rms_tracking_error_m': r.results.get('rms_tracking_error_m'),"
        " 'min_inter_uav_distance_m': r.results.get('min_inter_uav_distance_m'),"
        " 'maxrss_kb': __import__('resource').getrusage(__import__('resource').RUSAGE_SELF).ru_maxrss}))\n"
    )
    win = CpuWindow()
    p = subprocess.run([sys.executable, "-c", code, str(scenario)], capture_output=True, text=True,
                       env=bench_env(keep_openblas), cwd=REPO, timeout=timeout_s)
    acct = win.close()
    if p.returncode != 0:
        raise RuntimeError(f"simulator worker failed on {scenario}: {p.stderr.strip()[-2000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["x_real_time"] = out["sim_time_s"] / out["wall_s"]
    out["x_real_time_cpu"] = out["sim_time_s"] / out["cpu_s"]
    out["background_cores"] = acct["background_cores"]
    out["load1_start"] = acct["load1_start"]
    return out


# --------------------------------------------------------------------------- process tree sampling
def _children_map() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            s = Path(f"/proc/{d}/stat").read_text()
        except OSError:
            continue
        ppid = int(s[s.rindex(")") + 2:].split()[1])
        kids.setdefault(ppid, []).append(int(d))
    return kids


def descendants(pid: int) -> list[int]:
    kids = _children_map()
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        for c in kids.get(p, []):
            out.append(c)
            todo.append(c)
    return out


def proc_cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")[:-1]
    except OSError:
        return []


def role_of(argv: Sequence[str]) -> str:
    """Swarm role from a ``python -m zenswarm ...`` command line."""
    if "zenswarm" not in argv:
        return "?"
    i = list(argv).index("zenswarm")
    rest = list(argv[i + 1:])
    if not rest:
        return "?"
    if rest[0] == "agent" and "--id" in rest:
        return f"agent:{rest[rest.index('--id') + 1]}"
    if rest[0] == "up":
        return "supervisor"
    return rest[0]


def read_status(pid: int) -> dict[str, int]:
    """VmRSS / VmHWM in kB and utime+stime in seconds (as ``cpu_s``)."""
    out: dict[str, Any] = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(("VmRSS:", "VmHWM:", "RssAnon:", "RssFile:", "RssShmem:", "Threads:")):
                k, v = line.split(":", 1)
                out[k] = int(v.split()[0])
        s = Path(f"/proc/{pid}/stat").read_text()
        f = s[s.rindex(")") + 2:].split()
        out["cpu_s"] = (int(f[11]) + int(f[12])) / CLK_TCK
    except (OSError, ValueError, IndexError):
        return {}
    return out


def read_pss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return int(line.split()[1])
    except OSError:
        pass
    return None


@dataclass
class ProcSample:
    pid: int
    role: str
    rss_kb_max: int = 0
    hwm_kb: int = 0
    pss_kb_max: int = 0
    rss_anon_kb_max: int = 0
    cpu_s: float = 0.0
    threads: int = 0
    first_seen: float = 0.0
    last_seen: float = 0.0
    hist: list = field(default_factory=list)  # (monotonic time, cpu_s, rss_kb)

    def cpu_cores(self, t0: float, t1: float) -> float | None:
        """Mean cores this process used between t0 and t1 (monotonic), from the samples."""
        pts = [(t, c) for t, c, _ in self.hist if t0 <= t <= t1]
        if len(pts) < 2 or pts[-1][0] <= pts[0][0]:
            return None
        return (pts[-1][1] - pts[0][1]) / (pts[-1][0] - pts[0][0])


class TreeSampler(threading.Thread):
    """Polls the process tree under ``root_pid`` every ``period_s``: RSS, peak RSS, PSS, CPU time."""

    def __init__(self, root_pid: int, period_s: float = 0.25, pss: bool = False) -> None:
        super().__init__(daemon=True)
        self.root = root_pid
        self.period = period_s
        self.pss = pss
        self.procs: dict[int, ProcSample] = {}
        self.halt = threading.Event()

    def sample_once(self) -> None:
        now = time.monotonic()
        for pid in [self.root] + descendants(self.root):
            st = read_status(pid)
            if not st:
                continue
            ps = self.procs.get(pid)
            if ps is None:
                argv = proc_cmdline(pid)
                ps = self.procs[pid] = ProcSample(pid, role_of(argv) if pid != self.root else "supervisor", first_seen=now)
            elif ps.role == "?":  # first seen between fork and exec: look again
                ps.role = role_of(proc_cmdline(pid))
            ps.rss_kb_max = max(ps.rss_kb_max, st.get("VmRSS", 0))
            ps.hwm_kb = max(ps.hwm_kb, st.get("VmHWM", 0))
            ps.rss_anon_kb_max = max(ps.rss_anon_kb_max, st.get("RssAnon", 0))
            ps.cpu_s = max(ps.cpu_s, st.get("cpu_s", 0.0))
            ps.threads = max(ps.threads, st.get("Threads", 0))
            ps.last_seen = now
            ps.hist.append((now, st.get("cpu_s", 0.0), st.get("VmRSS", 0)))
            if self.pss:
                pss = read_pss_kb(pid)
                if pss:
                    ps.pss_kb_max = max(ps.pss_kb_max, pss)

    def run(self) -> None:
        while not self.halt.is_set():
            try:
                self.sample_once()
            except Exception:  # noqa: BLE001 - a process vanishing mid-read
                pass
            self.halt.wait(self.period)

    def stop(self) -> None:
        self.halt.set()
        self.join(timeout=5)

    def by_role(self) -> dict[str, ProcSample]:
        return {p.role: p for p in self.procs.values()}


def flight_cores(procs: dict[str, ProcSample], flight_s: float) -> dict[str, float] | None:
    """Mean CPU cores by role (the agents summed as ``agents``) over the middle 80 % of a flight of
    ``flight_s`` wall seconds that ended when the plant was last seen; None without a plant."""
    pl = procs.get("plant")
    if pl is None:
        return None
    t0, t1 = pl.last_seen - 0.9 * flight_s, pl.last_seen - 0.1 * flight_s
    cores: dict[str, float] = {}
    for role, ps in procs.items():
        c = ps.cpu_cores(t0, t1)
        if c is not None:
            key = "agents" if role.startswith("agent:") else role
            cores[key] = cores.get(key, 0.0) + c
    return cores


# --------------------------------------------------------------------------- message stamps (bench/stamps)
def stamps_env(stamp_dir: Path) -> dict[str, str]:
    """:func:`bench_env` with bench/stamps/sitecustomize.py on ``PYTHONPATH``: every process of the
    swarm then writes the stamps of its messages to ``stamp_dir`` (one JSON file each)."""
    env = bench_env()
    env["PYTHONPATH"] = os.pathsep.join([str(STAMPS)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    env["ZENSWARM_BENCH_STAMPS"] = str(stamp_dir)
    return env


def load_stamps(stamp_dir: Path) -> list[dict[str, Any]]:
    """The stamp files of one run (a process killed while writing leaves none or a broken one: skipped)."""
    out = []
    for p in sorted(stamp_dir.glob("*.json")):
        try:
            out.append(json.loads(p.read_text()))
        except (OSError, ValueError):
            pass
    return out


# --------------------------------------------------------------------------- zenswarm up
def free_port() -> int:
    """A TCP port free on 127.0.0.1 a moment ago (zenswarm.bus.free_port; imported here only when asked)."""
    from zenswarm.bus import free_port

    return free_port()


def port_is_free(port: int) -> bool:
    """No socket listens on 127.0.0.1:port now (TIME_WAIT doesn't count): the pytest plugin's check, without waiting."""
    from zenswarm.pytest_plugin import port_free

    return port_free(port, 0.0)


@dataclass
class UpRun:
    """One ``zenswarm up`` run: its command, exit code, wall time, results, process samples."""

    argv: list[str]
    swarm: str
    port: int
    out: Path
    returncode: int | None = None
    wall_s: float = 0.0
    results: dict[str, Any] = field(default_factory=dict)
    procs: dict[str, ProcSample] = field(default_factory=dict)
    leftovers: list[int] = field(default_factory=list)
    port_free_after: bool = True
    output_tail: str = ""
    cpu: dict[str, float] = field(default_factory=dict)
    timed_out: bool = False
    hung_after_plant_exit: bool = False
    hang_dumps: dict[str, str] = field(default_factory=dict)


def py_spy_dumps(root_pid: int, roles: Sequence[str] = ("plant", "leader", "agent:1", "supervisor")) -> dict[str, str]:
    """``py-spy dump`` (all threads, native frames) of some processes of a stuck swarm, if py-spy is installed."""
    import shutil as _sh

    exe = _sh.which("py-spy")
    if exe is None:
        return {}
    out = {}
    for pid in [root_pid] + descendants(root_pid):
        role = "supervisor" if pid == root_pid else role_of(proc_cmdline(pid))
        if role in roles:
            try:
                p = subprocess.run([exe, "dump", "--native", "--pid", str(pid)], capture_output=True, text=True, timeout=30)
                out[role] = p.stdout + p.stderr
            except (subprocess.TimeoutExpired, OSError) as e:
                out[role] = f"py-spy failed: {e}"
    return out


def print_hang_dumps(dumps: dict[str, str]) -> None:
    """The py-spy dumps of a stuck run (:func:`py_spy_dumps`), indented, 60 lines each."""
    for role, text in dumps.items():
        print(f"    py-spy dump of {role}:\n" + "\n".join("      " + x for x in text.splitlines()[:60]))


_LIVE: dict[int, tuple[subprocess.Popen, str]] = {}


def _kill_swarm(popen: subprocess.Popen, swarm: str) -> list[int]:
    """Stop a ``zenswarm up`` we started and any of its processes still alive; return those found."""
    kids = descendants(popen.pid) if popen.poll() is None else []
    if popen.poll() is None:
        popen.send_signal(signal.SIGTERM)  # the supervisor stops its children cleanly
        try:
            popen.wait(timeout=20)
        except subprocess.TimeoutExpired:
            popen.kill()  # its children die with it (PR_SET_PDEATHSIG)
            popen.wait()
    # anything that still carries our unique swarm name (and was started by us) goes, by pid
    left = []
    deadline = time.monotonic() + 5
    while True:
        left = [p for p in set(kids) | set(_pids_with(swarm)) if os.path.exists(f"/proc/{p}") and swarm in " ".join(proc_cmdline(p))]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    for p in left:
        try:
            os.kill(p, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return left


def _pids_with(token: str) -> list[int]:
    """Pids of processes whose command line holds ``--swarm <token>`` (our unique name)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            argv = proc_cmdline(int(d))
            if "--swarm" in argv and token in argv:
                out.append(int(d))
    return out


def cleanup_all() -> None:
    for pid, (popen, swarm) in list(_LIVE.items()):
        _kill_swarm(popen, swarm)
        _LIVE.pop(pid, None)


def install_cleanup() -> None:
    """SIGINT/SIGTERM -> stop every swarm we started, then exit 130."""

    def handler(signum: int, frame: Any) -> None:
        cleanup_all()
        raise SystemExit(130)

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def start_bench(tmp_prefix: str) -> tuple[tempfile.TemporaryDirectory[str], dict[str, Any]]:
    """A swarm benchmark's start: every swarm it starts stopped on Ctrl-C/SIGTERM, a temporary
    directory (removed when the returned object goes), the machine described and printed."""
    install_cleanup()
    tmp = tempfile.TemporaryDirectory(prefix=tmp_prefix)
    info = machine_info()
    for line in machine_lines(info):
        print(line)
    return tmp, info


def run_up(
    scenario: Path,
    out: Path,
    tag: str,
    extra: Sequence[str] = (),
    env: dict[str, str] | None = None,
    timeout_s: float = 900.0,
    sample_period_s: float = 0.25,
    pss: bool = False,
    end_grace_s: float | None = None,
) -> UpRun:
    """``zenswarm up SCEN --out OUT --quiet --quiet-children --swarm <unique> --listen tcp/127.0.0.1:<free>``."""
    swarm = f"bench{tag}{os.getpid()}x{int(time.time() * 1000) % 10**7}"
    port = free_port()
    argv = [sys.executable, "-m", "zenswarm", "up", str(scenario), "--out", str(out), "--quiet", "--quiet-children",
            "--swarm", swarm, "--listen", f"tcp/127.0.0.1:{port}", *extra]
    run = UpRun(argv, swarm, port, out)
    win = CpuWindow()
    t0 = time.perf_counter()
    popen = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                             text=True, cwd=REPO, env=env or bench_env())
    _LIVE[popen.pid] = (popen, swarm)
    sampler = TreeSampler(popen.pid, sample_period_s, pss=pss)
    sampler.start()
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(popen.stdout), daemon=True)  # type: ignore[arg-type]
    reader.start()
    plant_gone_at: float | None = None
    try:
        deadline = time.monotonic() + timeout_s
        while popen.poll() is None:
            now = time.monotonic()
            if now > deadline:
                lines.append(f"[bench] timeout after {timeout_s:.0f} s; stopping the swarm\n")
                run.timed_out = True
                run.hang_dumps = py_spy_dumps(popen.pid)
                break
            if end_grace_s is not None:
                try:
                    pl = sampler.by_role().get("plant")
                except RuntimeError:  # the sampler thread added a process meanwhile
                    pl = None
                if pl is not None and now - pl.last_seen > 1.0 and plant_gone_at is None:
                    plant_gone_at = now
                if plant_gone_at is not None and now - plant_gone_at > end_grace_s:
                    lines.append(f"[bench] the plant exited {end_grace_s:.0f} s ago and the swarm is still running;"
                                 " stopping it (SIGTERM to zenswarm up)\n")
                    run.hung_after_plant_exit = True
                    run.hang_dumps = py_spy_dumps(popen.pid)
                    break
            time.sleep(0.2)
    finally:
        run.wall_s = time.perf_counter() - t0
        sampler.stop()
        run.leftovers = _kill_swarm(popen, swarm)
        _LIVE.pop(popen.pid, None)
        reader.join(timeout=5)
    run.cpu = win.close()
    run.returncode = popen.returncode
    run.output_tail = "".join(lines[-15:])
    run.procs = sampler.by_role()
    time.sleep(0.2)
    run.port_free_after = port_is_free(port)
    rj = out / "results.json"
    if rj.exists():
        run.results = json.loads(rj.read_text())
    return run


# --------------------------------------------------------------------------- statistics and output
def median(xs: Iterable[float | None]) -> float | None:
    v = [x for x in xs if x is not None]
    return statistics.median(v) if v else None


def pct(xs: Sequence[float], p: float) -> float | None:
    """Percentile p (0-100) by linear interpolation between order statistics."""
    if not xs:
        return None
    s = sorted(xs)
    if len(s) == 1:
        return s[0]
    r = (len(s) - 1) * p / 100.0
    lo = int(r)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (r - lo)


def fmt(x: Any, nd: int = 2) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        return f"{x:.{nd}f}"
    return str(x)


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A Markdown table (readable as plain text too)."""
    cells = [[str(h) for h in headers]] + [[c if isinstance(c, str) else fmt(c) for c in r] for r in rows]
    w = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    line = lambda r: "| " + " | ".join(c.rjust(w[i]) if i else c.ljust(w[i]) for i, c in enumerate(r)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (x + 2) for x in w) + "|"
    return "\n".join([line(cells[0]), sep] + [line(r) for r in cells[1:]])


def write_json(path: Path | None, payload: dict[str, Any]) -> None:
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=2, sort_keys=True, default=str) + "\n")
    print(f"wrote {path}")


def command_line() -> str:
    return " ".join([Path(sys.executable).name, *sys.argv])


def write_report(path: Path | None, benchmark: str, info: dict[str, Any], **figures: Any) -> None:
    """:func:`write_json` of a benchmark's report: its name, command line, machine (``info``),
    load average at the end and ``figures`` (top-level keys of their own)."""
    write_json(path, {"benchmark": benchmark, "command": command_line(), "machine": info,
                      "loadavg_at_end": list(os.getloadavg()), **figures})

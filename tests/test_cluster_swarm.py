"""Issue 45: one swarm across a Dask cluster, each UAV still its own OS process.

A real ``dask scheduler`` and two ``dask worker`` processes, each worker in its own network
namespace (tests/netns.py: a veth pair to the root namespace, routed through it), the router on the
supervisor's side listening on a non-loopback address (so secure mode is on, the default: each role's
credentials travel to its worker). The swarm flies in lockstep equal to the simulator bit for bit;
a worker killed mid-flight is the named failure (host lost, the roles it held), with results;
``--restart`` re-places its roles on the other worker and the flight goes on; a SIGKILLed
supervisor leaves nothing behind (the workers' watchdog); bad input exits 2 within seconds. After
each test no process of its swarm is left on any worker (the namespaces share this process table)
and no credentials are left in the workers' temporary directory.

Skipped (with the reason) only where network namespaces cannot be created (no privilege).
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from zenswarm.api import fly
from zenswarm.bus import free_port
from zenswarm.compose.cluster import HEARTBEAT_LOST_S, sweep_stale_keys
from zenswarm.compose.sim import simulate
from zenswarm.judge.metrics import TimeSeries
from zenswarm.scenario.config import load_scenario
from zenswarm.scenario.generate import generate_scenario, to_toml

from netns import Netns, namespace
from swarmtest import ROOT, SCENARIOS, kill_mentioning, processes_mentioning, read_results, scenario_variant, unique_swarm
from test_swarm import _assert_equal_to_sim

pytestmark = pytest.mark.swarm  # a Dask scheduler, two workers in namespaces, swarms

DASK = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
WORKER = [sys.executable, "-m", "distributed.cli.dask_worker"]


@dataclass
class DaskCluster:
    """A scheduler (root namespace, on the first namespace's veth address) and one worker per
    namespace (``w1``, ``w2``), each worker's process and log."""

    scheduler: str
    router_ip: str  # where the workers reach this host (the router listens there)
    namespaces: list[Netns]
    workers: dict[str, subprocess.Popen] = field(default_factory=dict)
    procs: list[subprocess.Popen] = field(default_factory=list)

    def kill_worker(self, name: str) -> None:
        self.workers[name].send_signal(signal.SIGKILL)
        self.workers[name].wait(10)


def _wait_workers(address: str, n: int, timeout: float = 60.0) -> None:
    import distributed

    with distributed.Client(address, timeout=timeout, set_as_default=False) as c:  # waits for the scheduler to be up
        if n:
            c.wait_for_workers(n, timeout=timeout)


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[DaskCluster]:
    with ExitStack() as stack:
        nss = [stack.enter_context(namespace(default_route=True)) for _ in range(2)]
        port = free_port(nss[0].root_ip)
        addr = f"tcp://{nss[0].root_ip}:{port}"
        dc = DaskCluster(addr, nss[0].root_ip, nss)
        logs = [stack.enter_context(open(tmp_path / f"dask{i}.log", "w")) for i in range(3)]
        try:
            dc.procs.append(subprocess.Popen([*DASK, "--host", nss[0].root_ip, "--port", str(port), "--no-dashboard"], stdout=logs[0],
                                             stderr=subprocess.STDOUT, start_new_session=True))  # fmt: skip
            for i, ns in enumerate(nss, start=1):
                w = subprocess.Popen(
                    ["ip", "netns", "exec", ns.name, *WORKER, addr, "--host", ns.ns_ip, "--name", f"w{i}", "--nthreads", "1",
                     "--no-nanny", "--no-dashboard"],
                    stdout=logs[i], stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT,
                )  # fmt: skip
                dc.workers[f"w{i}"] = w
                dc.procs.append(w)
            _wait_workers(addr, 2)
            yield dc
        finally:
            for p in dc.procs:
                if p.poll() is None:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait(10)


def _leftovers(swarm: str, wait_s: float = 0.0, killed_worker: int | None = None) -> list[tuple[int, str]]:
    """Processes of ``swarm`` alive (after up to ``wait_s`` for them to go), killed; and the
    credentials left in the workers' temporary directory (they share this /tmp), but those of
    ``killed_worker`` (its pid: a SIGKILLed worker cannot remove them; the next role host on its
    machine does, :func:`sweep_stale_keys`, checked here)."""
    deadline = time.monotonic() + wait_s
    while processes_mentioning(f"--swarm {swarm}") and time.monotonic() < deadline:
        time.sleep(0.1)
    found = processes_mentioning(f"--swarm {swarm}")
    kill_mentioning(f"--swarm {swarm}")
    keys = [p for p in Path(tempfile.gettempdir()).glob(f"zenswarm-{swarm}-*")]
    stale = [p for p in keys if p.name.startswith(f"zenswarm-{swarm}-w{killed_worker}-")]
    if stale:
        # each role's own credentials only: one directory per role it held, its own files (no CA key)
        assert sorted(d.name for d in stale[0].iterdir()) == ["agent-1", "agent-2", "agent-3"], list(stale[0].iterdir())
        for d in stale[0].iterdir():
            assert sorted(f.name for f in d.iterdir()) == ["ca.pem", "cert.pem", "credentials.json", "key.pem"], d
            assert f'"process": "{d.name.replace("-", ":")}"' in (d / "credentials.json").read_text().replace('":"', '": "')
        assert sweep_stale_keys() and not stale[0].exists()
    return found + [(-1, str(k)) for k in keys if k not in stale]


def _port_free(ip: str, port: int, timeout: float = 10.0) -> bool:
    """True once nothing listens on ip:port (the router's, on the veth address)."""
    deadline = time.monotonic() + timeout
    while True:
        with socket.socket() as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((ip, port))
                return True
            except OSError:
                if time.monotonic() > deadline:
                    return False
        time.sleep(0.1)


def _up(dc: DaskCluster, scenario: Path, out: Path, swarm: str, *extra: str, timeout: float = 300.0) -> subprocess.CompletedProcess:
    port = free_port(dc.router_ip)
    try:
        cp = subprocess.run(
            [sys.executable, "-m", "zenswarm", "up", str(scenario), "--out", str(out), "--swarm", swarm, "--scheduler", dc.scheduler,
             "--listen", f"tcp/{dc.router_ip}:{port}", "--progress-every", "5", "--quiet-children", *extra],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=timeout, cwd=ROOT,
        )  # fmt: skip
    finally:
        left = _leftovers(swarm)
    assert not left, f"left behind: {left}"
    assert _port_free(dc.router_ip, port), f"router port {dc.router_ip}:{port} still bound"
    return cp


def _gen8(tmp: Path) -> Path:
    p = tmp / "gen8.toml"
    p.write_text(to_toml(generate_scenario(8, topology="knn", k=3, n_obstacles=1, seed=7, time_limit_s=4.0)))
    return p


def test_example1_and_a_generated_8_uav_swarm_on_two_namespace_workers_equal_the_simulator(tmp_path: Path, cluster: DaskCluster) -> None:
    """Both fly spread over both workers, secure by default (the router is not on loopback), in
    lockstep, equal to the simulator bit for bit; results.json says where each process ran."""
    for scenario, n in ((SCENARIOS / "paper_example1.toml", 3), (_gen8(tmp_path), 8)):
        out = tmp_path / scenario.stem
        if n == 3:  # zenswarm up --scheduler
            cp = _up(cluster, scenario, out, unique_swarm("c"))
            code, log = cp.returncode, cp.stdout
        else:  # api.fly(scheduler=...)
            swarm = unique_swarm("c")
            try:
                f = fly(scenario, mode="swarm", scheduler=cluster.scheduler, out=out, swarm=swarm,
                        listen=f"tcp/{cluster.router_ip}:{free_port(cluster.router_ip)}")
            finally:
                left = _leftovers(swarm)
            assert not left, f"left behind: {left}"
            code, log = f.exit_code, f.log
        assert code in (0, 1), log[-3000:]  # gen8 (4 s) cannot reach its goal
        assert "secure mode: user/password" in log, log[-3000:]
        _assert_equal_to_sim(scenario, out)
        ref, got = simulate(load_scenario(scenario)).series, TimeSeries.load(str(out / "timeseries.npz"))
        for name in TimeSeries.FIELDS:  # bit for bit, not only within test_swarm's 1e-9
            assert getattr(got, name).tobytes() == getattr(ref, name).tobytes(), name
        res = read_results(out)
        roles = ["plant", "leader"] + [f"agent:{i}" for i in range(1, n + 1)]
        assert res["scheduler"] == cluster.scheduler and res["lost_workers"] == []
        assert all(res["processes"][r] == 0 for r in roles), res["processes"]
        where = res["where"]
        by_worker = {w: [r for r in roles if where[r]["worker_name"] == w] for w in ("w1", "w2")}
        assert abs(len(by_worker["w1"]) - len(by_worker["w2"])) <= 1, by_worker  # spread evenly
        ips = {ns.ns_ip for ns in cluster.namespaces}
        for r in roles:
            assert where[r]["worker"].split("//")[1].rsplit(":", 1)[0] in ips and where[r]["pid"] > 0 and where[r]["host"], where[r]


def _fly_and_kill_worker(dc: DaskCluster, scenario: Path, out: Path, swarm: str, *extra: str) -> tuple[int, str]:
    """Fly with plant and leader pinned to w1, the agents on w2; SIGKILL worker w2 once sim time
    passes 2 s. The supervisor's exit status and output."""
    port = free_port(dc.router_ip)
    sup = subprocess.Popen(
        [sys.executable, "-m", "zenswarm", "up", str(scenario), "--out", str(out), "--swarm", swarm, "--scheduler", dc.scheduler,
         "--listen", f"tcp/{dc.router_ip}:{port}", "--placement", "plant,leader=w1", "--placement", "agents=w2",
         "--progress-every", "0.25", "--quiet-children", "--lockstep-timeout", "1", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT,
    )  # fmt: skip
    lines: list[str] = []
    sim_t = [0.0]

    def pump() -> None:
        assert sup.stdout is not None
        for line in sup.stdout:
            lines.append(line.rstrip())
            m = re.search(r"t=\s*([\d.]+)/", line)
            if m:
                sim_t[0] = float(m.group(1))

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 120
        while sim_t[0] < 2.0 and sup.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert sim_t[0] >= 2.0, "\n".join(lines[-30:])
        dc.kill_worker("w2")
        try:
            sup.wait(timeout=180)
        except subprocess.TimeoutExpired:
            raise AssertionError("the supervisor did not end within 180 s of the worker's loss:\n" + "\n".join(lines[-60:])) from None
    finally:
        if sup.poll() is None:
            sup.kill()
            sup.wait()
        reader.join(timeout=5)
        left = _leftovers(swarm, wait_s=HEARTBEAT_LOST_S + 2, killed_worker=dc.workers["w2"].pid)
    assert not left, f"left behind: {left}"
    return sup.returncode, "\n".join(lines)


def test_a_worker_killed_mid_flight_is_host_lost_naming_its_roles(tmp_path: Path, cluster: DaskCluster) -> None:
    out = tmp_path / "out"
    rc, log = _fly_and_kill_worker(cluster, scenario_variant(tmp_path, time_limit_s=20.0), out, unique_swarm("k"))
    assert rc == 3, log[-3000:]
    assert re.search(r"host lost: worker w2 \(tcp://[\d.]+:\d+, host \S+\): .*; it held agent:1, agent:2, agent:3", log), log[-3000:]
    res = read_results(out)
    assert res["success"] is False and [(f["cause"], f.get("process")) for f in res["failures"]] == [("process_died", "agent:1")], res
    lost = res["lost_workers"]
    assert [w["worker_name"] for w in lost] == ["w2"] and lost[0]["roles"] == ["agent:1", "agent:2", "agent:3"], lost
    death = res["process_deaths"][0]
    assert death["process"].startswith("agent:") and death["how"].startswith("host lost: worker w2"), death
    assert res["where"]["plant"]["worker_name"] == "w1" and res["where"]["agent:2"]["worker_name"] == "w2"


def test_with_restart_the_roles_of_a_lost_worker_fly_on_on_the_other(tmp_path: Path, cluster: DaskCluster) -> None:
    out = tmp_path / "out"
    rc, log = _fly_and_kill_worker(cluster, scenario_variant(tmp_path, time_limit_s=8.0), out, unique_swarm("r"), "--restart")
    assert rc in (0, 1), log[-3000:]  # 8 s cannot reach the goal: 1 is the verdict, not a process failure
    res = read_results(out)
    assert res["sim_time_s"] == pytest.approx(8.0), log[-3000:]
    assert {d["process"] for d in res["process_deaths"]} == {"agent:1", "agent:2", "agent:3"}, res["process_deaths"]
    assert all(d["how"].startswith("host lost: worker w2") for d in res["process_deaths"])
    assert res["restarts"] == {"agent:1": 1, "agent:2": 1, "agent:3": 1}, res["restarts"]
    assert all(res["where"][f"agent:{i}"]["worker_name"] == "w1" for i in (1, 2, 3)), res["where"]  # re-placed
    assert all(rc == 0 for rc in res["processes"].values()), res["processes"]


def test_a_sigkilled_supervisor_leaves_nothing_on_the_workers(tmp_path: Path, cluster: DaskCluster) -> None:
    """The workers' watchdog ends the roles once the supervisor's polls stop (its heartbeat)."""
    swarm = unique_swarm("s")
    port = free_port(cluster.router_ip)
    sup = subprocess.Popen(
        [sys.executable, "-m", "zenswarm", "up", str(SCENARIOS / "paper_example1.toml"), "--out", str(tmp_path / "out"),
         "--swarm", swarm, "--scheduler", cluster.scheduler, "--listen", f"tcp/{cluster.router_ip}:{port}", "--progress-every", "0.25"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT, start_new_session=True,
    )  # fmt: skip
    assert sup.stdout is not None
    try:
        for line in sup.stdout:
            if re.search(r"t=\s*[1-9][\d.]*/", line):  # flying: sim time past 1 s
                break
        assert len(processes_mentioning(f"--swarm {swarm}")) >= 5  # the supervisor and its 5 roles, on the workers
        sup.send_signal(signal.SIGKILL)
        sup.wait(10)
        t0 = time.monotonic()
        while [p for p in processes_mentioning(f"--swarm {swarm}")] and time.monotonic() - t0 < HEARTBEAT_LOST_S + 10:
            time.sleep(0.1)
        took = time.monotonic() - t0
    finally:
        left = _leftovers(swarm)
    assert not left, f"left behind: {left}"
    assert took < HEARTBEAT_LOST_S + 5, took
    print(f"\ncluster: the roles of a SIGKILLed supervisor ended {took:.1f} s after it")


def test_bad_input_exits_2_within_seconds_and_starts_nothing(tmp_path: Path, cluster: DaskCluster) -> None:
    sc = str(SCENARIOS / "paper_example1.toml")
    cases = [
        (["--scheduler", cluster.scheduler], "--listen: the router listens on loopback only"),  # the workers are not on this host
        (["--scheduler", cluster.scheduler, "--listen", f"tcp/{cluster.router_ip}:{free_port(cluster.router_ip)}",
          "--placement", "plant=w9"],
         "--placement: 'plant=w9': no worker is named 'w9'"),
        (["--scheduler", cluster.scheduler, "--placement", "agent:4=w1"], "--placement: 'agent:4=w1': agent:4 is not a role of this swarm"),
        (["--scheduler", f"tcp://127.0.0.1:{free_port()}"], "--scheduler: cannot reach the Dask scheduler"),
        (["--placement", "plant=w1"], "--placement: places roles on a Dask cluster: give --scheduler"),
    ]  # fmt: skip
    for extra, named in cases:
        swarm = unique_swarm("b")
        t0 = time.monotonic()
        cp = subprocess.run([sys.executable, "-m", "zenswarm", "up", sc, "--out", str(tmp_path / swarm), "--swarm", swarm, *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=60, cwd=ROOT)  # fmt: skip
        took = time.monotonic() - t0
        assert cp.returncode == 2 and named in cp.stdout, (extra, cp.stdout[-2000:])
        assert took < 15, (extra, took)
        assert not (tmp_path / swarm / "results.json").exists()
        assert not _leftovers(swarm)


def test_a_scheduler_without_workers_exits_2(tmp_path: Path) -> None:
    port = free_port()
    sched = subprocess.Popen([*DASK, "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)  # fmt: skip
    try:
        addr = f"tcp://127.0.0.1:{port}"
        _wait_workers(addr, 0, timeout=30)
        cp = subprocess.run([sys.executable, "-m", "zenswarm", "up", str(SCENARIOS / "paper_example1.toml"), "--out", str(tmp_path / "o"),
                             "--scheduler", addr],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=60, cwd=ROOT)  # fmt: skip
    finally:
        os.killpg(sched.pid, signal.SIGKILL)
        sched.wait(10)
    assert cp.returncode == 2 and "--scheduler: the Dask scheduler has no workers" in cp.stdout, cp.stdout[-2000:]

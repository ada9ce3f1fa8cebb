"""Cost of the network hop: a lockstep swarm on two Dask workers in network namespaces against the
same swarm on one host, and the start-up of a large swarm placed on the cluster (issue 45).

Sets up (as root: ``ip netns``) two network namespaces, each joined to this machine by a veth pair
(tests/netns.py), a ``dask scheduler`` here and one ``dask worker --nthreads 1 --no-nanny`` in each
namespace. Then, per scenario and run, interleaved:

    one host:  zenswarm up SCEN --quiet-children --listen tcp/127.0.0.1:<free>
    cluster:   zenswarm up SCEN --quiet-children --listen tcp/<veth address>:<free> --scheduler tcp://... --insecure

(``--insecure`` on the cluster: the one-host flight is open too, so both pay the same; secure mode
adds one handshake per process at start-up only). Both run on the same cores: this measures what
the veth hop and the cluster's start-up cost, not a speed-up.

Figures per run: ``flight s`` = n_ticks x (step_ms_mean + wait_ms_mean) of the plant's diagnostics
(bench/swarm_lockstep.py: first tick to last, without start-up), ``x real time`` = simulated s /
flight s, ``start s`` = wall seconds from the command's start to its first progress line past tick 0
(imports, the Dask connection and placement, N+2 processes started and joined), ``up s`` the
command's wall time. The start-up swarm (``--startup``, default gen64) flies 0.5 s of sim time, on
one host and on the cluster.

    python bench/cluster_swarm.py                                   # gen16 gen32, 3 runs; start-up of gen64
    python bench/cluster_swarm.py --runs 1 --scenarios gen16 --startup gen16 --json bench/results/cluster.json

Every process it starts is stopped at the end (or on Ctrl-C), the namespaces removed. Not a test:
numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import _common as C
from netns import namespace  # tests/netns.py: the test suite's namespace helper

PY = sys.executable


def start_cluster(stack: ExitStack, logs: Path) -> tuple[str, str]:
    """Two namespaces, a scheduler and a worker in each; (scheduler address, router address)."""
    nss = [stack.enter_context(namespace(default_route=True)) for _ in range(2)]
    ip = nss[0].root_ip
    sport = C.free_port()
    addr = f"tcp://{ip}:{sport}"
    procs: list[subprocess.Popen] = []

    def stop() -> None:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(10)

    stack.callback(stop)
    procs.append(subprocess.Popen([PY, "-m", "distributed.cli.dask_scheduler", "--host", ip, "--port", str(sport), "--no-dashboard"],
                                  stdout=open(logs / "scheduler.log", "w"), stderr=subprocess.STDOUT, start_new_session=True))  # fmt: skip
    for i, ns in enumerate(nss, start=1):
        procs.append(subprocess.Popen(
            ["ip", "netns", "exec", ns.name, PY, "-m", "distributed.cli.dask_worker", addr, "--host", ns.ns_ip, "--name", f"w{i}",
             "--nthreads", "1", "--no-nanny", "--no-dashboard"],
            stdout=open(logs / f"w{i}.log", "w"), stderr=subprocess.STDOUT, start_new_session=True, cwd=C.REPO,
        ))  # fmt: skip
    import distributed

    with distributed.Client(addr, timeout=60, set_as_default=False) as c:
        c.wait_for_workers(2, timeout=120)
    return addr, ip


def fly(scenario: Path, out: Path, cluster: tuple[str, str] | None) -> dict[str, Any]:
    """One ``zenswarm up`` (one host, or on the cluster): its figures."""
    swarm = f"benchc{os.getpid()}x{int(time.time() * 1000) % 10**7}"
    ip = cluster[1] if cluster else "127.0.0.1"
    argv = [PY, "-m", "zenswarm", "up", str(scenario), "--out", str(out), "--quiet-children", "--progress-every", "0.25",
            "--swarm", swarm, "--listen", f"tcp/{ip}:{C.free_port()}"]  # fmt: skip
    if cluster:
        argv += ["--scheduler", cluster[0], "--insecure"]
    t0 = time.perf_counter()
    first_tick: list[float] = []
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=C.REPO, env=C.bench_env())
    lines: list[str] = []

    def pump() -> None:
        assert p.stdout is not None
        for line in p.stdout:
            lines.append(line)
            m = re.search(r"t=\s*([\d.]+)/", line)
            if m and float(m.group(1)) > 0 and not first_tick:
                first_tick.append(time.perf_counter() - t0)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        p.wait(timeout=1800)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        reader.join(5)
        left = C._pids_with(swarm)
        for pid in left:
            os.kill(pid, signal.SIGKILL)
    up_s = time.perf_counter() - t0
    res = json.loads((out / "results.json").read_text()) if (out / "results.json").exists() else {}
    plant = (res.get("diagnostics") or {}).get("plant") or {}
    n_ticks = C.scenario_facts(scenario)["n_ticks"]
    flight = n_ticks * (plant["step_ms_mean"] + plant["wait_ms_mean"]) / 1e3 if "step_ms_mean" in plant else None
    hosts = sorted({w.get("worker_name", "here") for w in (res.get("where") or {}).values()})
    return {"rc": p.returncode, "up_s": up_s, "start_s": first_tick[0] if first_tick else None, "flight_s": flight,
            "sim_s": res.get("sim_time_s"), "where": hosts, "leftovers": left, "tail": "".join(lines[-5:])}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="*", default=["gen16", "gen32"], help="example1, gen<N>, ... (default gen16 gen32)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--gen-time-limit", type=float, default=10.0, help="sim seconds of generated scenarios (default 10)")
    ap.add_argument("--startup", default="gen64", help="the swarm whose start-up on the cluster is timed (default gen64; '' for none)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    C.install_cleanup()
    rows: list[list[Any]] = []
    payload: dict[str, Any] = {"machine": C.machine_info(), "command": C.command_line(), "runs": []}
    with tempfile.TemporaryDirectory(prefix="bench-cluster-") as tmp, ExitStack() as stack:
        d = Path(tmp)
        cluster = start_cluster(stack, d)
        for spec in a.scenarios:
            label, scen = C.scenario_file(spec, d, a.gen_time_limit)
            for where in ("one host", "cluster"):
                figs = []
                for r in range(a.runs):
                    f = fly(scen, d / f"{label}-{where.replace(' ', '')}-{r}", cluster if where == "cluster" else None)
                    if f["rc"] not in (0, 1) or f["leftovers"]:
                        print(f"{label} {where} run {r}: exit {f['rc']}, leftovers {f['leftovers']}\n{f['tail']}", file=sys.stderr)
                    figs.append(f)
                    payload["runs"].append({"scenario": label, "where": where, **{k: v for k, v in f.items() if k != "tail"}})
                flight = C.median(f["flight_s"] for f in figs)
                sim_s = C.median(f["sim_s"] for f in figs)
                xrt = sim_s / flight if flight and sim_s else None
                rows.append([label, where, len(figs), C.fmt(C.median(f["start_s"] for f in figs)), C.fmt(flight), C.fmt(xrt),
                             C.fmt(C.median(f["up_s"] for f in figs)), ",".join(figs[-1]["where"])])  # fmt: skip
        if a.startup:
            label, scen = C.scenario_file(a.startup, d, 0.5)
            for where in ("one host", "cluster"):
                f = fly(scen, d / f"startup-{label}-{where.replace(' ', '')}", cluster if where == "cluster" else None)
                payload["runs"].append({"scenario": label, "where": f"{where} start-up", **{k: v for k, v in f.items() if k != "tail"}})
                if f["rc"] not in (0, 1):
                    print(f"start-up {label} {where}: exit {f['rc']}\n{f['tail']}", file=sys.stderr)
                rows.append([label + " (0.5 s)", f"{where} start-up", 1, C.fmt(f["start_s"]), C.fmt(f["flight_s"]), "", C.fmt(f["up_s"]),
                             ",".join(f["where"])])  # fmt: skip
    print("\n".join(C.machine_lines(payload["machine"])))
    print(C.table(["scenario", "where", "runs", "start s", "flight s", "x real time", "up s", "workers"], rows))
    C.write_json(a.json, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())

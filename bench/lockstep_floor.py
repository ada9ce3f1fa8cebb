"""The floor of a lockstep tick: what one tick's messages cost on this machine with no work.

One "plant" process and N "agent" processes exchange exactly the messages of a lockstep tick of
the swarm, and nothing else: the plant puts N states (~120 bytes each, one batch), each agent
answers its state with a cmd and a ref, each agent subscribes to the refs of its two ring
neighbours, and the plant starts the next round when all N cmds are in. Every process runs
zenoh as the swarm's do (one thread, ``bus.use_swarm_runtime``; callbacks on that thread,
``bus.direct_callback``); the router runs in the benchmark's own process, as in the supervisor, and
takes a copy of everything into a channel drained every 50 ms, as the supervisor's collector does. No decoding, no control law, no physics:
the figure is the cost of the chain plant -> router -> agents -> router -> plant itself, which a
lockstep tick of ``zenswarm up`` can only add to (bench/swarm_lockstep.py).

Modes: ``client`` (the swarm's topology: every process a client of the router) and ``peer``
(zenoh peers that find each other through the router's gossip and connect directly; the router
still receives a copy). The swarm uses ``client``: see BENCHMARKS.md for why.

    python bench/lockstep_floor.py                   # N = 3, both modes, 3 runs each, interleaved
    python bench/lockstep_floor.py --n 16 --runs 5 --json bench/results/lockstep_floor.json

Every process a run starts is stopped at the end. Not a test: numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

PAYLOAD = b"x" * 120


def _config(mode: str, router: str, own_port: int):
    from zenswarm import bus

    if mode == "client":
        return bus.client_config([router])
    conf = bus.client_config([router])
    return bus.apply_settings(conf, {"mode": "peer", "listen/endpoints": [f"tcp/127.0.0.1:{own_port}"],
                                     "scouting/gossip/enabled": True})


def run_agent(a: argparse.Namespace) -> None:
    from zenswarm import bus

    bus.use_swarm_runtime()
    with bus.open_session(_config(a.mode, a.router, a.own_port)) as s:
        i = a.index
        cmd = s.declare_publisher(f"floor/cmd/{i}")
        ref = s.declare_publisher(f"floor/ref/{i}")
        got = [0]

        def on_state(_sample) -> None:
            cmd.put(PAYLOAD)
            ref.put(PAYLOAD)

        def on_ref(_sample) -> None:
            got[0] += 1

        subs = [s.declare_subscriber(f"floor/state/{i}", bus.direct_callback(on_state))]
        for j in sorted({(i - 1) % a.n, (i + 1) % a.n} - {i}):
            subs.append(s.declare_subscriber(f"floor/ref/{j}", bus.direct_callback(on_ref)))
        print("ready", flush=True)
        sys.stdin.read()  # until the parent closes our stdin


def run_plant(a: argparse.Namespace) -> None:
    from zenswarm import bus

    bus.use_swarm_runtime()
    with bus.open_session(_config(a.mode, a.router, a.own_port)) as s:
        lock = threading.Lock()
        got = [0]
        done = threading.Event()

        def on_cmd(_sample) -> None:
            with lock:
                got[0] += 1
                if got[0] == a.n:
                    got[0] = 0
                    done.set()

        sub = s.declare_subscriber("floor/cmd/*", bus.direct_callback(on_cmd))
        pubs = [s.declare_publisher(f"floor/state/{i}") for i in range(a.n)]
        for p in pubs:
            if not bus.wait_matching(p, timeout=30.0):
                print(json.dumps({"error": "an agent never subscribed"}), flush=True)
                return
        time.sleep(1.0)  # peers: let the direct links come up
        times = []
        for r in range(a.warmup + a.rounds):
            done.clear()
            t0 = time.perf_counter()
            for p in pubs:
                p.put(PAYLOAD)
            if not done.wait(5.0):
                print(json.dumps({"error": f"round {r}: not every cmd came back"}), flush=True)
                return
            if r >= a.warmup:
                times.append(time.perf_counter() - t0)
        del sub
        print(json.dumps({"us_per_round": 1e6 * statistics.median(times), "mean_us": 1e6 * statistics.fmean(times)}), flush=True)


def one_run(mode: str, n: int, rounds: int, warmup: int) -> dict:
    """One run: a router in this process (as the supervisor's, with its copy of everything in a
    channel drained every 50 ms), N agent processes, then the plant process's rounds."""
    import zenoh

    from zenswarm import bus

    py = [sys.executable, __file__]
    router = f"tcp/127.0.0.1:{C.free_port()}"
    procs: list[subprocess.Popen] = []
    env = C.bench_env()
    conf = bus.router_config([router], settings={"scouting/gossip/enabled": True} if mode == "peer" else None)
    stop = threading.Event()
    with bus.open_session(conf, handle_signals=False) as session:
        copy = session.declare_subscriber("floor/**", zenoh.handlers.FifoChannel(1_000_000))

        def drain() -> None:
            while not stop.wait(0.05):
                while copy.try_recv() is not None:
                    pass

        t = threading.Thread(target=drain, daemon=True)
        t.start()
        try:
            common = ["--mode", mode, "--router", router, "--n", str(n)]
            for i in range(n):
                p = subprocess.Popen(py + ["agent", "--index", str(i), "--own-port", str(C.free_port()), *common],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
                procs.append(p)
                if not (p.stdout and p.stdout.readline().startswith("ready")):
                    return {"error": f"agent {i} did not start"}
            pl = subprocess.run(py + ["plant", "--own-port", str(C.free_port()), "--rounds", str(rounds), "--warmup",
                                      str(warmup), *common], capture_output=True, text=True, timeout=600, env=env)
            lines = [x for x in pl.stdout.splitlines() if x.startswith("{")]
            return json.loads(lines[-1]) if lines else {"error": pl.stderr[-500:]}
        finally:
            stop.set()
            for p in procs:
                if p.stdin:
                    p.stdin.close()
            for p in procs:
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
            t.join()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("role", nargs="?", default="main", choices=["main", "agent", "plant"], help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, default=3, help="agents (default 3, as paper example 1)")
    ap.add_argument("--runs", type=int, default=3, help="runs per mode, interleaved; median reported (default 3)")
    ap.add_argument("--rounds", type=int, default=3000, help="measured rounds per run (default 3000)")
    ap.add_argument("--warmup", type=int, default=300, help="rounds before measuring (default 300)")
    ap.add_argument("--modes", nargs="+", default=["client", "peer"], choices=["client", "peer"])
    ap.add_argument("--json", type=Path, metavar="FILE", help="also write the runs and medians here")
    ap.add_argument("--mode", default="client", help=argparse.SUPPRESS)
    ap.add_argument("--router", default="", help=argparse.SUPPRESS)
    ap.add_argument("--index", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--own-port", type=int, default=0, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.role == "agent":
        run_agent(a)
        return 0
    if a.role == "plant":
        run_plant(a)
        return 0
    if a.n < 1 or a.runs < 1 or a.rounds < 1:
        ap.error("--n, --runs and --rounds must be >= 1")
    from zenswarm import bus

    os.environ["ZENOH_RUNTIME"] = bus.ZENOH_RUNTIME_ROUTER  # this process is the router, as the supervisor
    C.install_cleanup()
    info = C.machine_info()
    print("\n".join(C.machine_lines(info)), flush=True)
    runs: dict[str, list[float]] = {m: [] for m in a.modes}
    for r in range(a.runs):
        for mode in a.modes:
            res = one_run(mode, a.n, a.rounds, a.warmup)
            if "error" in res:
                print(f"  run {r + 1}/{a.runs} {mode}: {res['error']}", flush=True)
                continue
            runs[mode].append(res["us_per_round"])
            print(f"  run {r + 1}/{a.runs} {mode:6s} N={a.n}: {res['us_per_round']:.0f} us per round (median of {a.rounds})",
                  flush=True)
    summary = {m: statistics.median(v) if v else None for m, v in runs.items()}
    print(f"\nlockstep floor, N = {a.n}, median of {a.runs} runs: "
          + ", ".join(f"{m} {v:.0f} us per round" for m, v in summary.items() if v is not None))
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        command = " ".join(["python", "bench/lockstep_floor.py", *sys.argv[1:]])
        a.json.write_text(json.dumps({"benchmark": "lockstep_floor", "command": command,
                                      "machine": info, "n": a.n, "rounds": a.rounds, "runs_us": runs, "median_us": summary},
                                     indent=2, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

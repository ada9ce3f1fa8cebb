"""Per-call cost of the pieces a control tick is made of, in one process (evidence for
BENCHMARKS.md's "what dominates the cost").

* agent: ``AgentCore.tick`` (generator 16-17, controller 28, inversion, ESO step) of one UAV
  with 2 and 4 neighbours, pinned;
* wire: ``wire.encode`` and ``wire.Decoder.decode`` of a State, a Ref and a Cmd (msgpack +
  validation);
* plant: one control period of physics (``timing.substeps`` x ``plant.quadrotor.step``) for N = 3,
  16, 32 UAVs;
* plant, the simulator's path: ``plant.quadrotor.step_held`` (Python floats) for N = 3, 8;
* simulator: ``generator_rates_all`` for N = 3, 16, 32 (the in-process simulator's per-agent
  Python loop);
* leader: ``integrate_leader`` over one control period (paper example 1, at the start);
* with ``--process-layer S...`` (alone): the swarm's process layer without zenoh, see
  :func:`process_layer` (``--ticks`` lockstep ticks of each scenario, a fresh interpreter per run);
* with ``--bus``: the cost of ``Publisher.put`` as the swarm declares its publishers
  (``SwarmProcess.publisher``: RELIABLE, BLOCK, express=True) against express=False, 16 puts of
  a State payload per round (what the plant does each tick for 16 UAVs), to a router in this
  process and one subscriber process: wall time of the 16 puts and CPU of this process (all its
  threads, Zenoh's included), per put.

Each figure is the median over ``--runs`` repeats of the mean time of ``--calls`` calls (CPU
time of this process, ``time.process_time_ns``, so other jobs on the machine matter less).

    python bench/micro_costs.py
    python bench/micro_costs.py --runs 7 --calls 3000 --json bench/results/micro.json
    python bench/micro_costs.py --runs 3 --process-layer example1 gen16 gen32 --ticks 500
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C

if TYPE_CHECKING:
    from zenswarm.process import runtime as rt


def bench(fn, calls: int) -> float:
    """Mean CPU microseconds per call of fn()."""
    fn()
    t0 = time.process_time_ns()
    for _ in range(calls):
        fn()
    return (time.process_time_ns() - t0) / calls / 1e3


def cases(tmpdir: Path):
    """The measured calls, as (label, fn), in the report's order."""
    from zenswarm.scenario.config import load_scenario
    from zenswarm.vehicle.params import QuadParams

    ex1 = load_scenario(C.PAPER["example1"])
    params = QuadParams.from_vehicle(ex1.vehicle)
    return _agent_cases(ex1, params, tmpdir) + _wire_cases() + _plant_cases(ex1, params) + _simulator_cases(ex1)


def _agent_cases(ex1, params, tmpdir: Path) -> list:
    import numpy as np

    from zenswarm.agents.core import AgentCore, AgentRow

    out = []
    for n, label in ((3, "example1 (UAV 1: 2 neighbours)"), (16, "gen16 (UAV 1: 4 neighbours)")):
        sc = ex1 if n == 3 else __import__("zenswarm.scenario.config", fromlist=["load_scenario"]).load_scenario(
            C.generated_scenario(16, tmpdir))
        row = AgentRow.from_scenario(sc, 0, params.mass, params.g)
        core = AgentCore(row)
        q = np.asarray(sc.initial_positions[0], dtype=float)
        v = np.zeros(3)
        core.reset(q, v)
        qn = np.asarray([sc.initial_positions[j] for j in row.neighbours], dtype=float)
        vn = np.zeros_like(qn)
        q0 = np.asarray(sc.leader.start, dtype=float)
        v0 = np.array([0.05, 0.02, 0.0])
        out.append((f"agent: AgentCore.tick, {label}", lambda core=core, q=q, v=v, qn=qn, vn=vn, q0=q0, v0=v0:
                    core.tick(q, v, qn, vn, q0, v0)))
    return out


def _wire_cases() -> list:
    import numpy as np

    from zenswarm.bus import wire

    out = []
    v3 = np.array([0.1, -0.2, 0.3])
    msgs = {
        "State": ("state", wire.State(t=10_000_000, seq=1, q=v3, v=v3, rpy=v3, w=v3)),
        "Ref": ("ref", wire.Ref(t=10_000_000, seq=1, q=v3, v=v3)),
        "Cmd": ("cmd", wire.Cmd(t=10_000_000, seq=1, thrust=0.3, rpy=v3, u=v3, d_hat=v3)),
    }
    dec = wire.Decoder()
    for name, (kind, m) in msgs.items():
        payload = wire.encode(m)
        out.append((f"wire: encode {name} ({len(payload)} B)", lambda m=m: wire.encode(m)))
        out.append((f"wire: Decoder.decode {name}", lambda kind=kind, payload=payload: dec.decode("k", kind, payload)))
        if name == "State":
            out.append(("wire: construct State (validation) + encode",
                        lambda: wire.encode(wire.State(t=10_000_000, seq=1, q=v3.copy(), v=v3.copy(), rpy=v3.copy(), w=v3.copy()))))
    return out


def _plant_cases(ex1, params) -> list:
    import numpy as np

    from zenswarm.plant.quadrotor import initial_state, step, step_held

    out = []
    h = ex1.timing.dt / ex1.timing.substeps
    for n in (3, 16, 32):
        st = initial_state(np.zeros((n, 3)) + np.array([0.0, 0.0, 0.4]))
        F = np.full(n, params.mass * params.g)
        rpy = np.zeros((n, 3))

        def period(st=st, F=F, rpy=rpy) -> None:
            for _ in range(ex1.timing.substeps):
                step(st, F, rpy, params, h)

        out.append((f"plant: one control period ({ex1.timing.substeps} physics steps), N={n}", period))

    for n in (3, 8):  # the simulator's path: step_held, on Python floats for N <= SCALAR_MAX_N
        st = initial_state(np.zeros((n, 3)) + np.array([0.0, 0.0, 0.4]))
        F = np.full(n, params.mass * params.g)
        rpy = np.tile([0.05, -0.03, 0.0], (n, 1))  # a small tilt: the attitude loop at work

        def held(st=st, F=F, rpy=rpy) -> None:
            step_held(st, F, rpy, params, h, ex1.timing.substeps)

        out.append((f"plant: step_held, one control period ({ex1.timing.substeps} physics steps), N={n}", held))
    return out


def _simulator_cases(ex1) -> list:
    import numpy as np

    from zenswarm.agents.generator import generator_rates_all
    from zenswarm.leader.aapf import AapfParams, integrate_leader

    out = []
    v3 = np.array([0.1, -0.2, 0.3])
    for n in (3, 16, 32):
        rng = np.random.default_rng(0)
        A = np.zeros((n, n))
        for i in range(n):
            for j in (i - 1, i + 1):
                A[i, j % n] = A[j % n, i] = 1.0
        b = np.zeros(n)
        b[0] = 1.0
        qs, vs, hh = rng.normal(size=(n, 3)), rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
        out.append((f"simulator: generator_rates_all, N={n}",
                    lambda qs=qs, vs=vs, hh=hh, A=A, b=b: generator_rates_all(qs, vs, hh, A, b, v3, v3, 0.1, 2.0)))

    aapf = AapfParams.from_scenario(ex1)
    q0 = np.asarray(ex1.leader.start, dtype=float)
    out.append(("leader: integrate_leader, one control period", lambda: integrate_leader(q0, ex1.timing.dt, aapf, ex1.timing.substeps)))
    return out


BUS_SUB = """
import sys, time
from zenswarm import bus
with bus.open_session(bus.client_config([sys.argv[1]]), handle_signals=False) as s:
    n = [0]
    sub = s.declare_subscriber("bench/put/**", lambda x: n.__setitem__(0, n[0] + 1))
    time.sleep(float(sys.argv[2]))
"""


def bus_costs(rounds: int, runs: int) -> dict[str, dict[str, float]]:
    """Wall and CPU microseconds per put, express on/off (see the module doc)."""
    import subprocess

    import numpy as np
    import zenoh

    from zenswarm import bus
    from zenswarm.bus import wire

    ep = bus.tcp_endpoint(bus.free_port())
    out: dict[str, dict[str, list[float]]] = {}
    with bus.open_session(bus.router_config([ep]), handle_signals=False):
        sub = subprocess.Popen([sys.executable, "-c", BUS_SUB, ep, str(10 + runs * rounds * 0.01)], cwd=C.REPO)
        try:
            time.sleep(2.0)
            with bus.open_session(bus.client_config([ep]), handle_signals=False) as s:
                v3 = np.array([0.1, -0.2, 0.3])
                payload = wire.encode(wire.State(t=1, seq=1, q=v3, v=v3, rpy=v3, w=v3))
                pubs = {
                    express: [s.declare_publisher(f"bench/put/{int(express)}/{i}", congestion_control=zenoh.CongestionControl.BLOCK,
                                                  express=express, reliability=zenoh.Reliability.RELIABLE) for i in range(16)]
                    for express in (True, False)
                }
                time.sleep(1.0)
                for _ in range(runs):
                    for express, ps in pubs.items():
                        name = f"bus: Publisher.put, express={express} (16 per round, 1 subscriber process)"
                        c0, w = time.process_time_ns(), 0
                        for _ in range(rounds):
                            w0 = time.perf_counter_ns()
                            for p in ps:
                                p.put(payload)
                            w += time.perf_counter_ns() - w0
                            time.sleep(0.002)
                        c = time.process_time_ns() - c0
                        d = out.setdefault(name, {"wall": [], "cpu": []})
                        d["wall"].append(w / rounds / 16 / 1e3)
                        d["cpu"].append(c / rounds / 16 / 1e3)
        finally:
            sub.terminate()
            sub.wait()
    return {k: {"wall_us_median": C.median(v["wall"]), "cpu_us_median": C.median(v["cpu"])} for k, v in out.items()}


class _Sample:
    """What SwarmProcess.handle_sample reads of a zenoh sample: its payload (no sender id)."""

    __slots__ = ("payload", "source_info", "_b")

    def __init__(self, payload: bytes) -> None:
        self.payload = self
        self.source_info = None
        self._b = payload

    def to_bytes(self) -> bytes:
        return self._b



class _LoopbackBus:
    """The bus of :func:`process_layer`, zenoh left out: a ``put`` queues (key, payload);
    :meth:`deliver_while` hands each queued message to every subscriber's ``handle_sample`` by a
    plain call, in the order a router would deliver it, timing the calls by role."""

    def __init__(self) -> None:
        self.queue: collections.deque[tuple[str, bytes]] = collections.deque()
        self.subs: dict[str, list[tuple[rt.SwarmProcess, str, Any, str]]] = collections.defaultdict(list)
        self.wall_ns: dict[str, int] = collections.defaultdict(int)  # by role

    def publisher(self, key: str) -> _LoopbackPub:
        return _LoopbackPub(self.queue, key)

    def subscribe(self, p: rt.SwarmProcess, key: str, kind: str, role: str) -> None:
        from zenswarm.process import runtime as rt

        senders = rt.expected_senders(p.keys, key)
        p.guard  # noqa: B018
        self.subs[key].append((p, kind, senders, role))

    def deliver_while(self, go_on: Callable[[], bool]) -> int:
        """Deliver the queued messages, and those they cause, while ``go_on()``; CPU ns of this process."""
        clock = time.perf_counter_ns  # the shares (process_time_ns costs 4 us a call here)
        c_start = time.process_time_ns()
        while self.queue and go_on():
            key, payload = self.queue.popleft()
            for p, kind, senders, role in self.subs.get(key, ()):
                c0 = clock()
                p.handle_sample(key, kind, _Sample(payload), senders)
                self.wall_ns[role] += clock() - c0
        return time.process_time_ns() - c_start


class _LoopbackPub:
    """What SwarmProcess uses of a zenoh publisher: ``put`` (here: onto the loopback bus's queue)."""

    def __init__(self, queue: collections.deque[tuple[str, bytes]], key: str) -> None:
        self.queue = queue
        self.key = key
        self.id = None

    def put(self, payload: bytes, source_info: object = None) -> None:
        self.queue.append((self.key, payload))


def _patch_runtime(bus: _LoopbackBus) -> None:
    """Every SwarmProcess of this interpreter publishes on ``bus``, without diagnostics (for good:
    :func:`process_layer` runs in an interpreter of its own)."""
    from zenswarm.process import runtime as rt

    rt.zenoh.SourceInfo = lambda *a: None  # type: ignore[assignment,misc]
    rt.SwarmProcess.publisher = lambda self, key: self._pubs.setdefault(key, bus.publisher(key))  # type: ignore[method-assign]
    rt.SwarmProcess.publish_diag = lambda self, *a, **k: None  # type: ignore[method-assign]


def _in_process_swarm(scenario: Path, bus: _LoopbackBus) -> tuple[Any, Any, rt.Lockstep, list[Any]]:
    """The plant, the leader and every agent of ``scenario`` (their ``SwarmProcess`` and lockstep
    shells, as ``zenswarm up`` starts them) subscribed on ``bus``: (plant, its lockstep shell, the
    leader's lockstep, the agents' lockstep shells)."""
    from zenswarm.agents import process as ap
    from zenswarm.bus import wire
    from zenswarm.leader import process as lp
    from zenswarm.plant import process as pp
    from zenswarm.process import runtime as rt
    from zenswarm.scenario.config import load_scenario

    sc = load_scenario(scenario)

    def proc(name: str) -> rt.SwarmProcess:
        p = rt.SwarmProcess(name, rt.ProcessOptions(swarm="bench"))
        p.scenario = sc
        return p

    plant_p = proc("plant")
    plant = pp._Plant(plant_p)
    lsp = pp._LockstepPlant(plant)
    plant_p.on_input = lsp.ls.poke
    for key in plant.cmd_keys:
        bus.subscribe(plant_p, key, "cmd", "plant")
    lead_p = proc("leader")
    leader = lp._Leader(lead_p)
    lsl = rt.Lockstep(leader.n_ticks, leader.ready, leader.step, 5.0, lead_p.stop, can_force=lambda k: False)
    lead_p.on_input = lsl.poke
    bus.subscribe(lead_p, lead_p.keys.clock, "clock", "leader")
    agents = []
    for i in range(1, sc.n + 1):
        p = proc(wire.agent(i))
        a = ap._Agent(p, i)
        la = ap._LockstepAgent(a)
        p.on_input = la.ls.poke
        for key, kind in ap.subscriptions(a.keys, a.row):
            bus.subscribe(p, key, kind, "agents")
        agents.append(la)
    return plant, lsp, lsl, agents


def process_layer(scenario: Path, ticks: int) -> dict[str, float]:
    """CPU of the swarm's process layer per lockstep tick, zenoh left out: the plant, the leader
    and every agent (their ``SwarmProcess`` and lockstep shells, as ``zenswarm up`` starts them)
    in this one process, each message handed from the publisher's ``put`` to every subscriber's
    ``handle_sample`` by a plain call (decode, input guard, inbox, lockstep, control law or
    physics, encode), in the order a router would deliver it. CPU us per tick of this process
    (``total``), shared out by role in proportion of their wall time."""
    bus = _LoopbackBus()
    _patch_runtime(bus)
    plant, lsp, lsl, agents = _in_process_swarm(scenario, bus)
    lsl.poke()
    for la in agents:
        la.ls.poke()
    with lsp.ls.lock:
        plant.publish_tick(0)
    c_all = bus.deliver_while(lambda: lsp.ls.k < ticks)
    for ls in [lsp.ls, lsl] + [la.ls for la in agents]:
        if ls.error is not None:
            raise ls.error
    n = lsp.ls.k
    if n < min(ticks, plant.n_ticks):
        raise SystemExit(f"process layer: the plant stopped at tick {n} of {min(ticks, plant.n_ticks)}")
    st = plant.core.state
    digest = hashlib.sha256(b"".join(x.tobytes() for x in (st.q, st.v, st.rpy, st.w))).hexdigest()[:16]
    roles = ("plant", "leader", "agents")
    wall = sum(bus.wall_ns[r] for r in roles)
    return {"ticks": n, "state_sha256": digest, "total": c_all / n / 1e3} | {
        role: c_all * bus.wall_ns[role] / wall / n / 1e3 for role in roles}


def _main_process_layer(a: argparse.Namespace, info: dict) -> int:
    """--process-layer: each run in a fresh interpreter (the patches of process_layer stay there)."""
    import json
    import subprocess
    import tempfile

    rows, out = [], {}
    with tempfile.TemporaryDirectory(prefix="zenswarm-micro-") as tmp:
        for spec in a.process_layer:
            label, path = C.scenario_file(spec, Path(tmp), 10.0)
            runs = []
            for _ in range(a.runs):
                code = ("import json, sys; sys.path.insert(0, sys.argv[1]); import micro_costs; from pathlib import Path; "
                        "print(json.dumps(micro_costs.process_layer(Path(sys.argv[2]), int(sys.argv[3]))))")
                r = subprocess.run([sys.executable, "-c", code, str(Path(__file__).resolve().parent), str(path), str(a.ticks)],
                                   check=True, capture_output=True, text=True, cwd=C.REPO)
                runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
            med = {k: C.median([r[k] for r in runs]) for k in ("total", "plant", "leader", "agents")}
            out[label] = {"median_us_per_tick": med, "ticks": runs[0]["ticks"], "state_sha256": runs[0]["state_sha256"], "runs": runs}
            rows.append([label, runs[0]["ticks"], med["total"], med["plant"], med["leader"], med["agents"], runs[0]["state_sha256"]])
    print(C.table(["scenario", "ticks", "CPU us/tick", "plant", "leader", "agents", "final state sha256"], rows))
    C.write_report(a.json, "micro_costs --process-layer", info, summary=out)
    return 0


def main(argv: list[str] | None = None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5, help="repeats (median reported; default 5)")
    ap.add_argument("--calls", type=int, default=2000, help="calls per repeat (default 2000)")
    ap.add_argument("--json", type=Path, metavar="FILE", help="write the figures to FILE")
    ap.add_argument("--bus", action="store_true", help="also measure Publisher.put (express on/off) through a router")
    ap.add_argument("--process-layer", nargs="+", metavar="S",
                    help="only the swarm's process layer in one process (process_layer) on these scenarios "
                         "(example1, example2, gen<N>, or TOML paths): CPU us per lockstep tick by role, median of --runs")
    ap.add_argument("--ticks", type=int, default=500, help="lockstep ticks per --process-layer run (default 500)")
    a = ap.parse_args(argv)
    info = C.machine_info()
    for line in C.machine_lines(info):
        print(line)
    if a.process_layer:
        return _main_process_layer(a, info)
    with tempfile.TemporaryDirectory(prefix="zenswarm-micro-") as tmp:
        cs = cases(Path(tmp))
        res: dict[str, list[float]] = {name: [] for name, _ in cs}
        for _ in range(a.runs):
            for name, fn in cs:
                res[name].append(bench(fn, a.calls))
    summary = {name: {"us_median": C.median(v), "us_min": min(v)} for name, v in res.items()}
    print(C.table(["call", "CPU us/call (median)", "min"], [[k, v["us_median"], v["us_min"]] for k, v in summary.items()]))
    if a.bus:
        bc = bus_costs(500, a.runs)
        summary.update(bc)
        print()
        print(C.table(["call", "wall us/put (median)", "CPU us/put, all threads (median)"],
                      [[k, v["wall_us_median"], v["cpu_us_median"]] for k, v in bc.items()]))
    C.write_report(a.json, "micro_costs", info, summary=summary, runs=res)
    return 0


if __name__ == "__main__":
    sys.exit(main())

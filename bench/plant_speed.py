"""Cost of a plant model per vehicle per physics step: the built-in ``quadrotor`` against ``rotorpy``.

Each run builds a :class:`zenswarm.plant.core.PlantCore` for paper example 1 (N = 3, 100 Hz
control, 10 physics sub-steps of 1 ms) with the model selected, holds commands about hover
(thrust m g (1 + 5 % sine), attitude setpoints within +-0.05 rad, as a flight does) and times
``--ticks`` calls of ``PlantCore.step`` (the failsafe, the model's control period and the state
check: what the plant process and the simulator pay per tick). The figure is the CPU time of this
process (``time.process_time_ns``, so other jobs on the machine matter less) divided by
ticks x N x sub-steps: microseconds per vehicle per physics step of 1 ms of sim time (RotorPy
takes one adaptive RK45 step per control tick, ``steps_per_tick = 1``; the normalisation is per
1 ms of flight either way, so the two figures compare what a second of flight costs). Median of
``--runs`` runs. The first row is the built-in's step as it was before plant models were plug-ins
(the failsafe, then ``step_held``), for the cost of the plug-in layer.

    python bench/plant_speed.py
    python bench/plant_speed.py --runs 7 --ticks 300 --json bench/results/plant_speed.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _common as C


def run_once(model: str, ticks: int, n: int | None) -> float:
    """CPU microseconds per vehicle per physics step of one run."""
    import numpy as np

    from zenswarm.plant.core import PlantCore
    from zenswarm.scenario.config import load_scenario
    from zenswarm.scenario.plugins import select

    sc = select(load_scenario(C.PAPER["example1"]), plant_model=model)
    core = PlantCore(sc)
    p, N = core.params, sc.n
    t0 = time.process_time_ns()
    for k in range(ticks):
        thrust = p.mass * p.g * (1.0 + 0.05 * np.sin(0.07 * k + np.arange(N)))
        rpy = 0.05 * np.sin(0.05 * k + np.arange(3 * N)).reshape(N, 3)
        core.hold_all(thrust, rpy, k)
        core.step(k)
    cpu = (time.process_time_ns() - t0) / 1e3
    return cpu / (ticks * N * sc.timing.substeps)


def run_direct(ticks: int) -> float:
    """The same for the plant step before plant models were plug-ins: the failsafe then
    ``step_held`` on a ``PlantState`` (what ``PlantCore.step`` ran), no model call, no state check."""
    import numpy as np

    from zenswarm.plant.core import PlantCore
    from zenswarm.plant.quadrotor import initial_state, step_held
    from zenswarm.scenario.config import load_scenario

    sc = load_scenario(C.PAPER["example1"])
    core = PlantCore(sc)
    p, N, h, nsub = core.params, sc.n, core.h, core.nsub
    st = initial_state(np.asarray(sc.initial_positions, dtype=float))
    t0 = time.process_time_ns()
    for k in range(ticks):
        thrust = p.mass * p.g * (1.0 + 0.05 * np.sin(0.07 * k + np.arange(N)))
        rpy = 0.05 * np.sin(0.05 * k + np.arange(3 * N)).reshape(N, 3)
        core.hold_all(thrust, rpy, k)
        f, r = core.failsafe.apply(k, [0.0] * N, st.q, st.v, core.thrust, core.rpy_cmd, p.mass, p.g, core.yaw)
        step_held(st, f, r, p, h, nsub, core.dist.sampler(k * core.dt, h))
    cpu = (time.process_time_ns() - t0) / 1e3
    return cpu / (ticks * N * sc.timing.substeps)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--ticks", type=int, default=200, help="control ticks per run (2 s of flight)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    info = C.machine_info()
    print("\n".join(C.machine_lines(info)))
    rows, out = [], {}
    for model in ("quadrotor (direct, before plug-ins)", "quadrotor", "rotorpy"):
        direct = model.startswith("quadrotor (")

        def one(ticks: int, model: str = model, direct: bool = direct) -> float:
            return run_direct(ticks) if direct else run_once(model, ticks, None)

        one(5)  # warm-up: imports, caches
        xs = [one(args.ticks) for _ in range(args.runs)]
        med = C.median(xs)
        out[model] = {"us_per_vehicle_physics_step": xs, "median": med}
        rows.append([model, C.fmt(med, 2), C.fmt(min(xs), 2), C.fmt(max(xs), 2), C.fmt(med * 10.0 / 1e3, 3)])
    print(C.table(["model", "us / vehicle / physics step (median)", "min", "max", "ms / vehicle / control tick"], rows))
    ratio = out["rotorpy"]["median"] / out["quadrotor"]["median"]
    print(f"rotorpy / quadrotor: {ratio:.0f}x")
    C.write_json(args.json, {"machine": info, "command": C.command_line(), "runs": args.runs, "ticks": args.ticks, "models": out})
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A growing swarm congests a fixed per-sender capacity (issue 18, bandwidth and queueing).

For each N, generates ``zenswarm scenario generate --n N --shape circle --topology complete``
(every UAV hears every other: a sender's load grows with N), puts a capacity on the agents'
reference links only (``[[faults.links]] kind = "ref"``, shared medium per sender, so the N - 1
copies of one reference queue behind each other) and flies it in the in-process simulator
(``zenswarm sim``, which the lockstep swarm equals bit for bit). Reported per N:

* offered load of one sender (bytes/s of its references, real encoded sizes) against the capacity;
* delivery ratio of the reference links (delivered / sent, ticks 1 .. end; drops are the full
  queue's);
* mean and 95th-percentile latency of the delivered references (queue wait + serialization), ms;
* the verdict and the maximum formation error of the vehicles (m), and the same without capacity.

    python bench/radio_capacity.py
    python bench/radio_capacity.py --n 3 5 8 10 12 --capacity 64kB/s --queue 8 --duration 30

Not a test.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from zenswarm.compose.sim import simulate
from zenswarm.link import FaultState, message_size, parse_capacity, plan_for, scenario_links
from zenswarm.scenario.config import scenario_from_dict
from zenswarm.scenario.generate import generate_scenario


def run(n: int, capacity: str, queue: str, duration: float | None, seed: int) -> dict:
    d = generate_scenario(n, shape="circle", topology="complete", seed=seed)
    base = scenario_from_dict(d)
    n_ticks = None if duration is None else int(round(duration / base.timing.dt))
    free = simulate(base, n_ticks=n_ticks).results
    d["faults"] = {"links": [{"kind": "ref", "capacity": capacity, "queue": queue}]}
    sc = scenario_from_dict(d)
    plan = plan_for(sc)
    assert plan is not None
    res = simulate(sc, n_ticks=n_ticks, faults=plan).results
    dt = sc.timing.dt
    flown = int(round(res["sim_time_s"] / dt))
    fs = FaultState(plan)
    ticks = np.arange(1, flown, dtype=np.int64)
    delays, sent, delivered = [], 0, 0
    for lk in scenario_links(sc):
        if lk[2] != "ref":
            continue
        b = fs.decide_batch(*lk, ticks, ticks * dt)
        sent += ticks.size
        delivered += int((~b.dropped).sum())
        delays.append(b.delay_s[~b.dropped])
    lat = np.concatenate(delays) if delays else np.zeros(0)
    load = (n - 1) * message_size("ref", flown, dt) / dt
    return {
        "n": n,
        "load_Bps": load,
        "capacity_Bps": parse_capacity(capacity),
        "delivery": delivered / max(sent, 1),
        "lat_mean_ms": 1e3 * float(lat.mean()) if lat.size else float("nan"),
        "lat_p95_ms": 1e3 * float(np.percentile(lat, 95)) if lat.size else float("nan"),
        "success": res["success"],
        "err_m": res.get("max_formation_error_m"),
        "free_err_m": free.get("max_formation_error_m"),
        "free_success": free["success"],
        "sim_time_s": res["sim_time_s"],
    }


def _f(x: float | None, fmt: str) -> str:
    return "n/a" if x is None else format(x, fmt)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, nargs="+", default=[3, 5, 8, 10, 12], help="swarm sizes")
    ap.add_argument("--capacity", default="64kB/s", help="per-sender capacity of the reference links (default 64kB/s)")
    ap.add_argument("--queue", default="8", help="queue bound per sender: messages or bytes (default 8)")
    ap.add_argument("--duration", type=float, default=None, help="sim seconds per run (default: the whole mission)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    print(f"capacity {a.capacity} per sender (reference links, shared medium), queue {a.queue}, topology complete, seed {a.seed}")
    print(
        "| N | offered load / capacity | delivery ratio | mean latency (ms) | p95 latency (ms) | verdict "
        "| max formation error (m) | without capacity (m) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for n in a.n:
        r = run(n, a.capacity, a.queue, a.duration, a.seed)
        print(
            f"| {n} | {r['load_Bps'] / 1e3:.1f} kB/s / {r['capacity_Bps'] / 1e3:.0f} kB/s | {r['delivery']:.3f} | "
            f"{r['lat_mean_ms']:.2f} | {r['lat_p95_ms']:.2f} | {'success' if r['success'] else 'FAILED'} | "
            f"{_f(r['err_m'], '.4f')} | {_f(r['free_err_m'], '.4f')} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

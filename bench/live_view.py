"""Cost of the live view (``zenswarm up --live``) on a lockstep flight's wall time.

Paper example 1 (70 s of sim time) flown by ``zenswarm up`` (lockstep), ``--runs`` times without
and ``--runs`` times with ``--live PORT``, interleaved (off, on, off, on, ...). With ``--live`` a
Foxglove WebSocket client (this script, ``websockets``) is connected and subscribed to every
channel for the whole flight, so the server encodes and sends every frame (the worst case; with no
client the SDK drops the messages unsent).

Per run: the flight's wall time (n_ticks x (step_ms_mean + wait_ms_mean) from the plant's
diagnostics: first tick to last, the part --live could slow down) and the whole command's wall
time (with start-up and shut-down). Median of each; cost = median(on) / median(off) - 1. Every
run's time series must equal the first's bit for bit (the live view is not on the flight's path).

    python bench/live_view.py                 # 3 + 3 runs
    python bench/live_view.py --runs 5 --json bench/results/live_view.json

Not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from zenswarm.judge.metrics import TimeSeries

import _common as C

SCENARIO = C.REPO / "compose" / "scenarios" / "paper_example1.toml"


class Client(threading.Thread):
    """A Foxglove WebSocket client subscribed to every channel; counts the messages it gets."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.messages = 0
        self.bytes = 0
        self.stop = threading.Event()

    def run(self) -> None:
        from websockets.sync.client import connect

        url = f"ws://127.0.0.1:{self.port}"
        while not self.stop.is_set():
            try:
                ws = connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], max_size=None)  # type: ignore[list-item]
                break
            except OSError:
                time.sleep(0.05)
        else:
            return
        with ws:
            while not self.stop.is_set():
                try:
                    raw = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except Exception:  # noqa: BLE001 - the server went away at the end of the flight
                    return
                if isinstance(raw, str):
                    op = json.loads(raw)
                    if op["op"] == "advertise":
                        subs = [{"id": ch["id"], "channelId": ch["id"]} for ch in op["channels"]]
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                else:
                    self.messages += 1
                    self.bytes += len(raw)


def flight_s(res: dict) -> float | None:
    d = res.get("diagnostics", {}).get("plant", {})
    if "step_ms_mean" not in d or "wait_ms_mean" not in d:
        return None
    n = round(res["sim_time_s"] / 0.01)
    return n * (d["step_ms_mean"] + d["wait_ms_mean"]) / 1e3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    C.install_cleanup()
    rows: dict[str, list[dict]] = {"off": [], "on": []}
    ref: TimeSeries | None = None
    same = True
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.runs):
            for mode in ("off", "on"):
                out = Path(tmp) / f"{mode}{r}"
                client = None
                extra: list[str] = []
                if mode == "on":
                    port = C.free_port()
                    extra = ["--live", str(port)]
                    client = Client(port)
                    client.start()
                run = C.run_up(SCENARIO, out, f"live{mode}", extra)
                if client is not None:
                    client.stop.set()
                    client.join(timeout=5)
                res = run.results or {}
                row = {"up_s": run.wall_s, "flight_s": flight_s(res), "rc": run.returncode,
                       "frames_received": client.messages if client else None, "bytes_received": client.bytes if client else None}
                rows[mode].append(row)
                ts = TimeSeries.load(str(out / "timeseries.npz"))
                if ref is None:
                    ref = ts
                else:
                    same &= all(np.array_equal(getattr(ts, f), getattr(ref, f), equal_nan=True) for f in TimeSeries.FIELDS)
                print(f"run {r + 1} {mode:3}: flight {C.fmt(row['flight_s'])} s  up {C.fmt(row['up_s'])} s  rc {run.returncode}"
                      + (f"  client got {client.messages} messages, {client.bytes / 1e6:.1f} MB" if client else ""), flush=True)
    med = {m: {k: C.median(x[k] for x in rows[m]) for k in ("flight_s", "up_s")} for m in rows}
    cost = {k: (med["on"][k] / med["off"][k] - 1.0) if med["on"][k] and med["off"][k] else None for k in ("flight_s", "up_s")}
    print(C.table(["", "flight s (median)", "up s (median)"],
                  [["without --live", C.fmt(med["off"]["flight_s"]), C.fmt(med["off"]["up_s"])],
                   ["with --live + client", C.fmt(med["on"]["flight_s"]), C.fmt(med["on"]["up_s"])],
                   ["cost", f"{100 * cost['flight_s']:+.1f} %" if cost["flight_s"] is not None else "-",
                    f"{100 * cost['up_s']:+.1f} %" if cost["up_s"] is not None else "-"]]))
    print(f"every run's time series equal bit for bit: {same}")
    C.write_json(a.json, {"command": C.command_line(), "machine": C.machine_info(), "runs": rows, "median": med, "cost": cost,
                          "bit_identical": same})
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())

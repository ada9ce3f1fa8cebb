"""The live Rerun view with a browser attached: what the browser receives and how far behind.

Paper example 1 (``--duration`` s of sim time, default the whole 70 s) flown by ``zenswarm up
--realtime --live rerun:PORT`` (stdin not a terminal); headless Chromium (``/usr/bin/chromium``,
driven over the DevTools protocol as in tests/test_rerun.py) opens the printed URL when it is
printed and stays until the end. Per run: the exit status and the mission's (results.json), the
bytes the browser received from Rerun's gRPC data server (DevTools ``Network.dataReceived`` of its
``ReadMessages`` stream), how long after the flight's end (the verdict line) the last of it came,
what the viewer itself held at the flight's end (read in the page through the web viewer's
``viewer_state()``, see ``tests/test_rerun.py``, ``VIEWER_STATE_JS``): the sim time it held and the
age of its newest frame (its lag), and a few seconds later; and whether the view said that not
everything reached the viewer.

``--python PY`` runs another checkout's zenswarm (its venv's python, run from that checkout) to
compare against the code before a change; ``--runs N`` repeats, interleaved with ``--vs``.

    python bench/live_rerun_browser.py --runs 3
    python bench/live_rerun_browser.py --runs 3 --vs OTHER/.venv/bin/python --json bench/results/live_rerun_browser.json

Not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from test_rerun import Browser, DataStream, settle_viewer

import _common as C

SCENARIO = C.REPO / "compose" / "scenarios" / "paper_example1.toml"


def one(python: str, duration: float | None, tmp: Path, tag: str) -> dict:
    out, web, router = tmp / f"out{tag}", C.free_port(), C.free_port()
    swarm = f"bench_rrbr_{tag}_{time.time_ns() % 10**8}"
    cmd = [python, "-m", "zenswarm", "up", str(SCENARIO), "--out", str(out), "--swarm", swarm,
           "--listen", f"tcp/127.0.0.1:{router}", "--realtime", "--live", f"rerun:{web}"]
    if duration is not None:
        cmd += ["--duration", str(duration)]
    cwd = Path(python).absolute().parent.parent.parent  # the checkout whose venv runs it
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True)
    lines: list[tuple[float, str]] = []
    browser = stream = None
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append((time.monotonic(), line))
            if "live view (Rerun) on " in line:
                break
        url = lines[-1][1].split("live view (Rerun) on ", 1)[1].split()[0]
        (tmp / f"chromium{tag}").mkdir()
        browser = Browser(tmp / f"chromium{tag}")
        browser.call("Network.enable")
        browser.call("Page.navigate", url=url)
        stream = DataStream(browser)
        stream.start()

        def read() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                lines.append((time.monotonic(), line))

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        proc.wait(timeout=600)
        reader.join(10)
        flown = json.loads((out / "results.json").read_text())["sim_time_s"] if (out / "results.json").is_file() else None
        settle_viewer(stream, None if flown is None else flown - 0.5)
        stream.stop()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if browser is not None:
            browser.close()
    text = "".join(x for _, x in lines)
    res = json.loads((out / "results.json").read_text()) if (out / "results.json").is_file() else {}
    end = next((t for t, x in lines if "SUCCESS" in x or "FAILED" in x), float("nan"))
    assert stream is not None
    at_end = stream.viewer_at(time.time() - (time.monotonic() - end))
    return {
        "rc": proc.returncode, "success": res.get("success"), "sim_time_s": res.get("sim_time_s"),
        "mb_received": stream.bytes / 1e6, "last_byte_after_end_s": stream.last() - end,
        "viewer_sim_at_end_s": at_end.sim if at_end else None, "viewer_lag_at_end_s": at_end.lag if at_end else None,
        "viewer_sim_held_s": max((x.sim for x in stream.samples if x.sim is not None), default=None),
        "traceback": "Traceback" in text, "not_everything": "not everything reached the viewer" in text,
    }  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--duration", type=float, default=None, help="sim seconds (default: the scenario's, 70 s)")
    ap.add_argument("--python", default=sys.executable, help="the python of the checkout to run (default this one)")
    ap.add_argument("--vs", default=None, help="another checkout's python, run interleaved (the code before)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    C.install_cleanup()
    pythons = {"this": a.python} | ({"vs": a.vs} if a.vs else {})
    rows: dict[str, list[dict]] = {k: [] for k in pythons}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.runs):
            for name, py in pythons.items():
                row = one(py, a.duration, Path(tmp), f"{name}{r}")
                rows[name].append(row)
                cells = ", ".join(f"{k} {C.fmt(v) if isinstance(v, float) else v}" for k, v in row.items())
                print(f"run {r + 1} {name}: {cells}", flush=True)
    for name, rs in rows.items():
        print(f"{name}: median {C.fmt(C.median(x['mb_received'] for x in rs))} MB received, "
              f"last byte {C.fmt(C.median(x['last_byte_after_end_s'] for x in rs))} s after the end, "
              f"the viewer {C.fmt(C.median(x['viewer_lag_at_end_s'] or float('nan') for x in rs))} s behind at the end; "
              f"exit statuses {[x['rc'] for x in rs]}, tracebacks {sum(x['traceback'] for x in rs)}")  # fmt: skip
    C.write_json(a.json, {"command": C.command_line(), "machine": C.machine_info(), "runs": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark-only instrumentation of the swarm processes (bench/swarm_realtime.py, swarm_lockstep.py).

Python imports ``sitecustomize`` at start-up from ``sys.path``; bench/swarm_realtime.py puts this
folder on ``PYTHONPATH`` and sets ``ZENSWARM_BENCH_STAMPS=<dir>`` for ``zenswarm up`` only, so the
plant, the leader and every agent it starts (``python -m zenswarm plant|leader|agent ...``) get
two wrappers, and nothing else changes (no source file of the project is touched):

* ``SwarmProcess.put`` (every publication passes there, encoded): the ``CLOCK_MONOTONIC`` time
  (``time.monotonic_ns``, system-wide on Linux, so comparable across processes) when a message is
  encoded, right before its ``put``, by (key, seq) (the original ``put`` runs unchanged); and, for
  ``Diag`` messages, the loop counters they carry (loop_ticks, missed_deadlines) so the in-flight
  share of missed deadlines can be separated from start-up.
* ``wire.Decoder.decode``: the time a sample reached the receiving process's Zenoh callback,
  taken on entry to the decoder (the first thing the subscriber callback does), by (key, seq).

At exit each process writes ``<dir>/<role>-<pid>.json`` with, per key, lists of (seq, message sim
time t in ns, stamp); the benchmark pairs publications with receptions by (key, seq): latency =
receive time - publish time (bench/swarm_realtime.py), or follows one lockstep tick through the
processes by the messages' sim time (bench/swarm_lockstep.py --breakdown). Other processes (the
supervisor, pip, ...) are left alone: the wrappers are installed only for the three roles.
"""

from __future__ import annotations

import os
import sys

_DIR = os.environ.get("ZENSWARM_BENCH_STAMPS")
_ROLE = None
if _DIR:
    _argv = list(sys.argv)  # at this point: ['-m', '<subcommand>', ...] for `python -m zenswarm ...`
    if len(_argv) > 1 and _argv[1] in ("agent", "plant", "leader"):
        _ROLE = _argv[1]
        if _ROLE == "agent" and "--id" in _argv:
            _ROLE = f"agent{_argv[_argv.index('--id') + 1]}"


def _install(role: str, out_dir: str) -> None:
    import atexit
    import json
    import time

    import msgspec

    from zenswarm.bus import wire
    from zenswarm.process import runtime

    mono = time.monotonic_ns
    pub: dict[str, list] = {}
    rx: dict[str, list] = {}
    diags: list = []

    orig_put = runtime.SwarmProcess.put
    peek = msgspec.msgpack.Decoder()

    def put(self, key, payload):  # SwarmProcess.put (every publication: encoded, about to be put)
        t = mono()
        m = peek.decode(payload)
        lst = pub.get(key)
        if lst is None:
            lst = pub[key] = []
        lst.append((m["seq"], m["t"], t))
        if m["k"] == "diag":
            info = m["info"]
            diags.append((t, info.get("loop_ticks"), info.get("missed_deadlines"), info.get("jitter_mean_ms")))
        return orig_put(self, key, payload)

    orig_decode = wire.Decoder.decode

    def decode(self, key, kind, payload):
        t = mono()
        msg = orig_decode(self, key, kind, payload)
        if msg is not None and kind != "diag":
            lst = rx.get(key)
            if lst is None:
                lst = rx[key] = []
            lst.append((msg.seq, msg.t, t))
        return msg

    runtime.SwarmProcess.put = put
    wire.Decoder.decode = decode

    def dump() -> None:
        path = os.path.join(out_dir, f"{role}-{os.getpid()}.json")
        with open(path, "w") as f:
            json.dump({"role": role, "pid": os.getpid(), "pub": pub, "rx": rx, "diags": diags}, f)

    atexit.register(dump)


if _ROLE is not None:
    _install(_ROLE, _DIR)

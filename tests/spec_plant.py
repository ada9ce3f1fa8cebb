"""A plant for a zenswarm swarm written from docs/protocol.md alone (zenoh + msgpack + numpy).

It imports nothing of zenswarm on purpose (``tests/test_protocol_plant.py`` checks that): it is
what a third party would write from the spec, and the test flies it in lockstep with zenswarm's
leader and agents (``zenswarm up ... --external plant``). Each step below cites the section of
docs/protocol.md it implements.

Model: a simplified quadrotor, eqs (1)-(3) of the paper with the attitude loop taken as perfect:
the commanded roll/pitch/yaw is reached at once, so the acceleration is
``R(rpy_cmd) e3 * thrust / m - g e3`` (R of eq. 2, ZYX Euler angles, body FLU -> inertial ENU),
integrated by semi-implicit Euler over the physics sub-steps of a tick. The state reports the
commanded attitude as ``rpy`` and a zero body rate ``w``.

Usage: python tests/spec_plant.py --connect tcp/127.0.0.1:7447 --swarm NAME [--expect recorder]
Exit status: 0 flown to the end, 2 bad input / no mission, 3 a process never announced itself.
"""

from __future__ import annotations

import argparse
import math
import queue
import sys
import time

import msgpack
import numpy as np
import zenoh

SCHEMA_VERSION = 1  # protocol.md, "Payloads"
CLOCK_EVERY = 4  # protocol.md, "Lockstep": at least every 4 ticks
LOCKSTEP_TIMEOUT_S = 5.0  # protocol.md, "Lockstep": wait this long for a cmd, then hold the last one
DEFAULT_MASS = 0.027  # protocol.md, "The mission": [vehicle] absent -> a Crazyflie 2.1
G = 9.81


def log(text: str) -> None:
    print(f"spec_plant: {text}", flush=True)


def rotation_e3(rpy: np.ndarray) -> np.ndarray:
    """Third column of R(phi, theta, psi) of eq. (2): the thrust direction in ENU."""
    phi, theta, psi = rpy
    return np.array([
        math.cos(psi) * math.sin(theta) * math.cos(phi) + math.sin(psi) * math.sin(phi),
        math.sin(psi) * math.sin(theta) * math.cos(phi) - math.cos(psi) * math.sin(phi),
        math.cos(phi) * math.cos(theta),
    ])


class SpecPlant:
    def __init__(self, session: zenoh.Session, swarm: str, expect: list[str]) -> None:
        self.s = session
        self.prefix = f"swarm/{swarm}"  # protocol.md, "Key expressions"
        self.expect = expect
        self.zid = str(session.zid())
        self.pubs: dict[str, tuple[zenoh.Publisher, zenoh.SourceInfo]] = {}
        self.seq: dict[str, int] = {}

    # ------------------------------------------------------------------ bus (protocol.md, "Sessions")
    def publish(self, key: str, body: dict) -> None:
        """Put ``{v, k, t, seq, ...}`` on ``key``: BLOCK + RELIABLE, stamped with our SourceInfo."""
        if key not in self.pubs:
            pub = self.s.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE
            )
            self.pubs[key] = (pub, zenoh.SourceInfo(pub.id, 0))
        pub, si = self.pubs[key]
        self.seq[key] = self.seq.get(key, 0) + 1  # strictly increasing per key
        msg = {"v": SCHEMA_VERSION, "seq": self.seq[key], **body}
        pub.put(msgpack.packb(msg, use_bin_type=True), source_info=si)

    def fetch_mission(self, timeout_s: float = 30.0) -> dict:
        """protocol.md, "The mission": query swarm/<name>/mission until the leader answers."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for reply in self.s.get(f"{self.prefix}/mission", timeout=2.0):
                ok = reply.ok
                if ok is None:
                    continue
                m = msgpack.unpackb(ok.payload.to_bytes(), raw=False)
                if m.get("v") == SCHEMA_VERSION and m.get("k") == "mission":
                    return m["scenario"]
            time.sleep(0.2)
        raise SystemExit(2)

    def wait_alive(self, names: list[str], timeout_s: float = 60.0) -> list[str]:
        """protocol.md, "Liveliness": a liveliness query on swarm/<name>/alive/* lists who is up."""
        deadline = time.monotonic() + timeout_s
        want = {f"{self.prefix}/alive/{n}": n for n in names}
        while True:
            seen = {str(r.ok.key_expr) for r in self.s.liveliness().get(f"{self.prefix}/alive/*", timeout=1.0) if r.ok}
            missing = [n for k, n in want.items() if k not in seen]
            if not missing or time.monotonic() > deadline:
                return missing
            time.sleep(0.02)

    # ------------------------------------------------------------------ the flight
    def run(self) -> int:
        sc = self.fetch_mission()
        tm = sc["timing"]
        dt = 1.0 / tm["control_rate_hz"]
        dt_ns = round(dt * 1e9)
        nsub = max(1, round(tm["physics_rate_hz"] / tm["control_rate_hz"]))
        h = dt / nsub
        n_ticks = round(tm["time_limit_s"] * tm["control_rate_hz"])
        q = np.array(sc["formation"]["initial_positions"], dtype=float)
        n = len(q)
        v = np.zeros((n, 3))
        mass = float(sc.get("vehicle", {}).get("mass", DEFAULT_MASS))
        yaw = float(sc["controller"]["yaw"])
        thrust = np.full(n, mass * G)  # hover, level, until the first command
        rpy = np.zeros((n, 3))
        rpy[:, 2] = yaw
        log(f"mission {sc['scenario']['name']}: {n} UAVs, {n_ticks} ticks of {dt:g} s")

        # protocol.md, "Liveliness": subscribe first, then both tokens
        cmds: queue.Queue = queue.Queue()
        sub = self.s.declare_subscriber(f"{self.prefix}/uav/*/cmd", lambda sample: cmds.put(sample))
        tokens = [
            self.s.liveliness().declare_token(f"{self.prefix}/alive/plant"),
            self.s.liveliness().declare_token(f"{self.prefix}/alive/plant/{self.zid}"),
        ]
        agents = [f"agent:{i}" for i in range(1, n + 1)]
        missing = self.wait_alive(["leader", *agents, *self.expect])
        if missing:
            log(f"never announced: {', '.join(missing)}")
            return 3

        got: dict[int, dict[int, dict]] = {}  # tick -> UAV -> cmd

        def publish_states(k: int) -> None:
            for i in range(n):
                self.publish(f"{self.prefix}/uav/{i + 1}/state", {
                    "k": "state", "t": k * dt_ns, "q": q[i].tolist(), "vel": v[i].tolist(),
                    "rpy": rpy[i].tolist(), "w": [0.0, 0.0, 0.0],
                })

        def take(sample) -> None:
            key = str(sample.key_expr)
            try:
                i = int(key.split("/")[-2])
                m = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
                ok = m["v"] == SCHEMA_VERSION and m["k"] == "cmd" and 1 <= i <= n
                thrust_i, rpy_i = float(m["thrust"]), [float(x) for x in m["rpy"]]
                ok = ok and math.isfinite(thrust_i) and all(math.isfinite(x) for x in rpy_i) and len(rpy_i) == 3
                k = (m["t"] + dt_ns // 2) // dt_ns
            except Exception:  # noqa: BLE001 - not a cmd: ignore it
                return
            if ok:
                got.setdefault(k, {})[i] = {"thrust": thrust_i, "rpy": rpy_i}

        timeouts = 0
        publish_states(0)  # protocol.md, "Lockstep": states(0) and clock(0) start the flight
        self.publish(f"{self.prefix}/clock", {"k": "clock", "t": 0})
        for k in range(n_ticks):
            deadline = time.monotonic() + LOCKSTEP_TIMEOUT_S
            while len(got.get(k, {})) < n:
                left = deadline - time.monotonic()
                if left <= 0:
                    timeouts += 1
                    break
                try:
                    take(cmds.get(timeout=left))
                except queue.Empty:
                    pass
            for i, c in got.pop(k, {}).items():
                thrust[i - 1] = c["thrust"]
                rpy[i - 1] = c["rpy"]
            if (k + 1) % CLOCK_EVERY == 0 or k + 1 == n_ticks:  # clock(k+1), and the last one
                self.publish(f"{self.prefix}/clock", {"k": "clock", "t": (k + 1) * dt_ns})
            acc = np.array([rotation_e3(rpy[i]) * thrust[i] / mass for i in range(n)]) - np.array([0.0, 0.0, G])
            for _ in range(nsub):
                v = v + h * acc
                q = q + h * v
            publish_states(k + 1)  # the last is the final state, t = time limit
        self.publish(f"{self.prefix}/diag/plant", {
            "k": "diag", "t": n_ticks * dt_ns, "process": "plant",
            "counters": {"cmd_timeouts": timeouts}, "info": {"finished": True, "implementation": "tests/spec_plant.py"},
        })
        log(f"flew {n_ticks} ticks, {timeouts} command timeouts")
        time.sleep(0.2)  # let the last messages leave before the tokens go
        for tok in tokens:
            tok.undeclare()
        sub.undeclare()
        return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--connect", required=True, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--swarm", required=True, help="swarm name")
    ap.add_argument("--expect", action="append", default=[], help="also wait for this process (e.g. recorder)")
    a = ap.parse_args()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{a.connect}"]')
    conf.insert_json5("connect/timeout_ms", "30000")  # the router may come up after us
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    try:
        return SpecPlant(session, a.swarm, a.expect).run()
    finally:
        session.close()  # a session left open with a Python callback subscriber hangs the exit


if __name__ == "__main__":
    sys.exit(main())

"""N simulated Crazyflies integrated in real time (:class:`CrazyflieFleet`): the plant's physics
(:func:`zenswarm.plant.quadrotor.step`, eqs 1-5 with the onboard attitude PID) for all vehicles
at once, ``timing.substeps`` sub-steps at ``timing.physics_rate_hz`` per loop period on the wall
clock, a flat ground at z = 0, and between ticks the vehicles' sockets
(:class:`zenswarm.plant.crazyflie.firmware.SimCrazyflie`). Vehicle i (0-based) listens on UDP
``host:base_port + i``. Positions in the swarm's ENU frame (m); the log variables' values are
the firmware's units (:mod:`zenswarm.plant.crazyflie.log`).
"""

from __future__ import annotations

import math
import select
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from zenswarm.plant.crazyflie.crtp import DEFAULT_BASE_PORT
from zenswarm.plant.crazyflie.firmware import SimCrazyflie
from zenswarm.plant.crazyflie.log import LOG_VARS
from zenswarm.plant.fleet import FleetThread, ground_contact
from zenswarm.plant.quadrotor import PlantState, initial_state, step
from zenswarm.vehicle import crazyflie as cfu
from zenswarm.vehicle.params import QuadParams


class CrazyflieFleet(FleetThread):
    """N simulated Crazyflies, integrated in real time; vehicle i (0-based) on UDP
    ``host:base_port + i``. :meth:`start` / :meth:`stop` run it in a background thread (tests,
    embedding), :meth:`run` in the calling thread (the CLI). ``state`` is the plant's
    :class:`zenswarm.plant.quadrotor.PlantState` (ENU), written by the loop; from another thread
    read :meth:`snapshot`, and do not write it while running."""

    thread_name = "crazyflie-fleet"

    def __init__(self, q0: Any, params: QuadParams, base_port: int = DEFAULT_BASE_PORT, host: str = "127.0.0.1",
                 physics_hz: float = 1000.0, chunk: int = 10) -> None:  # fmt: skip
        q = np.array(q0, dtype=float)
        if q.ndim != 2 or q.shape[1] != 3:
            raise ValueError(f"q0 must have shape (N, 3), got {q.shape}")
        q[:, 2] = 0.0
        self.n = q.shape[0]
        self.params = params
        self.state: PlantState = initial_state(q)
        self.h = 1.0 / float(physics_hz)
        self.chunk = int(chunk)
        self.period = self.chunk * self.h
        self.boot = time.monotonic()
        self.host = host
        self.base_port = int(base_port)
        self.vehicles: list[SimCrazyflie] = []
        try:
            for i in range(self.n):
                self.vehicles.append(SimCrazyflie(i, host, self.base_port + i, params, self.boot))
        except Exception:
            self.close()
            raise
        self.thrust = np.zeros(self.n)
        self.rpy_cmd = np.zeros((self.n, 3))
        self.ticks = 0
        self.overruns = 0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self.on_tick: Callable[[float], None] | None = None  # called after every tick (the mocap feeder)

    @classmethod
    def from_scenario(cls, sc: Any, base_port: int = DEFAULT_BASE_PORT, host: str = "127.0.0.1") -> CrazyflieFleet:
        """The scenario's fleet: on the ground under ``formation.initial_positions``, ``[vehicle]``
        parameters, physics rate and chunk from ``[timing]``."""
        return cls(np.asarray(sc.initial_positions, dtype=float), QuadParams.from_vehicle(sc.vehicle), base_port, host,
                   physics_hz=sc.timing.physics_rate_hz, chunk=sc.timing.substeps)  # fmt: skip

    def uris(self) -> list[str]:
        """Every vehicle's cflib URI, ``udp://HOST:PORT``."""
        return [f"udp://{self.host}:{v.port}" for v in self.vehicles]

    def silence(self, index: int, seconds: float) -> None:
        """Vehicle ``index`` (0-based) drops all its traffic, both ways, for ``seconds`` (a lost link)."""
        self.vehicles[index].muted_until = time.monotonic() + float(seconds)

    def reboot(self, index: int) -> None:
        """Vehicle ``index`` restarts its firmware (unlocks, disarmed, on the ground where it is)."""
        v = self.vehicles[index]
        self.vehicles[index] = SimCrazyflie(index, self.host, v.port, self.params, time.monotonic(), sock=v.sock)

    def _values(self, i: int) -> Callable[[int], float]:
        st = self.state
        veh = self.vehicles[i]
        roll, pitch, yaw = cfu.attitude_to_log(st.rpy[i])
        now = time.monotonic()
        w = np.degrees(st.w[i])
        q = veh.estimate(now, st.q[i], st.v[i])
        table = {
            "stateEstimate.x": q[0], "stateEstimate.y": q[1], "stateEstimate.z": q[2],
            "stateEstimate.vx": st.v[i, 0], "stateEstimate.vy": st.v[i, 1], "stateEstimate.vz": st.v[i, 2],
            "stateEstimate.roll": roll, "stateEstimate.pitch": pitch, "stateEstimate.yaw": yaw,
            "stabilizer.roll": roll, "stabilizer.pitch": pitch, "stabilizer.yaw": yaw,
            "gyro.x": w[0], "gyro.y": w[1], "gyro.z": w[2],
            "stabilizer.thrust": float(veh.motor_cmd),
            "motor.m1": veh.motor_cmd, "motor.m2": veh.motor_cmd, "motor.m3": veh.motor_cmd, "motor.m4": veh.motor_cmd,
            "pm.vbat": veh.vbat, "pm.batteryLevel": veh.battery_level(),
            "pm.state": 3.0 if veh.vbat < veh.param_values["pm.lowVoltage"] else 0.0,
            "radio.rssi": 40.0, "supervisor.info": float(veh.info_bits(now)),
        }  # fmt: skip
        return lambda ident: float(table[LOG_VARS[ident][0]])

    def poll(self, now: float) -> None:
        st = self.state
        for i, veh in enumerate(self.vehicles):
            veh.receive(now, veh.estimate(now, st.q[i], st.v[i]), st.rpy[i])

    def tick(self, now: float) -> None:
        """One loop period: control, a physics chunk, the log blocks that are due."""
        st = self.state
        for i, veh in enumerate(self.vehicles):
            q_est = veh.estimate(now, st.q[i], st.v[i]).copy()  # the controllers fly the estimate
            f, att = veh.control(now, self.period, q_est, st.v[i].copy(), st.rpy[i].copy())
            self.thrust[i] = f
            self.rpy_cmd[i] = att
        with self._lock:
            for _ in range(self.chunk):
                step(st, self.thrust, self.rpy_cmd, self.params, self.h)
                self._ground()
        self.ticks += 1
        for i, veh in enumerate(self.vehicles):
            if veh.blocks:
                veh.send_logs(now, self._values(i))
        if self.on_tick is not None:
            self.on_tick(now)

    def _ground(self) -> None:
        ground_contact(self.state, 0.0)

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> str:
        """Loop on the wall clock until ``stop`` is set or ``duration_s`` passed; between ticks it
        waits on the sockets, so requests (TOC, parameters) are answered at once. A stall of more
        than 0.5 s resynchronises (counted in ``overruns``)."""
        stop = stop or self._stop
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        socks = [v.sock for v in self.vehicles]
        next_tick = time.monotonic()
        while not stop.is_set():
            now = time.monotonic()
            if now >= end:
                return "duration reached"
            self.poll(now)
            if now >= next_tick:
                self.tick(now)
                next_tick += self.period
                if now - next_tick > 0.5:
                    next_tick = now + self.period
                    self.overruns += 1
                continue
            try:
                select.select(socks, [], [], max(0.0, min(next_tick - now, 0.05)))
            except (OSError, ValueError):
                time.sleep(0.001)
        return "stop requested"

    def status(self) -> list[dict[str, Any]]:
        """One line of facts per vehicle (for logs and tests)."""
        q = self.snapshot().q
        return [
            {"port": v.port, "supervisor": v.sup, "armed": v.armed, "hl": v.hl.state, "setpoint": v.sp_kind,
             "q": q[i].round(3).tolist(), **v.counters}
            for i, v in enumerate(self.vehicles)
        ]  # fmt: skip

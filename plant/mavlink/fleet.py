"""N simulated MAVLink vehicles integrated in real time (:class:`MavlinkFleet`): the plant's
physics (:func:`zenswarm.plant.quadrotor.step`, eqs 1-5 with the onboard attitude PID) for all
vehicles at once, ``timing.physics_rate_hz`` sub-steps in chunks of ``timing.substeps`` at
``timing.control_rate_hz`` on the wall clock, plus the scenario's disturbances and a flat ground
at ``ground_z``; each loop period every vehicle's autopilot
(:class:`zenswarm.plant.mavlink.autopilot.SimVehicle`) reads its messages, commands its thrust and
attitude, and streams its telemetry at its rate.

Frames: the plant's state is in the swarm's ENU frame (m, m/s, rad; body rates FLU); the
telemetry handed to the vehicles is MAVLink's local NED about each vehicle's origin (body FRD).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np

from zenswarm.plant.disturbance import DisturbanceModel
from zenswarm.plant.fleet import FleetThread, ground_contact
from zenswarm.plant.mavlink.autopilot import SimVehicle
from zenswarm.plant.mavlink.options import VehicleOptions, vehicle_options
from zenswarm.plant.quadrotor import PlantState, initial_state, step
from zenswarm.vehicle import frames
from zenswarm.vehicle.autopilot import mavlink_settings
from zenswarm.vehicle.params import QuadParams

__all__ = ["MavlinkFleet"]


class MavlinkFleet(FleetThread):
    """N simulated quadrotors as MAVLink vehicles, integrated in real time.

    Parameters
    ----------
    q0 : (N, 3) array_like
        Spawn positions, m ENU (z is replaced by ``opts.ground_z``: vehicles start on the ground).
    params : QuadParams
    base_port : int
        Vehicle i (0-based) listens on UDP ``opts.host:base_port + i``.
    opts : VehicleOptions
    sysids : sequence of int or None
        System id of each vehicle (default 1..N).
    physics_hz, chunk : float, int
        Physics sub-step rate and sub-steps per loop period (the loop runs at physics_hz / chunk).
    disturbance : (DisturbanceConfig, numpy Generator) or None

    Use :meth:`start` / :meth:`stop` (a background thread, for tests and embedding) or
    :meth:`run` (in the calling thread, for the CLI). Attribute ``state`` is the
    :class:`zenswarm.plant.quadrotor.PlantState` (ENU), written by the loop; from another thread
    read :meth:`snapshot`, and do not write it while running.
    """

    thread_name = "mavlink-fleet"

    def __init__(
        self,
        q0: Any,
        params: QuadParams,
        base_port: int,
        opts: VehicleOptions | None = None,
        sysids: Any = None,
        physics_hz: float = 1000.0,
        chunk: int = 10,
        disturbance: Any = None,
    ) -> None:
        self.opts = opts or VehicleOptions()
        self.params = params
        q = np.array(q0, dtype=float)
        if q.ndim != 2 or q.shape[1] != 3:
            raise ValueError(f"q0 must have shape (N, 3), got {q.shape}")
        q[:, 2] = self.opts.ground_z
        self.n = q.shape[0]
        self.state: PlantState = initial_state(q)
        self.h = 1.0 / float(physics_hz)
        self.chunk = int(chunk)
        self.period = self.chunk * self.h
        self.loop_hz = 1.0 / self.period
        self.tel_every = max(1, round(self.loop_hz / self.opts.telemetry_hz))
        self.hb_every = max(1, round(self.loop_hz / self.opts.heartbeat_hz))
        self.ss_every = max(1, round(self.loop_hz / self.opts.sys_status_hz))
        self.dist = DisturbanceModel(disturbance[0], self.n, disturbance[1]) if disturbance is not None else None
        ids = list(sysids) if sysids is not None else list(range(1, self.n + 1))
        if len(ids) != self.n:
            raise ValueError(f"need {self.n} system ids, got {len(ids)}")
        self.boot = time.monotonic()
        self.vehicles: list[SimVehicle] = []
        try:
            for i in range(self.n):
                veh = SimVehicle(i, int(ids[i]), int(base_port) + i, self.opts, params, self.boot, spawn=q[i])
                veh.period = self.period
                self.vehicles.append(veh)
        except Exception:
            self.close()
            raise
        self.origins = np.array([veh.origin for veh in self.vehicles])
        self.thrust = np.zeros(self.n)
        self.rpy_cmd = np.zeros((self.n, 3))
        self.sim_t = 0.0
        self.ticks = 0
        self.overruns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.error: BaseException | None = None

    @classmethod
    def from_scenario(cls, sc: Any, base_port: int | None = None, opts: VehicleOptions | None = None, **kw: Any) -> MavlinkFleet:
        """Fleet of the scenario: spawn under ``formation.initial_positions``, ``[vehicle]``
        parameters, ``[disturbance]`` (seeded by ``scenario.seed``), timing from ``[timing]``,
        ports/ids/options from ``[mavlink]`` (``base_port``, ``host``, ``sysids``, ``autopilot``,
        ``telemetry_hz``, ``offboard_loss_s``, ``failsafe_land_s``, ``ground_z``,
        ``hover_throttle``); ``opts`` given explicitly wins over the table."""
        ms = mavlink_settings(sc)
        if opts is None:
            opts = vehicle_options(sc)
        params = QuadParams.from_vehicle(sc.vehicle)
        dist = (sc.disturbance, np.random.default_rng(sc.seed)) if sc.disturbance.active else None
        return cls(
            np.asarray(sc.initial_positions, dtype=float),
            params,
            ms.base_port if base_port is None else base_port,
            opts,
            sysids=ms.sysids,
            physics_hz=sc.timing.physics_rate_hz,
            chunk=sc.timing.substeps,
            disturbance=dist,
            **kw,
        )

    # ------------------------------------------------------------------ test / fault hooks
    def silence(self, index: int, seconds: float) -> None:
        """Vehicle ``index`` (0-based) drops all its traffic, both ways, for ``seconds``."""
        self.vehicles[index].link.muted_until = time.monotonic() + float(seconds)

    def set_prearm_failure(self, index: int, reason: str | None) -> None:
        """Vehicle ``index`` fails its pre-arm checks with ``reason`` (None: passes again): its
        SYS_STATUS says so (PREARM_CHECK and 3D_MAG unhealthy) and arming is refused with a
        STATUSTEXT, as a vehicle with an uncalibrated compass would."""
        self.vehicles[index].prearm_failure = reason

    def set_mode_override(self, index: int, custom_mode: int | None) -> None:
        """Vehicle ``index`` accepts mode requests but reports and flies ``custom_mode``."""
        self.vehicles[index].mode_override = custom_mode

    # ------------------------------------------------------------------ loop
    def tick(self, now: float) -> None:
        """One loop period: receive, autopilot logic, physics chunk, telemetry."""
        st = self.state
        with self._lock:
            for i, veh in enumerate(self.vehicles):
                veh.poll(now, st.q[i], float(st.rpy[i, 2]))
            for i, veh in enumerate(self.vehicles):
                veh.on_ground = bool(st.q[i, 2] <= self.opts.ground_z + 0.01 and abs(st.v[i, 2]) < 0.05)
                if not veh.on_ground:
                    veh.ground_since = math.inf
                elif not math.isfinite(veh.ground_since):
                    veh.ground_since = now
                f, rpy = veh.update(now, st.q[i], st.v[i], st.rpy[i])
                self.thrust[i] = f
                self.rpy_cmd[i] = rpy
            d_p: np.ndarray | None
            d_a: np.ndarray | None
            for j in range(self.chunk):
                if self.dist is not None:
                    d_p, d_a = self.dist.sample(self.sim_t + j * self.h, self.h)
                else:
                    d_p = d_a = None
                step(st, self.thrust, self.rpy_cmd, self.params, self.h, d_p, d_a)
                self._ground()
            self.sim_t += self.period
            self.ticks += 1
            k = self.ticks
            if k % self.tel_every == 0:
                p_ned = frames.enu_to_ned(st.q - self.origins)
                v_ned = frames.enu_to_ned(st.v)
                rpy_ned = frames.euler_enu_to_ned(st.rpy)
                w_frd = frames.flu_to_frd(st.w)
                for i, veh in enumerate(self.vehicles):
                    veh.send_telemetry(now, p_ned[i], v_ned[i], rpy_ned[i], w_frd[i])
            if k % self.hb_every == 1 % self.hb_every:
                for veh in self.vehicles:
                    veh.send_heartbeat(now)
            if k % self.ss_every == 1 % self.ss_every:
                for veh in self.vehicles:
                    veh.send_sys_status(now)
                    veh.send_status_extra(now)
            for veh in self.vehicles:
                if veh._pending:
                    veh.send_requested(now)

    def _ground(self) -> None:
        """Flat ground at ground_z: a vehicle below it is put back on it, at rest and level."""
        ground_contact(self.state, self.opts.ground_z)

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> str:
        """Loop on the wall clock until ``stop`` is set or ``duration_s`` passed; returns why it
        stopped. Late periods are caught up (physics stays on the wall clock); a stall of more
        than 0.5 s resynchronises instead (counted in ``overruns``; the simulation then runs
        behind the wall clock by the stall)."""
        from zenswarm.process.runtime import WallClock

        stop = stop or self._stop
        end = math.inf if duration_s is None else time.monotonic() + duration_s
        clock = WallClock(self.period, stop, first_wait=True, resync_after_s=0.5)
        while True:
            if stop.is_set():
                return "stop requested"
            now = time.monotonic()
            if now >= end:
                return "duration reached"
            self.tick(now)
            resyncs = clock.resyncs
            clock.wait()
            self.overruns += clock.resyncs - resyncs

    def status(self) -> list[dict[str, Any]]:
        """One line of facts per vehicle (for logs and tests)."""
        out = []
        q = self.snapshot().q
        for i, v in enumerate(self.vehicles):
            out.append(
                {
                    "sysid": v.sysid,
                    "port": v.port,
                    "armed": v.armed,
                    "mode": v.mode,
                    "q": q[i].round(3).tolist(),
                    **v.counters,
                }
            )
        return out

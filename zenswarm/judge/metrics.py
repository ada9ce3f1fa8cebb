"""A flight's time series and the fields of ``results.json`` computed from it.

Pure (numpy only). The in-process simulator, the distributed swarm and the flight report all
compute their results with :func:`compute_results` (the verdict of :mod:`zenswarm.judge.verdict`), so
the same flight gives the same JSON.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from zenswarm.errors import EXIT_PLUGIN_FAILED
from zenswarm.judge.verdict import criteria_from_scenario, judge

__all__ = [
    "TimeSeries", "fill_forward", "compute_results", "add_failure", "flight_differences", "lockstep_stalls",
    "RESULT_FIELDS", "FLIGHT_FIELDS", "RESULTS_SCHEMA_VERSION", "COMPRESS_MAX_BYTES",
]  # fmt: skip

RESULTS_SCHEMA_VERSION = 2
"""Version of ``results.json``'s layout. 2: the verdict from the vehicles' states (``failures``,
vehicle formation error, margins); 1 (unversioned): the leader's and the generator's."""

RESULT_FIELDS = (
    "goal_reached",
    "time_to_goal_s",
    "min_obstacle_clearance_m",
    "min_inter_uav_distance_m",
    "max_formation_error_m",
    "max_generator_formation_error_m",
    "rms_tracking_error_m",
    "sim_time_s",
)
"""The headline figures of a flight."""

FLIGHT_FIELDS = RESULT_FIELDS + (
    "success",
    "failures",
    "final_leader_goal_distance_m",
    "final_slot_errors_m",
    "min_obstacle_margin_m",
    "min_inter_uav_margin_m",
    "min_altitude_m",
    "finite",
    "ended_early",
)
"""The fields two judgements of the same flight agree on (a run and its report, the simulator and
the lockstep swarm); not the wall time nor the bus statistics."""


COMPRESS_MAX_BYTES = 32 << 20
"""Largest time series (bytes of its arrays) :meth:`TimeSeries.save` compresses (deflate costs
about 45 ms of CPU per MB and saves about 15 % on flight data; above this it is stored)."""


@dataclass
class TimeSeries:
    """One flight sampled at every control tick k (T samples, N UAVs).

    t: (T,) s. q0, v0: (T, 3) leader. qref, vref: (T, N, 3) generator output q*, v*.
    q, v, rpy: (T, N, 3) measured UAV state (m, m/s, rad; rpy is the attitude the vehicle has).
    u: (T, N, 3) virtual control, m/s^2. thrust: (T, N) N, the commanded collective thrust.
    d_hat: (T, N, 3) ESO disturbance estimate, m/s^2. rpy_cmd: (T, N, 3) rad, the commanded
    (desired) roll, pitch, yaw the controller sent with the thrust (the inversion after eq. 28;
    NaN in a series saved before it was recorded). plant: what the plant model records
    (:attr:`zenswarm.plant.api.PlantModel.records`), name -> (T, N, *shape), sampled with the state
    (``plant.<name>`` in the ``.npz``; empty for a model that records nothing).
    """

    t: np.ndarray
    q0: np.ndarray
    v0: np.ndarray
    qref: np.ndarray
    vref: np.ndarray
    q: np.ndarray
    v: np.ndarray
    rpy: np.ndarray
    u: np.ndarray
    thrust: np.ndarray
    d_hat: np.ndarray
    rpy_cmd: np.ndarray
    plant: dict[str, np.ndarray] = field(default_factory=dict)

    FIELDS = ("t", "q0", "v0", "qref", "vref", "q", "v", "rpy", "u", "thrust", "d_hat", "rpy_cmd")
    """The fixed series (:attr:`plant` holds the plant model's own, by name)."""
    PLANT_PREFIX = "plant."
    """The ``.npz`` key of plant series NAME is ``plant.NAME``."""

    def arrays(self) -> dict[str, np.ndarray]:
        """Every series by its ``.npz`` key: :data:`FIELDS`, then ``plant.<name>`` in order."""
        out = {f: getattr(self, f) for f in self.FIELDS}
        out.update((self.PLANT_PREFIX + name, a) for name, a in self.plant.items())
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> TimeSeries:
        """The inverse of :meth:`arrays`."""
        pre = cls.PLANT_PREFIX
        plant = {k[len(pre):]: a for k, a in arrays.items() if k.startswith(pre)}
        return cls(**{f: arrays[f] for f in cls.FIELDS}, plant=plant)

    def formation_error(self, offsets: Any) -> np.ndarray:
        """The vehicles' formation error per tick and UAV: ||q_i - q0 - h_i||, (T, N) m, from
        the formation offsets h (N, 3) m (``scenario.offsets``). Its maximum over the ticks at or
        after ``timing.settle_time_s`` is the verdict's ``max_formation_error_m``."""
        h = np.asarray(offsets, dtype=float)
        return np.asarray(np.linalg.norm(self.q - (self.q0[:, None, :] + h[None]), axis=2))

    def generator_formation_error(self, offsets: Any) -> np.ndarray:
        """The references' formation error ||q*_i - q0 - h_i||, (T, N) m (the generator's, eqs 16-17)."""
        h = np.asarray(offsets, dtype=float)
        return np.asarray(np.linalg.norm(self.qref - (self.q0[:, None, :] + h[None]), axis=2))

    def tracking_error(self) -> np.ndarray:
        """The vehicles' tracking error ||q*_i - q_i||, (T, N) m."""
        return np.asarray(np.linalg.norm(self.qref - self.q, axis=2))

    @classmethod
    def allocate(cls, T: int, n: int, plant: dict[str, tuple[int, ...]] | None = None) -> TimeSeries:
        """All NaN, for T ticks and n UAVs; ``plant``: the plant model's series, name -> shape per UAV."""

        def nan3() -> np.ndarray:
            return np.full((T, n, 3), np.nan)

        return cls(
            t=np.full(T, np.nan),
            q0=np.full((T, 3), np.nan),
            v0=np.full((T, 3), np.nan),
            qref=nan3(),
            vref=nan3(),
            q=nan3(),
            v=nan3(),
            rpy=nan3(),
            u=nan3(),
            thrust=np.full((T, n), np.nan),
            d_hat=nan3(),
            rpy_cmd=nan3(),
            plant={name: np.full((T, n, *shape), np.nan) for name, shape in (plant or {}).items()},
        )

    def truncated(self, T: int) -> TimeSeries:
        return TimeSeries.from_arrays({k: a[:T] for k, a in self.arrays().items()})

    def series(self, upto_tick: int | None = None, fill: bool = False) -> TimeSeries:
        """Ticks 0 .. ``upto_tick`` - 1 (all without it), its arrays views of this one's; ``fill``:
        a copy with the gaps filled (:func:`fill_forward`). What the end-of-flight watch reads of
        the simulator's series as it fills (:class:`zenswarm.judge.watch.Record`, as the
        supervisor's collector)."""
        ts = self if upto_tick is None else self.truncated(max(0, min(len(self.t), upto_tick)))
        return fill_forward(TimeSeries.from_arrays({k: np.array(a) for k, a in ts.arrays().items()})) if fill else ts

    def save(self, path: str) -> None:
        """Write an ``.npz`` (one array per field, ``plant.<name>`` for the plant model's):
        compressed up to :data:`COMPRESS_MAX_BYTES` of data, stored beyond (flight data
        compresses by about 15 %: at 1000 UAVs x 10 s, 176 MB stored in 0.2 s of CPU, 150 MB
        compressed in 7.7 s). ``np.load`` reads either."""
        arrays: dict[str, Any] = self.arrays()
        if sum(a.nbytes for a in arrays.values()) <= COMPRESS_MAX_BYTES:
            np.savez_compressed(path, **arrays)
        else:
            np.savez(path, **arrays)

    @classmethod
    def load(cls, path: str) -> TimeSeries:
        with np.load(path) as z:
            got = {f: np.array(z[f]) for f in cls.FIELDS if f in z.files or f != "rpy_cmd"}
            plant = {k[len(cls.PLANT_PREFIX):]: np.array(z[k]) for k in z.files if k.startswith(cls.PLANT_PREFIX)}
        got.setdefault("rpy_cmd", np.full_like(got["rpy"], np.nan))  # saved before it was recorded
        return cls(**got, plant=plant)


def fill_forward(ts: TimeSeries) -> TimeSeries:
    """Realtime: a tick a process skipped holds its previous value (latest value wins), in place;
    returns the series without the ticks before every field (the plant model's signals too) had its
    first value."""
    if not len(ts.t):
        return ts
    first = 0
    arrays = ts.arrays()
    for a in arrays.values():
        for k in range(1, len(a)):
            bad = np.isnan(a[k])
            if np.any(bad):
                a[k][bad] = a[k - 1][bad]
        rows = np.isnan(a.reshape(len(a), -1)).any(axis=1)
        if np.any(rows):
            first = max(first, int(np.flatnonzero(rows)[-1]) + 1)
    return TimeSeries.from_arrays({k: a[first:] for k, a in arrays.items()})


def compute_results(
    ts: TimeSeries, scenario: Any, wall_time_s: float | None = None, early_end: bool = True
) -> dict[str, Any]:
    """The mission results of a flight: the verdict of :func:`zenswarm.judge.verdict.judge` on the
    UAVs' real states, as the JSON-ready fields of ``results.json`` (:data:`RESULTS_SCHEMA_VERSION`).

    With ``early_end`` the flight is judged up to the tick where its outcome was decided (a stalled
    leader, a diverged UAV; :func:`zenswarm.judge.verdict.decide_end`), as the run itself ends there;
    ``early_end=False`` judges every tick (``--full-time``). ``wall_time_s`` is the run's wall
    time (None when judged from a recording). See :data:`FLIGHT_FIELDS` for what two judgements
    of the same flight must agree on.
    """
    crit = criteria_from_scenario(scenario)
    v = judge(ts.t, ts.q0, ts.q, ts.qref, crit, early_end=early_end, n_ticks=scenario.timing.n_ticks)
    n = ts.q.shape[1] if ts.q.ndim == 3 and len(ts.t) else scenario.n
    dt = 1.0 / scenario.timing.control_rate_hz
    causes = v.causes
    res: dict[str, Any] = {
        "schema_version": RESULTS_SCHEMA_VERSION,
        "scenario": scenario.name,
        "n_uav": int(n),
        "success": v.success,
        "failures": [f.to_json() for f in v.failures],
        "goal_reached": v.goal_reached,
        "time_to_goal_s": v.time_to_goal_s,
        "final_leader_goal_distance_m": v.final_leader_goal_distance_m,
        "max_formation_error_m": v.max_formation_error_m,
        "max_generator_formation_error_m": v.max_generator_formation_error_m,
        "rms_tracking_error_m": v.rms_tracking_error_m,
        "final_slot_errors_m": v.final_slot_errors_m,
        "max_final_slot_error_m": max((e for e in v.final_slot_errors_m if e is not None), default=None)
        if all(e is not None for e in v.final_slot_errors_m)
        else None,
        "vehicle_radius_m": v.vehicle_radius_m,
        "min_obstacle_clearance_m": v.min_obstacle_clearance_m,
        "min_obstacle_margin_m": v.min_obstacle_margin_m,
        "min_inter_uav_distance_m": v.min_inter_uav_distance_m,
        "min_inter_uav_margin_m": v.min_inter_uav_margin_m,
        "min_altitude_m": v.min_altitude_m,
        "obstacle_collision": "collision_obstacle" in causes,
        "uav_collision": "collision_uav" in causes,
        "ground_collision": "collision_ground" in causes,
        "finite": v.finite,
        "leader_stall": v.stall,
        "ended_early": v.ended_early,
        "sim_time_s": float(v.end_tick * dt),
        "wall_time_s": wall_time_s,
    }
    return res


def add_failure(res: dict[str, Any], cause: str, detail: str, t_s: float | None = None, **more: Any) -> None:
    """Add a failure the flight's states cannot show (``process_died``, ``interrupted``) to a
    results dict, in place of the ``incomplete`` or ``no_data`` it explains; the run is then not a
    success."""
    res["failures"] = [f for f in res["failures"] if f["cause"] not in ("incomplete", "no_data")]
    res["failures"].append({"cause": cause, "t_s": t_s, "detail": detail, "uavs": [], **more})
    res["success"] = False


def add_plugin_failures(res: dict[str, Any], failures: Sequence[Any], dt: float) -> None:
    """Add the ``plugin_error`` failures a run ended on (:class:`zenswarm.errors.PluginFailure`
    each, at sim time tick * dt, ``dt`` the control tick in s) to a results dict, in place of the
    ``incomplete`` or ``no_data`` they explain; the run is then not a success."""
    res["failures"] = [f for f in res["failures"] if f["cause"] not in ("incomplete", "no_data")]
    res["failures"].extend(f.failure(dt) for f in failures)
    res["success"] = False


def exit_code_of(res: dict[str, Any]) -> int:
    """The exit status a results dict stands for: 130 interrupted, 4 a plug-in failed
    (``plugin_error``), 3 a process died, 0 success, else 1 (the mission failed)."""
    causes = {f["cause"] for f in res.get("failures") or ()}
    if "interrupted" in causes:
        return 130
    if "plugin_error" in causes:
        return EXIT_PLUGIN_FAILED
    if "process_died" in causes:
        return 3
    return 0 if res["success"] else 1


def flight_differences(a: TimeSeries, res_a: dict[str, Any], b: TimeSeries, res_b: dict[str, Any]) -> list[str]:
    """What differs between two flights: every series compared bit for bit (NaN equal to NaN,
    shapes included; the first differing tick, the UAV and the two values named), the series
    that differ earliest first (the field order of :class:`TimeSeries` among those of one tick),
    then the :data:`FLIGHT_FIELDS` of their results. Empty when they are the same flight (the
    lockstep swarm against the simulator)."""
    out: list[str] = []
    series: list[tuple[int, str]] = []
    xs, ys = a.arrays(), b.arrays()
    for f in [*xs, *(k for k in ys if k not in xs)]:
        if f not in xs or f not in ys:
            out.append(f"series.{f}: only in the {'first' if f in xs else 'second'} flight")
            continue
        x, y = xs[f], ys[f]
        if x.shape != y.shape:
            out.append(f"series.{f}: shape {x.shape} != {y.shape}")
        elif not np.array_equal(x, y, equal_nan=True):
            bad = np.argwhere(~((x == y) | (np.isnan(x) & np.isnan(y))))
            tick = int(bad[0][0])
            gaps = int(np.sum(np.isnan(x) != np.isnan(y)))  # a value on one side, none (NaN) on the other
            why = f"; {gaps} of them missing on one side" if gaps else ""
            uav = f", UAV {int(bad[0][1]) + 1}" if x.ndim >= 2 and f not in ("q0", "v0") else ""
            at = tuple(int(i) for i in bad[0])
            vals = f": {float(x[at])!r} != {float(y[at])!r}"
            when = f"first at tick {tick} (t = {float(a.t[tick]):.3f} s{uav})"
            series.append((tick, f"series.{f}: {len(bad)} values differ, {when}{vals}{why}"))
    out += [text for _, text in sorted(series, key=lambda s: s[0])]
    for key in FLIGHT_FIELDS:
        if res_a.get(key) != res_b.get(key):
            out.append(f"results.{key}: {res_a.get(key)!r} != {res_b.get(key)!r}")
    return out


def lockstep_stalls(results: dict[str, Any]) -> dict[str, int]:
    """The processes of a lockstep swarm flight that waited out ``--lockstep-timeout`` and ran a
    tick on held inputs, each with how many ticks it forced (``forced_ticks`` of its final
    diagnostics in ``results["diagnostics"]``); empty when none did, or for a simulator flight.
    A flight with stalls is not the simulator's flight from the first forced tick on: its
    differences from the simulator come from a starved or stalled process, not from the law."""
    diag = results.get("diagnostics") or {}
    out: dict[str, int] = {}
    for name, d in sorted(diag.items()):
        n = d.get("forced_ticks", 0) if isinstance(d, dict) else 0
        if isinstance(n, (int, float)) and not isinstance(n, bool) and n > 0:
            out[name] = int(n)
    return out

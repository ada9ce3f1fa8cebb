"""A supervised flight's results: judged on the series its collector assembled (the ticks its
:class:`~zenswarm.judge.watch.EndWatch` says), written and said by the code the simulator's are
(:mod:`zenswarm.judge.results`), with what only the supervisor knows beside the verdict
(:func:`run_facts`: the mode, the router, its processes, their deaths and restarts, the vehicles as
the bridge reported them, the recording and its loss, :func:`recording_lost`; each death as it
comes, :func:`process_death`). In lockstep the
series is judged once the last tick's messages arrived (:func:`await_last_tick`).
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from zenswarm import bus
from zenswarm.compose.children import Child
from zenswarm.errors import PluginFailure
from zenswarm.judge.results import closing_lines, flight_results, write_outputs
from zenswarm.judge.watch import EndWatch
from zenswarm.link import FaultPlan
from zenswarm.process.collector import Collector
from zenswarm.scenario.config import Scenario

__all__ = ["await_last_tick", "exit_how", "judge_and_write", "process_death", "recording_lost", "run_facts", "vehicles_figures"]

BRIDGE_FIGURES = ("phases", "armed_uavs", "airborne_uavs", "unhealthy_uavs", "max_latency_ms", "max_state_age_ms", "refused",
                  "link_lost", "positioning", "max_extpos_age_ms")  # fmt: skip
"""The fields of the bridge's last diagnostics results.json's ``vehicles`` keeps."""


def exit_how(rc: int) -> str:
    """``killed by SIGKILL`` or ``exit status 3``: how a process ended, as said and in results.json."""
    return f"killed by {signal.Signals(-rc).name}" if rc < 0 else f"exit status {rc}"


def await_last_tick(
    collector: Collector, poll: Callable[[], object], *, realtime: bool, timeout_s: float, stop: threading.Event, say: Callable[[str], None]
) -> None:
    """Lockstep, every process done: a process's last messages (the last ticks' clock, refs and
    commands) are sent as it exits and may still be on their way through the router, so ``poll``
    until the last tick flown (:meth:`Collector.last_tick_flown`) is complete, at most
    ``timeout_s`` (``--lockstep-timeout``; then said) or until ``stop``. Without this wait a loaded
    machine judged a series whose last ticks were partly missing (NaN where the simulator has
    values). Realtime: nothing to wait for (a tick without a message holds the previous value)."""
    if realtime or collector.sim_t_ns < 0:
        return
    deadline = time.monotonic() + timeout_s
    while not collector.tick_complete(last := collector.last_tick_flown()):
        if time.monotonic() > deadline or stop.is_set():
            say(f"the messages of tick {last} did not all arrive within {timeout_s:g} s "
                "(--lockstep-timeout) after the processes ended; judging what arrived")  # fmt: skip
            return
        time.sleep(0.01)
        poll()


def judge_and_write(
    collector: Collector, watch: EndWatch, sc: Scenario, out: Path, *, stopped: bool, fill: bool, full_time: bool,
    faults: FaultPlan | None, facts: Callable[[], dict[str, Any]], t_start: float, died: tuple[str, str] | None, interrupted: str | None,
    plugin_failures: Sequence[PluginFailure], say: Callable[[str], None],
) -> dict[str, Any]:  # fmt: skip
    """Judge the flight on the ticks ``watch`` says (``stopped`` by a dead process or a signal: the
    ticks flown; ``fill``: a tick without a message holds the previous value), write
    OUT/results.json and OUT/timeseries.npz, ``say`` the closing lines; the results. ``facts()``
    (:func:`run_facts`) is asked once the series is taken (the decoder's counters then count the
    spooled samples too), and the spool is then freed; ``t_start``: when the flight started
    (monotonic s)."""
    ts = collector.series(watch.judged_ticks(collector, stopped, fill), fill=fill)
    collector.close()  # every sample is in the series: free the spool
    res = flight_results(
        ts, sc, wall_time_s=time.monotonic() - t_start, full_time=full_time, faults=faults, facts=facts(), died=died,
        interrupted=interrupted, plugin_failures=plugin_failures,
    )  # fmt: skip
    write_outputs(out, ts, res)
    for line in closing_lines(res, out):
        say(line)
    return res


def run_facts(
    collector: Collector, *, realtime: bool, swarm: str, record: Path | None, listen: Sequence[str], children: Mapping[str, Child],
    deaths: list[dict[str, Any]], restarts: dict[str, int], recording_loss: dict[str, Any] | None, cluster: Mapping[str, Any] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """What results.json says of the run beside the verdict: mode (``realtime`` or lockstep),
    swarm, router (the endpoints it listened on), processes (exit statuses) and where each ran
    (host, pid; on a cluster its worker too), vehicles, deaths, restarts, the collector's facts
    (failsafe, diagnostics, decoder rejects, foreign samples), the recording (``record``) and its
    loss; with ``--scheduler`` the ``cluster``'s facts (the scheduler, the workers lost)."""
    res: dict[str, Any] = {
        "mode": "realtime" if realtime else "lockstep",
        "swarm": swarm,
        "router": list(listen),  # its port: chosen free without --listen
        # a child stopped by terminate_all has its code on its process only (returncode is set when one dies)
        "processes": {name: c.status() for name, c in children.items()},
        "where": {name: c.proc.where() for name, c in children.items()},
        "vehicles": vehicles_figures(children, collector.diag),
        "process_deaths": deaths,
        "restarts": restarts,
        **(cluster or {}),
        **collector.facts(),
        "supervisor_zenoh_threads": bus.zenoh_threads(),  # the router's (ZENOH_RUNTIME_ROUTER)
    }
    if record is not None:
        res["recording"] = str(record)
        if recording_loss is not None:
            res["recording_loss"] = recording_loss
    return res


def vehicles_figures(children: Mapping[str, Child], diag: Mapping[str, dict[str, Any]]) -> dict[str, Any] | None:
    """results.json ``vehicles``: the MAVLink vehicles as the bridge last reported them
    (phases, armed/airborne/unhealthy counts, worst link latency and state age in ms, -1 if
    unmeasured; the Crazyflie bridge's positioning and oldest fed position's age, ms) and the
    vehicles process's exit status; None without ``--plant mavlink`` (or crazyflie)."""
    if "vehicles" not in children and "bridge" not in diag:
        return None
    d = diag.get("bridge", {})
    out: dict[str, Any] = {k: d[k] for k in BRIDGE_FIGURES if k in d}
    c = children.get("vehicles")
    if c is not None:
        out["process_exit"] = c.status()
    return out


def process_death(child: Child, rc: int, t_s: float, say: Callable[[str], None]) -> dict[str, Any]:
    """A process of the flight (``child``, its output read to its end) exited with ``rc`` != 0 at
    sim time ``t_s``: said (how, when, its last output), and the death as results.json's
    ``process_deaths`` keeps it (process, how, sim_time_s). With ``--scheduler`` a process whose
    worker was lost says so (its ``lost``, :mod:`zenswarm.compose.cluster`)."""
    how = getattr(child.proc, "lost", None) or exit_how(rc)
    tail = "; last output: " + " | ".join(child.lines[-3:]) if child.lines else ""
    say(f"process {child.name} died ({how}) at sim time {t_s:.2f} s{tail}")
    return {"process": child.name, "how": how, "sim_time_s": t_s}


def recording_lost(child: Child, rc: int, sim_t_ns: int, recording: Path | None, say: Callable[[str], None]) -> dict[str, Any]:
    """The recorder (``child``) exited with ``rc`` mid-flight, at sim time ``sim_t_ns``: the loss,
    as results.json's ``recording_loss`` (when, how, the file; why, in the recorder's words, e.g.
    the disk is full), said now. The recorder is not a vehicle: the flight goes on; the file keeps
    what was written (chunks are flushed every 0.25 s; ``zenswarm recover`` closes it)."""
    child.join_output(1.0)  # its last lines (why it stopped): the output ends with it, read by another thread
    how = exit_how(rc)
    t = max(sim_t_ns, 0) / 1e9
    loss: dict[str, Any] = {"died_at_sim_time_s": t, "how": how, "recording": str(recording)}
    error = next((ln for ln in reversed(child.lines) if ln.startswith("recorder: error:")), None)
    if error is not None:
        loss["error"] = error.removeprefix("recorder: error: ")
    tail = "; last output: " + " | ".join(child.lines[-3:]) if child.lines else ""
    say(f"recording lost: the recorder died ({how}) at sim time {t:.2f} s; the flight goes on unrecorded, "
        f"{recording} holds what was written before (results.json: recording_loss){tail}")  # fmt: skip
    return loss

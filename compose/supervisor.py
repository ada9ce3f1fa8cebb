"""The supervisor of ``zenswarm up``: it supervises. It opens the swarm's Zenoh router
(:func:`zenswarm.compose.router.open_router`, secured by :mod:`zenswarm.compose.credentials`),
starts the plant, the leader and N agents as separate OS processes, restarts them by the policy
(:mod:`zenswarm.compose.restarts`), watches them (their exit statuses; their liveliness tokens and
the ``--external`` roles', :mod:`zenswarm.compose.liveliness`; the plug-in failures they report,
:mod:`zenswarm.compose.plugin_failures`), merges their logs and stops them cleanly. It takes a
checked :class:`zenswarm.process.settings.FlightSettings` and hands each part what it reads; the
command line and the settings' building are :mod:`zenswarm.compose.up`'s (their checks
:mod:`zenswarm.compose.flight_checks`'), which also attaches what only looks on: the live view (a
:class:`~zenswarm.compose.hooks.Tap`) and the report (an end hook).

The router session subscribes to the swarm's whole key space to assemble the flight's time series
(the same :class:`zenswarm.judge.metrics.TimeSeries` the in-process simulator writes); when the
flight ends is :class:`zenswarm.judge.watch.EndWatch`'s, and ``results.json`` is written by the same
code for both (:mod:`zenswarm.compose.flight_results`). Apart from the recorder it is the only
subscriber to the whole key space; the swarm's processes see only their graph rows.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from zenswarm import bus
from zenswarm.bus import wire
from zenswarm.compose import commands
from zenswarm.compose.children import Child, start_with_settings, stop_in_order, swarm_env
from zenswarm.compose.commands import role_names, swarm_roles
from zenswarm.compose.credentials import router_security
from zenswarm.compose.flight_results import await_last_tick, judge_and_write, process_death, recording_lost, run_facts
from zenswarm.compose.hooks import EndHook, FlightEnd, Tap, feeds
from zenswarm.compose.kills import Kills
from zenswarm.compose.liveliness import EXTERNAL_GONE_GRACE_S, ExternalRoles, Tokens
from zenswarm.compose.plugin_failures import SETTLE_GRACE_S, PluginFailures, await_settled
from zenswarm.compose.policy import restart_policy
from zenswarm.compose.progress import SwarmProgress, swarm_health
from zenswarm.compose.restarts import FLIGHT_OVER_GRACE_S, Restarts
from zenswarm.compose.router import open_router, swarm_channel, undeclare_all
from zenswarm.errors import EXIT_INTERRUPTED, EXIT_MISSION_FAILED, EXIT_OK, EXIT_PLUGIN_FAILED, EXIT_PROCESS_FAILED
from zenswarm.judge.verdict import criteria_from_scenario
from zenswarm.judge.watch import EndWatch
from zenswarm.process.collector import Collector
from zenswarm.process.paths import lock_output_dir
from zenswarm.process.runtime import gc_safe_point, gc_startup_done
from zenswarm.process.settings import FlightSettings, decode_role
from zenswarm.scenario.config import Scenario

__all__ = ["Supervisor", "role_names", "swarm_roles", "EXTERNAL_GONE_GRACE_S", "EXIT_OK", "EXIT_MISSION_FAILED", "EXIT_PROCESS_FAILED"]

LIVE_CHECK_S = 0.25
"""Wall seconds between two looks at whether the flight's outcome is decided (early end)."""


class Supervisor:
    """Starts and watches one swarm. ``run()`` returns the exit code."""

    def __init__(self, args: FlightSettings, scenario: Scenario | None = None) -> None:
        if args.plant in ("mavlink", "crazyflie"):
            args = msgspec.structs.replace(args, realtime=True)  # real vehicles (or their simulation over UDP) run on the wall clock
        self.args = args
        self.sc = scenario = args.scenario if scenario is None else scenario
        self.keys = wire.Keys(args.swarm)
        rt = os.environ.get("ZENOH_RUNTIME")  # the user's choice, unless it is a swarm process's own
        self.user_runtime = None if rt == bus.ZENOH_RUNTIME_DEFAULT else rt  # None: ours (spawn, run)
        self.children: dict[str, Child] = {}
        self.collector: Collector | None = None
        self.listen: list[str] = []  # the router's endpoints, once it listens (:meth:`_open_router`)
        self.stop = threading.Event()
        self.stop_reason = ""
        self.print_lock = threading.Lock()
        # --kill: killed from here at a sim time, or (lockstep roles) by themselves at a tick
        self.kills = Kills(args.kill or (), realtime=args.realtime, dt=scenario.timing.dt)
        self.policy = restart_policy(scenario.restart, force=args.restart)
        self.restarts = Restarts(self.policy)  # the processes' deaths, the restarts due and made
        self.deaths = self.restarts.deaths  # (tests read them here)
        everyone = swarm_roles(scenario.n, args.plant)  # every role of this swarm (whoever starts it), in start order
        self.started = [r for r in everyone if r not in args.external]  # those started here
        self.mav_base_port, self.cf_base_port = commands.vehicle_ports(args, scenario.n)  # the simulated vehicles' UDP ports
        self.connect_endpoints: list[str] = []  # where the roles join the router, once it listens
        self.tokens = Tokens(self.keys, lambda: self.collector.sim_t_ns if self.collector is not None else -1)
        self._on_liveliness, self.gone_at = self.tokens.on_token, self.tokens.gone_at  # (tests drive the tokens by these)
        watched = [r for r in everyone if r in args.external and r != "vehicles"]  # the vehicles: no Zenoh, no token
        self.external = ExternalRoles(watched, self.tokens, timeout_s=args.external_timeout, swarm=args.swarm,
                                      time_limit_s=scenario.timing.time_limit_s, policy=self.policy, say=lambda text: self.say(text))
        # when the flight ends (decided, --stop-at-goal, a plug-in failed) and which ticks are judged
        self.watch = EndWatch(criteria_from_scenario(scenario), scenario.timing.n_ticks, full_time=args.full_time,
                              stop_at_goal=args.stop_at_goal, realtime=args.realtime)
        self.recording_loss: dict | None = None  # the recorder died mid-flight (_check_children)
        self.plugin_failures = PluginFailures(lambda text: self.say(text))  # what processes that exited with 4 reported
        self.t_start: float  # monotonic s when the run starts (set by _run_up, just before run())
        self.taps: list[Tap] = []  # views fed every message of the bus (--live: attached by compose/up.py)
        self.on_end: list[EndHook] = []  # called once the results are written (--report: attached by compose/up.py)
        self.cluster: Any = None  # --scheduler: the Dask cluster the roles run on (zenswarm.compose.cluster.Cluster), set by run()

    # ------------------------------------------------------------------ output
    def say(self, text: str) -> None:
        with self.print_lock:
            print(f"[supervisor] {text}", flush=True)

    def _on_line(self, child: Child, line: str) -> bool:
        """One line of a child's output: a plug-in's failure report is taken (not kept), the rest
        printed (unless children are quiet) and kept."""
        if self.plugin_failures.take_line(line):  # a plug-in failed in this child: taken, not printed
            return False
        if not self.args.quiet_children:
            with self.print_lock:
                print(f"[{child.name}] {line}", flush=True)
        return True

    # ------------------------------------------------------------------ processes
    def command(self, role: str) -> tuple[list[str], bytes]:
        """What ``role`` is started with: its command line and its settings
        (:func:`zenswarm.compose.commands.command`). A role named by ``--kill`` in lockstep kills
        itself at the tick, on its first start only."""
        kill_at = self.kills.take_tick(role)  # the first start only: a restarted process is not killed again
        if kill_at is not None:
            self.say(f"{role} will SIGKILL itself just before tick {kill_at} (sim time {kill_at * self.sc.timing.dt:.2f} s; --kill)")
        at = commands.Launch(self.args, tuple(self.connect_endpoints), self.keys_dir, self.mav_base_port, self.cf_base_port, os.getpid())
        return commands.command(role, at, kill_at)

    def spawn(self, role: str) -> Child:
        """Start ``role`` (here, or with ``--scheduler`` a plant, leader or agent on its worker) with
        its settings on standard input, and read its output (:meth:`_on_line`)."""
        # the swarm's processes: zenoh on one thread (bus.use_swarm_runtime), unless the user chose
        env = swarm_env(os.environ, bus.ZENOH_RUNTIME_DEFAULT if self.user_runtime is None else None)
        argv, settings = self.command(role)
        if self.cluster is not None and role.partition(":")[0] in commands.ROLES_BY_SETTINGS:  # its settings travel with the start
            wanted = {k: env[k] for k in ("PYTHONUNBUFFERED", "ZENOH_RUNTIME") if k in env}
            c: Child = self.cluster.start(role, decode_role(settings), argv[1:], wanted)
        else:
            c = start_with_settings(role, argv, settings, env, term_on_parent_death=role == "recorder")
        c.read(self._on_line)
        self.children[role] = c
        return c

    def terminate_all(self, grace_s: float = 5.0) -> None:
        """Stop every started role (:func:`zenswarm.compose.children.stop_in_order`: the recorder
        last) and say the recorder's closing line (what it wrote) when children are quiet."""
        stop_in_order(self.children, {f.process for f in self.plugin_failures}, grace_s, self.say)
        rec = self.children.get("recorder")
        for line in rec.lines[-1:] if rec is not None and self.recording_loss is None and self.args.quiet_children else ():
            self.say(line)

    def _on_signal(self, signum: int, frame: Any) -> None:
        self.stop_reason = f"received {signal.Signals(signum).name}"
        self.stop.set()

    # ------------------------------------------------------------------ main loop
    def run(self) -> int:
        a = self.args
        out: Path = a.out
        listen = list(a.listen) or [f"tcp/127.0.0.1:{bus.free_port()}"]
        if a.scheduler is not None:  # the cluster, its workers and the plan: bad input exits 2 before anything starts
            from zenswarm.compose.cluster import Cluster

            self.cluster = Cluster(a.scheduler, a.placement, self.say)
            placed = [r for r in self.started if r.partition(":")[0] in commands.ROLES_BY_SETTINGS]
            self.cluster.open(placed, self.sc.n, list(a.connect) or listen, a.swarm)
        try:
            settings, listen = self._security(listen, out)
            # a second flight into this OUT would overwrite our results: exit 2 naming --out, now
            out_lock = lock_output_dir(out, "--out")
            try:
                return self._run_locked(listen, settings, out)
            finally:
                out_lock.release()
        finally:
            if self.cluster is not None:
                self.cluster.close()  # every role it placed ends, on every worker

    def _run_locked(self, listen: list[str], settings: dict, out: Path) -> int:
        """:meth:`run` once the output directory is locked: the router, the processes, the watch."""
        a = self.args
        sc = self.sc
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)

        # zenoh reads ZENOH_RUNTIME when this process opens its first session: the router's
        if self.user_runtime is None:
            os.environ["ZENOH_RUNTIME"] = bus.ZENOH_RUNTIME_ROUTER
        session_cm, session, listen = self._open_router(listen, settings)
        self.listen = listen
        self.connect_endpoints = list(a.connect) or list(listen)
        collector = self.collector = Collector(sc, self.keys, spool_dir=out)  # spool: flat memory
        self._bus_sub: Any = None
        subs = []
        try:
            try:
                self._bus_sub = swarm_channel(session, self.keys)  # drained by _watch every loop
                subs.append(self._bus_sub)
                subs += self.tokens.subscribe(session, collector.token)
                self.say(
                    f"swarm '{a.swarm}': router on {', '.join(listen)}; {sc.n} UAVs; "
                    f"{'realtime' if a.realtime else 'lockstep'}; scenario {sc.name}"
                )
                if a.record is not None:
                    a.record.parent.mkdir(parents=True, exist_ok=True)
                    self.spawn("recorder")  # first: the plant waits for it, so no tick goes unrecorded
                for role in self.started:
                    self.spawn(role)
                if a.realtime:
                    gc_startup_done()  # the children are started: see zenswarm.process.gcpolicy.GcPolicy (realtime only)
                code = self._watch(collector)
            finally:
                self.terminate_all()
                if self._bus_sub is not None:
                    collector.poll(self._bus_sub, feeds(self.taps))  # what arrived after the last loop
                for t in self.taps:
                    t.publish()  # the flight's last frame
                undeclare_all(subs)
            # results first, then the router's close: with a link to a host that is gone (a cut
            # cable, a dead remote role) zenoh's close waits about 10 s for it to time out
            return self._finish(collector, code, out)
        finally:
            session_cm.__exit__(None, None, None)

    def _open_router(self, listen: list[str], settings: dict) -> tuple[Any, zenoh.Session, list[str]]:
        """The router's session (:func:`zenswarm.compose.router.open_router`: a free port taken again if another program bound it)."""
        a = self.args
        return open_router(listen, settings, router_connect=a.router_connect, given=bool(a.listen), say=self.say)

    def _security(self, listen: list[str], out: Path) -> tuple[dict, list[str]]:
        """The router's settings and listen endpoints (:func:`~zenswarm.compose.credentials.router_security`); keeps the keys' dir."""
        a = self.args
        sec = router_security(
            self.sc, listen, out, self.say, swarm=a.swarm, connect=a.connect, secure=a.secure, tls=a.tls, insecure=a.insecure, keys=a.keys
        )
        self.keys_dir = sec.keys_dir
        return sec.settings, sec.listen

    def _watch_external(self, collector: Collector, now: float, since: float) -> int | None:
        """``--external`` roles, known only through their liveliness tokens: one whose token went
        away before it finished, or that never announced itself within ``--external-timeout``, is a
        process that died (:meth:`ExternalRoles.check`): exit 3. None while all is well."""
        death = self.external.check(collector, now, since, self.connect_endpoints)
        if death is None:
            return None
        self.restarts.deaths.append(death)
        self.failed = death["process"]
        return EXIT_PROCESS_FAILED

    def _health(self) -> str:
        """The roles' states for the progress line (:func:`~zenswarm.compose.progress.swarm_health`)."""
        return swarm_health(self.children, self.tokens, self.external, self.collector.diag if self.collector is not None else {})

    def _watch(self, collector: Collector) -> int:
        """Watch the flight until it ends; returns the exit code so far (see :meth:`_finish`)."""
        last_check = 0.0
        wall0 = time.monotonic()
        a, sc = self.args, self.sc
        progress = SwarmProgress(sc.leader.goal, sc.timing.time_limit_s, a.progress_every, a.quiet, self.say, wall0)
        tap = feeds(self.taps)
        while True:
            collector.poll(self._bus_sub, tap)
            for t in self.taps:
                t.maybe_publish(time.monotonic())
            if self.stop.is_set():
                self.say(f"stopping: {self.stop_reason}")
                return EXIT_INTERRUPTED
            now = time.monotonic()
            done, code = self._check_children(collector, now)
            self.plugin_failures.from_diagnostics(collector.diag, self.external.names)  # --external roles' failures
            if code == EXIT_PLUGIN_FAILED or self.plugin_failures:
                return self._drain_plugin_failures(collector)
            if code is None:
                code = self._watch_external(collector, now, wall0)
            if code is not None:
                return code
            if done:  # lockstep: the last ticks' messages may still be on their way
                await_last_tick(collector, lambda: collector.poll(self._bus_sub, tap), realtime=a.realtime,
                                timeout_s=a.lockstep_timeout, stop=self.stop, say=self.say)  # fmt: skip
                return EXIT_OK
            running = [name for name, c in self.children.items() if c.proc.poll() is None] if self.kills.pending else []
            for role in self.kills.kills_due(collector.sim_t_ns, running):  # --kill ROLE@T
                self.say(f"injecting SIGKILL into {role} at sim time {collector.sim_t_ns / 1e9:.2f} s (--kill)")
                self.children[role].proc.kill()
            if now - last_check >= LIVE_CHECK_S:
                last_check = now
                end = self.watch.look(collector)  # has the flight's outcome been decided (or, --stop-at-goal, the goal)?
                if end is not None:
                    self.say(end.why)
                    return EXIT_OK
            progress(time.monotonic(), collector.sim_t_ns, collector.leader_q, self._health)
            gc_safe_point()
            time.sleep(0.05)

    def _check_children(self, collector: Collector, now: float) -> tuple[bool, int | None]:
        """One look at the processes started here (restarting those due): (all done, exit code
        if one died for good, else None). The recorder and the vehicles never keep the run going."""
        done = True
        for c in list(self.children.values()):
            if self.restarts.waiting(c.name):
                done = False
                if (n := self.restarts.restart_now(c.name, now)) is not None:
                    self.say(f"restarting {c.name} (restart {n} of {self.policy.max_restarts})")
                    self.spawn(c.name)
                continue
            rc = c.proc.poll()
            if rc is None:
                if c.name not in ("recorder", "vehicles"):  # both are stopped once the rest is done
                    done = False
                continue
            if c.returncode is not None:
                continue
            c.returncode = rc
            if c.name == "recorder":  # any exit before the end is a loss (said; results.json), never a failure
                self.recording_loss = recording_lost(c, rc, collector.sim_t_ns, self.args.record, self.say)
                continue
            if rc == EXIT_PLUGIN_FAILED and self.plugin_failures.reported_at_exit(c):
                return done, EXIT_PLUGIN_FAILED
            if rc != 0:
                code = self._child_died(c, rc, collector, now)
                if code is not None:
                    return done, code
                done = False
        return done or self._flight_over(now), None

    def _flight_over(self, now: float) -> bool:
        """The process that keeps the flight's clock (the plant; the bridge with real or simulated
        vehicles) ended it (exit 0): a restart still due is not made, and a process still running
        :data:`FLIGHT_OVER_GRACE_S` later (one restarted after the end waits for a tick that never
        comes) no longer keeps the run going: it is stopped with the rest."""
        clock = self.children.get("bridge" if self.args.plant in ("mavlink", "crazyflie") else "plant")
        if clock is None or clock.returncode != 0:
            return False
        cancelled, over = self.restarts.flight_ended(now, FLIGHT_OVER_GRACE_S + self.args.lockstep_timeout)
        for role in cancelled:
            self.say(f"{role}: not restarted, the flight is over ({clock.name} ended it)")
        return over

    def _drain_plugin_failures(self, collector: Collector) -> int:
        """A plug-in failed: wait until its (tick, stage) is settled
        (:func:`~zenswarm.compose.plugin_failures.await_settled`), then judge the ticks before it,
        unless the outcome was decided before (as the simulator: :meth:`EndWatch.plugin_failed`).
        Returns 4, or 0 when the run was decided before."""
        a = self.args
        first = await_settled(self.plugin_failures, collector, partial(self._reap, collector), realtime=a.realtime,
                              roles=self.started, announced=self.tokens.seen, stop=self.stop, say=self.say,
                              timeout_s=a.lockstep_timeout + SETTLE_GRACE_S)  # fmt: skip
        end = self.watch.plugin_failed(collector, first[0].tick)
        self.plugin_failures.keep(first if end.plugin_failed else [])  # none when decided before: the run ended there
        if not end.plugin_failed:
            self.say(end.why)
        return EXIT_PLUGIN_FAILED if end.plugin_failed else EXIT_OK

    def _reap(self, collector: Collector) -> set[str]:
        """One look while a plug-in's failure settles: the bus drained, the processes' exits taken
        (with their failure reports) and the external roles' failures; the processes that exited."""
        collector.poll(self._bus_sub, feeds(self.taps))
        exited = self.plugin_failures.take_exits(list(self.children.values()))
        self.plugin_failures.from_diagnostics(collector.diag, self.external.names)
        return exited

    def _child_died(self, c: Child, rc: int, collector: Collector, now: float) -> int | None:
        """A process of ours exited with status ``rc`` != 0: schedule its restart (None) when the
        policy allows, else the exit code (3)."""
        c.join_output(1.0)  # its output ended with it: its last lines are read at once
        # when the collector's clock saw it (a few ticks behind, loaded), or the tick it killed itself at (--kill)
        t_s = self.kills.death_time(c.name, rc, c.lines, max(collector.sim_t_ns, 0) / 1e9)
        delay = self.restarts.died(process_death(c, rc, t_s, self.say), now)
        if delay is not None:
            self.say(f"{c.name} will be restarted in {delay:.2f} s")
            return None
        if self.restarts.limit_reached(c.name):
            self.say(f"{c.name}: restart limit ({self.policy.max_restarts}) reached; aborting the mission")
        self.failed = c.name
        return EXIT_PROCESS_FAILED

    def _finish(self, collector: Collector, code: int, out: Path) -> int:
        """Judge the flight, write OUT/results.json and OUT/timeseries.npz
        (:func:`~zenswarm.compose.flight_results.judge_and_write`), then call the end hooks (the
        report with ``--report``); the exit code: ``code`` if not 0, else 0 or 1 by the verdict."""
        a = self.args
        dead = getattr(self, "failed", "?")  # exit 3: the process that died for good
        how = self.restarts.how_died(dead)
        facts = partial(run_facts, collector, realtime=a.realtime, swarm=a.swarm, record=a.record, listen=self.listen,
                        children=self.children, deaths=self.deaths, restarts=self.restarts.done,
                        recording_loss=self.recording_loss,
                        cluster=self.cluster.facts() if self.cluster is not None else None)  # fmt: skip
        res = judge_and_write(
            collector, self.watch, self.sc, out, stopped=code not in (EXIT_OK, EXIT_PLUGIN_FAILED), fill=a.realtime or bool(self.deaths),
            full_time=a.full_time, faults=a.faults.plan(self.sc), facts=facts, t_start=self.t_start,
            died=(dead, how) if code == EXIT_PROCESS_FAILED else None, interrupted=self.stop_reason if code == EXIT_INTERRUPTED else None,
            plugin_failures=list(self.plugin_failures) if code == EXIT_PLUGIN_FAILED else (), say=self.say,
        )  # fmt: skip
        end = FlightEnd(out, code, res, a.record, self.recording_loss, self.say)
        for hook in self.on_end:
            hook(end)
        if code != EXIT_OK:
            return code
        return EXIT_OK if res["success"] else EXIT_MISSION_FAILED

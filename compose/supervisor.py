"""The supervisor of ``zenswarm up``: start a Zenoh router, then the plant, the leader and N agents
as separate OS processes; watch them, show progress, merge their logs, stop them cleanly, write
results. It takes a checked :class:`zenswarm.process.settings.FlightSettings`; the command line,
its checks and the settings' building are :mod:`zenswarm.compose.up`'s.

The supervisor's router session subscribes to the swarm's whole key space to assemble the
flight's time series (the same :class:`zenswarm.judge.metrics.TimeSeries` the in-process simulator
writes), so ``results.json`` is computed by the same code for both. Apart from the recorder it
is the only subscriber to the whole key space; the swarm's processes see only their graph rows.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from zenswarm import bus
from zenswarm.bus import wire
from zenswarm.compose.children import Child, start_local
from zenswarm.compose.policy import restart_policy
from zenswarm.compose.progress import SwarmProgress
from zenswarm.errors import EXIT_INTERRUPTED, EXIT_PLUGIN_FAILED, PluginFailure, ScenarioError, ZenswarmError
from zenswarm.judge.results import closing_lines, flight_results, write_outputs
from zenswarm.judge.verdict import criteria_from_scenario
from zenswarm.judge.watch import EndWatch
from zenswarm.process import security
from zenswarm.process.collector import Collector
from zenswarm.process.paths import check_output_dir, lock_output_dir
from zenswarm.process.runtime import PLUGIN_FAILURE_MARK, gc_safe_point, gc_startup_done, kill_self_line
from zenswarm.process.settings import (
    FlightSettings,
    RoleSettings,
    encode,
)
from zenswarm.scenario.config import Scenario
from zenswarm.scenario.plugins import STAGE_BUILD, STAGE_SHARE, STAGE_STEP, first_failures

__all__ = ["Supervisor", "role_names", "swarm_roles"]

LIVE_CHECK_S = 0.25
"""Wall seconds between two looks at whether the flight's outcome is decided (early end)."""

COLLECTOR_QUEUE = 4_000_000
"""Capacity of the supervisor's bus queue, in messages (drained every ~50 ms, so it never fills)."""

EXIT_OK, EXIT_MISSION_FAILED, EXIT_PROCESS_FAILED = 0, 1, 3
"""``zenswarm up``'s own exit statuses: the mission succeeded, it failed, a process died (bad input 2,
a plug-in failure 4 and Ctrl-C 130 are :mod:`zenswarm.errors`'s)."""

SITL_SEND_OFFSET = 40
"""With ``--plant mavlink`` simulated vehicle i sends from UDP P+40+i (PX4 SITL: 14580+i -> 14540+i)."""

ROUTER_PORT_TRIES = 5
"""Without ``--listen`` the router's port is a free one, chosen a moment before the router binds
it; another program (a second flight started at the same moment) may take it in between. Then a
new free port, up to this many ports in all."""

EXTERNAL_GONE_GRACE_S = 0.5
"""An external role's liveliness token must stay gone this long before the role counts as dead:
its final diagnostics (``finished``), sent just before a normal exit, reach the collector's queue
first but are read on the watch loop's next poll."""


def role_names(n: int) -> list[str]:
    """Process names of a swarm of n UAVs, in start order."""
    return ["plant", "leader"] + [f"agent:{i}" for i in range(1, n + 1)]


def swarm_roles(n: int, plant: str = "sim") -> list[str]:
    """The roles ``zenswarm up --plant PLANT`` runs for n UAVs, in start order (the recorder,
    started first with ``--record``, aside): with ``mavlink`` the simulated vehicles and the
    bridge take the plant's place (also with ``crazyflie``: simulated Crazyflies and the Crazyflie bridge)."""
    names = role_names(n)
    return ["vehicles", "bridge"] + names[1:] if plant in ("mavlink", "crazyflie") else names


ROLES_BY_SETTINGS = ("plant", "leader", "agent")
"""The roles started with their :class:`RoleSettings` on standard input; the recorder, the bridges
and the simulated vehicles still take a command line (the edges' own flags)."""


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
        self.alive: set[str] = set()
        self.seen: set[str] = set()  # processes whose token appeared at least once
        self.gone_at: dict[str, tuple[float, int]] = {}  # process -> when its token went away (monotonic s, sim ns)
        self.pending_kills: dict[str, int] = {role: wire.t_ns(t) for role, t in (args.kill or ())}
        # lockstep: a swarm role kills itself at the exact tick (--kill-at-tick, its first start
        # only), so the fault falls on the same tick in every run; the rest are killed from here
        # when the collector's sim time gets there (the recorder, realtime flights)
        self.kill_ticks: dict[str, int] = {}
        self.self_killed: dict[str, int] = {}  # role -> the tick it was started to kill itself at
        if not args.realtime:
            dt_ns = wire.t_ns(scenario.timing.dt)
            for role in [r for r in self.pending_kills if r in ("plant", "leader") or r.startswith("agent:")]:
                self.kill_ticks[role] = -(-self.pending_kills.pop(role) // dt_ns)  # the first tick at or after T
        self.policy = restart_policy(scenario.restart, force=args.restart)
        self.restart_at: dict[str, float] = {}
        self.restarts: dict[str, int] = {}
        self.deaths: list[dict] = []
        # when the flight ends (decided, --stop-at-goal, a plug-in failed) and which ticks are judged
        self.watch = EndWatch(criteria_from_scenario(scenario), scenario.timing.n_ticks, full_time=args.full_time,
                              stop_at_goal=args.stop_at_goal, realtime=args.realtime)
        self.recording_loss: dict | None = None  # the recorder died mid-flight (_recorder_died)
        self.plugin_failures: list[PluginFailure] = []  # what processes that exited with 4 reported
        # the vehicles' ports P+i (the bridge listens) and their send ports P+40+i, all free
        self.mav_base_port = args.mavlink_base_port or bus.free_udp_block(scenario.n, also=(SITL_SEND_OFFSET,))
        # --plant crazyflie: simulated Crazyflie i on udp://127.0.0.1:P+i
        self.cf_base_port = (args.crazyflie_base_port or bus.free_udp_block(scenario.n)) if args.plant == "crazyflie" else None
        self.t_start: float  # monotonic s when the run starts (set by _run_up, just before run())
        self.live: Any = None  # --live: the view (zenswarm.bridge.views.live.open_view), bound by _run_up before run()
        self.cluster: Any = None  # --scheduler: the Dask cluster the roles run on (zenswarm.compose.cluster.Cluster), set by run()

    # ------------------------------------------------------------------ output
    def say(self, text: str) -> None:
        with self.print_lock:
            print(f"[supervisor] {text}", flush=True)

    def _on_line(self, child: Child, line: str) -> bool:
        """One line of a child's output: a plug-in's failure report is taken (not kept), the rest
        printed (unless children are quiet) and kept."""
        at = line.find(PLUGIN_FAILURE_MARK)
        if at >= 0:  # a plug-in failed in this child (zenswarm.process.runtime.report_plugin_failure)
            try:
                f = PluginFailure.from_dict(json.loads(line[at + len(PLUGIN_FAILURE_MARK) :]))
            except (ValueError, KeyError, TypeError, AssertionError):
                pass
            else:
                self.plugin_failures.append(f)
                self.say(f"plug-in failed: {f}")
                return False
        if not self.args.quiet_children:
            with self.print_lock:
                print(f"[{child.name}] {line}", flush=True)
        return True

    # ------------------------------------------------------------------ processes
    def child_argv(self, role: str) -> list[str]:
        """The command line of ``role`` (a swarm role or ``recorder``), this interpreter's. The
        plant, the leader and the agents are named on it (role, ``--swarm``, this supervisor's pid:
        to find them in the process table) and read their :class:`RoleSettings` (:meth:`role_settings`)
        on standard input; the others take their flags."""
        argv = [sys.executable, "-m", "zenswarm"]
        if role.partition(":")[0] in ROLES_BY_SETTINGS:
            words = ["agent", "--id", role.split(":", 1)[1]] if role.startswith("agent:") else [role]
            return argv + words + ["--swarm", self.args.swarm, "--settings", "-", "--supervisor", str(os.getpid())]
        if role == "recorder":
            return argv + self._recorder_argv()
        if role == "vehicles" and self.cf_base_port is not None:  # simulated Crazyflies (CRTP over UDP, no Zenoh)
            argv += ["crazyflie-vehicle", str(self.args.scenario_file), "--base-port", str(self.cf_base_port)]
            if self.sc.crazyflie is not None and self.sc.crazyflie.positioning == "extpos":  # they are the mocap system too
                argv += ["--mocap", "--swarm", self.args.swarm, *[w for ep in self.connect_endpoints for w in ("--connect", ep)]]
            return argv
        if role == "vehicles":  # simulated MAVLink vehicles (no Zenoh): the bridge talks to them over UDP
            a = self.args
            # as PX4 SITL and real autopilots: each vehicle's NED about where it booted, and
            # vehicle i sending from P+40+i to P+i where the bridge listens (udpin)
            return argv + [
                "mavlink-vehicle", str(a.scenario_file), "--base-port", str(self.mav_base_port), "--telemetry-hz", "100",
                "--own-origin", "--sitl-ports", *a.rt_argv(),
            ]
        if role == "bridge":
            return argv + self._bridge_argv()
        raise ValueError(f"not a process of this swarm: {role!r}")

    def _join_words(self) -> list[str]:
        """``--connect`` each endpoint, then ``--keys DIR [--tls]`` in secure mode."""
        words = [w for ep in self.connect_endpoints for w in ("--connect", ep)]
        if self.keys_dir is not None:
            words += ["--keys", str(self.keys_dir)] + (["--tls"] if self.args.tls else [])
        return words

    def _recorder_argv(self) -> list[str]:
        a = self.args
        argv = ["record", "--swarm", a.swarm, "--out", str(a.record), "--scenario", str(a.scenario_file)]
        argv += [w for ep in self.connect_endpoints for w in ("--connect", ep)]
        if a.realtime:
            argv.append("--realtime")
        if self.keys_dir is not None:
            argv += ["--keys", str(self.keys_dir)] + (["--tls"] if a.tls else [])
        return argv + a.faults.argv() + a.plugin_argv()

    def _bridge_argv(self) -> list[str]:
        a = self.args
        if self.cf_base_port is not None:  # the Crazyflie bridge; to the simulated ones unless they are external
            argv = ["bridge", "crazyflie", str(a.scenario_file), "--swarm", a.swarm, *self._join_words()]
            if "vehicles" not in a.external:
                argv += [w for i in range(self.sc.n) for w in ("--uri", f"{i + 1}=udp://127.0.0.1:{self.cf_base_port + i}")]
            return argv + a.faults.argv() + (["--expect", "recorder"] if a.record is not None else [])
        argv = ["bridge", "mavlink", str(a.scenario_file), "--base-port", str(self.mav_base_port), "--swarm", a.swarm]
        argv += self._join_words()
        # the simulated vehicles (own origins, SITL ports): listen where vehicle i sends, and put
        # its origin where it boots, on the ground under its initial position
        gz = self.sc.mavlink.ground_z if self.sc.mavlink is not None else 0.0
        for i, q in enumerate(self.sc.initial_positions):
            argv += ["--conn", f"{i + 1}=udpin:127.0.0.1:{self.mav_base_port + i}", "--origin", f"{i + 1}={q[0]!r},{q[1]!r},{gz!r}"]
        return argv + a.faults.argv() + (["--expect", "recorder"] if a.record is not None else []) + a.rt_argv()

    def role_settings(self, role: str) -> RoleSettings:
        """plant, leader, agent:<i>: what the role is started with (its part of the flight's
        settings); the plant waits for the recorder with ``--record``. A role named by ``--kill``
        in lockstep kills itself at the tick, on its first start only."""
        a = self.args
        kill_at = self.kill_ticks.pop(role, None)  # the first start only: a restarted process is not killed again
        if kill_at is not None:
            self.self_killed[role] = kill_at
            self.say(f"{role} will SIGKILL itself just before tick {kill_at} (sim time {kill_at * self.sc.timing.dt:.2f} s; --kill)")
        expect = ("recorder",) if role == "plant" and a.record is not None else ()
        return a.role(role, tuple(self.connect_endpoints), self.keys_dir, kill_at_tick=kill_at, expect=expect)

    def spawn(self, role: str) -> Child:
        env = dict(os.environ)
        env.setdefault("PYTHONUNBUFFERED", "1")
        if self.user_runtime is None:  # the swarm's processes: zenoh on one thread (bus.use_swarm_runtime)
            env["ZENOH_RUNTIME"] = bus.ZENOH_RUNTIME_DEFAULT
        if self.cluster is not None and role.partition(":")[0] in ROLES_BY_SETTINGS:
            return self._spawn_placed(role, env)
        stdin: Any = subprocess.DEVNULL
        if role.partition(":")[0] in ROLES_BY_SETTINGS:  # its settings on stdin: a file of its own, already gone from the disk
            stdin = tempfile.TemporaryFile()
            stdin.write(encode(self.role_settings(role)))
            stdin.seek(0)
        try:
            c = start_local(role, self.child_argv(role), env, stdin, term_on_parent_death=role == "recorder")
        finally:
            if stdin is not subprocess.DEVNULL:
                stdin.close()  # the child holds its own descriptor
        c.read(self._on_line)
        self.children[role] = c
        return c

    def _spawn_placed(self, role: str, env: dict[str, str]) -> Child:
        """``--scheduler``: start ``role`` on its worker (:class:`zenswarm.compose.cluster.Cluster`),
        its settings and environment travelling with the start; watched as a local one."""
        wanted = {k: env[k] for k in ("PYTHONUNBUFFERED", "ZENOH_RUNTIME") if k in env}
        c: Child = self.cluster.start(role, self.role_settings(role), self.child_argv(role)[1:], wanted)
        c.read(self._on_line)
        self.children[role] = c
        return c

    def terminate_all(self, grace_s: float = 5.0) -> None:
        """SIGTERM the swarm's roles and wait (then SIGKILL); the recorder last, after a moment for
        messages in flight, with time to drain its queue and write the summary."""
        rec = self.children.get("recorder")
        last = ("recorder", "bridge", "vehicles")
        # a process whose plug-in failed is leaving by itself with status 4 (after its report):
        # the others are stopped first, then it is given the grace to exit before any signal, so
        # results.json's processes say 4, not the signal that caught it on its way out
        failed = {f.process for f in self.plugin_failures}
        leaving = [c for c in self.children.values() if c.name in failed and c.name not in last]
        self._terminate([c for c in self.children.values() if c.name not in last and c not in leaving], grace_s)
        self._await_exit(leaving, grace_s)
        self._terminate(leaving, grace_s)
        # MAVLink: the bridge lands and disarms its vehicles, which must still be running for that
        for name, grace in (("bridge", 25.0), ("vehicles", grace_s)):
            if name in self.children:
                self._terminate([self.children[name]], grace)
        if rec is not None:
            if rec.proc.poll() is None:
                time.sleep(0.3)
            self._terminate([rec], 60.0)
            # its closing line (what it wrote): already on the console unless children are quiet
            for line in rec.lines[-1:] if self.recording_loss is None and self.args.quiet_children else ():
                self.say(line)

    @staticmethod
    def _await_exit(children: list, grace_s: float) -> None:
        """Wait (at most ``grace_s`` in all) for ``children`` to exit by themselves."""
        deadline = time.monotonic() + grace_s
        for c in children:
            try:
                c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass

    def _terminate(self, children: list, grace_s: float) -> None:
        for c in children:
            if c.proc.poll() is None:
                c.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for c in children:
            left = max(0.0, deadline - time.monotonic())
            try:
                c.proc.wait(timeout=left)
            except subprocess.TimeoutExpired:
                self.say(f"{c.name} did not stop within {grace_s:.0f} s; killing it")
                c.proc.kill()
                c.proc.wait()
        for c in children:
            c.join_output(2.0)

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
            placed = [r for r in self.roles() if r.partition(":")[0] in ROLES_BY_SETTINGS]
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
                # A channel, drained by _watch every loop: no Python callback per message (each would
                # wake a thread of this process, on the cores the swarm shares). The capacity holds
                # minutes of a large swarm's traffic, so the router never waits on this queue.
                self._bus_sub = session.declare_subscriber(self.keys.all, zenoh.handlers.FifoChannel(COLLECTOR_QUEUE))
                subs.append(self._bus_sub)
                subs.append(session.liveliness().declare_subscriber(self.keys.alive_all, self._on_liveliness, history=True))
                subs.append(session.liveliness().declare_subscriber(self.keys.alive_all + "/*", self._on_sender_token, history=True))
                self.say(
                    f"swarm '{a.swarm}': router on {', '.join(listen)}; {sc.n} UAVs; "
                    f"{'realtime' if a.realtime else 'lockstep'}; scenario {sc.name}"
                )
                if a.record is not None:
                    a.record.parent.mkdir(parents=True, exist_ok=True)
                    self.spawn("recorder")  # first: the plant waits for it, so no tick goes unrecorded
                for role in self.roles():
                    self.spawn(role)
                if a.realtime:
                    gc_startup_done()  # the children are started: see zenswarm.process.runtime.GcPolicy (realtime only)
                code = self._watch(collector)
            finally:
                self.terminate_all()
                if self._bus_sub is not None:
                    collector.poll(self._bus_sub, self._live_tap())  # what arrived after the last loop
                if self.live is not None:
                    self.live.publish()  # the flight's last frame
                for s in subs:
                    try:
                        s.undeclare()
                    except Exception:  # noqa: BLE001 - best effort on shutdown
                        pass
            # results first, then the router's close: with a link to a host that is gone (a cut
            # cable, a dead remote role) zenoh's close waits about 10 s for it to time out
            return self._finish(collector, code, out)
        finally:
            session_cm.__exit__(None, None, None)

    def _open_router(self, listen: list[str], settings: dict) -> tuple[Any, zenoh.Session, list[str]]:
        """The router's session (its context manager, entered; the session; the endpoints it
        listens on). Without ``--listen`` the port was chosen free a moment ago: if another program
        bound it since (two flights started at once), the router takes a new free port, up to
        :data:`ROUTER_PORT_TRIES` ports, and says so. A port given with ``--listen`` is never changed:
        :class:`zenswarm.bus.BusError` naming ``--listen`` (exit 2)."""
        a = self.args
        for attempt in range(1, ROUTER_PORT_TRIES + 1):
            cm = bus.open_session(bus.router_config(listen, connect=list(a.router_connect), settings=settings), handle_signals=False)
            try:
                return cm, cm.__enter__(), listen
            except bus.BusError as e:
                if "Address already in use" not in str(e) or attempt == ROUTER_PORT_TRIES:
                    raise
                if a.listen:
                    raise bus.BusError(f"--listen {', '.join(listen)}: the port is taken by another program (another flight?); "
                                       "give another port, or leave --listen out for a free one") from None
                port = bus.free_port()
                self.say(f"the router's port was taken by another program before the router bound it ({', '.join(listen)}); "
                         f"taking port {port}")
                listen = [ep.rpartition(":")[0] + f":{port}" for ep in listen]
        raise AssertionError("unreachable")  # the last try returns or raises

    def _security(self, listen: list[str], out: Path) -> tuple[dict, list[str]]:
        """Router settings and listen endpoints for --secure/--tls (secure by default off loopback)."""
        a = self.args
        self.keys_dir = None
        open_net = not all(security.is_loopback_endpoint(e) for e in listen)
        asked = a.secure or a.tls or a.keys is not None
        if not (asked or (open_net and not a.insecure)):
            if open_net:
                self.say("WARNING: --insecure on a non-loopback address: anyone who reaches the router can command the swarm")
            return {}, listen
        auth: security.AuthMode = "tls" if a.tls else "usrpwd"
        if a.tls:
            listen = [security.tls_endpoint(e) for e in listen]
        # before anything starts: the processes would each die on such an endpoint
        try:
            security.check_endpoints([*listen, *a.connect], auth)
        except security.CredentialsError as e:
            why = "secure mode" if asked else "secure mode (the default when the router is not on loopback only)"
            raise security.CredentialsError(f"{why}: {e}") from None
        if a.keys is not None:
            self.keys_dir = self._user_keys(a.keys)
        else:
            self.keys_dir = self._run_keys(out / "keys")
        self.say(f"secure mode: {'mutual TLS' if a.tls else 'user/password'} authentication, access control from the graph")
        return security.router_security_config(self.keys_dir, self.sc, a.swarm, auth=auth), listen

    def _user_keys(self, keys: Path) -> Path:
        """``--keys DIR``: the user's own credentials, checked against this swarm, never rewritten."""
        swarm = self.args.swarm
        try:
            why = security.manifest_mismatch(security.load_manifest(keys), self.sc, swarm)
        except security.CredentialsError as e:
            raise ScenarioError("--keys", str(e)) from None
        if why:
            raise ScenarioError(
                "--keys",
                f"the credentials in {keys} {why}; generate matching ones with "
                f"`zenswarm keys SCENARIO --swarm {swarm} --out DIR` (see docs/security.md)",
            )
        return keys

    def _run_keys(self, keys_dir: Path) -> Path:
        """Credentials generated for this OUT (``OUT/keys``): reused while they fit this swarm,
        else generated again (and said so)."""
        swarm = self.args.swarm
        check_output_dir(keys_dir, "--out")
        manifest = keys_dir / security.MANIFEST_FILE
        why = None
        if manifest.exists():
            try:
                why = security.manifest_mismatch(security.load_manifest(keys_dir), self.sc, swarm, all_files=True)
            except security.CredentialsError as e:
                why = f"are unreadable ({e})"
        if why is not None or not manifest.exists():
            security.generate_credentials(self.sc, keys_dir, swarm, force=True)
            if why is None:
                self.say(f"generated credentials for this run in {keys_dir}")
            else:
                self.say(f"regenerated the credentials in {keys_dir}: the previous ones {why}")
        return keys_dir

    def all_roles(self) -> list[str]:
        """Every role of this swarm (whoever starts it), in start order."""
        return swarm_roles(self.sc.n, self.args.plant)

    def roles(self) -> list[str]:
        """The processes this supervisor starts, in start order (``--external`` ones excluded)."""
        external = set(self.args.external)
        return [r for r in self.all_roles() if r not in external]

    def external_roles(self) -> list[str]:
        """The ``--external`` roles this supervisor watches through their liveliness tokens (the
        simulated MAVLink vehicles have no Zenoh session: they cannot be watched)."""
        external = set(self.args.external)
        return [r for r in self.all_roles() if r in external and r != "vehicles"]

    def _report(self, out: Path, recording: Path) -> None:
        """Flight report from the recording (``--record``) alone (``--report``); partial if the recorder died."""
        if self.recording_loss is not None:
            self.say(
                f"report: warning: the recorder died at sim time {self.recording_loss['died_at_sim_time_s']:.2f} s: "
                "the report is partial, from what was recorded before"
            )
        try:
            from zenswarm.bridge.reports.report import report_recording

            written = report_recording(
                recording, out / "report", full_time=self.args.full_time, warn=lambda text: self.say(f"report: warning: {text}"),
                formats=self.args.report_format,
            )
        except ZenswarmError as e:
            self.say(f"report failed: {e}")
            return
        self.say(f"report: {len(written)} files in {out / 'report'}")

    def _on_liveliness(self, sample: Any) -> None:
        try:
            _, _, proc = self.keys.parse(str(sample.key_expr))
        except ZenswarmError:
            return
        if proc is None:
            return
        if str(sample.kind).endswith("PUT"):
            self.alive.add(proc)
            self.seen.add(proc)
            self.gone_at.pop(proc, None)
        else:
            self.alive.discard(proc)
            sim_t = self.collector.sim_t_ns if self.collector is not None else -1
            self.gone_at[proc] = (time.monotonic(), max(sim_t, 0))

    def _on_sender_token(self, sample: Any) -> None:
        """``alive/<process>/<zid>``: which session is which process (for the collector)."""
        parts = str(sample.key_expr).rsplit("/", 2)
        if len(parts) == 3 and self.collector is not None:
            self.collector.token(parts[1], parts[2], str(sample.kind).endswith("PUT"))

    def _recorder_died(self, child: Child, rc: int, collector: Collector) -> None:
        """The recorder is not a vehicle: its death does not end the flight. The loss is said
        now and goes into results.json (``recording_loss``); the file keeps what was written
        (chunks are flushed every 0.25 s; ``zenswarm recover`` closes it). The plant waited for
        the recorder only before tick 0, so nothing waits for it now."""
        how = f"killed by {signal.Signals(-rc).name}" if rc < 0 else f"exit status {rc}"
        t = max(collector.sim_t_ns, 0) / 1e9
        self.recording_loss = {"died_at_sim_time_s": t, "how": how, "recording": str(self.args.record)}
        error = next((ln for ln in reversed(child.lines) if ln.startswith("recorder: error:")), None)
        if error is not None:  # why it stopped, in its words (e.g. the disk is full: ENOSPC)
            self.recording_loss["error"] = error.removeprefix("recorder: error: ")
        tail = "; last output: " + " | ".join(child.lines[-3:]) if child.lines else ""
        self.say(
            f"recording lost: the recorder died ({how}) at sim time {t:.2f} s; the flight goes on unrecorded, "
            f"{self.args.record} holds what was written before (results.json: recording_loss){tail}"
        )

    @staticmethod
    def _token_names(role: str) -> tuple[str, ...]:
        """The processes whose token stands for ``role``: an external plant may be the MAVLink
        bridge run by hand (``zenswarm bridge mavlink``), which announces itself as ``bridge``."""
        return ("plant", "bridge") if role == "plant" else (role,)

    def _role_ended_normally(self, role: str, collector: Collector) -> bool:
        """A role's token went away: did it end its part of the flight? Yes if its last
        diagnostics say ``finished``, or if the plant's clock already reached the time limit (the
        flight is over: the others leave once the plant is gone)."""
        if any(collector.diag.get(p, {}).get("finished") is True for p in self._token_names(role)):
            return True
        return collector.sim_t_ns >= wire.t_ns(self.sc.timing.time_limit_s)

    def _watch_external(self, collector: Collector, now: float, since: float) -> int | None:
        """``--external`` roles, known only through their liveliness tokens: one whose token
        went away before it finished is a process that died (exit 3; this supervisor did not
        start it, so it cannot restart it), one that never announced itself within
        ``--external-timeout`` too. Returns the exit code, or None while all is well."""
        a = self.args
        for role in self.external_roles():
            names = self._token_names(role)
            if any(p in self.alive for p in names):
                continue
            t = max(collector.sim_t_ns, 0) / 1e9
            if not any(p in self.seen for p in names):
                if now - since < a.external_timeout:
                    continue
                self.say(f"external role {role} never announced itself within {a.external_timeout:g} s "
                         f"(--external-timeout); start it with `zenswarm up SCENARIO --only {role} --swarm {a.swarm} "
                         f"--connect {self.connect_endpoints[0]}`; aborting")
                self.deaths.append({"process": role, "how": f"never announced itself within {a.external_timeout:g} s", "sim_time_s": t})
                self.failed = role
                return EXIT_PROCESS_FAILED
            gone = max((g for p in names if (g := self.gone_at.get(p)) is not None), default=None)
            if gone is None or now - gone[0] < EXTERNAL_GONE_GRACE_S or self._role_ended_normally(role, collector):
                continue
            t = gone[1] / 1e9
            self.say(f"process {role} died (external: its liveliness token went away) at sim time {t:.2f} s")
            self.deaths.append({"process": role, "how": "liveliness token gone (external)", "sim_time_s": t})
            if self.policy.enabled and self.policy.allows(role):
                self.say(f"{role} is external: this supervisor did not start it and cannot restart it; aborting the mission")
            self.failed = role
            return EXIT_PROCESS_FAILED
        return None

    def _child_state(self, name: str, c: Child) -> str:
        """One of our roles for the progress line: up, exit N, leaving or starting. The simulated
        MAVLink vehicles have no Zenoh session (no liveliness token): they are up while their
        process runs and the bridge reports a vehicle past ``connecting`` (it hears them)."""
        if name in self.alive:
            return "up"
        if c.returncode is not None:
            return "exit " + str(c.returncode)
        if name == "vehicles" and c.proc.poll() is None and self._bridge_hears_vehicles():
            return "up"
        return "leaving" if name in self.seen else "starting"

    def _bridge_hears_vehicles(self) -> bool:
        """The bridge's last diag shows a UAV past ``connecting`` (``phases`` = "1:ready,...")."""
        d = self.collector.diag.get("bridge", {}) if self.collector is not None else {}
        phases = str(d.get("phases", ""))
        return any(p.partition(":")[2] not in ("", "connecting") for p in phases.split(","))

    def _vehicles_figures(self, collector: Collector) -> dict[str, Any] | None:
        """results.json ``vehicles``: the MAVLink vehicles as the bridge last reported them
        (phases, armed/airborne/unhealthy counts, worst link latency and state age in ms, -1 if
        unmeasured; the Crazyflie bridge's positioning and oldest fed position's age, ms) and the
        vehicles process's exit status; None without ``--plant mavlink``."""
        if "vehicles" not in self.children and "bridge" not in collector.diag:
            return None
        d = collector.diag.get("bridge", {})
        keys = ("phases", "armed_uavs", "airborne_uavs", "unhealthy_uavs", "max_latency_ms", "max_state_age_ms", "refused", "link_lost",
                "positioning", "max_extpos_age_ms")  # fmt: skip
        out: dict[str, Any] = {k: d[k] for k in keys if k in d}
        c = self.children.get("vehicles")
        if c is not None:
            out["process_exit"] = c.status()
        return out

    def _health(self) -> str:
        """The roles' states for the progress line: ours (up, starting, leaving, exit N) and the external
        ones (waiting until their token appears, up, gone)."""
        out = [f"{name}:{self._child_state(name, c)}" for name, c in self.children.items()]
        for role in self.external_roles():
            names = self._token_names(role)
            state = "up" if any(p in self.alive for p in names) else ("gone" if any(p in self.seen for p in names) else "waiting")
            out.append(f"{role}:{state}(external)")
        return " ".join(out)

    def _watch(self, collector: Collector) -> int:
        """Watch the flight until it ends; returns the exit code so far (see :meth:`_finish`)."""
        last_check = 0.0
        wall0 = time.monotonic()
        a, sc = self.args, self.sc
        progress = SwarmProgress(sc.leader.goal, sc.timing.time_limit_s, a.progress_every, a.quiet, self.say, wall0)
        tap = self._live_tap()
        while True:
            collector.poll(self._bus_sub, tap)
            if self.live is not None:
                self.live.maybe_publish(time.monotonic())
            if self.stop.is_set():
                self.say(f"stopping: {self.stop_reason}")
                return EXIT_INTERRUPTED
            now = time.monotonic()
            done, code = self._check_children(collector, now)
            self._external_plugin_failures(collector)
            if code == EXIT_PLUGIN_FAILED or self.plugin_failures:
                return self._drain_plugin_failures(collector)
            if code is None:
                code = self._watch_external(collector, now, wall0)
            if code is not None:
                return code
            if done:
                self._await_last_tick(collector)
                return EXIT_OK
            self._inject_kills(collector)
            if now - last_check >= LIVE_CHECK_S:
                last_check = now
                end = self.watch.look(collector)  # has the flight's outcome been decided (or, --stop-at-goal, the goal)?
                if end is not None:
                    self.say(end.why)
                    return EXIT_OK
            progress(time.monotonic(), collector.sim_t_ns, collector.leader_q, self._health)
            gc_safe_point()
            time.sleep(0.05)

    def _await_last_tick(self, collector: Collector) -> None:
        """Lockstep, every process done: a process's last messages (the last ticks' clock, refs and
        commands) are sent as it exits and may still be on their way through the router, so poll
        until the last tick flown (:meth:`Collector.last_tick_flown`) is complete, at most
        ``--lockstep-timeout``. Without this wait a loaded machine judged a series whose last ticks
        were partly missing (NaN where the simulator has values). Realtime: nothing to wait for (a
        tick without a message holds the previous value)."""
        if self.args.realtime or collector.sim_t_ns < 0:
            return
        deadline = time.monotonic() + self.args.lockstep_timeout
        while not collector.tick_complete(last := collector.last_tick_flown()):
            if time.monotonic() > deadline or self.stop.is_set():
                self.say(f"the messages of tick {last} did not all arrive within {self.args.lockstep_timeout:g} s "
                         "(--lockstep-timeout) after the processes ended; judging what arrived")
                return
            time.sleep(0.01)
            collector.poll(self._bus_sub, self._live_tap())

    def _live_tap(self) -> Any:
        """The live view's feed (``--live``), else None."""
        return self.live.feed if self.live is not None else None

    def _check_children(self, collector: Collector, now: float) -> tuple[bool, int | None]:
        """One look at the processes started here (restarting those due): (all done, exit code
        if one died for good, else None). The recorder and the vehicles never keep the run going."""
        done = True
        for c in list(self.children.values()):
            if c.name in self.restart_at:
                done = False
                self._restart_if_due(c, now)
                continue
            rc = c.proc.poll()
            if rc is None:
                if c.name not in ("recorder", "vehicles"):  # both are stopped once the rest is done
                    done = False
                continue
            if c.returncode is not None:
                continue
            c.returncode = rc
            if c.name == "recorder":  # any exit before the end is a loss, never a failure
                self._recorder_died(c, rc, collector)
                continue
            if rc == EXIT_PLUGIN_FAILED and self._took_plugin_failure(c):
                return done, EXIT_PLUGIN_FAILED
            if rc != 0:
                code = self._child_died(c, rc, collector, now)
                if code is not None:
                    return done, code
                done = False
        return done, None

    def _took_plugin_failure(self, c: Child) -> bool:
        """A child that exited with 4: did it report its plug-in's failure
        (:data:`zenswarm.process.runtime.PLUGIN_FAILURE_MARK`, read by :meth:`_pump`)? If not, it died."""
        c.join_output(5.0)  # its last lines: the output ends with the process
        return any(f.process == c.name for f in self.plugin_failures)

    def _external_plugin_failures(self, collector: Collector) -> None:
        """A role on another host (``--external``) reports its plug-in's failure in its
        diagnostics (:func:`zenswarm.process.runtime.report_plugin_failure`): take it as a child's line."""
        for name in self.external_roles():
            text = (collector.diag.get(name) or {}).get("plugin_failure")
            if not isinstance(text, str) or any(f.process == name for f in self.plugin_failures):
                continue
            try:
                f = PluginFailure.from_dict(json.loads(text))
            except (ValueError, KeyError, TypeError, AssertionError):
                continue
            self.plugin_failures.append(f)
            self.say(f"plug-in failed on {name}: {f}")

    def _drain_plugin_failures(self, collector: Collector) -> int:
        """A plug-in failed: wait until the flight before it is complete and every process
        that could fail in the same (tick, stage) has either given its output of that stage or
        failed too (the processes run concurrently; the simulator calls them in turn), then
        judge: the ticks before the failed one, unless the outcome was decided before it (as
        the simulator: :meth:`EndWatch.plugin_failed`). Returns 4, or 0 when the run was decided before."""
        deadline = time.monotonic() + self.args.lockstep_timeout + 10.0
        while True:
            collector.poll(self._bus_sub, self._live_tap())
            for c in list(self.children.values()):
                rc = c.proc.poll()
                if rc is not None and c.returncode is None:
                    c.returncode = rc
                    if rc == EXIT_PLUGIN_FAILED:
                        self._took_plugin_failure(c)  # its last lines read
            self._external_plugin_failures(collector)
            first = first_failures(self.plugin_failures)
            if self._resolved(collector, first) or self.stop.is_set():
                break
            if time.monotonic() > deadline:
                self.say("not every process gave its output of the failed tick in time; judging what arrived")
                break
            time.sleep(0.02)
        end = self.watch.plugin_failed(collector, first[0].tick)
        if not end.plugin_failed:  # decided before the plug-in failed: the run had ended there
            self.plugin_failures = []
            self.say(end.why)
            return EXIT_OK
        self.plugin_failures = first
        return EXIT_PLUGIN_FAILED

    def _resolved(self, collector: Collector, first: list[PluginFailure]) -> bool:
        """Lockstep: the ticks before the failed one are complete and every other process has
        passed the failed (tick, stage) or failed in it. Realtime: at once (ticks are held)."""
        if self.args.realtime:
            return True
        k, stage = first[0].order
        failed = {f.process for f in first}
        exited = {name for name, c in self.children.items() if c.returncode is not None}
        if stage == STAGE_BUILD:
            return all(r in self.seen or r in exited or r in failed for r in self.roles())
        if k > 0 and not collector.tick_complete(k - 1):
            return False
        if stage in (STAGE_SHARE, STAGE_STEP) and k < collector.T:
            have = collector.outputs_of_tick("ref" if stage == STAGE_SHARE else "cmd", k)
            agents = [wire.agent(i + 1) for i in range(self.sc.n)]
            return all(have[i] or a in failed or a in exited for i, a in enumerate(agents))
        return True

    def _restart_if_due(self, c: Child, now: float) -> None:
        if now >= self.restart_at[c.name]:
            del self.restart_at[c.name]
            self.restarts[c.name] = self.restarts.get(c.name, 0) + 1
            self.say(f"restarting {c.name} (restart {self.restarts[c.name]} of {self.policy.max_restarts})")
            self.spawn(c.name)

    def _child_died(self, c: Child, rc: int, collector: Collector, now: float) -> int | None:
        """A process of ours exited with status ``rc`` != 0: schedule its restart (None) when the
        policy allows, else the exit code (3)."""
        how = f"killed by {signal.Signals(-rc).name}" if rc < 0 else f"exit status {rc}"
        how = getattr(c.proc, "lost", None) or how  # --scheduler: its worker was lost (zenswarm.compose.cluster)
        c.join_output(1.0)  # its output ended with it: its last lines are read at once
        tail = "; last output: " + " | ".join(c.lines[-3:]) if c.lines else ""
        t_s = max(collector.sim_t_ns, 0) / 1e9  # when the collector's clock (a few ticks behind, loaded) saw it
        k = self.self_killed.pop(c.name, None)
        if k is not None and rc == -signal.SIGKILL and any(ln.endswith(kill_self_line(k)) for ln in c.lines[-3:]):
            t_s = k * self.sc.timing.dt  # --kill in lockstep: it killed itself just before this tick
        self.say(f"process {c.name} died ({how}) at sim time {t_s:.2f} s{tail}")
        self.deaths.append({"process": c.name, "how": how, "sim_time_s": t_s})
        delay = self.policy.delay(self.restarts.get(c.name, 0)) if self.policy.allows(c.name) else None
        if delay is not None:
            self.restart_at[c.name] = now + delay
            self.say(f"{c.name} will be restarted in {delay:.2f} s")
            return None
        if self.policy.enabled and self.policy.allows(c.name):
            self.say(f"{c.name}: restart limit ({self.policy.max_restarts}) reached; aborting the mission")
        self.failed = c.name
        return EXIT_PROCESS_FAILED

    def _inject_kills(self, collector: Collector) -> None:
        """``--kill ROLE@T``: SIGKILL each role whose time has come (sim time)."""
        for role, at_ns in list(self.pending_kills.items()):
            if collector.sim_t_ns >= at_ns and role in self.children and self.children[role].proc.poll() is None:
                self.say(f"injecting SIGKILL into {role} at sim time {collector.sim_t_ns / 1e9:.2f} s (--kill)")
                self.children[role].proc.kill()
                del self.pending_kills[role]

    def _finish(self, collector: Collector, code: int, out: Path) -> int:
        """Judge the flight, write OUT/results.json and OUT/timeseries.npz (and the report with
        ``--report``); the exit code: ``code`` if not 0, else 0 or 1 by the verdict."""
        sc = self.sc
        # realtime, or a process that was down: a tick without a message holds the previous value
        fill = self.args.realtime or bool(self.deaths)
        stopped = code not in (EXIT_OK, EXIT_PLUGIN_FAILED)  # by a dead process or a signal: judge the ticks flown
        ts = collector.series(self.watch.judged_ticks(collector, stopped, fill), fill=fill)
        collector.close()  # every sample is in the series: free the spool
        dead = getattr(self, "failed", "?")  # exit 3: the process that died for good
        how = next((d["how"] for d in reversed(self.deaths) if d["process"] == dead), "unknown")
        res = flight_results(
            ts, sc, wall_time_s=time.monotonic() - self.t_start, full_time=self.args.full_time, faults=self.args.faults.plan(sc),
            facts=self._run_facts(collector), died=(dead, how) if code == EXIT_PROCESS_FAILED else None,
            interrupted=self.stop_reason if code == EXIT_INTERRUPTED else None,
            plugin_failures=self.plugin_failures if code == EXIT_PLUGIN_FAILED else (),
        )  # fmt: skip
        write_outputs(out, ts, res)
        for line in closing_lines(res, out):
            self.say(line)
        if self.args.record is not None and self.args.report:
            self._report(out, self.args.record)
        if code != EXIT_OK:
            return code
        return EXIT_OK if res["success"] else EXIT_MISSION_FAILED

    def _run_facts(self, collector: Collector) -> dict[str, Any]:
        """What results.json says of the run beside the verdict: mode, processes, recording, diagnostics."""
        a = self.args
        res: dict[str, Any] = {
            "mode": "realtime" if a.realtime else "lockstep",
            "swarm": a.swarm,
            "router": list(self.listen),  # the endpoints the router listened on (its port: chosen free without --listen)
            # a child stopped by terminate_all has its code on its process only (returncode is set when one dies)
            "processes": {name: c.status() for name, c in self.children.items()},
            "where": {name: c.proc.where() if hasattr(c.proc, "where") else {"host": socket.gethostname(), "pid": c.proc.pid}
                      for name, c in self.children.items()},  # fmt: skip
            "vehicles": self._vehicles_figures(collector),
            "process_deaths": self.deaths,
            "restarts": self.restarts,
            **({"scheduler": a.scheduler, "lost_workers": self.cluster.lost} if self.cluster is not None else {}),
            **collector.facts(),  # failsafe, diagnostics, decoder_rejects, foreign_samples
            "supervisor_zenoh_threads": bus.zenoh_threads(),  # the router's (ZENOH_RUNTIME_ROUTER)
        }
        if a.record is not None:
            res["recording"] = str(a.record)
            if self.recording_loss is not None:
                res["recording_loss"] = self.recording_loss
        return res

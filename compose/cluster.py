"""The roles of a swarm started on a Dask cluster: ``zenswarm up --scheduler tcp://HOST:8786``.

Two halves, one per side of the Dask connection:

- :class:`RoleHost`, on each worker: a Dask actor that owns the role processes started there.
  It forks them from one thread of its own that lives as long as they do (``PR_SET_PDEATHSIG``
  fires when the *thread* that forked a child ends: when the worker dies, its roles die with
  it), reads their output, and runs a watchdog: when the supervisor stops calling (its heartbeat,
  :data:`HEARTBEAT_LOST_S`), the client disconnected or was SIGKILLed, it ends every child
  (SIGTERM, then SIGKILL) and deletes the credentials it was sent.
- :class:`Cluster`, in the supervisor: connects to the scheduler, lists its workers, plans where
  each role runs (:mod:`zenswarm.compose.placement`), creates one :class:`RoleHost` per worker and
  polls them all from one thread (the heartbeat; each poll brings every child's new output lines
  and exit status). Each started role is a :class:`DaskProc`, the :class:`zenswarm.compose.children.Proc`
  the supervisor watches as it watches a local one. A worker that stops answering is lost
  (:data:`HOST_LOST_S`): each of its roles ends as killed, with :attr:`DaskProc.lost` saying so.

In secure mode a role's credentials travel with its start (only its own directory of the key
tree, :func:`zenswarm.process.security.process_dir`): the worker writes them into a private
temporary directory (0700, files 0600) and removes it when the role ends.

Dask itself is imported only by the supervisor's half (``zenswarm[sweep]``, as ``zenswarm sweep
--scheduler``); a worker imports this module to run :class:`RoleHost`.
"""

from __future__ import annotations

import contextlib
import os
import queue
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from zenswarm.compose.children import Child, pdeathsig
from zenswarm.compose.placement import Rule, Worker, parse_rule, plan, replace, rules_by_role
from zenswarm.errors import ScenarioError
from zenswarm.process import security
from zenswarm.process.settings import RoleSettings, encode

__all__ = ["RoleHost", "Cluster", "DaskProc", "connect", "local_address", "HEARTBEAT_LOST_S", "HOST_LOST_S"]

POLL_S = 0.1
"""Wall seconds between two polls of every worker (the heartbeat)."""

HEARTBEAT_LOST_S = 6.0
"""A worker ends its roles when no call came for this long (the supervisor is gone or cut off)."""

HOST_LOST_S = 4.0
"""The supervisor counts a worker lost when a poll gets no answer within this long (or fails);
shorter than :data:`HEARTBEAT_LOST_S`, so a worker slow to answer is declared lost (its roles
named) before its watchdog ends them. Each worker is polled from a thread of its own."""

CONNECT_TIMEOUT_S = 5.0
"""How long the supervisor tries to reach the scheduler (and a new worker) before exit 2."""

TERM_GRACE_S = 2.0
"""The watchdog's grace between SIGTERM and SIGKILL of a role."""


# ============================================================================ the worker's side

_KEYS_DIR = re.compile(r"^zenswarm-.+-w(\d+)-[^-]+$")


def sweep_stale_keys(tmp: Path | None = None) -> list[Path]:
    """Remove the credentials left in this host's temporary directory by a worker that was killed
    (it could not remove them: ``zenswarm-<swarm>-w<pid>-*`` whose worker pid is gone); run by each
    new :class:`RoleHost`. The directories removed."""
    gone = []
    for d in Path(tmp or tempfile.gettempdir()).glob("zenswarm-*-w*-*"):
        m = _KEYS_DIR.match(d.name)
        if m is None or not d.is_dir():
            continue
        try:
            os.kill(int(m.group(1)), 0)
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
            gone.append(d)
        except PermissionError:  # another user's worker, alive
            pass
    return gone


class RoleHost:
    """The role processes of one supervisor on one worker (a Dask actor: ``client.submit(RoleHost,
    ..., actor=True, workers=[address])``). Every method is called by the supervisor's
    :class:`Cluster`; each call counts as a heartbeat."""

    def __init__(self, swarm: str, heartbeat_lost_s: float = HEARTBEAT_LOST_S) -> None:
        self.swarm = swarm
        self.heartbeat_lost_s = heartbeat_lost_s
        self.last_call = time.monotonic()
        self.procs: dict[int, subprocess.Popen[str]] = {}
        self.readers: dict[int, threading.Thread] = {}
        self.lines: dict[int, list[str]] = {}
        self.key_dirs: dict[int, Path] = {}
        self.lock = threading.Lock()
        self.closed = threading.Event()
        sweep_stale_keys()
        self.keys_root = Path(tempfile.mkdtemp(prefix=f"zenswarm-{swarm}-w{os.getpid()}-"))  # 0700: mkdtemp's own mode
        self._starts: queue.Queue[tuple[Callable[[], Any], Future[Any]] | None] = queue.Queue()
        threading.Thread(target=self._forker, name="zenswarm-forker", daemon=True).start()
        threading.Thread(target=self._watchdog, name="zenswarm-watchdog", daemon=True).start()

    # ---------------------------------------------------------------- threads
    def _forker(self) -> None:
        """The one thread that forks the roles (their PR_SET_PDEATHSIG is tied to it): it runs
        until the host is closed and every child it started has ended."""
        while True:
            try:
                job = self._starts.get(timeout=0.5)
            except queue.Empty:
                if self.closed.is_set() and not self._running():
                    return
                continue
            if job is None:
                continue
            fn, fut = job
            try:
                fut.set_result(fn())
            except BaseException as e:  # noqa: BLE001 - handed to the caller
                fut.set_exception(e)

    def _watchdog(self) -> None:
        """Ends every role when the supervisor stopped calling (heartbeat lost), then closes."""
        while not self.closed.is_set():
            time.sleep(0.2)
            if time.monotonic() - self.last_call > self.heartbeat_lost_s:
                print(f"zenswarm: no call from the supervisor of swarm {self.swarm} for {self.heartbeat_lost_s:g} s: "
                      "ending its roles", file=sys.stderr, flush=True)  # fmt: skip
                self.close()
                return

    def _running(self) -> bool:
        with self.lock:
            return any(p.poll() is None for p in self.procs.values())

    # ---------------------------------------------------------------- calls
    def info(self) -> dict[str, Any]:
        """This worker's host name, its pid and Python, and the directory credentials go to."""
        self.last_call = time.monotonic()
        return {"host": socket.gethostname(), "pid": os.getpid(), "python": sys.executable, "keys_root": str(self.keys_root)}

    def start(self, role: str, argv: list[str], stdin: bytes, env: dict[str, str], files: dict[str, bytes]) -> int:
        """Start ``python -m zenswarm ARGV`` (this worker's Python) with ``stdin`` on its
        standard input, the worker's environment updated with ``env``; ``files`` (name -> bytes):
        the role's credentials, written to ``keys_root/<role>``. Returns its pid."""
        self.last_call = time.monotonic()
        if self.closed.is_set():
            raise RuntimeError(f"the role host of swarm {self.swarm} is closed")
        key_dir = None
        if files:
            key_dir = self.keys_root / security.process_slug(role)
            shutil.rmtree(key_dir, ignore_errors=True)
            key_dir.mkdir(mode=0o700)
            for name, data in files.items():
                f = key_dir / Path(name).name
                f.write_bytes(data)
                f.chmod(0o600)

        def fork() -> subprocess.Popen[str]:
            with tempfile.TemporaryFile() as fin:  # a file of its own, already gone from the disk
                fin.write(stdin)
                fin.seek(0)
                return subprocess.Popen(
                    [sys.executable, *argv], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=fin, text=True,
                    start_new_session=True, preexec_fn=pdeathsig, env={**os.environ, **env},
                )  # fmt: skip

        fut: Future[subprocess.Popen[str]] = Future()
        self._starts.put((fork, fut))
        p = fut.result(timeout=30)
        self.last_call = time.monotonic()
        with self.lock:
            self.procs[p.pid] = p
            self.lines[p.pid] = []
            if key_dir is not None:
                self.key_dirs[p.pid] = key_dir
        t = threading.Thread(target=self._pump, args=(p,), name=f"zenswarm-out-{role}", daemon=True)
        self.readers[p.pid] = t
        t.start()
        return p.pid

    def _pump(self, p: subprocess.Popen[str]) -> None:
        assert p.stdout is not None
        for raw in p.stdout:
            with self.lock:
                self.lines[p.pid].append(raw.rstrip("\n"))
        p.wait()
        kd = self.key_dirs.pop(p.pid, None)
        if kd is not None:
            shutil.rmtree(kd, ignore_errors=True)

    def poll(self) -> dict[int, tuple[int | None, list[str]]]:
        """pid -> (exit status once it ended and its output was read to the end, else None; the
        output lines since the last poll). The heartbeat."""
        self.last_call = time.monotonic()
        out: dict[int, tuple[int | None, list[str]]] = {}
        with self.lock:
            for pid, p in list(self.procs.items()):
                rc = p.poll()
                r = self.readers.get(pid)
                ended = rc is not None and (r is None or not r.is_alive())
                lines, self.lines[pid] = self.lines[pid], []
                out[pid] = (rc if ended else None, lines)
                if ended:
                    del self.procs[pid]
                    self.readers.pop(pid, None)
                    self.lines.pop(pid, None)
        return out

    def signal(self, pid: int, sig: int) -> None:
        """Send ``sig`` to a role started here (nothing if it has ended)."""
        self.last_call = time.monotonic()
        with self.lock:
            p = self.procs.get(pid)
        if p is not None and p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                p.send_signal(sig)

    def close(self) -> None:
        """End every role (SIGTERM, SIGKILL after :data:`TERM_GRACE_S`) and delete the credentials;
        the forker thread ends once they have."""
        self.closed.set()
        with self.lock:
            procs = list(self.procs.values())
        for p in procs:
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + TERM_GRACE_S
        for p in procs:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        shutil.rmtree(self.keys_root, ignore_errors=True)


# ============================================================================ the supervisor's side


def connect(address: str, timeout: float = CONNECT_TIMEOUT_S) -> Any:
    """A :class:`distributed.Client` of the scheduler at ``address``; ScenarioError naming
    ``--scheduler`` (exit 2) when distributed is missing or the scheduler cannot be reached."""
    try:
        import distributed
    except ImportError:
        raise ScenarioError("--scheduler", "needs dask distributed: pip install 'zenswarm[sweep]'") from None
    try:
        # the default client of this process: an actor's proxy finds its client through it
        return distributed.Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as e:
        raise ScenarioError("--scheduler", f"cannot reach the Dask scheduler at {address}: {e}") from None


def workers_of(client: Any) -> list[Worker]:
    """The scheduler's workers, ordered by name."""
    try:
        info = client.scheduler_info(n_workers=-1)
    except TypeError:  # distributed before 2025: every worker, no argument
        info = client.scheduler_info()
    ws = [Worker(address=a, name=str(d.get("name", a)), host=str(d.get("host", "")), resources=dict(d.get("resources") or {}))
          for a, d in info.get("workers", {}).items()]  # fmt: skip
    return sorted(ws, key=lambda w: (w.name, w.address))


def local_address(host: str) -> bool:
    """Whether ``host`` (an IP address) is loopback or an address of this machine (network
    namespace): a socket can be bound to it here."""
    if host.startswith("127.") or host in ("::1", "localhost"):
        return True
    try:
        fam = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(fam, socket.SOCK_DGRAM) as s:
            s.bind((host, 0))
        return True
    except OSError:
        return False


@dataclass
class _Host:
    """One worker in use: its actor (None until created), what it said of itself, whether lost."""

    worker: Worker
    actor: Any = None
    future: Any = None  # the actor's future: the actor lives on the worker as long as it is held
    info: dict[str, Any] | None = None
    lost: str | None = None


class DaskProc:
    """A role started on a Dask worker (:class:`zenswarm.compose.children.Proc`): its exit status
    and output come from the :class:`Cluster`'s polls, signals go through the worker's :class:`RoleHost`."""

    def __init__(self, cluster: Cluster, host: _Host, role: str, pid: int) -> None:
        self.cluster, self.host, self.role, self.pid = cluster, host, role, pid
        self.returncode: int | None = None
        self.lost: str | None = None  # why the worker is gone (host lost), else None
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.ended = threading.Event()

    def where(self) -> dict[str, Any]:
        """results.json ``where``: the worker (address, name), its host name and the role's pid."""
        info = self.host.info or {}
        return {"worker": self.host.worker.address, "worker_name": self.host.worker.name,
                "host": info.get("host", self.host.worker.host), "pid": self.pid}  # fmt: skip

    def deliver(self, rc: int | None, lines: list[str]) -> None:
        """What a poll brought: new output lines, and the exit status once it ended."""
        for line in lines:
            self.lines.put(line)
        if rc is not None:
            self._end(rc)

    def _end(self, rc: int, lost: str | None = None) -> None:
        if self.ended.is_set():
            return
        self.lost = lost
        self.returncode = rc
        self.lines.put(None)
        self.ended.set()

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self.ended.wait(timeout):
            raise subprocess.TimeoutExpired(f"{self.role} on {self.host.worker.address}", timeout or 0.0)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.ended.is_set() or self.host.lost is not None:
            return
        try:
            self.host.actor.signal(self.pid, int(sig)).result(timeout=HOST_LOST_S)
        except Exception:  # noqa: BLE001 - the worker is going or gone: the poll thread says so
            pass

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def output(self) -> Iterator[str]:
        while (line := self.lines.get()) is not None:
            yield line


class Cluster:
    """The supervisor's Dask cluster: the workers, the plan of where each role runs, one
    :class:`RoleHost` per worker used, and the poll thread (the heartbeat)."""

    def __init__(self, address: str, rules: tuple[str, ...], say: Callable[[str], None]) -> None:
        self.address = address
        self.rules: list[Rule] = [parse_rule(r) for r in rules]
        self.say = say
        self.client: Any = None
        self.workers: list[Worker] = []
        self.plan: dict[str, str] = {}
        self.by_role: dict[str, Rule] = {}
        self.hosts: dict[str, _Host] = {}
        self.procs: dict[str, dict[int, DaskProc]] = {}  # worker address -> pid -> proc
        self.where: dict[str, str] = {}  # role -> the worker it runs (or last ran) on
        self.lost: list[dict[str, Any]] = []  # the workers lost: {"worker", "host", "roles", "why"}
        self._stop = threading.Event()
        self._lock = threading.Lock()  # the roles' registry, shared by the poll threads and start
        self._early: dict[tuple[str, int], tuple[int | None, list[str]]] = {}  # polled before its start returned
        self._pollers: list[threading.Thread] = []
        self.swarm = ""

    def facts(self) -> dict[str, Any]:
        """What results.json says of the cluster: ``scheduler`` (its address) and ``lost_workers``."""
        return {"scheduler": self.address, "lost_workers": self.lost}

    # ---------------------------------------------------------------- before anything starts
    def open(self, roles: list[str], n: int, listen: list[str], swarm: str) -> None:
        """Connect, list the workers and plan ``roles`` on them; check that the workers can reach
        the router (``listen``). Every error is a ScenarioError (exit 2) and leaves nothing
        running: the client is closed."""
        self.swarm = swarm
        self.client = connect(self.address)
        try:
            self.workers = workers_of(self.client)
            self.by_role = rules_by_role(roles, self.rules, n)
            self.plan = plan(roles, self.workers, self.rules, n)
            self._check_reach(listen)
        except BaseException:
            self.close()
            raise
        used = {w.address for w in self.workers if w.address in self.plan.values()}
        self.hosts = {w.address: _Host(w) for w in self.workers if w.address in used}
        counts = ", ".join(f"{w.name}: {sum(1 for a in self.plan.values() if a == w.address)}" for w in self.workers)
        self.say(f"Dask scheduler {self.address}: {len(self.workers)} workers; roles placed ({counts})")

    def _check_reach(self, listen: list[str]) -> None:
        """A router on loopback only cannot be reached by a worker on another host: exit 2 naming
        --listen, before anything starts."""
        if not all(security.is_loopback_endpoint(e) for e in listen):
            return
        far = [w for w in self.workers if w.address in self.plan.values() and not local_address(w.host)]
        if far:
            names = ", ".join(f"{w.name} ({w.host})" for w in far)
            raise ScenarioError("--listen", f"the router listens on loopback only ({', '.join(listen)}), which the workers "
                                f"{names} cannot reach: give --listen tcp/ADDRESS:PORT, an address of this host they reach")

    def _host(self, address: str) -> _Host:
        """The worker's :class:`RoleHost` (created on first use)."""
        h = self.hosts.setdefault(address, _Host(next(w for w in self.workers if w.address == address)))
        if h.actor is None:
            fut = self.client.submit(RoleHost, self.swarm, actor=True, workers=[address], allow_other_workers=False, pure=False,
                                     key=f"zenswarm-{self.swarm}-rolehost-{os.urandom(4).hex()}")  # fmt: skip
            try:
                h.actor = fut.result(timeout=30)
                h.info = h.actor.info().result(timeout=30)
            except Exception as e:
                self._lose(h, f"could not start its role host: {e!r}")
                raise
            h.future = fut
            t = threading.Thread(target=self._poll_loop, args=(h,), name=f"zenswarm-poll-{h.worker.name}", daemon=True)
            self._pollers.append(t)
            t.start()
        return h

    # ---------------------------------------------------------------- starting roles
    def start(self, role: str, settings: RoleSettings, argv: list[str], env: dict[str, str]) -> Child:
        """Start ``role`` (``argv``: after the interpreter, ``-m zenswarm ...``) on its worker:
        the planned one, or, restarted after its worker was lost, another its rule allows. The
        settings' credentials (secure mode) travel with it. A role that cannot be placed (its
        worker lost, none other allowed) or started ends at once as lost."""
        addr = self.where.get(role, self.plan.get(role))
        planned = self.hosts.get(addr) if addr is not None else None
        if addr is None or (planned is not None and planned.lost is not None):
            with contextlib.suppress(Exception):  # workers may have joined since (a nanny's restart, a new job)
                self.workers = workers_of(self.client)
            live = [w for w in self.workers if self.hosts.get(w.address) is None or self.hosts[w.address].lost is None]
            addr = replace(role, self.by_role.get(role), live, self.where)
        if addr is None:
            return self._lost_child(role, "no live worker its --placement allows")
        try:
            h = self._host(addr)
            files: dict[str, bytes] = {}
            if settings.keys is not None:
                d = security.process_dir(role, settings.keys)
                files = {f.name: f.read_bytes() for f in sorted(d.iterdir()) if f.is_file()}
                settings = msgspec.structs.replace(settings, keys=Path(str((h.info or {})["keys_root"])) / security.process_slug(role))
            pid = h.actor.start(role, argv, encode(settings), env, files).result(timeout=60)
        except Exception as e:  # noqa: BLE001 - the worker failed to start it: the role died
            return self._lost_child(role, f"could not start on worker {addr}: {e!r}")
        proc = DaskProc(self, h, role, pid)
        with self._lock:
            self.procs.setdefault(addr, {})[pid] = proc
            early = self._early.pop((addr, pid), None)
        if early is not None:
            proc.deliver(*early)
        self.where[role] = addr
        return Child(role, proc, time.monotonic())

    def _lost_child(self, role: str, why: str) -> Child:
        h = _Host(Worker("", "", ""), lost=why)
        proc = DaskProc(self, h, role, -1)
        proc._end(-signal.SIGKILL, f"not started: {why}")
        return Child(role, proc, time.monotonic())

    # ---------------------------------------------------------------- the heartbeat
    def _poll_loop(self, h: _Host) -> None:
        """One worker's polls (a thread per worker: one that hangs delays no other's heartbeat)."""
        while not self._stop.is_set() and h.lost is None:
            try:
                self.poll_once(h)
            except Exception as e:  # noqa: BLE001 - the heartbeat must go on: a dead poll thread would end the worker's roles
                self.say(f"cluster: a poll of worker {h.worker.name} failed: {e!r}")
            self._stop.wait(POLL_S)

    def poll_once(self, h: _Host) -> None:
        """Poll one worker; hand each of its roles its new lines and exit status. A worker whose
        poll fails or gets no answer within :data:`HOST_LOST_S` is lost."""
        try:
            got = h.actor.poll().result(timeout=HOST_LOST_S)
        except Exception as e:  # noqa: BLE001 - a worker that does not answer is lost, whatever the error
            if not self._stop.is_set():
                why = f"no answer within {HOST_LOST_S:g} s" if isinstance(e, TimeoutError) else f"it is gone ({type(e).__name__}: {e})"
                self._lose(h, why)
            return
        with self._lock:
            procs = self.procs.setdefault(h.worker.address, {})
            for pid, (rc, lines) in got.items():
                p = procs.get(pid)
                if p is None:  # started a moment ago: its start has not returned yet
                    early = self._early.setdefault((h.worker.address, pid), (None, []))
                    self._early[(h.worker.address, pid)] = (rc if rc is not None else early[0], early[1] + lines)
                    continue
                p.deliver(rc, lines)

    def _lose(self, h: _Host, why: str) -> None:
        """The worker is gone: each role it held ends as SIGKILLed (the worker's death killed
        it: PR_SET_PDEATHSIG), named host lost."""
        host = (h.info or {}).get("host", h.worker.host)
        with self._lock:
            live = [p for p in self.procs.get(h.worker.address, {}).values() if not p.ended.is_set()]
        roles = [p.role for p in live]
        h.lost = f"host lost: worker {h.worker.name} ({h.worker.address}, host {host}): {why}; it held {', '.join(roles) or 'no role'}"
        self.lost.append({"worker": h.worker.address, "worker_name": h.worker.name, "host": host, "roles": roles, "why": why})
        self.say(h.lost)
        for p in live:
            p._end(-signal.SIGKILL, h.lost)

    # ---------------------------------------------------------------- the end
    def close(self) -> None:
        """Stop polling, end every role still running on every worker, close the client."""
        self._stop.set()
        for t in self._pollers:
            t.join(timeout=HOST_LOST_S + 1)
        closes = []
        for h in self.hosts.values():
            if h.actor is not None and h.lost is None:
                with contextlib.suppress(Exception):
                    closes.append(h.actor.close())
        for f in closes:
            with contextlib.suppress(Exception):
                f.result(timeout=TERM_GRACE_S + 5)
        for procs in self.procs.values():
            for p in procs.values():
                p._end(p.returncode if p.returncode is not None else -signal.SIGKILL)
        if self.client is not None:
            with contextlib.suppress(Exception):
                self.client.close(timeout=5)
            self.client = None

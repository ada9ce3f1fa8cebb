"""``zenswarm verify``: an agent's computation run again on its recording, compared bit for bit.

``zenswarm verify FILE [--agent I|all]`` (also ``zenswarm replay --verify FILE --agent I``)
rebuilds agent I's controller from the recorded scenario (with the run's recorded ``--seed`` and
link-fault flags), feeds it agent I's recorded inputs tick by tick exactly as
:mod:`zenswarm.agents.process` does, and compares what it computes with what the agent published:
bit for bit (:func:`verify_agent`; the first :class:`Difference`). The tool for "why did UAV 2 do
that". No Zenoh: the recording alone. Publishing a recording back onto the bus is
:mod:`zenswarm.bridge.replay.replay`.
"""

from __future__ import annotations

import argparse
import bisect
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from zenswarm.bridge.recording.mcapio import Recording, read_recording
from zenswarm.bridge.replay.playback import original_swarm
from zenswarm.bus import wire
from zenswarm.errors import RecordingError, ScenarioError

__all__ = ["Difference", "VerifyResult", "verify_agent", "add_parser"]


@dataclass
class Difference:
    """First mismatch between the recording and the recomputation."""

    tick: int
    field: str
    recorded: Any
    recomputed: Any

    def __str__(self) -> str:
        return f"tick {self.tick}, {self.field}: recorded {_fmt(self.recorded)} vs recomputed {_fmt(self.recomputed)}"


@dataclass
class VerifyResult:
    agent: int
    ticks: int = 0
    mode: str | None = None
    difference: Difference | None = None
    notes: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.difference is None


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        return f"{x!r} (0x{struct.unpack('<Q', struct.pack('<d', x))[0]:016x})"
    return str(x)


def _same(a: float, b: float) -> bool:
    """Bit-for-bit equality of two float64 values."""
    return struct.pack("<d", a) == struct.pack("<d", b)


def _compare_vec(tick: int, name: str, rec: np.ndarray, new: np.ndarray) -> Difference | None:
    r = np.asarray(rec, dtype=np.float64).reshape(-1)
    n = np.asarray(new, dtype=np.float64).reshape(-1)
    for j in range(len(r)):
        if not _same(float(r[j]), float(n[j])):
            return Difference(tick, f"{name}[{j}]", float(r[j]), float(n[j]))
    return None


def _compare_cmd(tick: int, rec: wire.Cmd, cmd: Any) -> Difference | None:
    if not _same(rec.thrust, float(cmd.thrust)):
        return Difference(tick, "cmd.thrust", rec.thrust, float(cmd.thrust))
    for name in ("rpy", "u", "d_hat"):
        d = _compare_vec(tick, f"cmd.{name}", getattr(rec, name), getattr(cmd, name))
        if d is not None:
            return d
    return None


def _compare_ref(tick: int, rec: wire.Ref, shared: Any) -> Difference | None:
    """ref.q, ref.v and each extra shared quantity (:attr:`zenswarm.bus.wire.Ref.extra`), bit for bit."""
    d = _compare_vec(tick, "ref.q", rec.q, shared.q) or _compare_vec(tick, "ref.v", rec.v, shared.v)
    if d is not None:
        return d
    extra = dict(shared.extra)
    if sorted(extra) != sorted(rec.extra):
        return Difference(tick, "ref.extra", sorted(rec.extra), sorted(extra))
    for name, x in extra.items():
        d = _compare_vec(tick, f"ref.extra.{name}", np.asarray(rec.extra[name]), np.asarray(x))
        if d is not None:
            return d
    return None


def _swarm_of(rec: Recording) -> str:
    if rec.swarm:
        return rec.swarm
    for t in rec.topics():
        s = original_swarm(rec, t)
        if s:
            return s
    for m in rec.messages():
        s = original_swarm(rec, m.topic)
        if s:
            return s
    raise RecordingError(f"{rec.path}: cannot tell the swarm name (no metadata and no swarm/<name>/ topics)")


def _recorded_seed(rec: Recording, sc: Any) -> Any:
    """The scenario with the run's ``--seed`` (recorded with the fault flags) applied: the
    controllers' random streams (:func:`zenswarm.scenario.plugins.plugin_rng`) derive from it."""
    from dataclasses import replace

    from zenswarm.bridge.args import recorded_link_faults

    seed = recorded_link_faults(rec.info.get("fault_args", "[]"), rec.path).seed
    return sc if seed is None else replace(sc, seed=int(seed))


def _fault_plan(rec: Recording, sc: Any) -> Any:
    """The link-fault plan of the recorded run: the scenario's ``[faults]`` table plus the fault
    flags the recorder was given (metadata ``fault_args``). None when no fault was active."""
    from zenswarm.bridge.args import recorded_fault_plan

    return recorded_fault_plan(rec.info.get("fault_args", "[]"), sc, rec.path)


def verify_agent(path: str | Path, agent: int, *, strict: bool = False) -> VerifyResult:
    """Re-run agent ``agent``'s controller on its recorded inputs and compare its outputs.

    Lockstep (and unknown-mode) recordings are replayed as :mod:`zenswarm.agents.process` runs lockstep.
    The agent (re)starts where it published a reference with ``seq == 1`` (normally tick 0; a
    restarted process starts its sequence numbers again): it resets the generator and ESO from
    the state of that tick, and that recorded reference must equal the reset. Then for each tick
    k up to the last recorded command: own state of tick k, neighbours' refs and, if pinned, the
    leader's ref of tick k, holding the newest earlier value when one is missing from the
    recording (as the agent does after a timeout). With link faults (the scenario's ``[faults]``
    table and the recorder's fault flags) every input goes through the same
    :class:`zenswarm.link.swarm.Box` the agent uses, so the same messages are lost or delayed.
    The tick of a message is ``(t + dt_ns // 2) // dt_ns`` as in
    :meth:`zenswarm.process.runtime.SwarmProcess.subscribe`. A restarted agent's first tick is fed no
    inputs of that tick (they were sent before it subscribed): an approximation.
    Realtime recordings: the agent ticked on each new state with the latest inputs; the inputs
    are taken as the newest recorded before the command's receive time (an approximation: a
    difference may come from it; link faults are not replayed there).

    Compares, bit for bit, cmd(k) (thrust, rpy, u, d_hat) and ref(k + 1) (q, v), and stops at the
    first difference. strict: refuse a damaged file (default: verify what is readable and list
    the damage in ``problems``).
    """
    rec = read_recording(path, strict=strict)
    sc = _recorded_seed(rec, rec.load_scenario())
    if not 1 <= agent <= sc.n:
        raise ScenarioError("--agent", f"agent {agent} out of range 1..{sc.n} for scenario {sc.name}")
    v = _Verifier(rec, sc, agent)
    v.res.problems += rec.problems
    dropped = rec.dropped_note()
    if dropped is not None:
        v.res.notes.append(dropped)
    if v.decoder.rejected:
        v.res.notes.append(f"{v.decoder.rejected} recorded payloads of agent {agent}'s keys were rejected by the decoder")
    v.find_starts()
    try:
        if rec.mode == "realtime":
            v.verify_realtime()
        else:
            v.verify_lockstep(_fault_plan(rec, sc))
    except _Differs as e:
        v.res.difference = e.difference
        note = v.timeout_note(e.difference.tick)
        if note is not None:
            v.res.notes.append(note)
    return v.res


class _Differs(Exception):
    """The first difference: ends the verification."""

    def __init__(self, difference: Difference) -> None:
        super().__init__(str(difference))
        self.difference = difference


class _Verifier:
    """Agent ``agent``'s recorded messages, and its controller plug-in (the recorded scenario's
    ``[agents] controller``) fed with them tick by tick (as the agent process feeds it, through
    :func:`zenswarm.agents.api.prepare` and :func:`zenswarm.agents.api.finish`)."""

    def __init__(self, rec: Recording, sc: Any, agent: int) -> None:
        from zenswarm.agents.core import AgentRow
        from zenswarm.scenario.plugins import plant_vehicle

        self.sc = sc
        self.res = VerifyResult(agent=agent, mode=rec.mode)
        self.keys = keys = wire.Keys(_swarm_of(rec))
        self.me = wire.agent(agent)
        params = plant_vehicle(sc)  # the plant model's vehicle (mass, g), as the agent process
        self.row = AgentRow.from_scenario(sc, agent - 1, params.mass, params.g)
        self.quad = params
        self.ctrl = self._new_controller()
        self.dt_ns = wire.t_ns(sc.timing.dt)
        self.state_key, self.ref_key, self.cmd_key = keys.state(agent), keys.ref(agent), keys.cmd(agent)
        self.nbr_keys = [keys.ref(j + 1) for j in self.row.neighbours]
        self.input_keys = self.nbr_keys + ([keys.leader_ref] if self.row.pinned else [])
        self.sender = {self.state_key: "plant", keys.leader_ref: "leader"}
        self.sender.update({keys.ref(j + 1): wire.agent(j + 1) for j in self.row.neighbours})
        self.decoder = wire.Decoder()
        self._read(rec)

    def _read(self, rec: Recording) -> None:
        """Decode the agent's keys: the newest message per (key, tick), each key's timeline and
        the agent's start references (seq 1: a (re)start of the agent process)."""
        wanted = {self.state_key: "state", self.ref_key: "ref", self.cmd_key: "cmd"}
        wanted.update({k: "ref" for k in self.input_keys})
        self.by_tick: dict[str, dict[int, Any]] = {k: {} for k in wanted}
        self.timeline: dict[str, list[tuple[int, int, Any]]] = {k: [] for k in wanted}  # (log_time, tick, msg)
        self.start_refs: dict[int, wire.Ref] = {}
        self.timeout_ticks: list[int] = []
        self.timeouts = 0
        diag_key, diags = self.keys.diag(self.me), wire.Decoder()  # not the inputs' decoder: its counts are said
        dt_ns = self.dt_ns
        for m in rec.messages(topics=lambda t: t in wanted or t == diag_key):
            if m.topic == diag_key:
                d = diags.decode(m.topic, "diag", m.payload)
                if isinstance(d, wire.Diag):
                    self._timeout_tick(d)
                continue
            msg = self.decoder.decode(m.topic, wanted[m.topic], m.payload)
            if msg is None:
                continue
            k = (msg.t + dt_ns // 2) // dt_ns
            if m.topic == self.ref_key and isinstance(msg, wire.Ref) and msg.seq == 1:
                self.start_refs[k] = msg
            else:
                self.by_tick[m.topic][k] = msg  # the latest wins, as in the inbox
            self.timeline[m.topic].append((m.log_time, k, msg))
        self.cmds = self.by_tick[self.cmd_key]
        if not self.cmds:
            raise RecordingError(f"{rec.path}: no commands of agent {self.res.agent} ({self.cmd_key}) in the recording")
        self.last = max(self.cmds)
        self.refs = self.by_tick[self.ref_key]  # references published after a tick (seq > 1)
        self.states = self.by_tick[self.state_key]

    def _timeout_tick(self, d: wire.Diag) -> None:
        """Take one of the agent's diagnostics: the tick at which it waited out
        ``--lockstep-timeout`` and ticked on held inputs (``lockstep_timeout_tick``), and how
        often it did (``input_timeouts``; an agent of an older zenswarm says only that)."""
        k = d.info.get("lockstep_timeout_tick")
        if isinstance(k, int) and not isinstance(k, bool):
            self.timeout_ticks.append(k)
        self.timeouts = max(self.timeouts, int(d.counters.get("input_timeouts", 0)))

    def timeout_note(self, tick: int) -> str | None:
        """Why a difference at ``tick`` is expected: the agent waited out the lockstep timeout
        at or before it (its inputs then were not the recording's), or None."""
        before = sorted(k for k in set(self.timeout_ticks) if k <= tick)
        why = ("and ticked on the inputs it held (its diagnostics); the messages it did not wait for are in the "
               "recording, so the recomputation differs from there on: a starved or stalled process, not the controller")
        if before:
            more = f" (and {len(before) - 1} more)" if len(before) > 1 else ""
            return f"agent {self.res.agent} waited out --lockstep-timeout at tick {before[0]}{more} {why}"
        if self.timeouts > len(set(self.timeout_ticks)):  # counted, but not when
            return f"agent {self.res.agent} waited out --lockstep-timeout {self.timeouts} times in this flight {why}"
        return None

    def find_starts(self) -> None:
        """The ticks where the agent (re)started (its references with seq 1)."""
        self.starts = sorted(self.start_refs)
        if not self.starts:
            self.starts = [min(self.cmds)]
            self.res.notes.append(f"the agent's start reference (seq 1) is not in the recording; starting at tick {self.starts[0]}")
        if len(self.starts) > 1:
            self.res.notes.append(f"the agent (re)started at ticks {self.starts}")

    def state(self, k: int) -> wire.State:
        st = self.states.get(k)
        if st is None:
            raise _Differs(Difference(k, "input state", "<missing from the recording>", "needed to compute the tick"))
        return st

    def _new_controller(self) -> Any:
        from zenswarm.agents.api import make_controller

        return make_controller(self.sc, self.res.agent - 1, self.quad.mass, self.quad.g)

    def compute(self, k: int, st: wire.State, inputs: dict[str, Any], seg_end: int) -> None:
        """Tick k exactly as the agent process ticks (:func:`zenswarm.agents.api.prepare`, then
        :func:`zenswarm.agents.api.finish` with the nominal dt), then compare cmd(k) and ref(k + 1)."""
        from zenswarm.agents.api import finish, prepare

        ctrl = self.ctrl
        nbr = [inputs.get(key) for key in self.nbr_keys]
        cmd = finish(ctrl, st.q, st.v, prepare(ctrl, nbr, inputs.get(self.keys.leader_ref)), self.sc.timing.dt)
        shared = ctrl.share()
        q_ref = shared.q
        rc = self.cmds.get(k)
        if rc is None:
            raise _Differs(Difference(k, "cmd", "<missing from the recording>", f"thrust={float(cmd.thrust)!r}"))
        d = _compare_cmd(k, rc, cmd)
        if d is None:
            rr = self.refs.get(k + 1)
            if rr is None and k == seg_end:
                self.res.notes.append(f"ref of tick {k + 1} (after the last command of a run) is not in the recording")
            elif rr is None:
                d = Difference(k + 1, "ref", "<missing from the recording>", f"q={q_ref.tolist()}")
            else:
                d = _compare_ref(k + 1, rr, shared)
        if d is not None:
            raise _Differs(d)
        self.res.ticks += 1

    def restart(self, k: int, st: wire.State) -> None:
        """(Re)start the controller (a fresh one, as a restarted process builds) from the state of
        tick k; the recorded start reference of tick k, if any, must equal its share()."""
        if self.ctrl.initialised:
            self.ctrl = self._new_controller()
        self.ctrl.reset(st.q, st.v)
        r0 = self.start_refs.get(k)
        d = None if r0 is None else _compare_ref(k, r0, self.ctrl.share())
        if d is not None:
            raise _Differs(d)

    # ------------------------------------------------------------------ realtime
    def verify_realtime(self) -> None:
        """Each recorded command with the inputs newest before its receive time."""
        self.res.notes.append("realtime recording: inputs reconstructed from the recorder's receive times")
        lt_of = {key: [lt for lt, _, _ in self.timeline[key]] for key in self.input_keys}
        started: set[int] = set()
        for lt_cmd, k, _rc in self.timeline[self.cmd_key]:
            st = self.state(k)
            s = max((x for x in self.starts if x <= k), default=None)
            if s is not None and s not in started:
                started.add(s)
                self.restart(s, self.states.get(s, st))
            elif not self.ctrl.initialised:
                self.ctrl.reset(st.q, st.v)
            inputs = {}
            for key in self.input_keys:
                j = bisect.bisect_right(lt_of[key], lt_cmd) - 1
                if j >= 0:
                    inputs[key] = self.timeline[key][j][2]
            self.compute(k, st, inputs, self.last)

    # ------------------------------------------------------------------ lockstep
    def verify_lockstep(self, plan: Any) -> None:
        """Each run of the agent process (from one start to the next), tick by tick."""
        if plan is not None:
            self.res.notes.append("link faults replayed through the agent's receive boxes")
        for idx, s in enumerate(self.starts):
            hi = self.starts[idx + 1] - 1 if idx + 1 < len(self.starts) else self.last
            seg = [k for k in self.cmds if s <= k <= hi]
            if seg:
                inputs = _BoxedInputs(self, plan, s) if plan is not None else _HeldInputs(self, s)
                for k in range(s, max(seg) + 1):
                    st_raw = self.state(k)
                    if k == s:
                        self.restart(k, st_raw)
                    st, got = inputs.at(k, st_raw)
                    self.compute(k, st, got, max(seg))


class _HeldInputs:
    """A run's inputs without link faults: the newest recorded value of each input key, held
    (a new process holds nothing; a rejoining one hears no input of its first tick)."""

    def __init__(self, v: _Verifier, start: int) -> None:
        self.v = v
        self.start = start
        self.held: dict[str, Any] = {}

    def at(self, k: int, st: wire.State) -> tuple[wire.State, dict[str, Any]]:
        if not (k == self.start and self.start > 0):  # the inputs of a rejoin tick were sent before it subscribed
            for key in self.v.input_keys:
                m = self.v.by_tick[key].get(k)
                if m is not None:
                    self.held[key] = m
        return st, self.held


class _BoxedInputs:
    """A run's inputs with link faults: every input through the receive box the agent uses
    (:class:`zenswarm.link.swarm.Box`), fed the recorded messages in order."""

    def __init__(self, v: _Verifier, plan: Any, start: int) -> None:
        from zenswarm.link import Box, FaultState

        fstate = FaultState(plan)
        kinds = {v.state_key: "state", v.keys.leader_ref: "leader"}
        self.v = v
        self.start = start
        self.boxes = {
            key: Box(fstate, v.sender[key], v.me, kinds.get(key, "ref"), v.sc.timing.dt) for key in [v.state_key] + v.input_keys
        }
        self.feed = {key: [(k, msg) for _, k, msg in v.timeline[key] if k >= start] for key in self.boxes}
        self.pos = {key: 0 for key in self.feed}

    def _offer(self, k: int, rejoin: bool) -> None:
        """Offer every recorded message up to tick k (none of a rejoin tick but the state)."""
        for key, box in self.boxes.items():
            lst, i = self.feed[key], self.pos[key]
            while i < len(lst) and lst[i][0] <= k:
                if not (rejoin and key != self.v.state_key and lst[i][0] == k):
                    box.offer(lst[i][0], lst[i][1].seq, lst[i][1])
                i += 1
            self.pos[key] = i

    def at(self, k: int, st_raw: wire.State) -> tuple[wire.State, dict[str, Any]]:
        rejoin = k == self.start and self.start > 0  # the inputs of this tick were sent before it subscribed
        self._offer(k, rejoin)
        for box in self.boxes.values():
            if not box.ready(k) and not rejoin:
                due = box.due(k)
                assert due is not None, "a box that is not ready has a due message"
                box.mark_timeout(due)
        got = {key: box.at(k) for key, box in self.boxes.items()}
        h = got.pop(self.v.state_key)
        return (h.value if h is not None else st_raw), {key: g.value for key, g in got.items() if g is not None}


def agents_arg(text: str) -> str:
    """``--agent``'s value (of ``verify`` and ``replay --verify``): a UAV number >= 1 or ``all``."""
    if text != "all":
        try:
            if int(text) < 1:
                raise ValueError
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a UAV number >= 1 or 'all', got {text!r}") from None
    return text


def run_verify(args: argparse.Namespace) -> int:
    """``zenswarm verify`` and ``zenswarm replay --verify``: each agent asked, a line each; exit 1
    at a difference."""
    if args.agent is None:
        if getattr(args, "command", None) == "replay":
            raise ScenarioError("--agent", "replay --verify needs --agent I (a UAV number) or --agent all")
        args.agent = "all"
    if args.agent == "all":
        rec = read_recording(args.file, strict=False)
        agents = list(range(1, rec.load_scenario().n + 1))
    else:
        agents = [int(args.agent)]
    code = 0
    warned: set[str] = set()  # the file's problems are the same for every agent: said once
    for i in agents:
        r = verify_agent(args.file, i, strict=args.strict)
        for p in r.problems:
            if p not in warned:
                warned.add(p)
                print(f"verify: warning: {args.file}: {p}", file=sys.stderr)
        for n in r.notes:
            print(f"verify: agent {i}: note: {n}", file=sys.stderr)
        if r.ok:
            print(f"agent {i}: verified {r.ticks} ticks")
        else:
            d = r.difference
            assert d is not None
            print(f"agent {i}: first difference at {d} (after {r.ticks} verified ticks)")
            code = 1
    return code


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``verify``."""
    v = sub.add_parser(
        "verify",
        help="check that agents reproduce their recorded commands bit for bit (same as replay --verify)",
        description=(
            "For each agent (or --agent I): rebuild its controller from the recorded scenario, feed it "
            "its recorded inputs tick by tick, and compare its commands and references with the "
            "recorded ones, bit for bit. Exit 0 if all match, 1 at the first difference (named)."
        ),
    )
    v.add_argument("file", type=Path, metavar="FILE", help="recording (.mcap)")
    v.add_argument("--agent", type=agents_arg, default="all", metavar="I", help="UAV number I (1..N) or 'all' (default)")
    v.add_argument("--strict", action="store_true", help="refuse a truncated or damaged recording")
    v.set_defaults(func=run_verify, verify=True)

"""The MAVLink bridge as a swarm process: the agents' commands (or references) subscribed
through the link-fault delay line (:func:`_make_bridge`), and the process loop
(:class:`_BridgeLoop`, shared with the Crazyflie bridge): pre-mission phases, the mission clock,
setpoint pacing, diag, then landing."""

from __future__ import annotations

import math
import time
from typing import Any

from zenswarm.bridge.vehicles.mavlink.bridge import Bridge
from zenswarm.bridge.vehicles.mavlink.link import UavLink
from zenswarm.vehicle.autopilot import MavlinkSettings, mavlink_settings

__all__ = ["_BridgeLoop", "_make_bridge", "_run"]


def _make_bridge(proc: Any, settings: MavlinkSettings) -> Bridge:
    """Subscribe to the agents' commands (or references) through the link-fault delay line and
    build the :class:`Bridge` that reads them."""
    sc = proc.scenario
    n = sc.n
    keys = proc.keys
    cmd_keys = [keys.cmd(i + 1) for i in range(n)]
    ref_keys = [keys.ref(i + 1) for i in range(n)]
    inbox = proc.inbox

    def latest(key: str) -> tuple[Any, float]:
        m = inbox.latest.get(key)
        if m is None:
            return None, math.inf
        return m, time.monotonic() - inbox.latest_rx.get(key, -math.inf)

    # Link faults (--link-delay/--link-jitter/--link-loss/--partition, or the scenario's [faults]):
    # the bridge takes the plant's place, so agent i's link to it is the plant's `agent:i -> plant`
    # cmd link (also when it forwards uav/<i>/ref as position setpoints), decided on receipt and
    # released after its delay, exactly as in the realtime plant.
    from zenswarm.link import FaultState

    in_keys = cmd_keys if settings.setpoint == "attitude" else ref_keys
    plan = proc.options.fault_plan(sc)
    if plan is not None:
        proc.use_delay_line(FaultState(plan), {key: (f"agent:{i + 1}", "plant", "cmd") for i, key in enumerate(in_keys)})
    for key in in_keys:
        proc.subscribe(key, "cmd" if settings.setpoint == "attitude" else "ref")
    return Bridge(
        settings,
        sc,
        proc.counters,
        get_cmd=lambda i: latest(cmd_keys[i - 1]),
        get_ref=lambda i: latest(ref_keys[i - 1]),
        log=proc.log,
    )


class _BridgeLoop:
    """The bridge process's loop: pre-mission phases, the mission clock, setpoint pacing, diag,
    then landing. ``code`` is the process's exit code (3: no UAV ready, or a process missing)."""

    def __init__(self, proc: Any, bridge: Bridge, settings: MavlinkSettings) -> None:
        from zenswarm.bus import wire
        from zenswarm.process.runtime import WallClock

        sc = proc.scenario
        self.proc = proc
        self.bridge = bridge
        self.settings = settings
        self.n = sc.n
        self.dt = sc.timing.dt
        self.dt_ns = wire.t_ns(self.dt)
        self.n_ticks = sc.timing.n_ticks
        sub = max(1, math.ceil(settings.rate_hz / sc.timing.control_rate_hz - 1e-9))
        self.period = self.dt / sub  # s between loop iterations (setpoints)
        # the loop's pacing: more than a period behind, start again from now (no burst of
        # back-to-back setpoints); the deadline is moved to "now + period" where the loop restarts
        self.clock = WallClock(self.period, first_wait=True, resync_after_s=self.period)
        self.stats = self.clock.stats
        self.code = 0
        self.k_tick = 0  # control tick of the mission clock last published
        self.t0 = math.inf  # time.monotonic() of mission time 0
        self.seq = 0
        self.started = False
        self.finished = False
        self.start_deadline = time.monotonic() + settings.start_timeout_s
        self.next_diag = 0.0
        self.waited_alive = getattr(proc.args, "no_wait_alive", False)
        self.last = time.monotonic()  # when the last iteration ran (stall detection)

    def fly(self) -> None:
        """Until the mission ends, the process is asked to stop, or the start fails."""
        proc, bridge = self.proc, self.bridge
        self.last = time.monotonic()
        self.clock.next = self.last + self.period
        while not proc.stop.is_set():
            now = time.monotonic()
            bridge.note_stall(now - self.last)
            self.last = now
            proc.release_delayed()
            bridge.poll(now)
            bridge.advance(now)
            if not self.started and (bridge.settled or now >= self.start_deadline):
                started_at = self._start(now)
                if started_at is None:
                    break
                now = started_at
            if self._publish_tick(now):
                break
            bridge.send(now)
            self._diag(now, {"started": self.started}, with_stats=True)
            self._pace()

    def _start(self, now: float) -> float | None:
        """Start the mission clock (after waiting for the other processes' liveliness); the start
        time, or None (``code`` = 3) if no UAV is ready or a process never announced itself."""
        proc, bridge = self.proc, self.bridge
        if not bridge.ready:
            proc.log("bridge: no UAV is ready: " + "; ".join(f"uav {lk.uav}: {lk.phase} {lk.reason}" for lk in bridge.links))
            self.code = 3
            return None
        if not self.waited_alive:
            others = ["leader"] + [f"agent:{i + 1}" for i in range(self.n)] + list(getattr(proc.args, "expect", None) or [])
            missing = proc.wait_for_alive(others, timeout_s=60.0)
            self.waited_alive = True
            if missing and not proc.stop.is_set():
                proc.log(f"bridge: these processes never announced themselves: {', '.join(missing)}")
                self.code = 3
                return None
            now = self.last = time.monotonic()
            self.clock.next = now + self.period
        self.started = True
        self.t0 = now
        self.k_tick = -1
        proc.log(f"bridge: mission clock started with UAV(s) {[lk.uav for lk in bridge.ready]}")
        return now

    def _publish_tick(self, now: float) -> bool:
        """Publish the clock and the ready UAVs' states if a control tick is due; True at the
        mission's last tick (``finished``)."""
        from zenswarm.bus import wire

        if not self.started:
            return False
        proc = self.proc
        # Mission time is wall time since the start: the tick due now is published (once), and
        # ticks the loop missed (an overloaded host) are skipped, never caught up in a burst.
        # Every stream derived from the clock (the leader's and agents' refs, the commands)
        # then advances with the wall clock, as the receivers' input guards expect.
        # The tick is taken from the clock right before publishing: a message sent late for its
        # tick would look, to the receivers, like the stream slowing down and then jumping.
        k_due = min(self.n_ticks, int((time.monotonic() - self.t0) / self.dt + 1e-9))
        if k_due <= self.k_tick:
            return False
        if k_due > self.k_tick + 1:
            proc.counters["ticks_skipped"] += k_due - self.k_tick - 1
        self.k_tick = k_due
        t = self.k_tick * self.dt_ns
        self.seq += 1
        seq = self.seq
        proc.publish(proc.keys.clock, wire.Clock(t=t, seq=seq))
        for link in self.bridge.ready:
            st = self.bridge.state_enu(link, now)
            if st is not None:
                q, v, rpy, w = st
                proc.publish(
                    proc.keys.state(link.uav), wire.State(t=t, seq=seq, q=q, v=v, rpy=rpy, w=w, stamp=self.stamp_ns(link))
                )
                proc.counters["states_published"] += 1
        proc.inbox.forget_before(self.k_tick - 2)
        if self.k_tick >= self.n_ticks:
            self.finished = True
        return self.finished

    def stamp_ns(self, link: UavLink) -> int | None:
        """The state's ``stamp`` (wire ``ts``): :meth:`Bridge.sample_time` on the mission clock
        (ns since mission time 0, negative for a sample measured before the start; clipped to
        +-``wire.MAX_T_NS``), or None (left out) without a TIMESYNC clock offset."""
        from zenswarm.bus import wire

        ts = self.bridge.sample_time(link)
        if ts is None or not math.isfinite(self.t0):
            return None
        return max(-wire.MAX_T_NS, min(wire.MAX_T_NS, round((ts - self.t0) * 1e9)))

    def _diag(self, now: float, extra: dict[str, Any], with_stats: bool = False) -> None:
        """``diag/bridge`` once a second, and at once after a phase or health change."""
        bridge = self.bridge
        if now >= self.next_diag or bridge.changed:
            self.next_diag = now + 1.0
            bridge.changed = False
            stats = self.stats.as_dict() if with_stats else {}
            self.proc.publish_diag(max(self.k_tick, 0) * self.dt_ns, {**bridge.info(now), **stats, **extra})

    def _pace(self) -> None:
        """Sleep until the next iteration is due (:class:`zenswarm.process.clocks.WallClock`); more than
        a period behind: start again from now, counted in ``loop_resync``."""
        resyncs = self.clock.resyncs
        self.clock.wait()
        self.proc.counters["loop_resync"] += self.clock.resyncs - resyncs

    def land(self) -> None:
        """Land and disarm whatever the bridge armed: end of mission, SIGTERM/SIGINT, or an error."""
        proc, bridge = self.proc, self.bridge
        why = "mission finished" if self.finished else ("stop requested" if proc.stop.is_set() else "bridge stopping")
        bridge.begin_landing(time.monotonic(), why)
        deadline = time.monotonic() + self.settings.land_timeout_s
        while time.monotonic() < deadline:
            now = time.monotonic()
            # a stall here (the host loaded by the other processes ending with the mission) is
            # the bridge's own, as in fly(): not judged as the vehicles' silence
            bridge.note_stall(now - self.last)
            self.last = now
            bridge.poll(now)
            bridge.send(now)
            if bridge.land_step(now):
                break
            self._diag(now, {"landing": True})
            time.sleep(0.02)
        else:
            bridge.give_up_landing(time.monotonic())
        now = time.monotonic()
        proc.publish_diag(max(self.k_tick, 0) * self.dt_ns, {**bridge.info(now), **self.stats.as_dict(), "finished": self.finished})
        proc.log("bridge: done: " + "; ".join(f"uav {lk.uav}: {lk.phase} {lk.reason}" for lk in bridge.links))


def _run(proc: Any) -> int:
    settings = mavlink_settings(proc.scenario, proc.args.overrides())
    bridge = _make_bridge(proc, settings)
    proc.announce()
    n = proc.scenario.n
    loop = _BridgeLoop(proc, bridge, settings)
    proc.log(
        f"bridge: {n} UAV(s), setpoint={settings.setpoint}, {1 / loop.period:g} Hz setpoints, "
        + ", ".join(f"uav {i + 1}: sysid {settings.sysids[i]} @ {settings.connections[i]}" for i in range(n))
    )
    try:
        loop.fly()
        loop.land()
    finally:
        bridge.close()
    return loop.code

"""The swarm's processes as their liveliness tokens show them to ``zenswarm up``'s supervisor, and
the roles it watches only that way (``--external``: started elsewhere, by hand or on another host).

Every swarm process declares ``swarm/<name>/alive/<process>`` (:class:`Tokens`: which processes are
up, which ever were, when a token went away) and ``.../alive/<process>/<zid>`` (which session is
which process: the collector's check of each sample's sender). An external role whose token goes
away before it finished its part, or that never announces itself, is a process that died
(:class:`ExternalRoles`); the supervisor did not start it, so it cannot restart it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

from zenswarm.bus import wire
from zenswarm.compose.policy import RestartPolicy
from zenswarm.errors import ZenswarmError
from zenswarm.process.collector import Collector

__all__ = ["EXTERNAL_GONE_GRACE_S", "Tokens", "ExternalRoles", "token_names"]

EXTERNAL_GONE_GRACE_S = 0.5
"""An external role's liveliness token must stay gone this long before the role counts as dead:
its final diagnostics (``finished``), sent just before a normal exit, reach the collector's queue
first but are read on the watch loop's next poll."""


class Tokens:
    """The processes' liveliness tokens of swarm ``keys``, as a router session sees them: who is
    up (:attr:`alive`), who ever was (:attr:`seen`), and when each token went away
    (:attr:`gone_at`: process -> (monotonic s, sim time ns from ``sim_t_ns()``, >= 0))."""

    def __init__(self, keys: wire.Keys, sim_t_ns: Callable[[], int]) -> None:
        self.keys = keys
        self.sim_t_ns = sim_t_ns
        self.alive: set[str] = set()
        self.seen: set[str] = set()
        self.gone_at: dict[str, tuple[float, int]] = {}

    def subscribe(self, session: Any, senders: Callable[[str, str, bool], None]) -> list[Any]:
        """Subscribe ``session`` to the processes' tokens (:meth:`on_token`) and to the senders'
        (``alive/<process>/<zid>``: ``senders(process, zid, alive)``, the collector's
        :meth:`~zenswarm.process.collector.Collector.token`), both with history; the subscribers."""

        def on_sender(sample: Any) -> None:
            parts = str(sample.key_expr).rsplit("/", 2)
            if len(parts) == 3:
                senders(parts[1], parts[2], str(sample.kind).endswith("PUT"))

        lv = session.liveliness()
        return [
            lv.declare_subscriber(self.keys.alive_all, self.on_token, history=True),
            lv.declare_subscriber(self.keys.alive_all + "/*", on_sender, history=True),
        ]

    def on_token(self, sample: Any) -> None:
        """A process's token appeared (``PUT``) or went away."""
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
            self.gone_at[proc] = (time.monotonic(), max(self.sim_t_ns(), 0))


def token_names(role: str) -> tuple[str, ...]:
    """The processes whose token stands for ``role``: an external plant may be the MAVLink
    bridge run by hand (``zenswarm bridge mavlink``), which announces itself as ``bridge``."""
    return ("plant", "bridge") if role == "plant" else (role,)


class ExternalRoles:
    """The ``--external`` roles ``names`` of swarm ``swarm``, known only through their ``tokens``:
    each must announce itself within ``timeout_s`` wall seconds and keep its token until it ends
    its part of a flight of ``time_limit_s``. ``policy``: the restart policy (said when it would
    have restarted one); ``say``: the supervisor's console."""

    def __init__(
        self, names: Sequence[str], tokens: Tokens, *, timeout_s: float, swarm: str, time_limit_s: float, policy: RestartPolicy,
        say: Callable[[str], None],
    ) -> None:  # fmt: skip
        self.names = list(names)
        self.tokens = tokens
        self.timeout_s = timeout_s
        self.swarm = swarm
        self.time_limit_ns = wire.t_ns(time_limit_s)
        self.policy = policy
        self.say = say

    def ended_normally(self, role: str, collector: Collector) -> bool:
        """A role's token went away: did it end its part of the flight? Yes if its last
        diagnostics say ``finished``, or if the plant's clock already reached the time limit (the
        flight is over: the others leave once the plant is gone)."""
        if any(collector.diag.get(p, {}).get("finished") is True for p in token_names(role)):
            return True
        return collector.sim_t_ns >= self.time_limit_ns

    def check(self, collector: Collector, now: float, since: float, connect: Sequence[str]) -> dict[str, Any] | None:
        """One look at wall time ``now`` (monotonic s; the flight started at ``since``): the first
        role whose token went away before it finished (for :data:`EXTERNAL_GONE_GRACE_S`), or that
        never announced itself within the timeout (how to start it, joining ``connect``, is said),
        as a death (process, how, sim_time_s); None while all is well."""
        alive, seen = self.tokens.alive, self.tokens.seen
        for role in self.names:
            names = token_names(role)
            if any(p in alive for p in names):
                continue
            if not any(p in seen for p in names):
                if now - since < self.timeout_s:
                    continue
                self.say(f"external role {role} never announced itself within {self.timeout_s:g} s "
                         f"(--external-timeout); start it with `zenswarm up SCENARIO --only {role} --swarm {self.swarm} "
                         f"--connect {connect[0]}`; aborting")  # fmt: skip
                how = f"never announced itself within {self.timeout_s:g} s"
                return {"process": role, "how": how, "sim_time_s": max(collector.sim_t_ns, 0) / 1e9}
            gone = max((g for p in names if (g := self.tokens.gone_at.get(p)) is not None), default=None)
            if gone is None or now - gone[0] < EXTERNAL_GONE_GRACE_S or self.ended_normally(role, collector):
                continue
            t = gone[1] / 1e9
            self.say(f"process {role} died (external: its liveliness token went away) at sim time {t:.2f} s")
            if self.policy.enabled and self.policy.allows(role):
                self.say(f"{role} is external: this supervisor did not start it and cannot restart it; aborting the mission")
            return {"process": role, "how": "liveliness token gone (external)", "sim_time_s": t}
        return None

    def health(self) -> list[str]:
        """Each role's state for the progress line: waiting (until its token appears), up, gone."""
        out = []
        for role in self.names:
            names = token_names(role)
            up, was = any(p in self.tokens.alive for p in names), any(p in self.tokens.seen for p in names)
            out.append(f"{role}:{'up' if up else ('gone' if was else 'waiting')}(external)")
        return out

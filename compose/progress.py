"""``zenswarm up``'s progress line: how far the flight is (sim time of the time limit, speed-up over
wall time, the leader's distance to the goal) and the roles' health (:func:`children_health`; the
``--external`` roles' is :meth:`zenswarm.compose.liveliness.ExternalRoles.health`), said on the
supervisor's console."""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from zenswarm.compose.children import Child
from zenswarm.compose.liveliness import ExternalRoles, Tokens

__all__ = ["PROGRESS_SAME_T_S", "SwarmProgress", "children_health", "child_state"]

PROGRESS_SAME_T_S = 10.0
"""Wall seconds between two progress lines at the same sim time (the processes starting, a
stalled flight); a line is printed every ``--progress-every`` s while sim time moves."""


class SwarmProgress:
    """Says a progress line every ``every_s`` wall seconds while sim time moves (at the same sim
    time, to its 0.01 s, every :data:`PROGRESS_SAME_T_S`); nothing when ``quiet``. ``goal`` (3,) m,
    ``time_limit_s`` the flight's; ``wall0``: when the flight started (monotonic s)."""

    def __init__(
        self, goal: npt.ArrayLike, time_limit_s: float, every_s: float, quiet: bool, say: Callable[[str], None], wall0: float
    ) -> None:
        self.goal = np.asarray(goal, dtype=float)
        self.time_limit_s = time_limit_s
        self.every_s = every_s
        self.quiet = quiet
        self.say = say
        self.wall0 = wall0
        self.last_print = 0.0
        self.last_t: float | None = None  # sim time the last line showed, s (to its 0.01 s)

    def __call__(self, now: float, sim_t_ns: int, leader_q: np.ndarray | None, health: Callable[[], str]) -> None:
        """One look at wall time ``now`` (monotonic s): the line, if one is due."""
        due = now - self.last_print >= self.every_s and not self.quiet
        shown = round(max(sim_t_ns, 0) / 1e9, 2)
        if not (due and (shown != self.last_t or now - self.last_print >= PROGRESS_SAME_T_S)):
            return
        self.last_print, self.last_t = now, shown
        el = now - self.wall0
        t = max(sim_t_ns, 0) / 1e9
        dist = f"{np.linalg.norm(leader_q - self.goal):.3f} m" if leader_q is not None else "-"
        self.say(f"t={t:6.2f}/{self.time_limit_s:g} s  {t / el if el > 0 else 0:5.1f}x  leader->goal {dist}  {health()}")


def swarm_health(children: Mapping[str, Child], tokens: Tokens, external: ExternalRoles, diag: Mapping[str, Any]) -> str:
    """The roles' states for the progress line: those started here (up, starting, leaving, exit N:
    :func:`children_health`, by the liveliness ``tokens``) and the ``external`` ones (waiting, up,
    gone: :meth:`zenswarm.compose.liveliness.ExternalRoles.health`). ``diag``: the last diagnostics by process."""
    return " ".join(children_health(children, tokens.alive, tokens.seen, diag.get("bridge", {})) + external.health())


def children_health(
    children: Mapping[str, Child], alive: Collection[str], seen: Collection[str], bridge_diag: Mapping[str, Any]
) -> list[str]:
    """``name:state`` of each process the supervisor started (:func:`child_state`)."""
    return [f"{name}:{child_state(name, c, alive, seen, bridge_diag)}" for name, c in children.items()]


def child_state(name: str, c: Child, alive: Collection[str], seen: Collection[str], bridge_diag: Mapping[str, Any]) -> str:
    """One started role for the progress line: up (its liveliness token is ``alive``), exit N,
    leaving (its token was ``seen``, and went away) or starting. The simulated MAVLink vehicles
    have no Zenoh session (no token): they are up while their process runs and the bridge's last
    diagnostics (``bridge_diag``) show a vehicle past ``connecting`` (``phases`` = "1:ready,...": it hears them)."""
    if name in alive:
        return "up"
    if c.returncode is not None:
        return "exit " + str(c.returncode)
    if name == "vehicles" and c.proc.poll() is None:
        phases = str(bridge_diag.get("phases", ""))
        if any(p.partition(":")[2] not in ("", "connecting") for p in phases.split(",")):
            return "up"
    return "leaving" if name in seen else "starting"

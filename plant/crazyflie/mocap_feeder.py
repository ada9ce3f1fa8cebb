"""A motion-capture system for the simulated Crazyflies (``zenswarm crazyflie-vehicle --mocap``):
:class:`MocapFeeder` publishes every vehicle's true position (m, the swarm's ENU frame) on
``swarm/<name>/mocap/<i>`` (:mod:`zenswarm.bus.mocap`), from the fleet's loop.
"""

from __future__ import annotations

import time
from typing import Any

from zenswarm.plant.crazyflie.fleet import CrazyflieFleet


class MocapFeeder:
    """A motion-capture system for the simulated fleet: publishes every vehicle's true position
    on ``swarm/<name>/mocap/<i>`` (:mod:`zenswarm.bus.mocap`) at ``rate_hz``, from the fleet's
    loop (:attr:`CrazyflieFleet.on_tick`)."""

    def __init__(self, fleet: CrazyflieFleet, session: Any, prefix: str, rate_hz: float = 100.0) -> None:
        from zenswarm.bus.mocap import mocap_key

        self.fleet = fleet
        self.pubs = [session.declare_publisher(mocap_key(prefix, i + 1)) for i in range(fleet.n)]
        self.period = 1.0 / float(rate_hz)
        self.next_t = 0.0
        self.sent = 0
        self.mute: set[int] = set()  # vehicles (0-based) whose feed is cut (a test hook: a lost marker)

    def __call__(self, now: float) -> None:
        from zenswarm.bus.mocap import encode_mocap

        if now < self.next_t:
            return
        self.next_t = max(self.next_t + self.period, now - self.period)
        t = time.time()
        for i, pub in enumerate(self.pubs):
            if i not in self.mute:
                pub.put(encode_mocap(t, *self.fleet.state.q[i]))
        self.sent += 1

    def close(self) -> None:
        from zenswarm.bus import undeclare

        for pub in self.pubs:
            undeclare(pub)

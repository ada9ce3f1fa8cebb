"""The MAVLink bridge (:class:`Bridge`): its core and the four things it does with it, one
module each: read (:mod:`.receive`), move each UAV through its phases (:mod:`.phases`), send
setpoints and give states out (:mod:`.setpoints`), land (:mod:`.landing`)."""

from __future__ import annotations

from zenswarm.bridge.vehicles.mavlink.landing import Landing
from zenswarm.bridge.vehicles.mavlink.phases import PhaseMachine
from zenswarm.bridge.vehicles.mavlink.receive import Receiver
from zenswarm.bridge.vehicles.mavlink.setpoints import Setpoints

__all__ = ["Bridge"]


class Bridge(Receiver, PhaseMachine, Setpoints, Landing):
    """The bridge's MAVLink side, phase machines, setpoints and landing; the bus side is injected
    (:class:`zenswarm.bridge.vehicles.mavlink.core.BridgeCore` takes the settings, the scenario,
    the diag counters, ``get_cmd`` / ``get_ref`` and the log)."""

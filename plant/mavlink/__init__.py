"""The simulated MAVLink vehicles' parts, one idea a module: their options (:mod:`.options`), the
autopilots' parameters (:mod:`.params`), a vehicle's UDP link and its messages, NED (:mod:`.link`),
its autopilot (:mod:`.autopilot`) and the fleet that flies them on the wall clock, ENU
(:mod:`.fleet`). Their front door and command is :mod:`zenswarm.plant.mavlink_vehicle`."""

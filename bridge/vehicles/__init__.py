"""Bridges to flight controllers: the swarm's agents fly MAVLink vehicles (PX4, ArduPilot, their
SITL or ``zenswarm mavlink-vehicle``; :mod:`.mavlink`) or Crazyflies through cflib
(:mod:`.crazyflie`), ``zenswarm bridge mavlink|crazyflie``."""

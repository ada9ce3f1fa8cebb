"""The swarm bus and the outside world: MCAP recorder and replay, MAVLink bridge."""

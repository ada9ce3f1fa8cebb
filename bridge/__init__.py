"""The swarm bus and the outside world, a folder per concern: ``vehicles`` (the MAVLink and
Crazyflie bridges), ``recording`` (the MCAP file, the recorder, info), ``replay`` (replay and
verify), ``views`` (the scene, Foxglove and Rerun, the live view, export), ``reports`` (a flight's
and a campaign's); ``cli`` (the recorder commands) and ``args`` (the command-line flags the edges
share)."""

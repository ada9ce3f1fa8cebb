"""What every swarm process shares (the roles and edges build on it).

- :mod:`zenswarm.process.settings`: a flight's settings as one typed value (``FlightSettings``) and each
  role's part (``RoleSettings``), and their one serialized form (msgpack).
- :mod:`zenswarm.process.runtime`: a process's Zenoh session (``SwarmProcess``), diagnostics,
  plug-in failures and exit statuses; its parts, one concept a module: ``options`` (``ProcessOptions``),
  ``guard`` (the input guard), ``inbox``, ``clocks`` (a realtime loop's wall clock), ``lockstep``
  (the lockstep loop, ``--kill-at-tick``), ``gcpolicy`` (the garbage collector at safe points).
- :mod:`zenswarm.process.security`: credentials and access control (``zenswarm keys``, ``up --secure``),
  one concept a module: ``manifest`` (process names, users, a key directory's manifest),
  ``certificates``, ``credentials`` (the files, written and read), ``acl`` (access control from
  the graph), ``zenoh_config`` (the router's and clients' configuration, endpoints).
- :mod:`zenswarm.process.collector`: the flight's time series assembled from the bus (what ``up`` judges).
- :mod:`zenswarm.process.rtsched`: ``SCHED_FIFO`` for a realtime flight's control loops.
- :mod:`zenswarm.process.paths`: output paths checked (and locked) before any work.
"""

"""A scenario: one TOML file that says what is flown, loaded into a frozen, validated object.

- :mod:`zenswarm.scenario.config`: :class:`~zenswarm.scenario.config.Scenario`, ``load_scenario``,
  ``scenario_from_dict`` / ``scenario_to_dict`` and the cross-field checks (the tables' types are
  :mod:`zenswarm.schema`; ``[faults]`` and ``[mavlink]`` are checked by their owners,
  :mod:`zenswarm.link` and :mod:`zenswarm.vehicle.autopilot`, on load).
- :mod:`zenswarm.scenario.overrides`: ``--set KEY=VALUE`` and ``api.fly(overrides=)`` by dotted path.
- :mod:`zenswarm.scenario.generate`: valid scenario files of N UAVs (``zenswarm scenario generate``).
- :mod:`zenswarm.scenario.plugins`: which controller, planner and plant model a flight runs, and the
  boundary they are called through (a plug-in's failure, named).
"""

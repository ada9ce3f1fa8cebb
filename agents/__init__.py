"""Per-UAV agents: reference generator (eqs 16-17), ESO (27), composite controller (28) and the
thrust/attitude inversion; :mod:`zenswarm.agents.process` is the agent OS process."""

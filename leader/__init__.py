"""Virtual leader: AAPF planner (eqs 8-15) in :mod:`zenswarm.leader.aapf`; the leader process."""

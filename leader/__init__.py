"""Virtual leader: AAPF planner (eqs 8-15) in :mod:`leader.aapf`; the leader process."""

"""Scenarios (``compose/scenarios/*.toml``) and the supervisor that launches and watches a swarm."""

"""Issue 7 end to end: the swarm flies with the router checking credentials and the graph's ACL."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from zenswarm.metrics import TimeSeries

from swarmtest import SCENARIOS, read_results, scenario_variant, unique_swarm
from test_swarm import _assert_equal_to_sim, _up


def test_secure_example1_reaches_goal_and_equals_open_run(tmp_path: Path) -> None:
    """User/password + ACL: example 1 reaches the goal; the trajectory equals the open run's
    (the open lockstep run equals the in-process simulator, asserted in test_swarm)."""
    out = tmp_path / "secure"
    cp = _up(SCENARIOS / "paper_example1.toml", out, unique_swarm("s"), "--secure")
    assert cp.returncode == 0, cp.stdout[-3000:]
    assert "secure mode: user/password" in cp.stdout
    assert (out / "keys" / "manifest.json").exists()
    res = _assert_equal_to_sim(SCENARIOS / "paper_example1.toml", out)
    assert res["success"]


def test_tls_swarm_equals_open_swarm(tmp_path: Path) -> None:
    """Mutual TLS: a short flight equals the in-process simulator bit for bit, as the open swarm
    does (tests/test_swarm.py), so it equals the open swarm."""
    scenario = scenario_variant(tmp_path, time_limit_s=3.0, settle_time_s=1.0)
    cp_tls = _up(scenario, tmp_path / "tls", unique_swarm("t"), "--tls")
    assert cp_tls.returncode in (0, 1), cp_tls.stdout[-3000:]
    assert "mutual TLS" in cp_tls.stdout
    _assert_equal_to_sim(scenario, tmp_path / "tls")
    b = TimeSeries.load(str(tmp_path / "tls" / "timeseries.npz"))
    assert not any(np.isnan(getattr(b, f)).any() for f in TimeSeries.FIELDS)
    assert read_results(tmp_path / "tls")["decoder_rejects"]["rejected"] == 0


def test_secure_mode_refuses_an_endpoint_it_cannot_authenticate_before_starting(tmp_path: Path) -> None:
    """A unix-socket router is not loopback TCP, so secure mode is on by default, and user/password
    needs tcp/ or tls/ endpoints: `up` says so and exits 2 before starting anything (it once
    started the router and let every process die on the endpoint)."""
    from swarmtest import processes_mentioning, zenswarm

    swarm = unique_swarm()
    sock = tmp_path / "router.sock"
    cp = zenswarm("up", str(SCENARIOS / "paper_example1.toml"), "--out", str(tmp_path / "out"), "--swarm", swarm,
                  "--listen", f"unixsock-stream/{sock}", timeout=60)
    assert cp.returncode == 2, cp.stdout[-2000:]
    assert "secure mode" in cp.stdout and f"'unixsock-stream/{sock}'" in cp.stdout and "tcp/<host>:<port>" in cp.stdout
    assert not (tmp_path / "out").exists() and not sock.exists()
    assert not processes_mentioning(f"--swarm {swarm}")

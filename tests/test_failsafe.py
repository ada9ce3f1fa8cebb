"""The vehicle-side command-loss failsafe (plant/failsafe.py) and the restart policy."""

from __future__ import annotations

import numpy as np
import pytest

from zenswarm.compose.policy import RestartPolicy, restart_policy
from zenswarm.errors import ScenarioError
from zenswarm.plant.failsafe import HOVER, LAND, LANDED, NOMINAL, FailsafeConfig, FailsafeState, failsafe_config, hold_command, mode_for_age
from zenswarm.plant.quadrotor import initial_state, step
from zenswarm.vehicle.params import QuadParams


def test_mode_for_age_thresholds() -> None:
    cfg = FailsafeConfig(hover_after_s=0.5, land_after_s=5.0)
    assert mode_for_age(0.5, NOMINAL, cfg) == NOMINAL
    assert mode_for_age(0.51, NOMINAL, cfg) == HOVER
    assert mode_for_age(5.0, HOVER, cfg) == HOVER
    assert mode_for_age(5.01, HOVER, cfg) == LAND
    assert mode_for_age(9.0, LANDED, cfg) == LANDED  # sticky on the ground ...
    assert mode_for_age(0.0, LANDED, cfg) == NOMINAL  # ... until commands are fresh


def test_hover_command_at_rest_is_mg_and_level() -> None:
    p = QuadParams()
    F, rpy = hold_command(HOVER, np.array([1.0, 2.0, 0.5]), np.zeros(3), np.array([1.0, 2.0, 0.5]), p.mass, p.g, 0.3, FailsafeConfig())
    assert F == pytest.approx(p.mass * p.g, rel=1e-12)
    np.testing.assert_allclose(rpy, [0.0, 0.0, 0.3], atol=1e-15)
    F, _ = hold_command(LANDED, np.zeros(3), np.zeros(3), np.zeros(3), p.mass, p.g, 0.0, FailsafeConfig())
    assert F == 0.0


def test_failsafe_holds_then_lands_a_uav_in_the_plant() -> None:
    """A UAV whose commands stopped while it drifted holds its position within 5 cm, then lands
    at land_speed and cuts its motors; the other UAV is untouched."""
    p = QuadParams()
    cfg = FailsafeConfig(hover_after_s=0.5, land_after_s=3.0, land_speed=0.3)
    fs = FailsafeState(2, cfg)
    st = initial_state(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]))
    st.v[0] = [0.3, -0.2, 0.0]  # drifting when the link dies
    thrust = np.full(2, p.mass * p.g)
    rpy = np.zeros((2, 3))
    dt, nsub = 0.01, 10
    hold_at = None
    for k in range(1000):
        ages = [k * dt, 0.0]  # UAV 1's last command was at tick 0; UAV 2 is fresh
        f_app, r_app = fs.apply(k, ages, st.q, st.v, thrust, rpy, p.mass, p.g, 0.0)
        if fs.modes[0] == HOVER and hold_at is None:
            hold_at = st.q[0].copy()
        for _ in range(nsub):
            step(st, f_app, r_app, p, dt / nsub)
        if k * dt == pytest.approx(2.9):
            assert np.linalg.norm(st.q[0] - hold_at) < 0.05
    kinds = [(e[1], e[2], e[3]) for e in fs.events]
    assert kinds[:3] == [(1, "nominal", "hover"), (1, "hover", "land"), (1, "land", "landed")]
    assert fs.modes[0] == LANDED and st.q[0][2] < cfg.ground_z + 0.01
    assert fs.modes[1] == NOMINAL
    land_tick = fs.events[1][0]
    landed_tick = fs.events[2][0]
    # descending ~0.97 m at 0.3 m/s takes ~3.2 s
    assert 2.5 < (landed_tick - land_tick) * dt < 4.5


def test_failsafe_config_errors_name_the_field() -> None:
    with pytest.raises(ScenarioError) as e:
        failsafe_config({"hover_after_s": 2.0, "land_after_s": 1.0})
    assert e.value.field == "failsafe.land_after_s"
    with pytest.raises(ScenarioError) as e:
        failsafe_config({"hover_after": 1.0})
    assert e.value.field == "failsafe.hover_after"
    with pytest.raises(ScenarioError) as e:
        failsafe_config({"land_speed": float("nan")})
    assert e.value.field == "failsafe.land_speed"


def test_restart_policy_backoff_and_limit() -> None:
    pol = restart_policy({"initial_delay_s": 0.5, "factor": 2.0, "max_delay_s": 1.5, "max_restarts": 4})
    assert pol.enabled and pol.allows("agent:2") and not pol.allows("plant")
    assert [pol.delay(n) for n in range(5)] == [0.5, 1.0, 1.5, 1.5, None]
    assert not restart_policy(None).enabled and restart_policy(None, force=True).enabled
    assert restart_policy({"enabled": False}).enabled is False
    for bad, field in (({"factor": 0.5}, "restart.factor"), ({"max_restarts": -1}, "restart.max_restarts"), ({"x": 1}, "restart.x")):
        with pytest.raises(ScenarioError) as e:
            restart_policy(bad)
        assert e.value.field == field
    assert RestartPolicy().delay(0) == 0.2

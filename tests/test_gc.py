"""Issue 16: how the swarm processes manage Python's garbage collector, and that their ticks
make no cyclic garbage (so a collector that runs only at safe points keeps memory flat).

Pure tests (milliseconds): the cores' ticks and the wire's encode/decode run N times with the
collector disabled; ``gc.collect()`` then finds nothing unreachable, and the young generation
(``gc.get_count()[0]``: GC-tracked objects allocated and not freed) does not grow with N.
"""

from __future__ import annotations

import gc
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from zenswarm.agents.core import AgentCore, AgentRow
from zenswarm.bus import wire
from zenswarm.errors import ScenarioError
from zenswarm.leader.core import LeaderCore
from zenswarm.plant.core import PlantCore
from zenswarm.process.runtime import GC_FORCE_LIMIT, GC_YOUNG_LIMIT, GcPolicy
from zenswarm.scenario.config import load_scenario
from zenswarm.vehicle.params import QuadParams

from swarmtest import SCENARIOS

SC = load_scenario(SCENARIOS / "paper_example1.toml")


@pytest.fixture
def collector_off() -> Iterator[None]:
    """The collector disabled (and everything alive frozen) for the test; restored after it."""
    was = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if was:
            gc.enable()


def _swarm_ticks() -> Callable[[int], None]:
    """One closure running tick k of everything a swarm process computes per tick: the plant
    step, the leader step, each agent's rates/command/advance (nominal and elapsed dt) and the
    wire messages they exchange, encoded and decoded."""
    params = QuadParams.from_vehicle(SC.vehicle)
    plant = PlantCore(SC)
    leader = LeaderCore.from_scenario(SC)
    agents = [AgentCore(AgentRow.from_scenario(SC, i, params.mass, params.g)) for i in range(SC.n)]
    for i, a in enumerate(agents):
        a.reset(plant.state.q[i], plant.state.v[i])
    dt_ns = wire.t_ns(SC.timing.dt)

    def tick(k: int) -> None:
        t = k * dt_ns
        q0, v0 = leader.ref()
        lead = wire.decode("ref", wire.encode(wire.Ref(t=t, seq=k + 1, q=q0.copy(), v=v0)))
        refs = [wire.decode("ref", wire.encode(wire.Ref(t=t, seq=k + 1, q=a.q_ref, v=a.v_ref))) for a in agents]
        st = plant.state
        for i, a in enumerate(agents):
            s = wire.decode("state", wire.encode(wire.State(t=t, seq=k + 1, q=st.q[i].copy(), v=st.v[i].copy(),
                                                              rpy=st.rpy[i].copy(), w=st.w[i].copy())))
            rates = a.rates_from([refs[j] for j in a.row.neighbours], lead if a.row.pinned else None)
            cmd = a.finish(s.q, s.v, rates, None if k % 3 else 2 * SC.timing.dt)
            c = wire.decode("cmd", wire.encode(wire.Cmd(t=t, seq=k + 1, thrust=cmd.thrust, rpy=cmd.rpy, u=cmd.u, d_hat=cmd.d_hat)))
            plant.hold(i, c.thrust, c.rpy, k)
        plant.step(k)
        leader.advance()

    return tick


def test_swarm_ticks_make_no_cyclic_garbage_and_young_objects_do_not_accumulate(collector_off: None) -> None:
    tick = _swarm_ticks()
    for k in range(20):  # warm-up: caches, first-use allocations
        tick(k)
    assert gc.collect() >= 0
    young = []
    for n in (100, 300):
        c0 = gc.get_count()[0]
        for k in range(20, 20 + n):
            tick(k)
        young.append(gc.get_count()[0] - c0)
        assert gc.collect() == 0, "a tick made cyclic garbage (only the collector would free it)"
    # what stays allocated does not grow with the number of ticks (no leak through the young generation)
    assert young[1] <= max(young[0], 0) + 50, young


def test_managed_policy_freezes_disables_and_collects_only_at_safe_points(collector_off: None) -> None:
    pol = GcPolicy("managed")
    gc.enable()
    pol.startup_done()
    assert pol.active and not gc.isenabled() and pol.frozen > 0
    assert pol.safe_point() == 0  # nothing due yet

    def cycles(n: int) -> None:
        for _ in range(n):
            a: list = []
            a.append(a)

    cycles(GC_YOUNG_LIMIT + 100)
    assert pol.safe_point(slack_s=0.0) == 0, "no slack left before the deadline: wait for the next safe point"
    assert pol.safe_point(slack_s=0.01) >= GC_YOUNG_LIMIT
    c = pol.counters()
    assert c["gc.collections"] == 1 and c["gc.collected"] >= GC_YOUNG_LIMIT and c["gc.max_ms"] > 0
    cycles(GC_FORCE_LIMIT + 500)
    assert pol.safe_point(slack_s=0.0) >= GC_FORCE_LIMIT, "above the force limit a late loop collects anyway"


def test_python_mode_leaves_the_collector_alone(collector_off: None) -> None:
    gc.enable()
    pol = GcPolicy("python")
    pol.startup_done()
    assert gc.isenabled() and not pol.active
    assert pol.safe_point() == 0 and pol.counters()["gc.managed"] == 0.0


def test_bad_mode_names_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ZENSWARM_GC", "off")
    with pytest.raises(ScenarioError) as e:
        GcPolicy()
    assert e.value.field == "ZENSWARM_GC"
    monkeypatch.setenv("ZENSWARM_GC", "python")
    assert GcPolicy().mode == "python"


def test_elapsed_dt_core_nominal_is_bit_identical_and_long_gaps_stay_stable() -> None:
    """advance(dt = row.dt) is advance(dt=None) bit for bit; a long gap is sub-stepped (ESO)
    and clamped (generator), where one explicit-Euler step would diverge."""
    from zenswarm.agents.core import elapsed_dt
    from zenswarm.agents.eso import eso_step

    params = QuadParams.from_vehicle(SC.vehicle)
    row = AgentRow.from_scenario(SC, 0, params.mass, params.g)
    assert elapsed_dt(5, None, row.dt) is None and elapsed_dt(5, 4, row.dt) is None and elapsed_dt(5, 5, row.dt) is None
    assert elapsed_dt(7, 4, row.dt) == 3 * row.dt

    rng = np.random.default_rng(3)
    q, v = rng.normal(size=3), rng.normal(size=3)
    a, b = AgentCore(row), AgentCore(row)
    for c in (a, b):
        c.reset(q, v)
        c.d_hat = np.array([0.1, -0.2, 0.3])
    rates = (rng.normal(size=3), rng.normal(size=3))
    qm = q + 0.01
    a.finish(qm, v, rates)
    b.finish(qm, v, rates, row.dt)
    for x, y in ((a.q_ref, b.q_ref), (a.v_ref, b.v_ref), (a.q_hat, b.q_hat), (a.v_hat, b.v_hat), (a.d_hat, b.d_hat)):
        assert np.array_equal(x, y)

    # a 0.6 s gap: omega_o * h = 3 > 2, one Euler step of the ESO is unstable; sub-stepped it converges
    gap = 60 * row.dt
    u = np.array([0.0, 0.0, row.g])
    c = AgentCore(row)
    c.reset(np.zeros(3), np.zeros(3))
    naive = (c.q_hat, c.v_hat, c.d_hat)
    for _ in range(20):
        c.advance(np.ones(3), u, np.zeros(3), np.zeros(3), gap)
        naive = eso_step(*naive, np.ones(3), u, row.beta, gap, row.g)
    assert np.allclose(c.q_hat, 1.0, atol=1e-3) and np.allclose(c.d_hat, 0.0, atol=1e-2)
    assert np.max(np.abs(naive[0])) > 1e3, "one big Euler step should have diverged (the test would not show anything)"
    # generator: the step is clamped to 1 / (max(mu) d_i)
    c.reset(np.zeros(3), np.zeros(3))
    c.advance(np.zeros(3), u, np.ones(3), np.ones(3), gap)
    h = c.generator_max_step()
    assert h == pytest.approx(1.0 / (max(row.mu1, row.mu2) * (float(np.sum(row.weights)) + row.b)))
    assert np.allclose(c.q_ref, h) and h < gap
    with pytest.raises(ValueError):
        c.advance(np.zeros(3), u, np.ones(3), np.ones(3), float("nan"))

"""Link-fault model (zenswarm.link: units, names, plan, decisions, inbox, config): parsing, pure decisions, statistics against closed forms,
partitions, lockstep delivery ticks and the receiver's hold-last-value inbox.

Statistical tolerances are stated per test; the seeds are fixed, so every test is deterministic.
"""

from __future__ import annotations

import math
import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from zenswarm.errors import ScenarioError
from zenswarm.link.config import plan_from_cli, plan_from_scenario
from zenswarm.link.decisions import BLOCK, FaultState, decide
from zenswarm.link.inbox import LinkInbox
from zenswarm.link.names import agent_links, link_kind, parse_process, plant_links
from zenswarm.link.plan import FaultPlan, GilbertElliott, LinkFaultSpec, Partition, parse_partition
from zenswarm.link.units import delivery_tick, parse_duration, parse_loss

A1, A2, A3 = "agent:1", "agent:2", "agent:3"


# ------------------------------------------------------------------------------------------------
# parsing


@pytest.mark.parametrize(
    "text, seconds",
    [
        ("50ms", 0.05),
        ("1.5s", 1.5),
        ("200us", 200e-6),
        ("200µs", 200e-6),
        ("0", 0.0),
        ("0.0", 0.0),
        ("0s", 0.0),
        (" 10 ms ", 0.01),
        ("1e-3s", 1e-3),
        ("2min", 120.0),
        ("750ns", 750e-9),
        (".5s", 0.5),
    ],
)
def test_parse_duration_good(text, seconds):
    assert parse_duration(text) == pytest.approx(seconds, rel=1e-12, abs=0)


@pytest.mark.parametrize("text", ["", "50", "-5ms", "5 parsecs", "ms", "inf", "nans", "1e999s", "5ms5", "5 m s"])
def test_parse_duration_bad_names_the_text(text):
    with pytest.raises(ValueError) as e:
        parse_duration(text)
    assert repr(text) in str(e.value)


def test_parse_duration_messages_say_why():
    with pytest.raises(ValueError, match="missing unit"):
        parse_duration("50")
    with pytest.raises(ValueError, match=">= 0"):
        parse_duration("-5ms")


@pytest.mark.parametrize("text, p", [("0.2", 0.2), ("20%", 0.2), (0.2, 0.2), (1, 1.0), ("0", 0.0)])
def test_parse_loss_good(text, p):
    assert parse_loss(text) == pytest.approx(p)


@pytest.mark.parametrize("text", ["1.5", "-0.1", "abc", "nan", "120%", True])
def test_parse_loss_bad(text):
    with pytest.raises(ValueError) as e:
        parse_loss(text)
    assert repr(text) in str(e.value)


def test_parse_process():
    assert parse_process("agent:02") == "agent:2"
    assert parse_process("plant") == "plant"
    for bad in ["agent:0", "agent:", "robot:1", "agent:-1", "Plant", "recorder"]:
        with pytest.raises(ValueError) as e:
            parse_process(bad)
        assert repr(bad) in str(e.value)


def test_link_kinds():
    assert link_kind(A1, A2) == "ref"
    assert link_kind("leader", A2) == "leader"
    assert link_kind("plant", A2) == "state"
    assert link_kind(A2, "plant") == "cmd"
    with pytest.raises(ValueError):
        link_kind(A1, A1)
    with pytest.raises(ValueError):
        link_kind("plant", "leader")
    assert agent_links(2, [1, 3], pinned=True) == [
        ("plant", A2, "state"),
        (A1, A2, "ref"),
        (A3, A2, "ref"),
        ("leader", A2, "leader"),
    ]
    assert plant_links(2) == [(A1, "plant", "cmd"), (A2, "plant", "cmd")]


def test_parse_partition_good():
    p = parse_partition("agent:2@10s-13s")
    assert (p.process_or_link, p.t_start_s, p.t_end_s) == (A2, 10.0, 13.0)
    p = parse_partition("agent:1->agent:02@1e-3s-2500ms")
    assert (p.process_or_link, p.t_start_s, p.t_end_s) == ("agent:1->agent:2", 1e-3, 2.5)
    p = parse_partition("leader@0-inf")
    assert p.t_end_s == math.inf
    assert str(parse_partition("agent:2@10s-13s")) == "agent:2@10s-13s"


@pytest.mark.parametrize(
    "text, why",
    [
        ("agent:2", "TARGET@START-END"),
        ("agent:0@1s-2s", "agent:0"),
        ("robot:2@1s-2s", "robot:2"),
        ("agent:2@13s-10s", "end must be after start"),
        ("agent:2@10s-10s", "end must be after start"),
        ("agent:1->agent:1@1s-2s", "two different"),
        ("agent:2@10-13s", "START-END"),
        ("agent:2@10s", "START-END"),
    ],
)
def test_parse_partition_bad(text, why):
    with pytest.raises(ValueError) as e:
        parse_partition(text)
    assert why in str(e.value)


def test_dataclass_validation():
    with pytest.raises(ValueError, match="loss"):
        LinkFaultSpec(loss=1.5)
    with pytest.raises(ValueError, match="delay_s"):
        LinkFaultSpec(delay_s=-0.1)
    with pytest.raises(ValueError, match="p_good_to_bad"):
        GilbertElliott(-0.1, 0.5)
    with pytest.raises(ValueError, match="both be 0"):
        GilbertElliott(0.0, 0.0)
    with pytest.raises(ValueError, match="end"):
        Partition(A2, 3.0, 3.0)
    with pytest.raises(ValueError, match="kind"):
        FaultPlan(per_link={(A1, A2, "bogus"): LinkFaultSpec()})
    plan = FaultPlan(per_link={"agent:1->agent:*": LinkFaultSpec(loss=0.5)})
    assert plan.spec_for(A1, A3, "ref").loss == 0.5
    assert plan.spec_for(A3, A1, "ref").loss == 0.0
    assert hash(plan) == hash(FaultPlan(per_link={"agent:1->agent:*": LinkFaultSpec(loss=0.5)}))


# ------------------------------------------------------------------------------------------------
# plans from the CLI and from a scenario


def test_plan_from_cli():
    plan = plan_from_cli("50ms", "10ms", "0.2", ["agent:2@10s-13s"], seed=7)
    assert plan.default == LinkFaultSpec(0.05, 0.01, 0.2)
    assert plan.partitions == (Partition(A2, 10.0, 13.0),)
    assert plan.seed == 7 and plan.active
    assert not plan_from_cli(seed=1).active


@pytest.mark.parametrize(
    "kwargs, flag, text",
    [
        ({"link_delay": "50"}, "--link-delay", "'50'"),
        ({"link_jitter": "fast"}, "--link-jitter", "'fast'"),
        ({"link_loss": "1.2"}, "--link-loss", "'1.2'"),
        ({"partitions": ["agent:2@13s-10s"]}, "--partition", "'agent:2@13s-10s'"),
    ],
)
def test_plan_from_cli_bad(kwargs, flag, text):
    with pytest.raises(ScenarioError) as e:
        plan_from_cli(seed=0, **kwargs)
    assert e.value.field == flag
    assert text in str(e.value)


EXAMPLE = {
    "delay": "50ms",
    "jitter": "10ms",
    "loss": 0.2,
    "burst": {"p_good_to_bad": 0.01, "p_bad_to_good": 0.25},
    "partitions": ["agent:2@10s-13s", {"target": "agent:1->agent:3", "start": "20s", "end": "21.5s"}],
    "links": [
        {"src": "agent:*", "dst": "agent:3", "kind": "ref", "delay": "100ms", "loss": 0, "burst": False},
        {"src": "plant", "kind": "state", "loss": 0.05},
    ],
}


def test_plan_from_scenario_example():
    plan = plan_from_scenario(EXAMPLE, seed=3)
    assert plan.seed == 3
    assert plan.default == LinkFaultSpec(0.05, 0.01, 0.2, GilbertElliott(0.01, 0.25))
    assert plan.partitions == (Partition(A2, 10.0, 13.0), Partition("agent:1->agent:3", 20.0, 21.5))
    # first entry: overrides delay and loss, inherits jitter, burst turned off
    assert plan.spec_for(A1, A3, "ref") == LinkFaultSpec(0.1, 0.01, 0.0, None)
    # second entry: inherits everything but loss
    assert plan.spec_for("plant", A3, "state") == LinkFaultSpec(0.05, 0.01, 0.05, GilbertElliott(0.01, 0.25))
    assert plan.spec_for(A3, "plant", "cmd") == plan.default
    assert plan_from_scenario({}, seed=0) == FaultPlan(seed=0)
    assert plan_from_scenario(None, seed=0) == FaultPlan(seed=0)


def test_later_link_entries_win():
    plan = plan_from_scenario({"links": [{"dst": A2, "loss": 0.1}, {"src": A1, "dst": A2, "loss": 0.3}, {"dst": A2, "loss": 0.5}]}, 0)
    assert plan.spec_for(A1, A2, "ref").loss == 0.5
    plan = plan_from_scenario({"links": [{"dst": A2, "loss": 0.1}, {"src": A1, "dst": A2, "loss": 0.3}]}, 0)
    assert plan.spec_for(A1, A2, "ref").loss == 0.3
    assert plan.spec_for(A3, A2, "ref").loss == 0.1


@pytest.mark.parametrize(
    "section, field, text",
    [
        ({"links": [{"loss": 1.5}]}, "faults.links[0].loss", "1.5"),
        ({"links": [{"loss": "20%"}]}, "faults.links[0].loss", "'20%'"),
        ({"delay": "-5ms"}, "faults.delay", "'-5ms'"),
        ({"delay": 0.05}, "faults.delay", "0.05"),
        ({"links": [{}, {"jitter": "5 parsecs"}]}, "faults.links[1].jitter", "'5 parsecs'"),
        ({"links": [{"kind": "telemetry"}]}, "faults.links[0].kind", "'telemetry'"),
        ({"links": [{"src": "robot:1"}]}, "faults.links[0].src", "'robot:1'"),
        ({"links": [{"src": "plant", "kind": "ref"}]}, "faults.links[0].src", "'plant'"),
        ({"links": [{"src": A1, "dst": A1}]}, "faults.links[0].dst", "agent:1"),
        ({"links": [{"lost": 0.1}]}, "faults.links[0].lost", "unknown key"),
        ({"links": {"src": A1}}, "faults.links", "expected a list, got a table"),
        ({"partitions": ["agent:2@13s-10s"]}, "faults.partitions[0]", "end must be after start"),
        ({"partitions": [{"target": A2, "start": "13s", "end": "10s"}]}, "faults.partitions[0].end", "after start"),
        ({"partitions": [{"target": "agent:x", "start": "1s", "end": "2s"}]}, "faults.partitions[0].target", "agent:x"),
        ({"partitions": "agent:2@1s-2s"}, "faults.partitions", "list"),
        ({"burst": {"p_good_to_bad": 0.1}}, "faults.burst.p_bad_to_good", "missing"),
        ({"burst": {"p_good_to_bad": 2.0, "p_bad_to_good": 0.1}}, "faults.burst.p_good_to_bad", "<= 1.0, got 2.0"),
        ({"links": [{"burst": {"p_good_to_bad": 0, "p_bad_to_good": 0}}]}, "faults.links[0].burst.p_bad_to_good", "both be 0"),
        ({"loss": True}, "faults.loss", "True"),
        ({"seed": 3}, "faults.seed", "unknown key"),
        ("nope", "faults", "table"),
    ],
)
def test_plan_from_scenario_bad(section, field, text):
    with pytest.raises(ScenarioError) as e:
        plan_from_scenario(section, seed=0)
    assert e.value.field == field
    assert text in str(e.value)


# ------------------------------------------------------------------------------------------------
# decisions: purity and determinism

RICH = FaultPlan(
    LinkFaultSpec(0.05, 0.02, 0.2, GilbertElliott(0.05, 0.25, loss_good=0.01, loss_bad=0.9)),
    {("plant", "*", "state"): LinkFaultSpec(0.0, 0.0, 0.1)},
    seed=1234,
    partitions=(Partition(A2, 1.0, 2.0),),
)
LINKS = [(A1, A2, "ref"), (A3, A1, "ref"), ("leader", A1, "leader"), ("plant", A1, "state"), (A1, "plant", "cmd")]


def _reference(plan, link, seqs, dt=0.01):
    """Decisions computed in increasing seq order on one fresh state."""
    s = FaultState(plan)
    return {q: s.decide(*link, q, q * dt) for q in sorted(set(seqs))}


@settings(max_examples=25, deadline=None)
@given(
    seqs=st.lists(st.integers(0, 5 * BLOCK + 17), min_size=1, max_size=40),
    shuffle_seed=st.integers(0, 2**32 - 1),
    link=st.sampled_from(LINKS),
)
def test_decisions_do_not_depend_on_query_order(seqs, shuffle_seed, link):
    want = _reference(RICH, link, seqs)
    order = list(seqs)
    random.Random(shuffle_seed).shuffle(order)
    s = FaultState(RICH, cache_blocks=1)  # thrashing cache: must not change anything
    for q in order:
        assert s.decide(*link, q, q * 0.01) == want[q]
        assert decide(RICH, *link, q, q * 0.01) == want[q]  # a fresh state each time


def test_burst_chain_independent_of_earlier_queries():
    link = (A1, A2, "ref")
    far = 7 * BLOCK + 333
    a = FaultState(RICH)
    first = [a.ge_bad(*link, far), a.ge_bad(*link, 5)]
    b = FaultState(RICH)
    for q in range(0, far + 1, 97):
        b.ge_bad(*link, q)
    assert [b.ge_bad(*link, far), b.ge_bad(*link, 5)] == first
    # and equal to the chain stepped one seq at a time by its definition
    ge = RICH.default.burst
    c = FaultState(RICH)
    u0 = float(c._compute_ublock(link, "ge_init", 0)[0])
    state = u0 < ge.pi_bad
    chain = [state]
    for n in range(1, 3 * BLOCK + 5):
        u = c.uniform(link, "ge_trans", n)
        state = (u >= ge.p_bad_to_good) if state else (u < ge.p_good_to_bad)
        chain.append(state)
    d = FaultState(RICH)
    assert [d.ge_bad(*link, n) for n in reversed(range(len(chain)))] == chain[::-1]


def test_batch_equals_scalar():
    seqs = np.array([0, 1, 5, BLOCK - 1, BLOCK, 3 * BLOCK + 2, 100, 101, 102, 150, 199, 250])
    t = seqs * 0.01
    for link in LINKS:
        s = FaultState(RICH)
        b = s.decide_batch(*link, seqs, t)
        for n, q in enumerate(seqs):
            d = FaultState(RICH).decide(*link, int(q), float(t[n]))
            assert (bool(b.dropped[n]), float(b.delay_s[n]), b.REASONS[b.reason[n]]) == (d.dropped, d.delay_s, d.reason)


def _pattern(plan, link, n=2000):
    return FaultState(plan).decide_batch(*link, np.arange(n), np.arange(n) * 0.01)


def test_seeds_and_links_differ():
    p1 = FaultPlan(LinkFaultSpec(0.05, 0.01, 0.3), seed=1)
    p2 = FaultPlan(LinkFaultSpec(0.05, 0.01, 0.3), seed=2)
    a, b = _pattern(p1, (A1, A2, "ref")), _pattern(p2, (A1, A2, "ref"))
    assert (a.dropped != b.dropped).sum() > 500  # ~ 2 * 0.3 * 0.7 * 2000 = 840 expected
    assert not np.array_equal(a.delay_s, b.delay_s)
    c = _pattern(p1, (A2, A1, "ref"))
    assert (a.dropped != c.dropped).sum() > 500
    # same seed, fresh objects: identical
    again = _pattern(FaultPlan(LinkFaultSpec(0.05, 0.01, 0.3), seed=1), (A1, A2, "ref"))
    assert np.array_equal(a.dropped, again.dropped) and np.array_equal(a.delay_s, again.delay_s)


def test_golden_decisions():
    """Guards the definition of the streams: a change here changes every faulty run."""
    plan = FaultPlan(LinkFaultSpec(0.05, 0.01, 0.3, GilbertElliott(0.1, 0.3)), seed=42)
    b = _pattern(plan, (A1, A2, "ref"), 64)
    bits = "".join("1" if x else "0" for x in b.dropped)
    assert bits == GOLDEN_BITS
    assert float(b.delay_s[0]) == GOLDEN_DELAY0


GOLDEN_BITS = "1010011000000000111000111010111110010001001000001111110011100000"
GOLDEN_DELAY0 = 0.04822892489434743


def test_streams_are_coupled_across_settings():
    """The draws depend on (seed, link, seq) only, not on the settings: raising the loss drops a
    superset, and changing the loss does not move the jitter."""
    seqs = np.arange(20_000)
    lo = _pattern(FaultPlan(LinkFaultSpec(0.05, 0.01, 0.1), seed=4), (A1, A2, "ref"), 20_000)
    hi = _pattern(FaultPlan(LinkFaultSpec(0.05, 0.01, 0.3), seed=4), (A1, A2, "ref"), 20_000)
    assert np.all(hi.dropped[lo.dropped]) and hi.dropped.sum() > lo.dropped.sum()
    assert np.array_equal(lo.delay_s, hi.delay_s)
    assert seqs.size == lo.dropped.size


def test_plan_equality_respects_order():
    a = FaultPlan(per_link={(A1, "*", "*"): LinkFaultSpec(loss=0.1), ("*", A2, "*"): LinkFaultSpec(loss=0.2)})
    b = FaultPlan(per_link={("*", A2, "*"): LinkFaultSpec(loss=0.2), (A1, "*", "*"): LinkFaultSpec(loss=0.1)})
    assert a.spec_for(A1, A2, "ref").loss == 0.2 and b.spec_for(A1, A2, "ref").loss == 0.1
    assert a != b and a == FaultPlan(per_link=dict(a.per_link))


def test_no_faults_is_identity():
    s = FaultState(FaultPlan.none(seed=9))
    for q in range(0, 5000, 7):
        assert s.decide(A1, A2, "ref", q, q * 0.01) == decide(FaultPlan(), A1, A2, "ref", q, q * 0.01)
        assert s.decide(A1, A2, "ref", q, q * 0.01).dropped is False
        assert s.decide(A1, A2, "ref", q, q * 0.01).delay_s == 0.0


def test_decide_rejects_bad_inputs():
    s = FaultState(RICH)
    with pytest.raises(ValueError, match="kind"):
        s.decide(A1, A2, "telemetry", 0, 0.0)
    with pytest.raises(ValueError, match="seq"):
        s.decide(A1, A2, "ref", -1, 0.0)
    with pytest.raises(ValueError, match="another plan"):
        decide(FaultPlan(), A1, A2, "ref", 0, 0.0, state=s)


# ------------------------------------------------------------------------------------------------
# statistics against closed forms


def test_independent_loss_rate():
    """Loss 0.2 over 100k seqs: |rate - 0.2| < 0.01 (absolute; the standard error is 0.0013)."""
    plan = FaultPlan(LinkFaultSpec(loss=0.2), seed=5)
    n = 100_000
    for link in [(A1, A2, "ref"), ("plant", A3, "state")]:
        b = FaultState(plan).decide_batch(*link, np.arange(n), np.zeros(n))
        assert abs(b.dropped.mean() - 0.2) < 0.01
        assert set(np.unique(b.reason)) <= {0, 1}


def test_jitter_is_uniform_and_floored():
    plan = FaultPlan(LinkFaultSpec(delay_s=0.05, jitter_s=0.01), seed=6)
    d = FaultState(plan).decide_batch(A1, A2, "ref", np.arange(100_000), 0.0).delay_s
    assert d.min() >= 0.04 and d.max() <= 0.06
    assert abs(d.mean() - 0.05) < 1e-4  # sd of the mean: 0.01/sqrt(3)/sqrt(1e5) = 1.8e-5
    assert abs(d.std() - 0.01 / math.sqrt(3)) < 1e-4
    plan = FaultPlan(LinkFaultSpec(delay_s=0.01, jitter_s=0.03), seed=6)
    d = FaultState(plan).decide_batch(A1, A2, "ref", np.arange(100_000), 0.0).delay_s
    assert d.min() == 0.0 and abs((d == 0.0).mean() - 1 / 3) < 0.01  # P(0.01 + 0.03 (2u - 1) <= 0) = 1/3


def _runs(x: np.ndarray) -> np.ndarray:
    """Lengths of the runs of True in a bool array."""
    d = np.diff(np.concatenate(([0], x.astype(np.int8), [0])))
    return np.flatnonzero(d == -1) - np.flatnonzero(d == 1)


@pytest.mark.parametrize("p_gb, p_bg, seed", [(0.05, 0.25, 11), (0.01, 0.1, 12)])
def test_gilbert_elliott_closed_forms(p_gb, p_bg, seed):
    """1M seqs. Long-run loss = pi_bad * loss_bad + pi_good * loss_good within 2 % (relative;
    about 4 standard errors for the correlated chain), and mean burst length = 1 / p_bg within 5 %."""
    n = 1_000_000
    ge = GilbertElliott(p_gb, p_bg)  # loss_good 0, loss_bad 1: drops == bad state
    plan = FaultPlan(LinkFaultSpec(burst=ge), seed=seed)
    b = FaultState(plan).decide_batch(A1, A2, "ref", np.arange(n), 0.0)
    pi_bad = p_gb / (p_gb + p_bg)
    assert ge.mean_loss == pytest.approx(pi_bad)
    assert abs(b.dropped.mean() - pi_bad) < 0.02 * pi_bad
    runs = _runs(b.dropped)
    assert abs(runs.mean() - 1.0 / p_bg) < 0.05 / p_bg
    assert set(np.unique(b.reason)) <= {0, 2}


def test_gilbert_elliott_lossy_states():
    n = 1_000_000
    ge = GilbertElliott(0.05, 0.2, loss_good=0.02, loss_bad=0.7)
    plan = FaultPlan(LinkFaultSpec(burst=ge), seed=13)
    b = FaultState(plan).decide_batch("plant", A1, "state", np.arange(n), 0.0)
    want = 0.2 * 0.7 + 0.8 * 0.02
    assert ge.mean_loss == pytest.approx(want)
    assert abs(b.dropped.mean() - want) < 0.02 * want


# ------------------------------------------------------------------------------------------------
# partitions


def test_partition_drops_exactly_inside():
    plan = FaultPlan(seed=0, partitions=(parse_partition("agent:2@10s-13s"),))
    s = FaultState(plan)
    for link in [(A1, A2, "ref"), (A2, A1, "ref"), ("plant", A2, "state"), (A2, "plant", "cmd"), ("leader", A2, "leader")]:
        assert s.decide(*link, 0, 10.0) == s.decide(*link, 1, 12.999999) == s.decide(*link, 2, 10.0)
        assert s.decide(*link, 0, 10.0).reason == "partition"
        assert not s.decide(*link, 3, 13.0).dropped
        assert not s.decide(*link, 3, math.nextafter(10.0, 0.0)).dropped
    for link in [(A1, A3, "ref"), ("plant", A1, "state"), (A3, "plant", "cmd")]:
        assert not s.decide(*link, 0, 11.0).dropped
    # with dt = 10 ms the ticks 1000..1299 are cut, 999 and 1300 are not
    b = s.decide_batch(A1, A2, "ref", np.arange(2000), np.arange(2000) * 0.01)
    assert np.flatnonzero(b.dropped).tolist() == list(range(1000, 1300))


def test_directed_partition():
    plan = plan_from_cli(partitions=["agent:1->agent:2@1s-2s"], seed=0)
    s = FaultState(plan)
    assert s.decide(A1, A2, "ref", 0, 1.5).dropped
    assert not s.decide(A2, A1, "ref", 0, 1.5).dropped
    assert not s.decide(A1, "plant", "cmd", 0, 1.5).dropped


def test_link_spec_partitions_and_precedence():
    spec = LinkFaultSpec(loss=1.0, partitions=(Partition(A2, 0.0, 1.0),))
    s = FaultState(FaultPlan(spec, seed=0))
    assert s.decide(A1, A2, "ref", 0, 0.5).reason == "partition"
    assert s.decide(A1, A2, "ref", 0, 1.5).reason == "loss"
    assert s.decide(A1, A3, "ref", 0, 0.5).reason == "loss"


# ------------------------------------------------------------------------------------------------
# lockstep delivery


@pytest.mark.parametrize(
    "k, delay, dt, want",
    [
        (7, 0.0, 0.01, 7),
        (7, 0.05, 0.01, 12),
        (7, 0.049, 0.01, 12),
        (7, 0.0501, 0.01, 13),
        (0, 0.01, 0.01, 1),
        (0, 0.001, 0.01, 1),
        (3, 0.1, 1 / 30, 6),
        (3, 0.3, 0.1, 6),
    ],
)
def test_delivery_tick(k, delay, dt, want):
    assert delivery_tick(k, delay, dt) == want


@given(k=st.integers(0, 10**6), m=st.integers(0, 1000), dt=st.sampled_from([0.01, 0.001, 1 / 30, 0.02, 0.1, 1 / 3]))
def test_delivery_tick_multiples_of_dt(k, m, dt):
    """A delay of exactly m ticks (as computed in floating point) is m ticks, never m + 1."""
    assert delivery_tick(k, m * dt, dt) == k + m
    assert delivery_tick(k, (m + 0.5) * dt, dt) == k + m + 1


def test_delivery_tick_bad_dt():
    with pytest.raises(ValueError):
        delivery_tick(0, 0.1, 0.0)


# ------------------------------------------------------------------------------------------------
# LinkInbox: hold last value


def test_inbox_without_faults_is_same_tick():
    box = LinkInbox(FaultPlan(), A1, A2, "ref", 0.01)
    assert box.at(0) is None
    for k in range(1, 50):
        assert box.due(k) == k
        box.offer(k, 100 + k, f"v{k}")
        h = box.at(k)
        assert (h.value, h.send_tick, h.seq, h.age_ticks) == (f"v{k}", k, 100 + k, 0)
    c = box.counters()
    assert (c["received"], c["delivered"], c["dropped"], c["late"], c["max_age_ticks"]) == (49, 49, 0, 0, 0)


def test_inbox_fixed_delay():
    """50 ms at dt 10 ms: tick k holds the message of k - 5, age 5; nothing before tick 5."""
    box = LinkInbox(plan_from_cli("50ms", seed=0), A1, A2, "ref", 0.01)
    assert box.horizon == 5
    for k in range(40):
        box.offer(k, k, k)
        h = box.at(k)
        if k < 5:
            assert h is None and box.due(k) is None
        else:
            assert (h.value, h.age_ticks) == (k - 5, 5)
            assert box.due(k) == k - 5


def test_inbox_holds_last_value_through_drops():
    plan = FaultPlan(LinkFaultSpec(loss=0.3), seed=21)
    box = LinkInbox(plan, A1, A2, "ref", 0.01)
    dropped = [box.decision(j).dropped for j in range(500)]
    last = None
    for k in range(500):
        box.offer(k, k, k)
        h = box.at(k)
        if not dropped[k]:
            last = k
        if last is None:
            assert h is None
        else:
            assert (h.value, h.age_ticks) == (last, k - last)
            assert box.due(k) == last
    c = box.counters()
    assert c["dropped"] == c["dropped_loss"] == sum(dropped)
    assert c["delivered"] == 500 - sum(dropped)
    assert c["received"] == 500 and c["late"] == 0


def test_inbox_partition_ages_and_recovery():
    """agent:2 cut from 10 s to 13 s with 50 ms delay at dt 10 ms: the value held at 13.05 s is
    from 9.99 s (age 306 ticks); from tick 1305 on the age is back to 5."""
    plan = plan_from_cli("50ms", partitions=["agent:2@10s-13s"], seed=0)
    box = LinkInbox(plan, A1, A2, "ref", 0.01)
    ages = {}
    for k in range(1600):
        box.offer(k, k, k)
        ages[k] = box.at(k).age_ticks if k >= 5 else None
    assert ages[1004] == 5 and ages[1005] == 6
    assert ages[1304] == 1304 - 999
    assert ages[1305] == 5
    assert box.counters()["max_age_ticks"] == 305
    assert box.counters()["dropped_partition"] == 300


def test_inbox_duplicates_and_backwards():
    box = LinkInbox(FaultPlan(), A1, A2, "ref", 0.01)
    box.offer(3, 1, "a")
    box.offer(3, 2, "b")
    assert box.at(3).value == "a"
    box.offer(3, 3, "c")
    assert box.counters()["duplicates"] == 2
    with pytest.raises(ValueError, match="backwards"):
        box.at(2)


JITTERY = FaultPlan(
    LinkFaultSpec(0.05, 0.04, 0.2, GilbertElliott(0.05, 0.3)),
    seed=77,
    partitions=(Partition(A2, 1.0, 1.6),),
)


def _sim_style(plan, n_ticks, dt=0.01):
    """Simulator: every message is offered as it is sent (tick j offered at tick j)."""
    box = LinkInbox(plan, A1, A2, "ref", dt)
    out = []
    for k in range(n_ticks):
        box.offer(k, 1000 + k, ("v", k))
        h = box.at(k)
        out.append(None if h is None else (h.value, h.send_tick, h.seq, h.age_ticks))
    return out, box


@settings(max_examples=20, deadline=None)
@given(perm_seed=st.integers(0, 2**32 - 1), backlog=st.integers(0, 40))
def test_inbox_swarm_equals_sim(perm_seed, backlog):
    """Swarm process: messages arrive in a random order, some long after they were sent; at tick k
    the process waits only for the due message, then reads. Same held values, ages and final
    counters as the simulator, whatever the arrival order."""
    n = 250
    want, sim_box = _sim_style(JITTERY, n)
    rng = random.Random(perm_seed)
    box = LinkInbox(JITTERY, A1, A2, "ref", 0.01)
    sent: list[int] = []  # sent, not yet arrived
    for k in range(n):
        sent.append(k)
        rng.shuffle(sent)
        # a random subset arrives (the newest may lag behind by up to `backlog` ticks)
        keep = [j for j in sent if j >= k - backlog and rng.random() < 0.5]
        for j in [j for j in sent if j not in keep]:
            box.offer(j, 1000 + j, ("v", j))
        sent = keep
        need = box.due(k)
        if need is not None and not box.has(need):  # "wait" for it
            sent.remove(need)
            box.offer(need, 1000 + need, ("v", need))
        h = box.at(k)
        assert (None if h is None else (h.value, h.send_tick, h.seq, h.age_ticks)) == want[k]
        if h is not None:
            assert h.send_tick == need
    for j in sent:  # stragglers arrive at the end
        box.offer(j, 1000 + j, ("v", j))
    assert box.counters() == sim_box.counters()


def test_inbox_jitter_counts_late():
    _, box = _sim_style(JITTERY, 3000)
    c = box.counters()
    assert c["late"] > 0
    assert c["received"] == 3000 == c["delivered"] + c["dropped"]
    assert c["dropped"] == c["dropped_loss"] + c["dropped_burst"] + c["dropped_partition"]
    assert c["dropped_partition"] == 60


def test_due_incremental_equals_from_scratch():
    plan = plan_from_cli("30ms", "25ms", "0.4", ["agent:1@0.5s-2s"], seed=3)
    inc = LinkInbox(plan, A1, A2, "ref", 0.01)
    ref = LinkInbox(plan, A1, A2, "ref", 0.01)
    fate = [(ref.decision(j).dropped, delivery_tick(j, ref.decision(j).delay_s, 0.01)) for j in range(400)]
    for k in range(400):
        # brute force from the definition
        cands = [j for j in range(k + 1) if not fate[j][0] and fate[j][1] <= k]
        want = max(cands) if cands else None
        assert inc.due(k) == want
        if k % 37 == 0:  # a fresh inbox asked straight at k (no memo)
            assert LinkInbox(plan, A1, A2, "ref", 0.01).due(k) == want


def test_inbox_state_and_cmd_links_share_plan():
    plan = plan_from_scenario(EXAMPLE, seed=1)
    state = FaultState(plan)
    boxes = [LinkInbox(state, *link, 0.01) for link in agent_links(3, [1, 2], pinned=False) + plant_links(3)]
    assert [b.horizon for b in boxes] == [6, 11, 11, 6, 6, 6]
    for b in boxes:
        for k in range(100):
            b.offer(k, k, k)
            b.at(k)
        assert b.counters()["received"] == 100

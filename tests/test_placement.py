"""Where the roles of a swarm run on a Dask cluster (``zenswarm up --placement``): the rules'
parsing and the plan, pure (no cluster; tests/test_cluster_swarm.py flies one)."""

from __future__ import annotations

import pytest

from zenswarm.compose.placement import Worker, parse_rule, plan, replace, rules_by_role
from zenswarm.errors import ScenarioError

W = [Worker("tcp://10.0.0.2:4000", "w1", "10.0.0.2"), Worker("tcp://10.0.0.3:4000", "w2", "10.0.0.3", {"gpu": 1.0})]
ROLES = ["plant", "leader"] + [f"agent:{i}" for i in range(1, 9)]


def _count(where: dict[str, str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for a in where.values():
        out[a] = out.get(a, 0) + 1
    return out


def test_without_rules_the_roles_are_spread_evenly_in_start_order() -> None:
    where = plan(ROLES, W, [], 8)
    assert list(where) == ROLES
    assert _count(where) == {W[0].address: 5, W[1].address: 5}
    assert where["plant"] == W[0].address and where["leader"] == W[1].address and where["agent:1"] == W[0].address
    assert plan(ROLES, list(reversed(W)), [], 8) == where  # the workers' order does not matter: by name


def test_rules_pin_roles_by_name_address_range_and_resource() -> None:
    rules = [parse_rule("plant,leader=w1"), parse_rule("agent:1-3=tcp://10.0.0.3:4000"), parse_rule("agent:8=resource:gpu")]
    where = plan(ROLES, W, rules, 8)
    assert where["plant"] == where["leader"] == W[0].address
    assert {where[f"agent:{i}"] for i in (1, 2, 3, 8)} == {W[1].address}
    # the 4 unpinned agents even the load out: 2 + 2 on w1, 4 + 0 on w2 -> 5/5 in all
    assert _count(where) == {W[0].address: 5, W[1].address: 5}
    assert plan(ROLES, W, [parse_rule("agents=w2")], 8)["agent:5"] == W[1].address


@pytest.mark.parametrize(
    "text, named",
    [
        ("agent:2", "expected ROLES=TARGET"),
        ("=w1", "expected ROLES=TARGET"),
        ("agent:2=", "expected ROLES=TARGET"),
        ("robot=w1", "unknown role 'robot'"),
        ("agent:x=w1", "unknown role 'agent:x'"),
        ("agent:3-1=w1", "1 <= I <= J"),
        ("agent:0=w1", "1 <= I <= J"),
        ("plant=resource:", "resource name"),
    ],
)
def test_a_bad_rule_names_placement(text: str, named: str) -> None:
    with pytest.raises(ScenarioError) as e:
        parse_rule(text)
    assert e.value.field == "--placement" and named in str(e.value), str(e.value)


@pytest.mark.parametrize(
    "rules, named",
    [
        (["agent:9=w1"], "agent:9 is not a role of this swarm (8 UAVs"),
        (["plant=w3"], "no worker is named 'w3'; the workers: w1 (tcp://10.0.0.2:4000), w2"),
        (["plant=resource:fpga"], "no worker offers the resource 'fpga'"),
        (["agent:1-4=w1", "agent:4=w2"], "agent:4 is named by two rules"),
    ],
)
def test_a_rule_that_does_not_fit_the_swarm_or_the_cluster_names_placement(rules: list[str], named: str) -> None:
    with pytest.raises(ScenarioError) as e:
        plan(ROLES, W, [parse_rule(r) for r in rules], 8)
    assert e.value.field == "--placement" and named in str(e.value), str(e.value)


def test_no_worker_names_scheduler() -> None:
    with pytest.raises(ScenarioError) as e:
        plan(ROLES, [], [], 8)
    assert e.value.field == "--scheduler" and "no workers" in str(e.value)


def test_a_role_not_placed_on_the_cluster_is_refused() -> None:
    with pytest.raises(ScenarioError, match="plant is not started on the cluster"):
        plan(ROLES[1:], W, [parse_rule("plant=w1")], 8)


def test_a_restarted_role_goes_to_the_least_loaded_live_worker_its_rule_allows() -> None:
    where = plan(ROLES, W, [parse_rule("agent:1=resource:gpu")], 8)
    live = [W[0]]  # w2 is lost
    assert replace("agent:2", None, live, where) == W[0].address
    by_role = rules_by_role(ROLES, [parse_rule("agent:1=resource:gpu")], 8)
    assert replace("agent:1", by_role["agent:1"], live, where) is None  # only w2 offers gpu
    assert replace("agent:2", None, [], where) is None
    # pinned to w2 by name: once w2 is lost, anywhere
    assert replace("agent:3", parse_rule("agent:3=w2"), live, where) == W[0].address


@pytest.mark.parametrize("kw", [{"scheduler": "tcp://127.0.0.1:8786"}, {"placement": ["plant=w1"]}, {"listen": "tcp/10.0.0.1:7447"}])
def test_the_simulator_refuses_a_cluster(kw: dict) -> None:
    from zenswarm.api import fly

    with pytest.raises(ScenarioError) as e:
        fly("paper_example1", duration=0.1, **kw)
    assert e.value.field == next(iter(kw)) and "mode='swarm'" in str(e.value)


@pytest.mark.parametrize(
    "kw, field, named",
    [
        ({"placement": ("plant=w1",)}, "--placement", "give --scheduler"),
        ({"scheduler": "tcp://h:8786", "only": "agent:1"}, "--scheduler", "not with --only"),
        ({"scheduler": "tcp://h:8786", "external": ("agent:2",), "placement": ("agent:1-2=w1",)}, "--placement", "agent:2 is --external"),
        ({"scheduler": "tcp://h:8786", "placement": ("agent:4=w1",)}, "--placement", "agent:4 is not a role of this swarm"),
        ({"scheduler": " "}, "--scheduler", "expected a Dask scheduler's address"),
    ],
)
def test_the_cluster_flags_are_checked_before_anything_starts(kw: dict, field: str, named: str, tmp_path) -> None:
    from zenswarm.compose.up import check_up_args
    from zenswarm.process.settings import FlightSettings
    from zenswarm.scenario.config import load_scenario

    from swarmtest import SCENARIOS

    sc = load_scenario(SCENARIOS / "paper_example1.toml")
    with pytest.raises(ScenarioError) as e:
        check_up_args(FlightSettings(scenario=sc, scenario_file=SCENARIOS / "paper_example1.toml", out=tmp_path / "o", **kw), sc)
    assert e.value.field == field and named in str(e.value), str(e.value)

"""A flight's settings as one typed value (issue 44): built once by the front door (``zenswarm up``'s
flags, ``api.fly``), taken by the supervisor, and handed to each role it starts as msgpack on the
role's standard input (:mod:`zenswarm.process.settings`). No process starts: the roles' ``run``
functions are replaced by recorders of what they were given."""

from __future__ import annotations

import dataclasses
import importlib
import io
import sys
from pathlib import Path
from typing import Any

import msgspec
import pytest

from zenswarm.compose.cli import build_parser
from zenswarm.compose.cli import main as cli_main
from zenswarm.errors import ScenarioError
from zenswarm.process.runtime import ProcessOptions
from zenswarm.process.settings import FlightSettings, RoleSettings, decode_flight, decode_role, encode
from zenswarm.scenario.config import Scenario, load_scenario, scenario_from_dict, scenario_to_dict
from zenswarm.scenario.generate import generate_scenario

from swarmtest import SCENARIOS

EX1 = SCENARIOS / "paper_example1.toml"

#: overrides that fill the scenario's optional tables, each of its unions in some form
TABLES: dict[str, Any] = {
    "faults": {
        "delay": "20ms", "jitter": "5ms", "loss": 0.1, "range": "9m", "burst": {"p_good_to_bad": 0.1, "p_bad_to_good": 0.5},
        "partitions": ["agent:2@1s-2s"], "links": [{"src": "agent:1", "dst": "agent:2", "loss": 0.5, "burst": False}],
        "capacity": "20kB/s",
    },
    "restart": {"max_restarts": 5, "factor": 1.5},
    "failsafe": {"hover_after_s": 0.4},
    "mavlink": {"base_port": 14600, "autopilot": "px4"},
    "agents": {"controller": "paper", "params": {}},
}  # fmt: skip


def _scenarios() -> list[Scenario]:
    """The built-in scenarios, one with every optional table, and generated ones (a sparse graph)."""
    from zenswarm import api

    out = [load_scenario(SCENARIOS / "paper_example1.toml"), load_scenario(SCENARIOS / "paper_example2.toml")]
    out.append(api.load(EX1, {f"{table}.{key}": v for table, t in TABLES.items() for key, v in t.items()})[0])
    out.append(scenario_from_dict(generate_scenario(12, shape="grid", topology="knn", k=3, n_obstacles=2, seed=5)))
    out.append(scenario_from_dict(generate_scenario(5, topology="star", pinning="all", seed=9)))
    return out


@pytest.mark.parametrize("index", range(5))
def test_the_scenario_travels_typed_and_decodes_equal(index: int) -> None:
    """A role's settings carry the scenario itself: it decodes equal to what was sent, field for
    field (floats as IEEE doubles), its document the same, its graph built the same, with no TOML
    parse in the child."""
    sc = _scenarios()[index]
    rs = RoleSettings(role="agent:1", scenario=sc, swarm="s")
    got = decode_role(encode(rs))
    assert got == rs and got.scenario == sc
    assert scenario_to_dict(got.scenario) == scenario_to_dict(sc)
    assert got.scenario.comm_graph.neighbours(0) == sc.comm_graph.neighbours(0)
    assert [got.scenario.neighbours(i) for i in range(sc.n)] == [sc.neighbours(i) for i in range(sc.n)]
    if index == 2:  # every optional table was set
        assert all(getattr(got.scenario, t) is not None for t in ("faults", "restart", "failsafe", "mavlink"))


def _flags(*extra: str) -> Any:
    return build_parser().parse_args(["up", str(EX1), "--swarm", "s1", "--quiet", *extra])


def test_the_flight_settings_of_the_command_line_round_trip(tmp_path: Path) -> None:
    """Every flag of ``zenswarm up`` lands in one FlightSettings (the scenario parsed once, the
    overrides and plug-in names in it), and the settings decode equal to what was encoded."""
    from zenswarm.compose.up import flight_settings

    args, overrides = flight_settings(_flags(
        "--out", str(tmp_path / "o"), "--realtime", "--record", str(tmp_path / "r.mcap"), "--report", "--report-format", "png,svg",
        "--listen", "tcp/127.0.0.1:7999", "--connect", "tcp/127.0.0.1:7999", "--secure", "--keys", str(tmp_path / "k"),
        "--lockstep-timeout", "2.5", "--kill", "agent:2@1.5s", "--restart", "--stop-at-goal", "--progress-every", "3",
        "--link-loss", "20%", "--link-delay", "50ms", "--partition", "agent:1@1s-2s", "--seed", "7", "--controller", "paper",
        "--set", "timing.time_limit_s=12", "--live", "8799", "--rt-priority", "10", "--external", "agent:3",
    ))  # fmt: skip
    assert overrides == {"timing.time_limit_s": 12}
    assert args.scenario.timing.time_limit_s == 12.0 and args.scenario_file == EX1
    assert (args.realtime, args.mode, args.record, args.report, args.report_format) == (True, "realtime", tmp_path / "r.mcap", True,
                                                                                      ("png", "svg"))  # fmt: skip
    assert (args.kill, args.lockstep_timeout, args.external, args.rt_priority) == ((("agent:2", 1.5),), 2.5, ("agent:3",), 10)
    assert (args.faults.link_loss, args.faults.link_delay, args.faults.partitions, args.faults.seed) == ("20%", "50ms",
                                                                                                        ("agent:1@1s-2s",), 7)  # fmt: skip
    assert args.live is not None and (args.live.viewer, args.live.port) == ("foxglove", 8799)
    assert decode_flight(encode(args)) == args


def test_a_role_gets_what_its_command_line_said() -> None:
    """The settings a role is started with are those its command line carried before they went
    typed: the same ProcessOptions as ``zenswarm agent`` parsed from the words the supervisor used
    to write (the scenario itself in place of its file)."""
    from zenswarm.compose.roles import agent_options
    from zenswarm.compose.up import up_options

    args = up_options(_flags("--realtime", "--lockstep-timeout", "2.5", "--link-loss", "0.2", "--link-jitter", "5ms",
                             "--partition", "agent:2@1s-2s", "--seed", "7", "--planner", "aapf", "--tls", "--link-queue", "8"))  # fmt: skip
    connect = ("tls/127.0.0.1:7001", "tls/127.0.0.1:7002")
    new = args.role("agent:2", connect, Path("keys"), kill_at_tick=40).process_options()
    old_words = [
        "agent", "--id", "2", "--scenario", str(EX1), "--swarm", "s1", "--lockstep-timeout", "2.5", "--connect", connect[0],
        "--connect", connect[1], "--realtime", "--keys", "keys", "--tls", "--kill-at-tick", "40", *args.faults.argv(),
        *args.plugin_argv(),
    ]  # fmt: skip
    p = build_parser()
    old = agent_options(p.parse_args(old_words))
    assert old.id == 2 and isinstance(new.scenario, Scenario)
    assert dataclasses.replace(new, scenario=None) == dataclasses.replace(old.process, scenario=None)
    assert new.scenario == args.scenario
    # an open router: no credentials, and no --tls without them
    assert args.role("leader", connect).process_options().tls is False


def _recording_runs(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, ProcessOptions]]:
    """Replace the roles' run_process by a recorder of (process name, options)."""
    ran: list[tuple[str, ProcessOptions]] = []

    def run_process(fn: Any, name: str, options: Any) -> int:
        ran.append((name, ProcessOptions.of(options)))
        return 0

    for module in ("zenswarm.agents.process", "zenswarm.leader.process", "zenswarm.plant.process"):
        monkeypatch.setattr(importlib.import_module(module), "run_process", run_process)
    return ran


def _stdin(monkeypatch: pytest.MonkeyPatch, data: bytes) -> None:
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data)))


def test_the_supervisor_starts_each_role_with_its_settings_on_stdin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The supervisor names a role on its command line (role, --swarm, its own pid) and hands it
    its settings: the role runs with them, its kill tick on its first start only, the plant waiting
    for the recorder with --record."""
    import os

    from zenswarm.compose.roles import run_role
    from zenswarm.compose.supervisor import Supervisor
    from zenswarm.compose.up import up_options

    args = up_options(_flags("--kill", "agent:2@0.5s", "--record", str(tmp_path / "r.mcap"), "--link-loss", "0.1"))
    sup = Supervisor(args)
    sup.say = lambda text: None  # type: ignore[method-assign]
    sup.connect_endpoints, sup.keys_dir = ["tcp/127.0.0.1:7111"], None
    named = ["--swarm", "s1", "--settings", "-", "--supervisor", str(os.getpid())]
    agent_argv, data = sup.command("agent:2")
    assert agent_argv[agent_argv.index("zenswarm") + 1 :] == ["agent", "--id", "2", *named]
    first, again = decode_role(data), decode_role(sup.command("agent:2")[1])
    assert (first.kill_at_tick, again.kill_at_tick) == (50, None)
    started = {"agent:2": (agent_argv, data), "plant": sup.command("plant"), "leader": sup.command("leader")}
    assert decode_role(started["plant"][1]).expect == ("recorder",) and decode_role(started["leader"][1]).expect == ()
    argv, rec = sup.command("recorder")  # the edges too: named on the command line, their settings on stdin
    assert argv[argv.index("zenswarm") + 1 :] == ["record", *named] and rec

    ran = _recording_runs(monkeypatch)
    for words, settings in started.values():
        _stdin(monkeypatch, settings)
        assert run_role(words[words.index("zenswarm") + 1 :]) == 0
    assert [name for name, _ in ran] == ["agent:2", "plant", "leader"]
    o = ran[0][1]
    assert o.scenario == args.scenario and o.connect == ("tcp/127.0.0.1:7111",) and o.kill_at_tick == 50 and o.link_loss == "0.1"


def _launch(tmp_path: Path, *flags: str) -> Any:
    """A flight of EX1 with these flags, as its supervisor knows it once the router listens (a
    secured one: keys and TLS; MAVLink vehicles on 14600+, Crazyflies on 19900+ with --plant
    crazyflie; realtime with vehicles, as :class:`zenswarm.compose.supervisor.Supervisor` makes it)."""
    from zenswarm.compose.commands import Launch
    from zenswarm.compose.up import up_options

    flight = up_options(_flags("--record", str(tmp_path / "r.mcap"), "--link-loss", "0.1", "--seed", "7", "--tls", *flags))
    flight = msgspec.structs.replace(flight, realtime=flight.plant != "sim")  # as the Supervisor takes it
    cf = 19900 if flight.plant == "crazyflie" else None
    return Launch(flight, ("tls/127.0.0.1:7111",), tmp_path / "keys", 14600, cf, 4321)


def test_the_edges_get_what_their_command_lines_said(tmp_path: Path) -> None:
    """The recorder, the MAVLink and Crazyflie bridges and their simulated vehicles: the settings
    the supervisor hands them equal those their own commands build from the words the supervisor
    used to write (the scenario itself in place of its file; the vehicles' command had no swarm)."""
    from zenswarm.bridge.recording.recorder import recorder_settings
    from zenswarm.bridge.vehicles import crazyflie, mavlink
    from zenswarm.compose.commands import command, edge_settings
    from zenswarm.compose.roles import crazyflie_fleet_settings, mavlink_fleet_settings

    at = _launch(tmp_path, "--plant", "mavlink", "--rt-priority", "10")
    join = ["--swarm", "s1", "--connect", "tls/127.0.0.1:7111", "--keys", str(tmp_path / "keys"), "--tls"]
    faults = at.flight.faults.argv()
    assert faults == ["--link-loss", "0.1", "--seed", "7"]
    p = build_parser()
    old = recorder_settings(p.parse_args(["record", "--out", str(tmp_path / "r.mcap"), "--scenario", str(EX1), "--realtime", *join,
                                          *faults]))  # fmt: skip
    assert edge_settings("recorder", at) == old and old.mode == "realtime" and old.scenario == at.flight.scenario
    conns = [w for i in range(3) for w in ("--conn", f"{i + 1}=udpin:127.0.0.1:{14600 + i}")]
    gz = at.flight.scenario.mavlink.ground_z if at.flight.scenario.mavlink is not None else 0.0
    origins = [w for i, q in enumerate(at.flight.scenario.initial_positions) for w in ("--origin", f"{i + 1}={q[0]!r},{q[1]!r},{gz!r}")]
    old = mavlink.bridge_settings(p.parse_args(["bridge", "mavlink", str(EX1), "--base-port", "14600", *join, *conns, *origins, *faults,
                                               "--expect", "recorder", "--rt-priority", "10"]))  # fmt: skip
    assert edge_settings("bridge", at) == old and old.process.realtime and old.process.tls and old.conn[3] == "udpin:127.0.0.1:14602"
    old = mavlink_fleet_settings(p.parse_args(["mavlink-vehicle", str(EX1), "--base-port", "14600", "--telemetry-hz", "100",
                                               "--own-origin", "--sitl-ports", "--rt-priority", "10"]))  # fmt: skip
    assert edge_settings("vehicles", at) == msgspec.structs.replace(old, swarm="s1")

    at = _launch(tmp_path, "--plant", "crazyflie", "--rt-priority", "10")  # the Crazyflie bridge and its vehicles take it too
    uris = [w for i in range(3) for w in ("--uri", f"{i + 1}=udp://127.0.0.1:{19900 + i}")]
    old = crazyflie.bridge_settings(p.parse_args(["bridge", "crazyflie", str(EX1), *join, *uris, *faults, "--expect", "recorder",
                                                 "--rt-priority", "10"]))  # fmt: skip
    assert edge_settings("bridge", at) == old and old.uri[1] == "udp://127.0.0.1:19900" and old.process.rt_priority == 10
    old = crazyflie_fleet_settings(p.parse_args(["crazyflie-vehicle", str(EX1), "--base-port", "19900", "--rt-priority", "10"]))
    assert edge_settings("vehicles", at) == msgspec.structs.replace(old, swarm="s1") and old.rt_priority == 10
    # each started as the roles are: named on its command line (--swarm for the process table), its settings on stdin
    for role, words in (("recorder", ["record"]), ("bridge", ["bridge", "crazyflie"]), ("vehicles", ["crazyflie-vehicle"])):
        argv, data = command(role, at)
        assert argv[argv.index("zenswarm") + 1 :] == [*words, "--swarm", "s1", "--settings", "-", "--supervisor", "4321"] and data


@pytest.mark.parametrize("words", [["record"], ["bridge", "mavlink"], ["bridge", "crazyflie"], ["mavlink-vehicle"], ["crazyflie-vehicle"]])
def test_an_edge_runs_with_the_settings_on_its_stdin(words: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """``zenswarm COMMAND --swarm S --settings - --supervisor PID``: the edge runs with the
    settings it reads, equal to those sent; those of another swarm, or bytes that are none, are
    exit 2 naming --settings, nothing run."""
    from zenswarm.compose import commands

    plant = "crazyflie" if "crazyflie" in words[-1] else "mavlink"
    at = _launch(tmp_path, "--plant", plant)
    argv, data = commands.command({"record": "recorder", "bridge": "bridge"}.get(words[0], "vehicles"), at)
    ran: list[Any] = []
    kind, _ = commands.EDGES[tuple(words)]()
    monkeypatch.setitem(commands.EDGES, tuple(words), lambda: (kind, lambda s: ran.append(s) or 0))
    named = argv[argv.index("zenswarm") + 1 :]
    assert named[: len(words)] == words
    _stdin(monkeypatch, data)
    assert cli_main(named) == 0 and len(ran) == 1 and encode(ran[0]) == data and isinstance(ran[0], kind)
    for swarm, bad, needle in (("s2", data, "not of swarm 's2'"), ("s1", b"\x93junk", f"not the {kind.__name__} of a flight")):
        _stdin(monkeypatch, bad)
        assert cli_main([*words, "--swarm", swarm, "--settings", "-"]) == 2
        err = capsys.readouterr().err
        assert "--settings" in err and needle in err, err
    assert len(ran) == 1


def test_settings_of_another_role_or_swarm_are_refused(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A role started with the settings of another role, another swarm, or bytes that are no
    settings: exit 2 naming --settings, nothing run."""
    from zenswarm.compose.roles import run_role
    from zenswarm.compose.up import up_options

    ran = _recording_runs(monkeypatch)
    agent3 = encode(up_options(_flags()).role("agent:3", ()))
    for words, data, needle in (
        (["agent", "--id", "2", "--swarm", "s1", "--settings", "-"], agent3, "the settings of agent:3 in swarm 's1'"),
        (["agent", "--id", "3", "--swarm", "s2", "--settings", "-"], agent3, "not of agent:3 in swarm 's2'"),
        (["leader", "--swarm", "s1", "--settings", "-"], b"\x93junk", "not the RoleSettings of a flight"),
    ):
        _stdin(monkeypatch, data)
        assert run_role(words) == 2
        err = capsys.readouterr().err
        assert "--settings" in err and needle in err, err
    assert ran == []


def test_up_takes_typed_settings_from_the_api_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """``zenswarm up --help`` does not show the settings entry; the entry refuses settings of
    another swarm, and settings that are bad input are checked again there (exit 2, before
    anything starts)."""
    with pytest.raises(SystemExit):
        cli_main(["up", "--help"])
    assert "--settings" not in capsys.readouterr().out
    sc = load_scenario(EX1)
    settings = FlightSettings(scenario=sc, scenario_file=EX1, swarm="s1", out=tmp_path / "out")
    _stdin(monkeypatch, encode(settings))
    assert cli_main(["up", "--settings", "-", "--swarm", "s2"]) == 2
    assert "'s2', but the settings fly swarm 's1'" in capsys.readouterr().err
    bad = msgspec.structs.replace(settings, lockstep_timeout=0.0, kill=(("agent:9", 1.0),))
    _stdin(monkeypatch, encode(bad))
    assert cli_main(["up", "--settings", "-", "--swarm", "s1"]) == 2
    assert "--lockstep-timeout" in capsys.readouterr().err
    _stdin(monkeypatch, encode(msgspec.structs.replace(settings, kill=(("agent:9", 1.0),))))
    assert cli_main(["up", "--settings", "-", "--swarm", "s1"]) == 2
    assert "--kill" in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_only_runs_its_role_with_the_parsed_scenario_and_writes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``up --only agent:2 --connect EP``: the role runs in this process with its part of the
    settings, the scenario as overridden (no file written for it), its router given."""
    monkeypatch.chdir(tmp_path)
    ran = _recording_runs(monkeypatch)
    assert cli_main(["up", str(EX1), "--only", "agent:2", "--connect", "tcp/10.0.0.1:7447", "--swarm", "far",
                     "--set", "timing.time_limit_s=3", "--router-lost-timeout", "4", "--link-loss", "0.3"]) == 0  # fmt: skip
    assert cli_main(["up", str(EX1), "--only", "leader", "--swarm", "far"]) == 0
    (name, o), (name2, o2) = ran
    assert (name, name2) == ("agent:2", "leader")
    assert isinstance(o.scenario, Scenario) and o.scenario.timing.time_limit_s == 3.0
    assert (o.connect, o.swarm, o.router_lost_timeout, o.link_loss) == (("tcp/10.0.0.1:7447",), "far", 4.0, "0.3")
    assert o2.connect == ("tcp/127.0.0.1:7447",) and o2.scenario == load_scenario(EX1)
    assert list(tmp_path.iterdir()) == [], "nothing written"


def test_api_refuses_a_bad_lockstep_timeout_before_anything_starts() -> None:
    """``fly(mode="swarm", lockstep_timeout=...)``: what ``--lockstep-timeout`` refuses is a
    ScenarioError naming the argument, before any process starts."""
    from zenswarm import api

    for bad in (0.0, -1.0, float("nan"), float("inf"), True):
        with pytest.raises(ScenarioError, match="lockstep_timeout"):
            api.fly(EX1, mode="swarm", lockstep_timeout=bad, duration=0.1)


def test_crazyflie_vehicle_keys_are_the_mocap_feeds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``crazyflie-vehicle --keys DIR``: the credentials of the mocap feed (the user ``mocap``), so
    without ``--mocap`` they are exit 2 naming --keys, and credentials without that user (a
    scenario without extpos) are exit 2 naming it, before any port is bound or session opened."""
    from zenswarm.process.security import generate_credentials

    generate_credentials(EX1, tmp_path / "keys", "s1")
    assert cli_main(["crazyflie-vehicle", str(EX1), "--keys", str(tmp_path / "keys")]) == 2
    err = capsys.readouterr().err
    assert "--keys" in err and "--mocap" in err, err
    flags = ["--mocap", "--swarm", "s1", "--connect", "tcp/127.0.0.1:1", "--keys", str(tmp_path / "keys")]
    assert cli_main(["crazyflie-vehicle", str(EX1), *flags]) == 2
    err = capsys.readouterr().err
    assert "no credentials for mocap" in err and "Traceback" not in err, err

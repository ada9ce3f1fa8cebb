"""Bad input never crashes and never loses a run: every case exits with status 2 and a message
naming the flag, field or path, before any work (for ``zenswarm up``: before any process starts).

The CLI cases run ``python -m zenswarm`` for real; each fails at validation, so each takes about
a second.
"""

from __future__ import annotations

import os
import time
import tomllib
from pathlib import Path

import pytest

from zenswarm import bus
from zenswarm.errors import ScenarioError
from zenswarm.process.paths import check_output_dir, check_output_file
from zenswarm.scenario.config import MAX_SEED, scenario_from_dict
from zenswarm.scenario.generate import to_toml

from swarmtest import SCENARIOS, processes_mentioning, unique_swarm, zenswarm

EX1 = SCENARIOS / "paper_example1.toml"


def _variant(tmp: Path, name: str, edit) -> Path:
    d = tomllib.loads(EX1.read_text())
    edit(d)
    p = tmp / f"{name}.toml"
    p.write_text(to_toml(d))
    return p


def _bad(r, *needles: str) -> None:
    """Exit status 2, no traceback, every needle in the output."""
    assert r.returncode == 2, r.stdout
    assert "Traceback" not in r.stdout, r.stdout
    for n in needles:
        assert n in r.stdout, f"{n!r} not in {r.stdout!r}"


def _up_refused(tmp: Path, *args: str, needles: tuple[str, ...], scenario: Path = EX1, swarm: str | None = None) -> None:
    """``zenswarm up`` refuses at once: exit 2 naming what is wrong, no process of the swarm
    left (none started), nothing written to OUT."""
    swarm = swarm or unique_swarm("bad")
    out = tmp / f"out_{swarm}"
    t0 = time.monotonic()
    r = zenswarm("up", str(scenario), "--swarm", swarm, "--out", str(out), "--quiet", *args, timeout=60)
    took = time.monotonic() - t0
    _bad(r, *needles)
    assert took < 20, f"took {took:.1f} s: the refusal must come before the flight"
    assert "[supervisor]" not in r.stdout, r.stdout  # the router never opened
    assert processes_mentioning(swarm) == []
    assert not out.exists()


# ----------------------------------------------------------------------------- 1. scenario bounds


@pytest.mark.swarm
def test_absurd_time_limit_is_refused_by_check_sim_and_up(tmp_path: Path) -> None:
    """time_limit_s = 1e12 tried to allocate 728 TiB in sim; now all three refuse it on load."""
    sc = _variant(tmp_path, "long", lambda d: d["timing"].update(time_limit_s=1e12))
    _bad(zenswarm("scenario", "check", str(sc), timeout=60), "timing.time_limit_s", "at most 10,000,000")
    _bad(zenswarm("sim", str(sc), "--out", str(tmp_path / "sim"), timeout=60), "timing.time_limit_s")
    assert not (tmp_path / "sim").exists()
    _up_refused(tmp_path, needles=("timing.time_limit_s",), scenario=sc)


@pytest.mark.swarm
def test_too_many_substeps_is_refused(tmp_path: Path) -> None:
    sc = _variant(tmp_path, "substeps", lambda d: d["timing"].update(physics_rate_hz=1e7))
    _bad(zenswarm("scenario", "check", str(sc), timeout=60), "timing.physics_rate_hz", "at most 1000 physics sub-steps")


@pytest.mark.swarm
def test_seed_beyond_64_bits_is_refused_by_check_sim_and_up(tmp_path: Path) -> None:
    """A 2**80 seed passed check and sim but killed up's leader (the mission message carries the
    seed as a 64-bit integer): the bound is now one check, applied everywhere."""
    sc = _variant(tmp_path, "seed80", lambda d: d["scenario"].update(seed=2**80))
    _bad(zenswarm("scenario", "check", str(sc), timeout=60), "scenario.seed", "2**63 - 1")
    _bad(zenswarm("sim", str(sc), "--out", str(tmp_path / "sim"), timeout=60), "scenario.seed")
    _up_refused(tmp_path, needles=("scenario.seed",), scenario=sc)
    ok = _variant(tmp_path, "seedmax", lambda d: d["scenario"].update(seed=MAX_SEED))
    r = zenswarm("scenario", "check", str(ok), timeout=60)
    assert r.returncode == 0, r.stdout


@pytest.mark.parametrize("seed", ["-1", str(2**63), str(2**80), "seven"])
@pytest.mark.swarm
def test_bad_seed_flag_is_a_usage_error(tmp_path: Path, seed: str) -> None:
    _bad(zenswarm("sim", str(EX1), "--out", str(tmp_path / "sim"), "--seed", seed, timeout=60), "--seed")
    assert not (tmp_path / "sim").exists()


@pytest.mark.swarm
def test_bad_seed_flag_of_up_and_generate(tmp_path: Path) -> None:
    _up_refused(tmp_path, "--seed", "-1", needles=("argument --seed",))
    _bad(zenswarm("scenario", "generate", "--n", "3", "--seed", str(2**63), "--out", str(tmp_path / "g.toml"), timeout=60), "--seed")


# ----------------------------------------------------------------------------- 2. output paths


def _bad_paths(tmp: Path) -> dict[str, Path]:
    (tmp / "a_file").write_text("x")
    (tmp / "a_dir").mkdir()
    return {"file": tmp / "a_file", "dir": tmp / "a_dir", "proc": Path("/proc/zenswarm_x"), "under_file": tmp / "a_file" / "sub"}


@pytest.mark.parametrize("kind", ["file", "proc", "under_file"])
@pytest.mark.swarm
def test_output_directory_flags(tmp_path: Path, kind: str) -> None:
    """--out of sim, keys and report needs a directory that can be written."""
    bad = _bad_paths(tmp_path)[kind]
    _bad(zenswarm("sim", str(EX1), "--out", str(bad), timeout=60), "--out", str(bad))
    _bad(zenswarm("keys", str(EX1), "--out", str(bad), timeout=60), "--out", str(bad))
    _bad(zenswarm("report", "--series", "x.npz", "--scenario", str(EX1), "--out", str(bad), timeout=60), "--out", str(bad))


@pytest.mark.parametrize("kind", ["dir", "proc", "under_file"])
@pytest.mark.swarm
def test_output_file_flags(tmp_path: Path, kind: str) -> None:
    """--out of recover, export, record and scenario generate needs a file that can be written."""
    bad = _bad_paths(tmp_path)[kind]
    mcap = str(tmp_path / "missing.mcap")
    for args in (
        ("recover", mcap, "--out", str(bad)),
        ("export", "--foxglove", mcap, "--out", str(bad)),
        ("record", "--out", str(bad), "--connect-timeout", "0"),
        ("scenario", "generate", "--n", "3", "--out", str(bad)),
    ):
        _bad(zenswarm(*args, timeout=60), "--out", str(bad))


@pytest.mark.parametrize("kind", ["file", "proc", "under_file"])
@pytest.mark.swarm
def test_up_out_is_checked_before_the_flight(tmp_path: Path, kind: str) -> None:
    """`up --out /proc/x` flew the whole mission and then died with a traceback."""
    bad = _bad_paths(tmp_path)[kind]
    swarm = unique_swarm("badout")
    t0 = time.monotonic()
    r = zenswarm("up", str(EX1), "--swarm", swarm, "--out", str(bad), "--quiet", timeout=60)
    _bad(r, "--out", str(bad))
    assert time.monotonic() - t0 < 20 and "[supervisor]" not in r.stdout
    assert processes_mentioning(swarm) == []


@pytest.mark.parametrize("kind", ["dir", "proc", "under_file"])
@pytest.mark.swarm
def test_up_record_is_checked_before_the_flight(tmp_path: Path, kind: str) -> None:
    bad = _bad_paths(tmp_path)[kind]
    _up_refused(tmp_path, "--record", str(bad), needles=("--record", str(bad)))


def test_path_checks_create_nothing_and_accept_new_paths(tmp_path: Path) -> None:
    before = sorted(os.listdir(tmp_path))
    assert check_output_dir(tmp_path / "new" / "deeper", "--out") == tmp_path / "new" / "deeper"
    assert check_output_file(tmp_path / "new" / "f.mcap", "--record") == tmp_path / "new" / "f.mcap"
    assert check_output_dir(tmp_path, "--out") == tmp_path
    (tmp_path / "old.mcap").write_text("x")
    check_output_file(tmp_path / "old.mcap", "--out")  # an existing file is replaced: fine
    assert sorted(os.listdir(tmp_path)) == sorted(before + ["old.mcap"])  # no probe file, no directory
    with pytest.raises(ScenarioError) as ei:
        check_output_dir(tmp_path / "old.mcap", "--out")
    assert ei.value.field == "--out" and "not a directory" in ei.value.message


# ----------------------------------------------------------------------------- 3. flags naming things


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (("--kill", "agent:9@1s"), ("--kill", "agent:9", "not a process of this swarm (3 UAVs)")),
        (("--kill", "supervisor@1s"), ("--kill", "supervisor")),
        (("--kill", "recorder@1s"), ("--kill", "--record")),
        (("--external", "plant", "--kill", "plant@1s"), ("--kill", "--external")),
        (("--partition", "agent:9@1s-2s"), ("--partition", "agent:9 does not exist", "3 UAVs")),
        (("--partition", "agent:1->agent:4@1s-2s"), ("--partition", "agent:4 does not exist")),
        (("--external", "garbage"), ("--external", "'garbage'", "agent:3")),
        (("--external", "recorder"), ("--external", "'recorder'")),
        (("--only", "agent:4"), ("--only", "'agent:4'")),
        (("--link-range=-1m",), ("--link-range", "> 0")),
        (("--lockstep-timeout", "0"), ("--lockstep-timeout", "> 0")),
        (("--lockstep-timeout", "-1"), ("--lockstep-timeout",)),
        (("--lockstep-timeout", "nan"), ("--lockstep-timeout",)),
        (("--lockstep-timeout", "inf"), ("--lockstep-timeout",)),
        (("--connect", "garbage"), ("--connect", "'garbage'", "<protocol>/<address>")),
        (("--connect", "tcp/127.0.0.1:notaport"), ("--connect", "port")),
        (("--connect", "carrier-pigeon/127.0.0.1:7447"), ("--connect", "unknown protocol")),
        (("--listen", "tcp/127.0.0.1:99999"), ("--listen", "port in 0..65535")),
        (("--router-connect", "garbage"), ("--router-connect",)),
        (("--rt-priority", "5"), ("--rt-priority", "only for realtime flights")),
        (("--realtime", "--rt-priority", "0"), ("--rt-priority", "1-99")),
        (("--realtime", "--rt-priority", "100"), ("--rt-priority", "1-99")),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, tuple) and v and v[0].startswith("--") else None,
)
@pytest.mark.swarm
def test_up_flags_naming_what_does_not_exist(tmp_path: Path, args: tuple[str, ...], needles: tuple[str, ...]) -> None:
    _up_refused(tmp_path, *args, needles=needles)


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (("--fixed-gain", "0"), ("--fixed-gain", "> 0")),
        (("--fixed-gain", "-1"), ("--fixed-gain",)),
        (("--fixed-gain", "nan"), ("--fixed-gain",)),
        (("--partition", "agent:9@1s-2s"), ("--partition", "agent:9 does not exist")),
        (("--link-range", "0"), ("--link-range", "> 0")),
        (("--link-fade", "1m,-1m"), ("--link-fade", "> 0")),
    ],
)
@pytest.mark.swarm
def test_sim_flags(tmp_path: Path, args: tuple[str, ...], needles: tuple[str, ...]) -> None:
    _bad(zenswarm("sim", str(EX1), "--out", str(tmp_path / "sim"), *args, timeout=60), *needles)
    assert not (tmp_path / "sim").exists()


def test_scenario_faults_naming_a_missing_agent() -> None:
    for faults, field in (
        ({"partitions": ["agent:4@1s-2s"]}, "faults.partitions[0]"),
        ({"partitions": ["agent:1@1s-2s", {"target": "agent:1->agent:7", "start": "1s", "end": "2s"}]}, "faults.partitions[1]"),
        ({"links": [{"dst": "agent:5", "loss": 0.1}]}, "faults.links[0].dst"),
    ):
        d = tomllib.loads(EX1.read_text())
        d["faults"] = faults
        with pytest.raises(ScenarioError) as ei:
            scenario_from_dict(d)
        assert ei.value.field == field and "does not exist" in ei.value.message
    d = tomllib.loads(EX1.read_text())
    d["faults"] = {"partitions": ["agent:3@1s-2s"], "links": [{"src": "agent:*", "dst": "agent:3", "loss": 0.1}]}
    scenario_from_dict(d)  # agent:3 and globs exist


def test_endpoint_syntax_accepts_what_zenoh_dials() -> None:
    good = ["tcp/127.0.0.1:7447", "tcp/[::1]:7447", "tls/localhost:7447", "tcp/10.0.0.2:7447#iface=eth0", "udp/127.0.0.1:7447"]
    assert bus.check_endpoint_syntax(good, "--connect") == good
    assert bus.check_endpoint_syntax(["tcp/0.0.0.0:0"], "--listen", listen=True) == ["tcp/0.0.0.0:0"]
    with pytest.raises(ScenarioError) as ei:
        bus.check_endpoint_syntax(["tcp/0.0.0.0:0"], "--connect")
    assert ei.value.field == "--connect"


# ----------------------------------------------------------------------------- 4. credentials of another swarm


def _keys(tmp: Path, scenario: Path, swarm: str, name: str) -> Path:
    out = tmp / name
    r = zenswarm("keys", str(scenario), "--out", str(out), "--swarm", swarm, timeout=60)
    assert r.returncode == 0, r.stdout
    return out


def _four_uavs(tmp: Path) -> Path:
    p = tmp / "four.toml"
    r = zenswarm("scenario", "generate", "--n", "4", "--out", str(p), timeout=60)
    assert r.returncode == 0, r.stdout
    return p


@pytest.mark.swarm
def test_keys_flag_of_another_swarm_or_size_is_refused_and_kept(tmp_path: Path) -> None:
    """--keys are the user's: never rewritten; not matching the swarm or the scenario -> exit 2."""
    swarm = unique_swarm("beta")
    other_swarm = _keys(tmp_path, EX1, "alpha", "k_alpha")
    four = _keys(tmp_path, _four_uavs(tmp_path), swarm, "k_four")
    manifests = {d: (d / "manifest.json").read_bytes() for d in (other_swarm, four)}
    _up_refused(tmp_path, "--keys", str(other_swarm), needles=("--keys", "swarm 'alpha'", "zenswarm keys"))
    _up_refused(tmp_path, "--keys", str(four), needles=("--keys", "4 UAVs", "the 3 of scenario 'paper_example1'"), swarm=swarm)
    _up_refused(tmp_path, "--keys", str(tmp_path / "none"), needles=("--keys", "no manifest"))
    assert {d: (d / "manifest.json").read_bytes() for d in manifests} == manifests


def _security_of(out: Path, swarm: str, *extra: str):
    """Supervisor._security for `up EX1 --secure --out OUT --swarm SWARM` (no process started)."""
    from zenswarm.compose.cli import build_parser
    from zenswarm.compose.supervisor import Supervisor
    from zenswarm.compose.up import up_options
    from zenswarm.scenario.config import load_scenario

    args = build_parser().parse_args(["up", str(EX1), "--secure", "--out", str(out), "--swarm", swarm, "--quiet", *extra])
    sup = Supervisor(up_options(args), load_scenario(EX1))
    sup._security(["tcp/127.0.0.1:7447"], out)
    return sup


def test_generated_keys_are_reused_while_they_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    _security_of(out, "gamma")
    assert "generated credentials for this run" in capsys.readouterr().out
    before = (out / "keys" / "manifest.json").read_bytes()
    _security_of(out, "gamma")
    assert "generated" not in capsys.readouterr().out
    assert (out / "keys" / "manifest.json").read_bytes() == before
    _security_of(out, "delta")  # the same OUT for another swarm: generated again, and said so
    said = capsys.readouterr().out
    assert "regenerated the credentials" in said and "swarm 'gamma', not 'delta'" in said
    assert '"swarm": "delta"' in (out / "keys" / "manifest.json").read_text()
    (out / "keys" / "router" / "usrpwd.txt").unlink()  # a damaged tree is generated again too
    _security_of(out, "delta")
    assert "is missing" in capsys.readouterr().out and (out / "keys" / "router" / "usrpwd.txt").is_file()


def test_keys_in_place_of_the_keys_directory(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "keys").write_text("not a directory")
    with pytest.raises(ScenarioError) as ei:
        _security_of(out, "eps")
    assert ei.value.field == "--out" and "keys" in ei.value.message


@pytest.mark.swarm
def test_up_regenerates_keys_left_in_out_by_another_swarm(tmp_path: Path) -> None:
    """A reused --out whose OUT/keys were generated for a 4-UAV scenario: the run generates this
    scenario's, says so, and flies."""
    import shutil

    scenario = _variant(tmp_path, "short", lambda d: d["timing"].update(time_limit_s=0.3, settle_time_s=0.1))
    out = tmp_path / "out"
    out.mkdir()
    swarm = unique_swarm("rk")
    shutil.copytree(_keys(tmp_path, _four_uavs(tmp_path), swarm, "k_four"), out / "keys")
    r = zenswarm("up", str(scenario), "--secure", "--swarm", swarm, "--out", str(out), "--quiet", "--quiet-children", timeout=180)
    assert r.returncode in (0, 1), r.stdout[-3000:]  # 0.3 s: the goal is not reached, the flight completes
    assert "regenerated the credentials" in r.stdout and "4 UAVs" in r.stdout, r.stdout[-3000:]
    assert f'"swarm": "{swarm}"' in (out / "keys" / "manifest.json").read_text()
    assert not (out / "keys" / "agent-4").exists()
    assert (out / "results.json").exists() and processes_mentioning(swarm) == []


# ----------------------------------------------------------------------------- MAVLink ids and timeouts


@pytest.mark.parametrize(
    "flags, needle",
    [
        (("--sysid", "2=245"), "mavlink.sysids"),  # the bridge's own source_system
        (("--sysid", "3=1"), "mavlink.sysids"),  # two vehicles with one id
        (("--link-timeout", "1.0"), "mavlink.link_timeout_s"),  # not below the vehicles' 1 s loss time
    ],
)
def test_bridge_refuses_bad_ids_and_timeouts_before_connecting(flags: tuple[str, ...], needle: str) -> None:
    """``zenswarm bridge mavlink``: exit 2 naming the field, before any Zenoh session (the router
    endpoint here does not exist: trying it would fail with a Zenoh connection error)."""
    r = zenswarm("bridge", "mavlink", str(EX1), "--swarm", unique_swarm("bad"), "--connect", "tcp/127.0.0.1:1", *flags, timeout=60)
    _bad(r, needle)
    assert "zenoh" not in r.stdout.lower(), r.stdout


def test_up_refuses_duplicate_mavlink_sysids(tmp_path: Path) -> None:
    p = _variant(tmp_path, "dupids", lambda d: d.__setitem__("mavlink", {"sysids": [1, 2, 2]}))
    _up_refused(tmp_path, "--plant", "mavlink", scenario=p, needles=("mavlink.sysids", "UAV 2 and UAV 3"))


@pytest.mark.swarm
def test_up_refuses_busy_simulated_vehicle_ports(tmp_path: Path) -> None:
    """``--plant mavlink --mavlink-base-port P``: simulated vehicle i sends from UDP P+40+i (PX4
    SITL's direction); a busy one is named, exit 2, before anything starts (it used to fail in the
    vehicles' process, after the swarm had started)."""
    import socket

    base = bus.free_udp_block(3, also=(40,))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", base + 41))
        assert bus.udp_ports_in_use([base, base + 41, base + 42]) == [base + 41]
        _up_refused(
            tmp_path, "--plant", "mavlink", "--mavlink-base-port", str(base),
            needles=("--mavlink-base-port", f"UDP port {base + 41}", "vehicle 2's send port, P+40+1"),
        )

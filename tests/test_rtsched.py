"""Real-time scheduling of the flying processes (``--rt-priority``, :mod:`zenswarm.process.rtsched`).

The checks of the value and of the privilege run everywhere (the privilege refused by a patched
``os.sched_setscheduler``, and for real under ``setpriv`` without ``CAP_SYS_NICE``). What needs
the privilege (raising threads for real, a realtime flight under ``SCHED_FIFO``) is skipped, with
the reason printed, where this user may not use ``SCHED_FIFO``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from zenswarm.api import fly
from zenswarm.errors import ScenarioError
from zenswarm.process import rtsched

PRIORITY = 7


def _permitted(p: int = PRIORITY) -> str | None:
    """None if this process may use SCHED_FIFO p, else why not."""
    try:
        rtsched.probe(p)
    except rtsched.RtPriorityError as e:
        return str(e)
    return None


def _need_privilege() -> None:
    why = _permitted()
    if why is not None:
        print(f"skipped: this user may not use SCHED_FIFO ({why})")
        pytest.skip(f"missing privilege: {why}")


@pytest.mark.parametrize("value", [0, 100, -3, "x", "", "2.5", True, None])
def test_bad_priorities_name_the_flag(value: object) -> None:
    with pytest.raises(rtsched.RtPriorityError) as e:
        rtsched.check_priority(value)
    assert isinstance(e.value, ScenarioError) and e.value.field == "--rt-priority"
    assert "1-99" in str(e.value)


@pytest.mark.parametrize("value", [1, 50, 99, "20", " 3 "])
def test_good_priorities(value: object) -> None:
    assert rtsched.check_priority(value) == int(str(value).strip())


def test_validate_refuses_lockstep_and_passes_none() -> None:
    assert rtsched.validate(None, realtime=False) is None
    with pytest.raises(rtsched.RtPriorityError, match=r"--rt-priority: only for realtime flights \(--realtime\)"):
        rtsched.validate(5, realtime=False)
    with pytest.raises(rtsched.RtPriorityError, match="1-99"):
        rtsched.validate(0, realtime=False)  # the value is checked first


def test_a_process_started_with_rt_priority_in_lockstep_exits_2() -> None:
    r = subprocess.run([sys.executable, "-m", "zenswarm", "leader", "--scenario", "compose/scenarios/paper_example1.toml",
                        "--swarm", "rt-lockstep", "--connect", "tcp/127.0.0.1:1", "--rt-priority", "5"],
                       capture_output=True, text=True, timeout=60, cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 2, r.stdout + r.stderr
    assert "--rt-priority: only for realtime flights" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_probe_says_how_to_get_the_privilege(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple] = []

    def refuse(pid: int, policy: int, param: os.sched_param) -> None:
        calls.append((pid, policy, param.sched_priority))
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with pytest.raises(rtsched.RtPriorityError) as e:
        rtsched.probe(12)
    msg = str(e.value)
    assert msg.startswith("--rt-priority:") and "priority 12" in msg and "rtprio" in msg and "CAP_SYS_NICE" in msg
    assert calls == [(0, os.SCHED_FIFO, 12)]
    with pytest.raises(rtsched.RtPriorityError):
        rtsched.apply_to_process(12)  # the same answer where it is applied


def test_probe_changes_nothing() -> None:
    before = rtsched.current_policy()
    why = _permitted()
    assert rtsched.current_policy() == before, why


def _fifo_child(code: str, *prefix: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*prefix, sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=60)


def test_without_cap_sys_nice_the_probe_refuses_for_real() -> None:
    """Root without CAP_SYS_NICE and with RLIMIT_RTPRIO 0 (what an ordinary user has): refused."""
    setpriv = shutil.which("setpriv")
    if os.geteuid() != 0 or setpriv is None or _permitted() is not None:
        why = "not root" if os.geteuid() != 0 else "no setpriv" if setpriv is None else "SCHED_FIFO not permitted anyway"
        print(f"skipped: dropping CAP_SYS_NICE needs root, setpriv and the privilege to drop ({why})")
        pytest.skip(f"missing privilege: {why}")
    r = _fifo_child(
        """
        import resource
        from zenswarm.process import rtsched
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))
        try:
            rtsched.probe(5)
        except rtsched.RtPriorityError as e:
            print("REFUSED", e)
        else:
            print("ALLOWED")
        """,
        setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice",
    )
    assert r.returncode == 0, r.stderr
    assert "REFUSED --rt-priority:" in r.stdout and "rtprio" in r.stdout, r.stdout


def test_every_thread_is_raised_after_startup_and_new_threads_inherit() -> None:
    """The threads alive at the end of start-up are raised, the ones started later inherit the
    policy; before :func:`rtsched.apply_after_startup` nothing is."""
    _need_privilege()
    r = _fifo_child(
        f"""
        import json, os, threading
        from zenswarm.process import rtsched
        stop = threading.Event()
        early = threading.Thread(target=stop.wait); early.start()
        before = rtsched.process_policy(os.getpid())
        rtsched.set_requested({PRIORITY})
        n = rtsched.apply_after_startup()
        late_policy = []
        late = threading.Thread(target=lambda: late_policy.append(rtsched.current_policy())); late.start(); late.join()
        after = rtsched.process_policy(os.getpid())
        stop.set(); early.join()
        print(json.dumps({{"before": before, "n": n, "after": after, "late": late_policy[0],
                          "counters": rtsched.counters()}}))
        """
    )
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout.strip().splitlines()[-1])
    assert all(p == ["other", 0] for p in d["before"]), d
    assert d["n"] == len(d["before"]) >= 2
    assert all(p == ["fifo", PRIORITY] for p in d["after"]), d
    assert d["late"] == ["fifo", PRIORITY]
    assert d["counters"] == {"rt.priority": PRIORITY, "rt.threads": d["n"]}


@pytest.mark.swarm
def test_realtime_flight_under_sched_fifo() -> None:
    """``zenswarm.api.fly(..., realtime=True, rt_priority=P)`` (``zenswarm up --realtime
    --rt-priority P``): every flying process reports P and its raised threads in its diagnostics,
    and says so in the log; the calling process is not raised; no collision, no process left."""
    _need_privilege()
    flight = fly("paper_example1", mode="swarm", realtime=True, rt_priority=PRIORITY, duration=4.0,
                 overrides={"timing.settle_time_s": 1.0}, timeout=120)
    res = flight.results
    diag = res["diagnostics"]
    flying = ["plant", "leader"] + [f"agent:{i}" for i in range(1, res["n_uav"] + 1)]
    for name in flying:
        assert diag[name]["rt.priority"] == PRIORITY, (name, diag[name])
        assert diag[name]["rt.threads"] >= 2, (name, diag[name])  # the main thread and zenoh's
        assert diag[name]["loop_ticks"] > 0 and "idle_ticks" in diag[name], (name, diag[name])
    assert f"SCHED_FIFO priority {PRIORITY}" in flight.log
    assert rtsched.current_policy() == ("other", 0)  # this test process was never raised
    assert not res["uav_collision"] and res["finite"] and not flight.leftovers


@pytest.mark.parametrize(("kw", "needle"), [
    ({"mode": "sim", "realtime": False}, "mode='swarm', realtime=True"),
    ({"mode": "swarm", "realtime": False}, "only for realtime flights"),
])
def test_fly_refuses_rt_priority_without_a_realtime_swarm(kw: dict, needle: str) -> None:
    with pytest.raises(ScenarioError) as e:
        fly("paper_example1", rt_priority=5, **kw)
    assert e.value.field == "rt_priority" and needle in str(e.value)

"""Authenticated swarm (zenswarm.process.security): credentials, mutual TLS and graph-generated access control.

Process tests run a real Zenoh router and real client sessions, each in its own OS process (this
file, run as a script, is the worker: ``python test_security.py router|client JSON``), on a free
loopback port and a swarm name of their own. A worker exits when its stdin closes, so no process
outlives its test. "Gets nothing through" is asserted over a bounded wait (``DENY_WAIT_S``) that
starts only once a control message on an allowed key has arrived over the same router, so a
broken ACL (or a broken harness) fails the test instead of passing it by silence.

Observed with eclipse-zenoh 1.10.2: a client session without credentials, with a wrong password
or an unknown user, or presenting a certificate from another CA, is refused at ``zenoh.open``
(ZError "Unable to connect to any of [...]") immediately; an authenticated session that steps
outside its ACL stays open but the router drops the denied messages and declarations.
"""

from __future__ import annotations

import json
import os
import queue
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
EX1 = ROOT / "compose" / "scenarios" / "paper_example1.toml"  # graph 2 - 1 - 3, leader pinned to 1
DENY_WAIT_S = 2.0
OPEN_TIMEOUT_S = 15.0
CONTROL_TIMEOUT_S = 10.0


# =========================================================================== worker (subprocess side)


def _insert(conf: Any, fragments: dict[str, Any]) -> None:
    """What zenswarm.process.security.apply_config does (inlined: a worker imports zenoh only, to start fast)."""
    for path, value in fragments.items():
        conf.insert_json5(path, json.dumps(value))


def _worker_router(args: dict[str, Any]) -> int:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps(args["listen"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    _insert(conf, args.get("fragments", {}))
    out_lock = threading.Lock()

    def emit(**ev: Any) -> None:
        with out_lock:
            sys.stdout.write(json.dumps(ev) + "\n")
            sys.stdout.flush()

    session = zenoh.open(conf)
    held: list[Any] = []
    try:
        # The supervisor's view: a subscriber on the router's own session (not behind the ACL).
        if args.get("sub"):
            held.append(
                session.declare_subscriber(
                    args["sub"], lambda s: emit(ev="sample", sub="router", key=str(s.key_expr), payload=s.payload.to_bytes().decode())
                )
            )
        if args.get("alive_sub"):
            held.append(
                session.liveliness().declare_subscriber(
                    args["alive_sub"],
                    lambda s: emit(ev="sample", sub="router-alive", key=str(s.key_expr), payload=str(s.kind)),
                    history=True,
                )
            )
        emit(ev="ready")
        for line in sys.stdin:  # until the test closes our stdin (or says quit)
            if line.strip() == "quit":
                break
    finally:
        for h in held:
            h.undeclare()
        session.close()
    return 0


def _worker_client(args: dict[str, Any]) -> int:
    import zenoh

    out_lock = threading.Lock()

    def emit(**ev: Any) -> None:
        with out_lock:
            sys.stdout.write(json.dumps(ev) + "\n")
            sys.stdout.flush()

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps(args["connect"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    _insert(conf, args.get("fragments", {}))
    try:
        session = zenoh.open(conf)
    except Exception as e:  # noqa: BLE001 - report what zenoh says
        emit(ev="open_failed", error=f"{type(e).__name__}: {e}")
        return 3
    held: list[Any] = []
    pubs: dict[str, Any] = {}
    stop = threading.Event()
    threads: list[threading.Thread] = []
    try:
        emit(ev="open")
        for line in sys.stdin:
            cmd = json.loads(line)
            op = cmd["op"]
            if op == "quit":
                break
            key = cmd.get("key")
            if op == "sub":

                def cb(sample: Any, sub_key: str = key) -> None:
                    emit(ev="sample", sub=sub_key, key=str(sample.key_expr), payload=sample.payload.to_bytes().decode())

                held.append(session.declare_subscriber(key, cb))
            elif op == "pub":  # publish `payload` every `period` s, `count` times, in the background
                pub = pubs.get(key)
                if pub is None:
                    pub = pubs[key] = session.declare_publisher(key, reliability=zenoh.Reliability.RELIABLE)

                def run(
                    pub: Any = pub, n: int = cmd.get("count", 100), period: float = cmd.get("period", 0.05), payload: str = cmd["payload"]
                ) -> None:
                    for _ in range(n):
                        if stop.is_set():
                            return
                        pub.put(payload.encode())
                        stop.wait(period)

                t = threading.Thread(target=run, daemon=True)
                t.start()
                threads.append(t)
            elif op == "alive_sub":

                def on_alive(sample: Any, sub_key: str = key) -> None:
                    emit(ev="sample", sub=sub_key, key=str(sample.key_expr), payload=str(sample.kind))

                held.append(session.liveliness().declare_subscriber(key, on_alive, history=True))
            elif op == "token":
                held.append(session.liveliness().declare_token(key))
            elif op == "alive_get":
                seen = []
                for reply in session.liveliness().get(key, timeout=cmd.get("timeout", 2.0)):
                    ok = getattr(reply, "ok", None)
                    if ok is not None:
                        seen.append(str(ok.key_expr))
                emit(ev="alive", keys=sorted(seen))
            elif op == "queryable":

                def on_query(query: Any, payload: str = cmd["payload"], qkey: str = key) -> None:
                    query.reply(qkey, payload.encode())

                held.append(session.declare_queryable(key, on_query))
            elif op == "get":
                got = []
                for reply in session.get(key, timeout=cmd.get("timeout", 2.0)):
                    ok = getattr(reply, "ok", None)
                    if ok is not None:
                        got.append(ok.payload.to_bytes().decode())
                emit(ev="replies", key=key, payloads=got)
            else:
                emit(ev="error", error=f"unknown op {op!r}")
                continue
            emit(ev="done", op=op, key=key)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=2.0)
        for h in held:
            try:
                h.undeclare()
            except Exception:  # noqa: BLE001 - best effort on shutdown
                pass
        session.close()
    return 0


if __name__ == "__main__":
    _mode, _args = sys.argv[1], json.loads(sys.argv[2])
    sys.exit(_worker_router(_args) if _mode == "router" else _worker_client(_args))


# =========================================================================== test side

import pytest  # noqa: E402

from zenswarm.bus import free_port, wire  # noqa: E402
from zenswarm.process import security  # noqa: E402
from zenswarm.process.security import (  # noqa: E402
    CredentialsError,
    acl_rules,
    client_security_config,
    generate_credentials,
    load_credentials,
    load_manifest,
    router_security_config,
)
from zenswarm.scenario.config import load_scenario  # noqa: E402


class Worker:
    """One worker subprocess; its JSON events are queued by a reader thread."""

    def __init__(self, mode: str, args: dict[str, Any], name: str) -> None:
        self.name = name
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self.samples: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self.proc = subprocess.Popen(
            [sys.executable, __file__, mode, json.dumps(args)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**os.environ, "RUST_LOG": "off"},
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            if ev.get("ev") == "sample":
                with self._lock:
                    self.samples.append(ev)
            else:
                self.events.put(ev)

    def expect(self, *kinds: str, timeout: float = OPEN_TIMEOUT_S) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"{self.name}: no {kinds} event within {timeout} s; stderr: {self.stderr_tail()}")
            try:
                ev = self.events.get(timeout=left)
            except queue.Empty:
                continue
            if ev.get("ev") in kinds:
                return ev

    def send(self, **cmd: Any) -> dict[str, Any]:
        """Send a command and wait until it is done; return its result event (``alive``,
        ``replies``) or the ``done`` event."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(cmd) + "\n")
        self.proc.stdin.flush()
        result: dict[str, Any] | None = None
        while True:
            ev = self.expect("done", "alive", "replies", "error", timeout=CONTROL_TIMEOUT_S)
            if ev["ev"] == "error":
                raise AssertionError(f"{self.name}: {ev['error']}")
            if ev["ev"] == "done":
                return result or ev
            result = ev

    def got(self, sub: str | None = None, payload: str | None = None, key: str | None = None) -> list[dict[str, Any]]:
        with self._lock:
            return [
                s
                for s in self.samples
                if (sub is None or s["sub"] == sub) and (payload is None or s["payload"] == payload) and (key is None or s["key"] == key)
            ]

    def wait_for(self, timeout: float = CONTROL_TIMEOUT_S, **match: Any) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hits = self.got(**match)
            if hits:
                return hits[0]
            time.sleep(0.02)
        raise AssertionError(f"{self.name}: control message {match} did not arrive within {timeout} s")

    def stderr_tail(self) -> str:
        if self.proc.poll() is None:
            return "(running)"
        return (self.proc.stderr.read() if self.proc.stderr else "")[-2000:]

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.close()  # the worker quits on EOF and closes its session
            except (BrokenPipeError, OSError):
                pass
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5.0)
        self._reader.join(timeout=2.0)
        for f in (self.proc.stdout, self.proc.stderr, self.proc.stdin):
            try:
                if f is not None:
                    f.close()
            except OSError:
                pass


@pytest.fixture
def spawn():
    """Start workers; every one is stopped (and reaped) at the end of the test."""
    started: list[Worker] = []

    def _spawn(mode: str, args: dict[str, Any], name: str) -> Worker:
        w = Worker(mode, args, name)
        started.append(w)
        return w

    yield _spawn
    for w in reversed(started):
        w.close()
    assert all(w.proc.poll() is not None for w in started)


@pytest.fixture(scope="module")
def ex1():
    return load_scenario(EX1)


def start_router(spawn, keys, scenario, swarm: str, auth: str, sub: str | None = None, alive_sub: str | None = None) -> Worker:
    """A router with ``auth`` ("usrpwd" or "tls") and the scenario's ACL (``.endpoint`` to dial).
    ``sub`` / ``alive_sub``: subscribers on the router's own session, as the supervisor has."""
    port = free_port()
    endpoint = f"{'tls' if auth == 'tls' else 'tcp'}/127.0.0.1:{port}"
    frag = router_security_config(keys, scenario, swarm, auth=auth)
    r = spawn("router", {"listen": [endpoint], "fragments": frag, "sub": sub, "alive_sub": alive_sub}, f"router[{swarm}]")
    r.expect("ready")
    r.endpoint = endpoint  # type: ignore[attr-defined]
    return r


def client(spawn, endpoint: str, fragments: dict[str, Any], name: str) -> Worker:
    return spawn("client", {"connect": [endpoint], "fragments": fragments}, name)


def opened(w: Worker) -> bool:
    """True if the session opened; False if zenoh refused it (and the worker then exited)."""
    ev = w.expect("open", "open_failed")
    if ev["ev"] == "open_failed":
        assert "Unable to connect" in ev["error"], ev
        assert w.proc.wait(timeout=OPEN_TIMEOUT_S) == 3
        return False
    return True


def join(spawn, router: Worker, keys, auth: str, *processes: str) -> list[Worker]:
    """Start one authenticated client per process (in parallel); wait until all are open."""
    ws = [client(spawn, router.endpoint, client_security_config(p, keys, auth=auth), p) for p in processes]  # type: ignore[attr-defined]
    for w in ws:
        assert opened(w), f"{w.name} with valid credentials could not open a session: {w.stderr_tail()}"
    return ws


FOREVER = {"count": 100_000, "period": 0.05}  # publish at 20 Hz until the worker is stopped


# =========================================================================== credentials on disk


def test_generate_credentials_layout_and_permissions(tmp_path, ex1):
    m = generate_credentials(ex1, tmp_path / "k", "demo")
    assert [p.process for p in m.processes] == [
        "plant", "leader", "agent:1", "agent:2", "agent:3", "recorder", "bridge", "supervisor",
    ]  # fmt: skip
    assert m.process("agent:2").user == "agent-2@demo"
    assert load_manifest(tmp_path / "k") == m
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    secrets_ = [m.ca_key, m.usrpwd_file] + [f for p in m.processes for f in (p.key, p.credentials)]
    for f in secrets_:
        assert mode(f) == 0o600, f
    for p in m.processes:
        assert mode(p.dir) == 0o700
        assert p.dir == m.root / p.process.replace(":", "-")
    manifest_text = (m.root / "manifest.json").read_text()
    lines = m.usrpwd_file.read_text().splitlines()
    assert len(lines) == len(m.processes)
    passwords = set()
    for p, line in zip(m.processes, lines):
        c = load_credentials(p.process, m.root, "demo")
        assert line == f"{c['user']}:{c['password']}"
        assert len(c["password"]) >= 40 and c["password"] not in manifest_text  # 256 random bits, no secret in the manifest
        passwords.add(c["password"])
    assert len(passwords) == len(m.processes)


@pytest.mark.swarm
def test_certificates_chain_to_the_swarm_ca(tmp_path, ex1):
    from cryptography import x509
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    m = generate_credentials(ex1, tmp_path / "k", "demo", router_hosts=["10.0.0.5", "base.local"])
    ca = x509.load_pem_x509_certificate(m.ca_cert.read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for p in m.processes:
        cert = x509.load_pem_x509_certificate(p.cert.read_bytes())
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == p.process
        assert isinstance(cert.public_key(), ec.EllipticCurvePublicKey) and cert.public_key().curve.name == "secp256r1"
        assert p.ca_cert.read_bytes() == m.ca_cert.read_bytes()
        eku = set(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)
        if p.process == "supervisor":  # the router's certificate: the only one a client accepts as the router
            san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            assert set(san.get_values_for_type(x509.DNSName)) == {"localhost", "base.local"}
            assert {str(a) for a in san.get_values_for_type(x509.IPAddress)} == {"127.0.0.1", "::1", "10.0.0.5"}
            assert eku == {ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH}
        else:
            with pytest.raises(x509.ExtensionNotFound):
                cert.extensions.get_extension_for_class(x509.SubjectAlternativeName)
            assert eku == {ExtendedKeyUsageOID.CLIENT_AUTH}


def test_refuses_to_overwrite_without_force(tmp_path, ex1):
    m1 = generate_credentials(ex1, tmp_path / "k", "demo")
    before = m1.process("agent:1").key.read_bytes()
    with pytest.raises(CredentialsError, match="--force"):
        generate_credentials(ex1, tmp_path / "k", "demo")
    assert m1.process("agent:1").key.read_bytes() == before
    m2 = generate_credentials(ex1, tmp_path / "k", "other", force=True)
    assert m2.swarm == "other" and m2.process("agent:1").key.read_bytes() != before
    assert load_credentials("agent:1", tmp_path / "k")["user"] == "agent-1@other"


def test_cli_keys_prints_and_refuses_overwrite(tmp_path, capsys):
    import argparse

    from zenswarm.compose.keys import add_parsers

    parser = argparse.ArgumentParser(prog="zenswarm")
    add_parsers(parser.add_subparsers(dest="command"))
    out = tmp_path / "keys"
    args = parser.parse_args(["keys", str(EX1), "--out", str(out), "--swarm", "cli", "--router-host", "192.168.1.10"])
    assert args.func(args) == 0
    text = capsys.readouterr().out
    for needle in ("swarm 'cli'", "ca-key.pem", "usrpwd.txt", "agent-3@cli", "192.168.1.10", "manifest.json"):
        assert needle in text
    assert load_manifest(out).router_hosts == ("localhost", "127.0.0.1", "::1", "192.168.1.10")
    again = parser.parse_args(["keys", str(EX1), "--out", str(out)])
    with pytest.raises(CredentialsError, match="refusing to overwrite"):
        again.func(again)
    forced = parser.parse_args(["keys", str(EX1), "--out", str(out), "--force"])
    assert forced.func(forced) == 0


@pytest.mark.swarm
def test_client_config_from_a_copied_process_directory(tmp_path, ex1):
    import shutil

    m = generate_credentials(ex1, tmp_path / "k", "demo")
    host_b = tmp_path / "hostb" / "agent-2"
    shutil.copytree(m.process("agent:2").dir, host_b)  # what gets deployed to another host
    frag = client_security_config("agent:2", host_b, auth="usrpwd", swarm="demo")
    assert frag["transport/auth/usrpwd/user"] == "agent-2@demo"
    tls = client_security_config("agent:2", host_b, auth="tls")
    assert tls["transport/link/tls/connect_certificate"] == str(host_b / "cert.pem")
    assert tls["transport/link/tls/enable_mtls"] is True and tls["transport/link/protocols"] == ["tls"]
    with pytest.raises(CredentialsError, match="agent:2"):
        client_security_config("agent:3", host_b)  # another process's directory
    with pytest.raises(CredentialsError, match="swarm"):
        client_security_config("agent:2", host_b, swarm="other")
    with pytest.raises(CredentialsError, match="swarm"):
        router_security_config(m, ex1, "other")


def test_process_flags(tmp_path, ex1):
    import argparse

    from zenswarm.bridge.args import add_security_args, client_security

    m = generate_credentials(ex1, tmp_path / "k", "demo")
    p = argparse.ArgumentParser()
    p.add_argument("--swarm", default="default")
    p.add_argument("--connect", action="append")
    add_security_args(p)

    def frags(process: str, a: argparse.Namespace) -> dict:
        return security.client_fragments(process, client_security(a), connect=a.connect or (), swarm=a.swarm)

    assert frags("agent:1", p.parse_args([])) == {}  # an open swarm
    a = p.parse_args(["--swarm", "demo", "--keys", str(m.root), "--connect", "tcp/127.0.0.1:7447"])
    assert frags("agent:1", a)["transport/auth/usrpwd/user"] == "agent-1@demo"
    with pytest.raises(CredentialsError, match="tls/"):
        frags("agent:1", p.parse_args(["--swarm", "demo", "--keys", str(m.root), "--tls", "--connect", "tcp/127.0.0.1:7447"]))
    t = p.parse_args(["--swarm", "demo", "--keys", str(m.root), "--tls", "--connect", "tls/127.0.0.1:7447"])
    assert frags("agent:1", t)["transport/link/tls/enable_mtls"] is True
    with pytest.raises(CredentialsError, match="swarm"):
        frags("agent:1", p.parse_args(["--keys", str(m.root)]))  # credentials of swarm demo, flying swarm default
    assert security.is_loopback_endpoint("tcp/127.0.0.1:7447") and security.is_loopback_endpoint("tls/localhost:7447")
    assert not security.is_loopback_endpoint("tcp/0.0.0.0:7447") and not security.is_loopback_endpoint("tcp/192.168.1.2:7447")


# =========================================================================== access rules


def _allowed(acl: dict[str, Any], process: str, message: str, flow: str) -> set[str]:
    sid = {p["subjects"][0]: p for p in acl["policies"]}
    subj = next(
        s
        for s in acl["subjects"]
        if process in s.get("cert_common_names", []) or any(u.startswith(process.replace(":", "-") + "@") for u in s.get("usernames", []))
    )
    rules = {r["id"]: r for r in acl["rules"]}
    out: set[str] = set()
    for rid in sid[subj["id"]]["rules"]:
        r = rules[rid]
        if message in r["messages"] and flow in r["flows"]:
            assert r["permission"] == "allow"
            out |= set(r["key_exprs"])
    return out


def test_acl_follows_the_graph(ex1):
    k = wire.Keys("g")
    acl = acl_rules(ex1, "g")
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    ids = [r["id"] for r in acl["rules"]] + [s["id"] for s in acl["subjects"]]
    assert len(ids) == len(set(ids))
    A = ex1.graph
    for i in range(1, ex1.n + 1):
        p = f"agent:{i}"
        row = {k.state(i)} | {k.ref(j + 1) for j in ex1.neighbours(i - 1)} | ({k.leader_ref} if A.pinning[i - 1] > 0 else set())
        assert _allowed(acl, p, "declare_subscriber", "ingress") == row
        assert _allowed(acl, p, "put", "egress") == row
        assert _allowed(acl, p, "put", "ingress") == {k.ref(i), k.cmd(i), k.diag(p)}
        # its token and its session's (alive/<p>/<zid>: the receivers pin its keys to it)
        assert _allowed(acl, p, "liveliness_token", "ingress") == {k.alive(p), k.alive(p) + "/*"}
        assert _allowed(acl, p, "declare_queryable", "ingress") == set()
        # it watches the processes it waits for, and the sender tokens of its inputs
        deps = ["plant"] + [f"agent:{j + 1}" for j in ex1.neighbours(i - 1)] + (["leader"] if A.pinning[i - 1] > 0 else [])
        watch = {k.alive(d) for d in deps} | {k.alive(d) + "/*" for d in deps + ["bridge"]}
        assert _allowed(acl, p, "declare_liveliness_subscriber", "ingress") == watch
        assert _allowed(acl, p, "liveliness_query", "ingress") == watch
        assert _allowed(acl, p, "liveliness_token", "egress") == watch
    # the contract for paper example 1 (2 - 1 - 3, leader pinned to 1), spelled out
    assert _allowed(acl, "agent:2", "declare_subscriber", "ingress") == {k.state(2), k.ref(1)}
    assert _allowed(acl, "agent:1", "declare_subscriber", "ingress") == {k.state(1), k.ref(2), k.ref(3), k.leader_ref}
    for p in ("plant", "bridge"):
        assert _allowed(acl, p, "put", "ingress") == {"swarm/g/uav/*/state", k.clock, k.diag(p)}
        agents_zid = {k.alive(f"agent:{i}") + "/*" for i in range(1, ex1.n + 1)}
        assert _allowed(acl, p, "liveliness_query", "ingress") == {k.alive_all} | agents_zid
        assert _allowed(acl, p, "liveliness_token", "ingress") == {k.alive(p), k.alive(p) + "/*"}
    assert _allowed(acl, "plant", "declare_subscriber", "ingress") == {"swarm/g/uav/*/cmd"}
    assert _allowed(acl, "bridge", "declare_subscriber", "ingress") == {"swarm/g/uav/*/cmd", "swarm/g/uav/*/ref"}
    assert _allowed(acl, "leader", "put", "ingress") == {k.leader_ref, k.diag("leader")}
    assert _allowed(acl, "leader", "declare_queryable", "ingress") == {k.mission}
    assert _allowed(acl, "leader", "declare_subscriber", "ingress") == {k.clock}
    # the leader keeps its token until the plant is gone, so it must see the plant's token (and
    # the clock's senders' session tokens), and nothing else
    leader_watch = {k.alive("plant"), k.alive("plant") + "/*", k.alive("bridge") + "/*"}
    assert _allowed(acl, "leader", "declare_liveliness_subscriber", "ingress") == leader_watch
    assert _allowed(acl, "leader", "liveliness_query", "ingress") == leader_watch
    assert _allowed(acl, "leader", "liveliness_token", "egress") == leader_watch
    assert _allowed(acl, "leader", "liveliness_token", "ingress") == {k.alive("leader"), k.alive("leader") + "/*"}
    for p in ("recorder", "supervisor"):
        assert _allowed(acl, p, "declare_subscriber", "ingress") == {k.all}
        assert _allowed(acl, p, "put", "ingress") == {k.diag(p)}
        assert _allowed(acl, p, "liveliness_token", "ingress") == {k.alive(p)}
    assert {s["id"]: s["usernames"] for s in acl["subjects"]}["g.agent-2"] == ["agent-2@g"]
    tls = acl_rules(ex1, "g", auth="tls")
    assert {s["id"]: s["cert_common_names"] for s in tls["subjects"]}["g.agent-2"] == ["agent:2"]


def test_the_mocap_feed_has_its_own_user_only_with_extpos(tmp_path, ex1):
    """positioning = "extpos": a user ``mocap@<swarm>`` allowed to put ``mocap/<i>`` (i = 1..N)
    and nothing else, and the bridge may subscribe to ``mocap/*``; without it neither exists
    (a scenario without the feed is unchanged), and credentials without it do not fit."""
    from dataclasses import replace

    from zenswarm.process.security import generate_credentials, load_manifest, manifest_mismatch
    from zenswarm.schema import CrazyflieTable

    k = wire.Keys("g")
    assert "mocap" not in {s["id"].split(".", 1)[1] for s in acl_rules(ex1, "g")["subjects"]}
    assert _allowed(acl_rules(ex1, "g"), "bridge", "declare_subscriber", "ingress") == {"swarm/g/uav/*/cmd", "swarm/g/uav/*/ref"}
    ext = replace(ex1, crazyflie=CrazyflieTable(positioning="extpos"))
    acl = acl_rules(ext, "g")
    mocap = {f"{k.prefix}/mocap/{i}" for i in range(1, ext.n + 1)}
    assert _allowed(acl, "mocap", "put", "ingress") == mocap
    assert _allowed(acl, "mocap", "declare_subscriber", "egress") == {k.all}  # sees who subscribes, no data
    for message, flow in (("declare_subscriber", "ingress"), ("put", "egress"), ("liveliness_token", "ingress"),
                          ("query", "ingress"), ("liveliness_query", "ingress"), ("declare_queryable", "ingress")):
        assert _allowed(acl, "mocap", message, flow) == set(), (message, flow)
    assert _allowed(acl, "bridge", "declare_subscriber", "ingress") == {"swarm/g/uav/*/cmd", "swarm/g/uav/*/ref", "swarm/g/mocap/*"}
    assert _allowed(acl, "bridge", "put", "egress") >= {"swarm/g/mocap/*"}
    assert _allowed(acl, "plant", "declare_subscriber", "ingress") == {"swarm/g/uav/*/cmd"}
    assert {s["id"]: s["usernames"] for s in acl["subjects"]}["g.mocap"] == ["mocap@g"]
    assert {s["id"]: s["cert_common_names"] for s in acl_rules(ext, "g", auth="tls")["subjects"]}["g.mocap"] == ["mocap"]
    old = generate_credentials(ex1, tmp_path / "old", "g")
    assert "mocap" not in {p.process for p in old.processes} and manifest_mismatch(old, ex1, "g") is None
    assert "no credentials for mocap" in (manifest_mismatch(old, ext, "g") or "")
    new = load_manifest(generate_credentials(ext, tmp_path / "new", "g").root)
    assert new.process("mocap").user == "mocap@g" and manifest_mismatch(new, ext, "g", all_files=True) is None
    assert client_security_config("mocap", tmp_path / "new")["transport/auth/usrpwd/user"] == "mocap@g"


@pytest.mark.swarm
def test_router_config_is_accepted_by_zenoh(tmp_path, ex1):
    import zenoh

    m = generate_credentials(ex1, tmp_path / "k", "demo")
    for auth in ("usrpwd", "tls"):
        conf = security.apply_config(zenoh.Config(), router_security_config(m, ex1, auth=auth))
        acl = json.loads(conf.get_json("access_control"))
        assert acl["enabled"] is True and len(acl["policies"]) == len(m.processes)
        security.apply_config(zenoh.Config(), client_security_config("agent:1", m.root, auth=auth))
    assert security.tls_endpoint("tcp/127.0.0.1:7447") == "tls/127.0.0.1:7447"


# =========================================================================== a real router


@pytest.mark.swarm
def test_usrpwd_refuses_sessions_without_valid_credentials(spawn, tmp_path, ex1):
    m = generate_credentials(ex1, tmp_path / "k", "auth1")
    other = generate_credentials(ex1, tmp_path / "other", "auth1")  # same swarm and user names, other passwords
    router = start_router(spawn, m, ex1, "auth1", "usrpwd")
    ep = router.endpoint
    good = client_security_config("agent:1", m.root)
    wrong_pw = {**good, "transport/auth/usrpwd/password": "not-the-password"}
    unknown = {"transport/auth/usrpwd/user": "intruder@auth1", "transport/auth/usrpwd/password": "x"}
    attempts = {
        "no credentials": client(spawn, ep, {}, "anonymous"),
        "wrong password": client(spawn, ep, wrong_pw, "wrong-password"),
        "unknown user": client(spawn, ep, unknown, "unknown-user"),
        "another key set": client(spawn, ep, client_security_config("agent:1", other.root), "other-keys"),
    }
    control = client(spawn, ep, good, "agent:1")
    assert opened(control)
    for what, w in attempts.items():
        assert not opened(w), f"a session with {what} was opened"


@pytest.mark.swarm
def test_mtls_refuses_certificates_from_another_ca(spawn, tmp_path, ex1):
    m = generate_credentials(ex1, tmp_path / "k", "auth2")
    foreign = generate_credentials(ex1, tmp_path / "foreign", "auth2")  # same common names, another CA
    router = start_router(spawn, m, ex1, "auth2", "tls")
    ep = router.endpoint
    good = client_security_config("agent:1", m.root, auth="tls")
    # trusts the real router (our CA) but presents a certificate signed by the foreign CA
    forged = {**good, **{k: v for k, v in client_security_config("agent:1", foreign.root, auth="tls").items() if "connect_" in k}}
    no_cert = {"transport/link/tls/root_ca_certificate": good["transport/link/tls/root_ca_certificate"]}
    attempts = {
        "a certificate from another CA": client(spawn, ep, forged, "foreign-cert"),
        "no client certificate": client(spawn, ep, no_cert, "no-cert"),
        "plain TCP and a password": client(spawn, ep.replace("tls/", "tcp/"), client_security_config("agent:1", m.root), "tcp"),
    }
    control = client(spawn, ep, good, "agent:1")
    assert opened(control)
    for what, w in attempts.items():
        assert not opened(w), f"a session with {what} was opened"


@pytest.mark.parametrize("auth", ["usrpwd", "tls"])
@pytest.mark.swarm
def test_agent_cannot_publish_or_subscribe_outside_its_graph_row(spawn, tmp_path, ex1, auth):
    swarm = f"row-{auth}"
    k = wire.Keys(swarm)
    m = generate_credentials(ex1, tmp_path / "k", swarm)
    router = start_router(spawn, m, ex1, swarm, auth, sub=k.all)  # the router's own session = the supervisor's view
    plant, a1, a2, a3 = join(spawn, router, m.root, auth, "plant", "agent:1", "agent:2", "agent:3")

    plant.send(op="sub", key=f"{k.prefix}/uav/*/cmd")
    for key in (k.state(1), k.ref(2), k.ref(3), k.leader_ref):  # agent 1's row: neighbours 2, 3; pinned
        a1.send(op="sub", key=key)
    a2.send(op="sub", key=k.ref(1))  # its neighbour: allowed (control)
    for key in (k.ref(3), k.state(1), k.all):  # a non-neighbour's ref, another UAV's state, everything
        a2.send(op="sub", key=key)

    plant.send(op="pub", key=k.state(1), payload="state1", **FOREVER)
    a1.send(op="pub", key=k.ref(1), payload="ref1", **FOREVER)
    a3.send(op="pub", key=k.ref(3), payload="ref3", **FOREVER)
    a3.send(op="pub", key=k.cmd(3), payload="cmd3", **FOREVER)
    a2.send(op="pub", key=k.cmd(2), payload="cmd2", **FOREVER)
    a2.send(op="pub", key=k.cmd(3), payload="forged", **FOREVER)  # another agent's command
    a2.send(op="pub", key=k.ref(3), payload="forged", **FOREVER)  # another agent's reference
    a2.send(op="pub", key=k.leader_ref, payload="forged", **FOREVER)  # the leader's reference

    # controls on allowed keys, through the same router
    plant.wait_for(key=k.cmd(2), payload="cmd2")
    plant.wait_for(key=k.cmd(3), payload="cmd3")
    a1.wait_for(sub=k.ref(3), payload="ref3")
    a1.wait_for(sub=k.state(1), payload="state1")
    a2.wait_for(sub=k.ref(1), payload="ref1")
    router.wait_for(key=k.cmd(2), payload="cmd2")
    time.sleep(DENY_WAIT_S)

    assert plant.got(payload="forged") == [], "agent 2 published a command for UAV 3"
    assert a1.got(payload="forged") == [], "agent 2 published UAV 3's or the leader's reference"
    assert router.got(payload="forged") == [], "a forged message got into the router"
    assert a2.got(sub=k.ref(3), payload="ref3") == [], "agent 2 read a non-neighbour's reference"
    assert a2.got(sub=k.state(1)) == [], "agent 2 read UAV 1's state"
    # A session hands every sample it has (its own puts, and what the router sent it for its
    # allowed subscriptions) to all its matching local subscribers, so ``**`` sees those and
    # nothing else: nothing of UAV 1's state, UAV 3's reference or command.
    allowed_here = {"cmd2", "forged", "ref1"}
    assert {s["payload"] for s in a2.got(sub=k.all)} <= allowed_here, "agent 2 read the whole swarm"


@pytest.mark.swarm
def test_plant_states_reach_only_their_own_agent(spawn, tmp_path, ex1):
    swarm = "states"
    k = wire.Keys(swarm)
    m = generate_credentials(ex1, tmp_path / "k", swarm)
    router = start_router(spawn, m, ex1, swarm, "usrpwd")
    plant, recorder, *ags = join(spawn, router, m.root, "usrpwd", "plant", "recorder", "agent:1", "agent:2", "agent:3")
    agents = dict(zip((1, 2, 3), ags))
    recorder.send(op="sub", key=k.all)
    for i, a in agents.items():
        a.send(op="sub", key=k.state(i))
        for j in (1, 2, 3):
            if j != i:
                a.send(op="sub", key=k.state(j))
        a.send(op="sub", key=f"{k.prefix}/uav/*/state")
    for i in (1, 2, 3):
        plant.send(op="pub", key=k.state(i), payload=f"state{i}", **FOREVER)
    for i, a in agents.items():
        a.wait_for(sub=k.state(i), payload=f"state{i}")
        recorder.wait_for(key=k.state(i), payload=f"state{i}")  # the recorder reads everything
    time.sleep(DENY_WAIT_S)
    for i, a in agents.items():
        # (its own state may reach it twice: a session fans a sample out to all its matching
        # subscribers, here its allowed one and its denied ``uav/*/state``)
        got = {(s["key"], s["payload"]) for s in a.got()}
        assert got == {(k.state(i), f"state{i}")}, f"agent {i} received {sorted(got)}"


@pytest.mark.swarm
def test_liveliness_and_mission_only_from_their_owners(spawn, tmp_path, ex1):
    swarm = "alive"
    k = wire.Keys(swarm)
    m = generate_credentials(ex1, tmp_path / "k", swarm)
    router = start_router(spawn, m, ex1, swarm, "usrpwd", alive_sub=k.alive_all)
    plant, leader, recorder, a1, a2 = join(spawn, router, m.root, "usrpwd", "plant", "leader", "recorder", "agent:1", "agent:2")
    recorder.send(op="alive_sub", key=k.alive_all)
    leader.send(op="queryable", key=k.mission, payload="MISSION")
    a2.send(op="queryable", key=k.mission, payload="FAKE MISSION")  # impersonating the leader
    for p, w in (("leader", leader), ("agent:1", a1), ("agent:2", a2)):
        w.send(op="token", key=k.alive(p))
    a2.send(op="token", key=k.alive("agent:3"))  # forged tokens for processes that are not running
    a2.send(op="token", key=k.alive("recorder"))
    honest = {k.alive("leader"), k.alive("agent:1"), k.alive("agent:2")}
    recorder.wait_for(key=k.alive("agent:2"))
    deadline = time.monotonic() + CONTROL_TIMEOUT_S
    while set(plant.send(op="alive_get", key=k.alive_all, timeout=1.0)["keys"]) != honest:
        assert time.monotonic() < deadline, "the plant never saw exactly the honest tokens"
    assert a1.send(op="get", key=k.mission)["payloads"] == ["MISSION"]
    time.sleep(DENY_WAIT_S)
    assert {s["key"] for s in recorder.got()} == honest
    assert {s["key"] for s in router.got()} == honest  # the supervisor's liveliness view
    assert set(plant.send(op="alive_get", key=k.alive_all, timeout=1.0)["keys"]) == honest


@pytest.mark.swarm
def test_session_tokens_only_from_their_owners_and_seen_by_their_receivers(spawn, tmp_path, ex1):
    """alive/<p>/<zid> (which session is process p; the input guard pins each key to it): only p's
    credentials may declare it, and exactly the processes that receive p's messages see it. The
    leader sees the plant's token (it stays until the plant is gone: without it, it lingered
    30 s after every secure flight)."""
    swarm = "zid"
    k = wire.Keys(swarm)
    m = generate_credentials(ex1, tmp_path / "k", swarm)
    router = start_router(spawn, m, ex1, swarm, "usrpwd", alive_sub=f"{k.prefix}/alive/*/*")
    plant, leader, a1, a2, a3 = join(spawn, router, m.root, "usrpwd", "plant", "leader", "agent:1", "agent:2", "agent:3")
    leader.send(op="alive_sub", key=k.alive("plant"))
    leader.send(op="alive_sub", key=k.alive("plant") + "/*")
    plant.send(op="alive_sub", key=k.alive("agent:2") + "/*")
    plant.send(op="alive_sub", key=k.alive("agent:3") + "/*")
    a1.send(op="alive_sub", key=k.alive("agent:2") + "/*")  # UAV 2 is agent 1's neighbour
    a2.send(op="alive_sub", key=k.alive("agent:3") + "/*")  # UAV 3 is not agent 2's
    a2.send(op="alive_sub", key=k.alive("leader"))  # agent 2 is not pinned: it does not wait for the leader
    plant.send(op="token", key=k.alive("plant"))
    plant.send(op="token", key=k.alive("plant") + "/zp")
    leader.send(op="token", key=k.alive("leader"))
    a2.send(op="token", key=k.alive("agent:2") + "/z2")
    a3.send(op="token", key=k.alive("agent:3") + "/z3")
    a2.send(op="token", key=k.alive("agent:3") + "/forged")  # another agent's session token
    a2.send(op="token", key=k.alive("plant") + "/forged")  # the plant's
    a1.send(op="token", key=k.alive("agent:3") + "/forged1")
    # controls: allowed tokens reach their watchers through the same router
    leader.wait_for(key=k.alive("plant"))
    leader.wait_for(key=k.alive("plant") + "/zp")
    plant.wait_for(key=k.alive("agent:2") + "/z2")
    a1.wait_for(key=k.alive("agent:2") + "/z2")
    router.wait_for(key=k.alive("agent:2") + "/z2")
    plant.wait_for(key=k.alive("agent:3") + "/z3")
    time.sleep(DENY_WAIT_S)
    assert {s["key"] for s in leader.got()} == {k.alive("plant"), k.alive("plant") + "/zp"}
    assert {s["key"] for s in plant.got()} == {k.alive("agent:2") + "/z2", k.alive("agent:3") + "/z3"}, \
        "a forged session token reached the plant"
    assert {s["key"] for s in a1.got()} == {k.alive("agent:2") + "/z2"}
    # (a session shows its own tokens to its own subscribers without the router: agent 2 sees the
    # token it forged itself, and nothing from the others)
    assert {s["key"] for s in a2.got()} == {k.alive("agent:3") + "/forged"}, "agent 2 watched tokens outside its graph row"
    assert {s["key"] for s in router.got()} == {k.alive("plant") + "/zp", k.alive("agent:2") + "/z2", k.alive("agent:3") + "/z3"}

"""Wire protocol: keys, bit-exact round trips, every reject reason, never-raising Decoder."""

from __future__ import annotations

import math
import struct
from typing import Any

import msgpack
import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from zenswarm.bus import wire as w
from zenswarm.errors import DecodeError, ZenswarmError

# --------------------------------------------------------------------------- helpers

TRICKY = [0.1, -0.0, 5e-324, 1.7976931348623157e308, -2.2250738585072014e-308, 1 / 3, 123456.789e-7]


def _vec(*xs: float) -> np.ndarray:
    return np.array(xs, dtype=np.float64)


def _bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def _samples() -> list[w.Message]:
    return [
        w.Clock(t=w.t_ns(12.34), seq=1234),
        w.State(t=10, seq=1, q=TRICKY[:3], v=TRICKY[3:6], rpy=_vec(0.0, -0.1, math.pi), w=_vec(1e-300, -1e300, 7.0)),
        w.Ref(t=0, seq=0, q=_vec(1.0, 2.0, 3.0), v=[-0.0, 0.0, 0.1]),
        w.Cmd(t=w.MAX_T_NS, seq=w.MAX_SEQ, thrust=0.1 + 0.2, rpy=TRICKY[4:7], u=_vec(1, 2, 3), d_hat=_vec(-0.0, 5e-324, 1e-9)),
        w.Mission(t=5, seq=2, scenario={"a": [1, 2.5, None, True, "x"], "b": {"c": {"d": [[0.1], []]}}, "e": -(2**63)}),
        w.Diag(t=7, seq=3, process="agent:12", counters={"rejected": 3, "loop_s": 0.00123}, info={"last": "ok", "n": [1]}),
    ]


def _assert_bit_equal(a: w.Message, b: w.Message) -> None:
    assert type(a) is type(b)
    assert a == b
    for f in msgspec.structs.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert y.dtype == np.float64 and y.shape == (3,)
            assert _bits(x) == _bits(y), f.name
        elif isinstance(x, float):
            assert struct.pack("<d", x) == struct.pack("<d", y), f.name
        else:
            assert x == y and type(x) is type(y), f.name


def _wire_dict(msg: w.Message) -> dict[str, Any]:
    return msgpack.unpackb(w.encode(msg))


_VALID = {m.kind: _wire_dict(m) for m in _samples()}
DEL = object()


def _payload(kind: str, **changes: Any) -> bytes:
    d = dict(_VALID[kind])
    for k, v in changes.items():
        if v is DEL:
            d.pop(k, None)
        else:
            d[k] = v
    return msgpack.packb(d, use_bin_type=True)


# --------------------------------------------------------------------------- keys and names


def test_key_layout() -> None:
    k = w.Keys("demo_1-x")
    assert k.prefix == "swarm/demo_1-x"
    assert k.clock == "swarm/demo_1-x/clock"
    assert k.mission == "swarm/demo_1-x/mission"
    assert k.leader_ref == "swarm/demo_1-x/leader/ref"
    assert k.state(1) == "swarm/demo_1-x/uav/1/state"
    assert k.ref(12) == "swarm/demo_1-x/uav/12/ref"
    assert k.cmd(3) == "swarm/demo_1-x/uav/3/cmd"
    assert k.diag("plant") == "swarm/demo_1-x/diag/plant"
    assert k.alive("agent:2") == "swarm/demo_1-x/alive/agent:2"
    assert k.all == "swarm/demo_1-x/**"
    assert k.alive_all == "swarm/demo_1-x/alive/*"


def test_parse_inverts_every_key() -> None:
    k = w.Keys("s")
    cases = {
        k.clock: ("clock", None, None),
        k.mission: ("mission", None, None),
        k.leader_ref: ("leader_ref", None, None),
        k.state(4): ("state", 4, None),
        k.ref(40): ("ref", 40, None),
        k.cmd(1): ("cmd", 1, None),
    }
    for p in ("plant", "leader", "agent:7", "recorder", "bridge", "supervisor"):
        cases[k.diag(p)] = ("diag", None, p)
        cases[k.alive(p)] = ("alive", None, p)
    for key, expected in cases.items():
        assert k.parse(key) == expected
        assert w.message_kind(expected[0]) in (*w.KINDS, None)
    assert w.message_kind("leader_ref") == "ref"
    assert w.message_kind("alive") is None


@pytest.mark.parametrize(
    "key",
    [
        "swarm/s2/clock",  # another swarm with a longer name
        "swarm/s",
        "swarm/s/",
        "other/s/clock",
        "swarm/s/uav/0/state",
        "swarm/s/uav/01/state",
        "swarm/s/uav/x/state",
        "swarm/s/uav/1/pose",
        "swarm/s/uav/1/state/extra",
        "swarm/s/diag/agent:0",
        "swarm/s/alive/agent",
        "swarm/s/alive/nobody",
        "swarm/s/leader/state",
        "swarm/s/clock/x",
    ],
)
def test_parse_rejects(key: str) -> None:
    with pytest.raises(w.InvalidKeyError):
        w.Keys("s").parse(key)


@pytest.mark.parametrize("name", ["", "a/b", "a*", "a b", "x" * 65, "é", "a$", "a?", "a#b", None, 3])
def test_bad_swarm_name_is_named(name: Any) -> None:
    with pytest.raises(ZenswarmError) as ei:
        w.Keys(name)
    assert repr(name) in str(ei.value)
    assert isinstance(ei.value, w.InvalidKeyError)


def test_good_swarm_names() -> None:
    for name in ("a", "x" * 64, "A-b_9"):
        assert w.Keys(name).name == name


@pytest.mark.parametrize("p", ["agent:0", "agent:01", "agent", "agent:-1", "Plant", "agent:2 ", "agent-2", ""])
def test_bad_process_names(p: str) -> None:
    with pytest.raises(w.InvalidKeyError, match=repr(p).replace("(", r"\(")):
        w.Keys("s").alive(p)


@pytest.mark.parametrize("i", [0, -1, True, 1.0, "1", 10**9])
def test_bad_uav_index(i: Any) -> None:
    with pytest.raises(w.InvalidKeyError):
        w.Keys("s").state(i)


def test_process_helpers() -> None:
    assert w.agent(3) == "agent:3"
    assert w.process_uav("agent:3") == 3
    assert w.process_uav("plant") is None
    with pytest.raises(w.InvalidKeyError):
        w.process_uav("agent:0")


# --------------------------------------------------------------------------- time


def test_t_ns_exact_for_tick_multiples() -> None:
    for dt_ns, dt in ((10_000_000, 0.01), (1_000_000, 0.001), (2_500_000, 0.0025)):
        for k in range(0, 200_000, 7):
            assert w.t_ns(k * dt) == k * dt_ns
    assert w.t_s(w.t_ns(12.5)) == 12.5
    with pytest.raises(w.MessageError):
        w.t_ns(float("nan"))


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("msg", _samples(), ids=lambda m: m.kind)
def test_round_trip_bit_exact(msg: w.Message) -> None:
    data = w.encode(msg)
    assert isinstance(data, bytes)
    back = w.decode(msg.kind, data)
    _assert_bit_equal(msg, back)
    assert w.encode(back) == data


def test_wire_layout_is_a_versioned_map_of_float64() -> None:
    d = _VALID["state"]
    assert d["v"] == w.SCHEMA_VERSION and d["k"] == "state"
    assert set(d) == {"v", "k", "t", "seq", "q", "vel", "rpy", "w"}
    raw = w.encode(w.Ref(t=1, seq=1, q=[0.1, 0.2, 0.3], v=[0, 0, 0]))
    assert raw.count(b"\xcb") == 6  # six msgpack float64 markers, no float32 (\xca)
    assert b"\xca" not in raw


# Payloads as the hand-written codec before msgspec (commit 60b99a4) packed them, byte for byte:
# recordings made before decode, and what is sent now is what was sent then.
GOLDEN = {
    "state": (
        "88a17601a16ba57374617465a1740aa373657101a17193cb3fb999999999999acbbfc999999999999acb3fd3333333333333"
        "a376656c93cb3ff0000000000000cb4000000000000000cb4008000000000000a372707993cb0000000000000000cb0000000000000000"
        "cb0000000000000000a17793cb0000000000000000cb0000000000000000cb0000000000000000"
    ),
    "diag": (
        "87a17601a16ba464696167a17407a373657103a770726f63657373a86167656e743a3132a8636f756e7465727382a16e03a178cb3fe0"
        "000000000000a4696e666f81a1619201c0"
    ),
}


def test_wire_bytes_unchanged() -> None:
    msgs = {
        "state": w.State(t=10, seq=1, q=[0.1, -0.2, 0.3], v=[1, 2, 3], rpy=[0, 0, 0], w=[0, 0, 0]),
        "diag": w.Diag(t=7, seq=3, process="agent:12", counters={"n": 3, "x": 0.5}, info={"a": [1, None]}),
    }
    for kind, msg in msgs.items():
        old = bytes.fromhex(GOLDEN[kind])
        assert w.encode(msg) == old, kind
        assert w.decode(kind, old) == msg


def test_state_stamp_is_optional_and_left_out_when_absent() -> None:
    """``state.ts`` (the MAVLink bridge's vehicle time): absent, the payload is the golden one;
    present, it round-trips, signed, within +-MAX_T_NS; a bad one is rejected naming the field."""
    base = dict(t=10, seq=1, q=[0.1, -0.2, 0.3], v=[1, 2, 3], rpy=[0, 0, 0], w=[0, 0, 0])
    assert w.State(**base).stamp is None and w.encode(w.State(**base, stamp=None)) == bytes.fromhex(GOLDEN["state"])
    for stamp in (0, -3, 9, w.MAX_T_NS, -w.MAX_T_NS):
        m = w.State(**base, stamp=stamp)
        data = w.encode(m)
        assert data.startswith(b"\x89") and data.endswith(b"\xa2ts" + msgpack.packb(stamp))
        back = w.decode("state", data)
        assert back.stamp == stamp and back == m and back != w.State(**base)
    with pytest.raises(w.MessageError, match="stamp"):
        w.State(**base, stamp=1.5)
    with pytest.raises(w.MessageError, match="out_of_range"):
        w.State(**base, stamp=w.MAX_T_NS + 1)
    for bad, reason in ((1.5, "type"), (-w.MAX_T_NS - 1, "out_of_range"), ("x", "type")):
        payload = msgpack.packb({**_VALID["state"], "ts": bad})
        with pytest.raises(w.WireDecodeError) as e:
            w.decode("state", payload)
        assert e.value.reason == reason and e.value.field == "ts"


def test_messages_are_immutable_and_copied() -> None:
    src = np.array([1.0, 2.0, 3.0])
    r = w.Ref(t=1, seq=2, q=src, v=src)
    src[0] = 99.0
    assert r.q[0] == 1.0
    with pytest.raises(AttributeError):  # frozen
        r.t = 5  # type: ignore[misc]
    with pytest.raises(ValueError):
        r.q[0] = 5.0
    back = w.decode("ref", w.encode(r))
    with pytest.raises(ValueError):
        back.v[1] = 5.0


@pytest.mark.parametrize(
    "build, field, reason",
    [
        (lambda: w.Clock(t=-1, seq=0), "t", "negative"),
        (lambda: w.Clock(t=1.0, seq=0), "t", "type"),
        (lambda: w.Clock(t=True, seq=0), "t", "type"),
        (lambda: w.Clock(t=w.MAX_T_NS + 1, seq=0), "t", "out_of_range"),
        (lambda: w.Clock(t=0, seq=-3), "seq", "negative"),
        (lambda: w.Ref(t=0, seq=0, q=[1, 2], v=[0, 0, 0]), "q", "length"),
        (lambda: w.Ref(t=0, seq=0, q=[1, 2, float("nan")], v=[0, 0, 0]), "q", "nonfinite"),
        (lambda: w.Ref(t=0, seq=0, q=["a", 2, 3], v=[0, 0, 0]), "q", "type"),
        (lambda: w.Cmd(t=0, seq=0, thrust=float("inf"), rpy=[0] * 3, u=[0] * 3, d_hat=[0] * 3), "thrust", "nonfinite"),
        (lambda: w.Cmd(t=0, seq=0, thrust=True, rpy=[0] * 3, u=[0] * 3, d_hat=[0] * 3), "thrust", "type"),
        (lambda: w.Mission(t=0, seq=0, scenario={1: 2}), "scenario", "type"),
        (lambda: w.Mission(t=0, seq=0, scenario={"a": {1, 2}}), "scenario.a", "type"),
        (lambda: w.Mission(t=0, seq=0, scenario={"a": float("nan")}), "scenario.a", "nonfinite"),
        (lambda: w.Diag(t=0, seq=0, process="agent:0"), "process", "value"),
        (lambda: w.Diag(t=0, seq=0, process="plant", counters={"x": "1"}), "counters.x", "type"),
    ],
)
def test_constructors_validate(build: Any, field: str, reason: str) -> None:
    with pytest.raises(w.MessageError) as ei:
        build()
    assert ei.value.field == field and ei.value.reason == reason
    assert field in str(ei.value)


def test_mission_normalises_plain_types() -> None:
    m = w.Mission(t=0, seq=0, scenario={"a": (1, 2), "b": np.float64(0.5), "c": np.int64(3), "d": np.bool_(True)})
    assert m.scenario == {"a": [1, 2], "b": 0.5, "c": 3, "d": True}
    assert type(m.scenario["b"]) is float and type(m.scenario["c"]) is int and type(m.scenario["d"]) is bool
    assert w.decode("mission", w.encode(m)) == m


def test_encode_bounds_and_types() -> None:
    big = {"x": "a" * (w.MAX_PAYLOAD + 10)}
    mission = w.Mission(t=0, seq=0, scenario=big)  # missions may exceed MAX_PAYLOAD
    assert w.decode("mission", w.encode(mission)) == mission
    with pytest.raises(w.MessageError) as ei:
        w.encode(w.Diag(t=0, seq=0, process="plant", info=big))
    assert ei.value.reason == "oversize"
    with pytest.raises(w.MessageError):
        w.encode(w.Mission(t=0, seq=0, scenario={"x": "a" * (w.MAX_MISSION_PAYLOAD + 1)}))
    with pytest.raises(w.MessageError):
        w.encode({"v": 1})  # type: ignore[arg-type]


# --------------------------------------------------------------------------- rejects

_nested: Any = 0.0
for _ in range(w.MAX_DEPTH + 2):
    _nested = [_nested]

REJECTS: list[tuple[str, str, Any]] = [
    ("oversize", "state", b"\x80" + b"\x00" * w.MAX_PAYLOAD),
    ("oversize", "mission", b"\x80" * (w.MAX_MISSION_PAYLOAD + 1)),
    ("malformed", "state", b"\xc1"),
    ("malformed", "state", b""),
    ("malformed", "state", w.encode(_samples()[1])[:-3]),  # truncated
    ("malformed", "state", w.encode(_samples()[1]) + b"\x00"),  # trailing bytes
    ("malformed", "clock", b"\x81\xa1v\xc4\xff"),  # bin length beyond the payload
    ("malformed", "clock", b"\xa2\xff\xfe"),  # invalid utf-8 string
    ("malformed", "clock", "not bytes"),
    ("malformed", "clock", msgpack.packb({1: 2})),  # non-string map key
    ("not_map", "state", msgpack.packb([1, 2, 3])),
    ("not_map", "clock", msgpack.packb(None)),
    ("version", "state", _payload("state", v=DEL)),
    ("version", "state", _payload("state", v=2)),
    ("version", "state", _payload("state", v="1")),
    ("version", "state", _payload("state", v=True)),
    ("kind", "state", _payload("state", k=DEL)),
    ("kind", "state", _payload("ref")),
    ("kind", "no-such-kind", _payload("ref")),
    ("missing_field", "state", _payload("state", w=DEL)),
    ("missing_field", "diag", _payload("diag", info=DEL)),
    ("extra_field", "state", _payload("state", extra=1)),
    ("extra_field", "ref", _payload("ref", v_=1)),
    ("type", "state", _payload("state", t=1.0)),
    ("type", "state", _payload("state", t=True)),
    ("type", "state", _payload("state", seq="1")),
    ("type", "state", _payload("state", q=[True, 0.0, 0.0])),
    ("type", "state", _payload("state", q={"x": 1})),
    ("type", "state", _payload("state", q=[None, 0.0, 0.0])),
    ("type", "cmd", _payload("cmd", thrust="1")),
    ("type", "cmd", _payload("cmd", thrust=False)),
    ("type", "cmd", _payload("cmd", thrust=[1.0])),
    ("type", "mission", _payload("mission", scenario=[1])),
    ("type", "mission", _payload("mission", scenario={"a": b"bytes"})),
    ("type", "mission", _payload("mission", scenario={"a": msgpack.ExtType(5, b"x")})),
    ("type", "diag", _payload("diag", process=3)),
    ("type", "diag", _payload("diag", counters=[1])),
    ("type", "diag", _payload("diag", counters={"a": True})),
    ("type", "diag", _payload("diag", counters={"a": "1"})),
    ("type", "diag", _payload("diag", info=None)),
    ("length", "state", _payload("state", q=[0.0, 0.0])),
    ("length", "ref", _payload("ref", vel=[0.0, 0.0, 0.0, 0.0])),
    ("length", "cmd", _payload("cmd", d_hat=[])),
    ("nonfinite", "state", _payload("state", q=[0.0, float("nan"), 0.0])),
    ("nonfinite", "state", _payload("state", w=[float("inf"), 0.0, 0.0])),
    ("nonfinite", "cmd", _payload("cmd", thrust=float("-inf"))),
    ("nonfinite", "mission", _payload("mission", scenario={"a": [{"b": float("nan")}]})),
    ("nonfinite", "diag", _payload("diag", counters={"a": float("inf")})),
    ("negative", "state", _payload("state", t=-1)),
    ("negative", "clock", _payload("clock", seq=-5)),
    ("out_of_range", "state", _payload("state", t=w.MAX_T_NS + 1)),
    ("out_of_range", "clock", _payload("clock", seq=2**63)),
    ("nesting", "mission", _payload("mission", scenario={"a": _nested})),
    ("nesting", "diag", _payload("diag", info={"a": _nested})),
    ("nesting", "state", b"\x91" * 5000 + b"\xc0"),  # msgpack's own stack limit
    ("value", "diag", _payload("diag", process="agent:0")),
    ("value", "diag", _payload("diag", process="hacker")),
]


@pytest.mark.parametrize("reason, kind, payload", REJECTS, ids=[f"{r}-{k}-{i}" for i, (r, k, _) in enumerate(REJECTS)])
def test_decode_rejects_with_named_reason(reason: str, kind: str, payload: Any) -> None:
    with pytest.raises(DecodeError) as ei:
        w.decode(kind, payload)
    e = ei.value
    assert isinstance(e, w.WireDecodeError)
    assert e.reason == reason, str(e)
    assert str(e).startswith(reason)


def test_every_reason_is_exercised() -> None:
    covered = {r for r, _, _ in REJECTS} | {"stale"}  # stale: test_decoder_stale_seq
    assert covered == set(w.REASONS)


def test_reject_message_names_field() -> None:
    with pytest.raises(w.WireDecodeError) as ei:
        w.decode("state", _payload("state", rpy=[0.0, 0.0]))
    assert ei.value.field == "rpy" and "rpy" in str(ei.value) and "2" in str(ei.value)


def test_decode_accepts_ints_as_floats_and_bytes_like() -> None:
    m = w.decode("ref", _payload("ref", q=[1, 2, 3]))
    assert m.q.dtype == np.float64 and list(m.q) == [1.0, 2.0, 3.0]
    data = w.encode(_samples()[0])
    assert w.decode("clock", bytearray(data)) == w.decode("clock", memoryview(data)) == _samples()[0]


def test_big_mission_accepted_up_to_its_bound() -> None:
    sc = {"blob": "x" * (2 * w.MAX_PAYLOAD)}
    data = w.encode(w.Mission(t=0, seq=0, scenario=sc))
    assert len(data) > w.MAX_PAYLOAD
    assert w.decode("mission", data).scenario == sc
    with pytest.raises(w.WireDecodeError) as ei:
        w.decode("diag", data)
    assert ei.value.reason == "oversize"


# --------------------------------------------------------------------------- Decoder


def test_decoder_counts_per_key_and_reason() -> None:
    d = w.Decoder()
    good = w.encode(_samples()[1])
    assert d.decode("swarm/s/uav/1/state", "state", good) == _samples()[1]
    assert d.decode("swarm/s/uav/1/state", "state", b"\xc1") is None
    assert d.decode("swarm/s/uav/2/state", "state", _payload("state", q=[0.0])) is None
    assert d.decode("swarm/s/uav/2/state", "state", _payload("state", q=[0.0])) is None
    assert d.decode("swarm/s/uav/2/state", "no-kind", good) is None
    assert d.decode("swarm/s/uav/2/state", "state", 12345) is None  # type: ignore[arg-type]
    assert d.accepted == 1 and d.rejected == 5
    assert d.rejects == {"swarm/s/uav/1/state": 1, "swarm/s/uav/2/state": 4}
    assert d.reasons == {"malformed": 2, "length": 2, "kind": 1}
    assert d.counters() == {
        "decoded": 1,
        "rejected": 5,
        "rejected.malformed": 2,
        "rejected.length": 2,
        "rejected.kind": 1,
    }
    assert d.last_error is not None and "swarm/s/uav/2/state" in d.last_error
    w.Diag(t=0, seq=0, process="agent:1", counters=d.counters(), info={"rejects": d.rejects})


def test_decoder_stale_seq() -> None:
    def ref(seq: int) -> bytes:
        return w.encode(w.Ref(t=seq, seq=seq, q=[0, 0, 0], v=[0, 0, 0]))

    d = w.Decoder(check_seq=True)
    assert d.decode("a", "ref", ref(5)) is not None
    assert d.decode("a", "ref", ref(5)) is None  # repeated
    assert d.decode("a", "ref", ref(4)) is None  # older
    assert d.decode("b", "ref", ref(1)) is not None  # per key
    assert d.decode("a", "ref", ref(6)) is not None
    assert d.reasons == {"stale": 2} and d.rejects == {"a": 2}
    d.forget("a")
    assert d.decode("a", "ref", ref(0)) is not None  # publisher restarted
    assert w.Decoder().decode("a", "ref", ref(0)) is not None and w.Decoder().decode("a", "ref", ref(0)) is not None


def test_decoder_bounds_its_memory() -> None:
    d = w.Decoder(max_keys=3)
    for i in range(10):
        d.decode(f"k{i}", "clock", b"\xc1")
    assert len(d.rejects) == 4 and d.rejects[w.Decoder.OTHER] == 7


# --------------------------------------------------------------------------- properties

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
vec3 = st.lists(finite, min_size=3, max_size=3).map(lambda xs: np.array(xs, dtype=np.float64))
t_st = st.integers(0, w.MAX_T_NS)
seq_st = st.integers(0, w.MAX_SEQ)
plain = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | finite | st.text(max_size=8),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=6), kids, max_size=4),
    max_leaves=20,
)
messages = st.one_of(
    st.builds(w.Clock, t=t_st, seq=seq_st),
    st.builds(w.State, t=t_st, seq=seq_st, q=vec3, v=vec3, rpy=vec3, w=vec3),
    st.builds(w.Ref, t=t_st, seq=seq_st, q=vec3, v=vec3),
    st.builds(w.Cmd, t=t_st, seq=seq_st, thrust=finite, rpy=vec3, u=vec3, d_hat=vec3),
    st.builds(w.Mission, t=t_st, seq=seq_st, scenario=st.dictionaries(st.text(max_size=6), plain, max_size=5)),
    st.builds(
        w.Diag,
        t=t_st,
        seq=seq_st,
        process=st.sampled_from(["plant", "leader", "recorder", "bridge", "supervisor"])
        | st.integers(1, 10**6).map(w.agent),
        counters=st.dictionaries(st.text(max_size=8), st.integers(-(2**63), 2**63 - 1) | finite, max_size=6),
        info=st.dictionaries(st.text(max_size=6), plain, max_size=4),
    ),
)


@settings(max_examples=200, deadline=None)
@given(messages)
@pytest.mark.slow
def test_property_round_trip(msg: w.Message) -> None:
    back = w.decode(msg.kind, w.encode(msg))
    _assert_bit_equal(msg, back)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), st.sampled_from([*w.KINDS, "bogus"]))
def test_property_random_bytes_never_raise(data: bytes, kind: str) -> None:
    d = w.Decoder(check_seq=True)
    out = d.decode("swarm/s/x", kind, data)
    assert d.accepted + d.rejected == 1
    assert (out is None) == (d.rejected == 1)
    if out is None:
        assert set(d.reasons) <= set(w.REASONS)


_msgpack_obj = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8) | st.binary(max_size=8),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=6), kids, max_size=4),
    max_leaves=25,
)
_field_names = st.sampled_from(["v", "k", "t", "seq", "q", "vel", "rpy", "w", "thrust", "u", "d_hat", "scenario",
                                "process", "counters", "info", "zz"])
_near_valid = st.builds(
    lambda base, upd, drop: {**{k: v for k, v in base.items() if k not in drop}, **upd},
    st.sampled_from(list(_VALID.values())),
    st.dictionaries(_field_names, _msgpack_obj, max_size=3),
    st.sets(_field_names, max_size=2),
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_msgpack_obj | _near_valid, st.sampled_from(w.KINDS))
@pytest.mark.slow
def test_property_random_msgpack_never_raise(obj: Any, kind: str) -> None:
    d = w.Decoder()
    out = d.decode("swarm/s/y", kind, msgpack.packb(obj, use_bin_type=True))
    assert d.accepted + d.rejected == 1
    if out is None:
        assert d.rejects == {"swarm/s/y": 1} and set(d.reasons) <= set(w.REASONS)
    else:  # whatever is accepted is a valid message that re-encodes to an accepted payload
        assert out.kind == kind
        assert w.decode(kind, w.encode(out)) == out


# ----------------------------------------------------------------------------- hot-path encoders
_f64 = st.floats(allow_nan=False, allow_infinity=False, width=64)
_vec3 = st.lists(_f64, min_size=3, max_size=3).map(lambda x: np.array(x, dtype=np.float64))
_t = st.integers(0, w.MAX_T_NS)
_seq = st.integers(0, w.MAX_SEQ)


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(_t, _seq, _vec3, _vec3, _vec3, _vec3, _f64)
def test_hot_path_encoders_give_the_messages_bytes(t: int, seq: int, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                                                    d: np.ndarray, f: float) -> None:
    assert w.encode_state(t, seq, a, b, c, d) == w.encode(w.State(t=t, seq=seq, q=a, v=b, rpy=c, w=d))
    assert w.encode_ref(t, seq, a, b) == w.encode(w.Ref(t=t, seq=seq, q=a, v=b))
    assert w.encode_cmd(t, seq, f, a, b, c) == w.encode(w.Cmd(t=t, seq=seq, thrust=f, rpy=a, u=b, d_hat=c))
    assert w.encode_cmd(t, seq, np.float64(f), a, b, c) == w.encode_cmd(t, seq, f, a, b, c)


def test_hot_path_encoders_check_as_the_constructors() -> None:
    ok = np.array([1.0, 2.0, 3.0])
    # not the usual types: the checked path, the same bytes
    assert w.encode_state(1, 2, [1, 2, 3], ok, ok, ok) == w.encode(w.State(t=1, seq=2, q=ok, v=ok, rpy=ok, w=ok))
    assert w.encode_cmd(1, 2, 1, ok, ok, ok) == w.encode(w.Cmd(t=1, seq=2, thrust=1.0, rpy=ok, u=ok, d_hat=ok))
    # a sum that overflows is not a bad value: the checked path takes it
    huge = np.array([1.7e308, 1.7e308, 0.0])
    assert w.encode_ref(1, 2, huge, ok) == w.encode(w.Ref(t=1, seq=2, q=huge, v=ok))
    for bad, field, reason in ((np.array([1.0, np.nan, 0.0]), "q", "nonfinite"), (np.array([1.0, np.inf]), "q", "length")):
        with pytest.raises(w.MessageError) as e:
            w.encode_state(1, 2, bad, ok, ok, ok)
        assert (e.value.field, e.value.reason) == (field, reason)
    with pytest.raises(w.MessageError) as e:
        w.encode_ref(-1, 2, ok, ok)
    assert (e.value.field, e.value.reason) == ("t", "negative")
    with pytest.raises(w.MessageError) as e:
        w.encode_cmd(1, 2, math.inf, ok, ok, ok)
    assert (e.value.field, e.value.reason) == ("thrust", "nonfinite")

"""The external positioning feed on the bus: a motion-capture system's (or the simulated
vehicles' ``--mocap``) position of each UAV, which the Crazyflie bridge forwards to its vehicle
(``extpos``; docs/crazyflie.md "Positioning").

Key ``swarm/<name>/mocap/<i>`` (UAV i >= 1). Message :class:`MocapPosition`, msgpack, an array
``[t, x, y, z]``: ``t`` the feeder's wall-clock time of the measurement (s since the epoch, for
the record), ``x, y, z`` the position in m in the swarm's world frame (ENU, the positioning
system's origin). A lab's own feeder publishes the same four numbers, e.g. with
``msgspec.msgpack.encode([time.time(), x, y, z])``.
"""

from __future__ import annotations

import msgspec

__all__ = ["MocapPosition", "mocap_key", "mocap_all", "encode_mocap", "decode_mocap"]


class MocapPosition(msgspec.Struct, array_like=True, frozen=True):
    """One measured position: feeder time ``t`` (s, epoch) and ``x, y, z`` (m, world ENU)."""

    t: float
    x: float
    y: float
    z: float


_dec = msgspec.msgpack.Decoder(MocapPosition)
_enc = msgspec.msgpack.Encoder()


def mocap_key(prefix: str, i: int) -> str:
    """``<prefix>/mocap/<i>`` (``prefix`` = ``swarm/<name>``, :attr:`zenswarm.bus.keys.Keys.prefix`)."""
    if i < 1:
        raise ValueError(f"UAV index must be >= 1, got {i}")
    return f"{prefix}/mocap/{i}"


def mocap_all(prefix: str) -> str:
    """Every UAV's feed: ``<prefix>/mocap/*``."""
    return f"{prefix}/mocap/*"


def encode_mocap(t: float, x: float, y: float, z: float) -> bytes:
    return _enc.encode(MocapPosition(float(t), float(x), float(y), float(z)))


def decode_mocap(payload: bytes) -> MocapPosition:
    """The message, or :class:`msgspec.DecodeError` / :class:`msgspec.ValidationError`."""
    return _dec.decode(payload)

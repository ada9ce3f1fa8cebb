"""CRTP, the Crazyflie's packet protocol, as the simulated Crazyflies speak it
(:mod:`zenswarm.plant.crazyflie_vehicle`): the numbers and encodings of bitcraze's
crazyflie-firmware (``src/modules/src``, CRTP protocol version 12, ``crtp.h``) that cflib expects.

One CRTP packet per UDP datagram (cflib's ``udp://`` driver): byte 0 the header ``port << 4 |
0x0C | channel`` (:func:`header`), then up to 30 bytes of payload, little-endian. Here: the ports,
the table-of-contents (TOC v2) encoding the log and parameter services share (:func:`toc_crc`,
:func:`toc_item`), the log and parameter value types, a log block and its data packet
(:class:`LogBlock`, ``log.c``), and the supervisor's info bits (``supervisor.c``). No state, no
socket.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

__all__ = [  # in the order they are defined
    "DEFAULT_BASE_PORT", "CRTP_PROTOCOL_VERSION", "PORT_CONSOLE", "PORT_PARAM", "PORT_COMMANDER", "PORT_MEM", "PORT_LOG",
    "PORT_LOCALIZATION", "PORT_GENERIC", "PORT_HL", "PORT_SUPERVISOR", "PORT_PLATFORM", "PORT_LINK", "LOG_MAX_OPS",
    "LOG_MAX_BLOCKS", "LOG_MAX_PAYLOAD", "LOC_EXT_POSE", "LOG_TYPES", "LOG_UINT8", "LOG_UINT16", "LOG_INT8", "LOG_FLOAT",
    "PARAM_TYPES", "PARAM_UINT8", "PARAM_UINT16", "PARAM_UINT32", "PARAM_FLOAT", "PARAM_RONLY", "BIT_CAN_BE_ARMED",
    "BIT_IS_ARMED", "BIT_CAN_FLY", "BIT_IS_FLYING", "BIT_IS_LOCKED", "BIT_HL_ACTIVE", "BIT_HL_FINISHED", "BIT_HL_DISABLED",
    "header", "toc_crc", "toc_item", "param_bytes", "param_value", "LogBlock",
]

DEFAULT_BASE_PORT = 19850
"""cflib's UDP driver scans 19850..19859 for simulated Crazyflies."""
CRTP_PROTOCOL_VERSION = 12

# CRTP ports (crtp.h)
PORT_CONSOLE, PORT_PARAM, PORT_COMMANDER, PORT_MEM, PORT_LOG = 0x0, 0x2, 0x3, 0x4, 0x5
PORT_LOCALIZATION, PORT_GENERIC, PORT_HL, PORT_SUPERVISOR, PORT_PLATFORM, PORT_LINK = 0x6, 0x7, 0x8, 0x9, 0xD, 0xF

LOG_MAX_OPS, LOG_MAX_BLOCKS = 128, 16  # log.c
LOG_MAX_PAYLOAD = 26  # 30 bytes - block id - 3-byte timestamp
LOC_EXT_POSE = 8  # crtp_localization_service.c, the generic channel's EXT_POSE

# log types (log.h) -> struct code
LOG_TYPES = {1: "B", 2: "H", 3: "I", 4: "b", 5: "h", 6: "i", 7: "f", 8: "e"}
LOG_UINT8, LOG_UINT16, LOG_INT8, LOG_FLOAT = 1, 2, 4, 7
# param types (param.h): size bits 0-1, float 0x04, unsigned 0x08, read-only 0x40
PARAM_TYPES = {0x08: "B", 0x09: "H", 0x0A: "I", 0x00: "b", 0x01: "h", 0x02: "i", 0x06: "f"}
PARAM_UINT8, PARAM_UINT16, PARAM_UINT32, PARAM_FLOAT, PARAM_RONLY = 0x08, 0x09, 0x0A, 0x06, 0x40

# supervisor info bits (supervisor.c infoBitfield)
BIT_CAN_BE_ARMED, BIT_IS_ARMED, BIT_CAN_FLY, BIT_IS_FLYING, BIT_IS_LOCKED = 0, 1, 3, 4, 6
BIT_HL_ACTIVE, BIT_HL_FINISHED, BIT_HL_DISABLED = 8, 9, 10


def header(port: int, channel: int) -> int:
    """The CRTP header byte of ``port`` and ``channel`` (link bits 0x0C set)."""
    return ((port & 0xF) << 4) | 0x0C | (channel & 0x3)


def toc_crc(entries: list[tuple[str, int]]) -> int:
    """The TOC's CRC32 (a cache key for cflib's TocCache): over every entry's type and name."""
    return zlib.crc32(b"".join(bytes([t]) + n.encode() + b"\0" for n, t in entries)) & 0xFFFFFFFF


def toc_item(ident: int, name: str, typ: int) -> bytes:
    """A TOC v2 item answer: ``[2 (CMD_TOC_ITEM_V2), id u16, type, group\\0, name\\0]`` of ``group.name``."""
    group, _, var = name.partition(".")
    return struct.pack("<BHB", 2, ident, typ) + group.encode() + b"\0" + var.encode() + b"\0"


def param_bytes(typ: int, value: float) -> bytes:
    """A parameter's value as its type ``typ`` (read-only bit ignored) puts it on the wire."""
    code = PARAM_TYPES[typ & ~PARAM_RONLY]
    return struct.pack("<" + code, value if code == "f" else int(value))


def param_value(typ: int, raw: bytes) -> float:
    """The value of a parameter of type ``typ`` written as ``raw`` (struct.error if too short)."""
    return float(struct.unpack_from("<" + PARAM_TYPES[typ], raw, 0)[0])


@dataclass
class LogBlock:
    """One log block: its operations (storage type, fetch type, variable index) and period."""

    ops: list[tuple[int, int]] = field(default_factory=list)  # (fetch log type, variable index)
    period_s: float = 0.0
    running: bool = False
    next_due: float = 0.0
    sent: int = 0

    def size(self) -> int:
        return sum(struct.calcsize("<" + LOG_TYPES[t]) for t, _ in self.ops)

    def data(self, bid: int, stamp_ms: int, values: Callable[[int], float]) -> bytes:
        """Its data packet (channel 2): ``[id, 24-bit ms timestamp, values]``, each value
        ``values(variable index)`` packed as its fetch type (integers rounded and clamped)."""
        out = bytearray([bid]) + struct.pack("<I", stamp_ms & 0xFFFFFF)[:3]
        for typ, ident in self.ops:
            code = LOG_TYPES[typ]
            v = values(ident)
            if code in "fe":
                out += struct.pack("<" + code, v)
            else:
                lo, hi = {"B": (0, 255), "b": (-128, 127), "H": (0, 65535), "h": (-32768, 32767)}.get(code, (-(2**31), 2**31 - 1))
                out += struct.pack("<" + code, int(min(max(round(v), lo), hi)))
        return bytes(out)

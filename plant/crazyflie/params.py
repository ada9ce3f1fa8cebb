"""A simulated Crazyflie's parameter service (CRTP port 2, ``param_logic.c``): its table of
contents (:data:`PARAMS`) and values; TOC v2, read (channel 1, ``[id, status, value]``), write
(channel 2, echoed), set by name (channel 3); read-only parameters refuse writes. The encoding is
:mod:`zenswarm.plant.crazyflie.crtp`'s.
"""

from __future__ import annotations

import errno
import math
import struct
from collections.abc import Callable

from zenswarm.plant.crazyflie.crtp import (
    PARAM_FLOAT,
    PARAM_RONLY,
    PARAM_UINT8,
    PARAM_UINT16,
    PARAM_UINT32,
    param_bytes,
    param_value,
    toc_crc,
    toc_item,
)

PARAMS: dict[str, tuple[int, float]] = {
    "flightmode.stabModeYaw": (PARAM_UINT8, 0),  # 0 RATE (default), 1 ANGLE
    "commander.enHighLevel": (PARAM_UINT8, 1),
    "stabilizer.estimator": (PARAM_UINT8, 2),
    "stabilizer.controller": (PARAM_UINT8, 1),
    "stabilizer.stop": (PARAM_UINT8, 0),  # non-zero: motors off
    "kalman.resetEstimation": (PARAM_UINT8, 0),
    "crtpsrv.echoDelay": (PARAM_UINT16, 0),
    "hlCommander.vtoff": (PARAM_FLOAT, 0.5),
    "hlCommander.vland": (PARAM_FLOAT, 0.2),
    "pm.lowVoltage": (PARAM_FLOAT, 3.2),
    "firmware.revision0": (PARAM_UINT32 | PARAM_RONLY, 0x5A454E53),
}
"""The parameter TOC: name -> (type byte, default). Those the vehicle follows: ``flightmode.stabModeYaw``,
``stabilizer.stop``, ``kalman.resetEstimation``, ``crtpsrv.echoDelay``, ``pm.lowVoltage`` (pm.state)."""


class ParamService:
    """The parameters of one vehicle: ``values`` (name -> value, the firmware reads them) and
    ``names`` (in TOC order). :meth:`request` answers a packet (payload bytes, on the channel it
    came on); ``count`` is told what happened (``param_sets``, ``param_readonly``)."""

    def __init__(self, count: Callable[[str], None]) -> None:
        self.values = {name: float(v) for name, (_, v) in PARAMS.items()}
        self.names = list(PARAMS)
        self._count = count

    def _bytes(self, k: int) -> bytes:
        name = self.names[k]
        return param_bytes(PARAMS[name][0], self.values[name])

    def request(self, ch: int, d: bytes) -> bytes | None:
        """One packet on channel ``ch``: the answer on the same channel, or None for none."""
        if ch == 0:
            cmd = d[0]
            if cmd == 3:
                entries = [(n, t) for n, (t, _) in PARAMS.items()]
                return struct.pack("<BHI", 3, len(entries), toc_crc(entries))
            if cmd == 2:
                ident = struct.unpack_from("<H", d, 1)[0]
                if ident < len(self.names):
                    name = self.names[ident]
                    return toc_item(ident, name, PARAMS[name][0])
        elif ch == 1:  # read
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident >= len(self.names):
                return struct.pack("<HB", ident, errno.ENOENT)
            return struct.pack("<HB", ident, 0) + self._bytes(ident)
        elif ch == 2:  # write: echoes the stored value
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident < len(self.names):
                self.set(self.names[ident], d[2:])
                return struct.pack("<H", ident) + self._bytes(ident)
        elif ch == 3 and d[0] == 0:  # set by name: [0, group\0name\0, type, value]
            parts = d[1:].split(b"\0", 2)
            name = parts[0].decode() + "." + parts[1].decode()
            err = errno.ENOENT
            if name in PARAMS and len(parts) == 3 and parts[2]:
                err = 0 if self.set(name, parts[2][1:]) else errno.EACCES
            return d[: 1 + len(parts[0]) + len(parts[1]) + 2] + bytes([err])
        return None

    def set(self, name: str, raw: bytes) -> bool:
        """Write ``raw`` (the parameter's type) to ``name``; False if read-only or not finite."""
        typ = PARAMS[name][0]
        if typ & PARAM_RONLY:
            self._count("param_readonly")
            return False
        v = param_value(typ, raw)
        if not math.isfinite(v):
            return False
        self.values[name] = v
        self._count("param_sets")
        return True

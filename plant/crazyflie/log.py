"""A simulated Crazyflie's log service (CRTP port 5, ``log.c``): its table of contents
(:data:`LOG_VARS`) and the log blocks a client creates, starts and stops; the data packets of the
blocks that are due.

The variables' names, types and units are the firmware's: ``stateEstimate.{x,y,z,vx,vy,vz}`` (m,
m/s, the positioning system's frame: the swarm's ENU here), ``stateEstimate.{roll,pitch,yaw}``
(deg, pitch inverted: :mod:`zenswarm.vehicle.crazyflie`), ``gyro.{x,y,z}`` (deg/s, body),
``stabilizer.thrust``, ``motor.m1..m4`` (uint16), ``pm.vbat`` (V), ``pm.batteryLevel`` (%),
``pm.state``, ``radio.rssi``, ``supervisor.info``. Their values come from the fleet
(:meth:`zenswarm.plant.crazyflie.fleet.CrazyflieFleet.tick`); the encoding is
:mod:`zenswarm.plant.crazyflie.crtp`'s.
"""

from __future__ import annotations

import errno
import struct
from collections.abc import Callable, Iterator

from zenswarm.plant.crazyflie.crtp import (
    LOG_FLOAT,
    LOG_INT8,
    LOG_MAX_BLOCKS,
    LOG_MAX_OPS,
    LOG_MAX_PAYLOAD,
    LOG_TYPES,
    LOG_UINT8,
    LOG_UINT16,
    LogBlock,
    toc_crc,
    toc_item,
)

LOG_VARS: list[tuple[str, int]] = [
    *[(f"stateEstimate.{a}", LOG_FLOAT) for a in ("x", "y", "z", "vx", "vy", "vz", "roll", "pitch", "yaw")],
    *[(f"gyro.{a}", LOG_FLOAT) for a in ("x", "y", "z")],
    ("stabilizer.roll", LOG_FLOAT), ("stabilizer.pitch", LOG_FLOAT), ("stabilizer.yaw", LOG_FLOAT),
    ("stabilizer.thrust", LOG_FLOAT),
    *[(f"motor.m{k}", LOG_UINT16) for k in (1, 2, 3, 4)],
    ("pm.vbat", LOG_FLOAT), ("pm.batteryLevel", LOG_UINT8), ("pm.state", LOG_INT8),
    ("radio.rssi", LOG_UINT8), ("supervisor.info", LOG_UINT16),
]  # fmt: skip
"""The log TOC: (group.name, log type)."""


class LogService:
    """The log TOC and blocks of one vehicle. Requests in, answers out (payload bytes); the
    vehicle sends them (:meth:`zenswarm.plant.crazyflie.firmware.SimCrazyflie.send`)."""

    def __init__(self) -> None:
        self.blocks: dict[int, LogBlock] = {}

    def toc(self, d: bytes) -> bytes | None:
        """Channel 0 (TOC v2): info (command 3: count, CRC32, LOG_MAX_OPS, LOG_MAX_BLOCKS) or an
        item (command 2: id, type, group, name); None: nothing to answer."""
        cmd = d[0]
        if cmd == 3:  # info v2
            return struct.pack("<BHIBB", 3, len(LOG_VARS), toc_crc(LOG_VARS), LOG_MAX_OPS, LOG_MAX_BLOCKS)
        if cmd == 2:  # item v2
            ident = struct.unpack_from("<H", d, 1)[0]
            if ident < len(LOG_VARS):
                return toc_item(ident, *LOG_VARS[ident])
        return None

    def control(self, cmd: int, bid: int, d: bytes, now: float) -> int:
        """One log control command (channel 1, ``log.c``); the errno it answers (0: done)."""
        blk = self.blocks.get(bid)
        if cmd in (6, 7):  # create / append v2: (type byte, id u16)*
            return self._add(cmd, bid, d[2:])
        if cmd == 5:  # reset
            self.blocks.clear()
            return 0
        if cmd not in (2, 3, 4):
            return errno.ENOEXEC
        if blk is None:
            return errno.ENOENT
        if cmd == 2:  # delete
            del self.blocks[bid]
        elif cmd == 3:  # start, period in 10 ms
            blk.period_s = max(1, d[2] if len(d) > 2 else 1) * 0.01
            blk.running = True
            blk.next_due = now
        else:  # stop
            blk.running = False
        return 0

    def _add(self, cmd: int, bid: int, body: bytes) -> int:
        """Create (6) or append to (7) block ``bid`` the operations in ``body``; the errno."""
        if cmd == 6 and bid in self.blocks:
            return errno.EEXIST
        if cmd == 6 and len(self.blocks) >= LOG_MAX_BLOCKS:
            return errno.ENOMEM
        if cmd == 7 and bid not in self.blocks:
            return errno.ENOENT
        ops = []
        for k in range(0, len(body) - 2, 3):
            typ, ident = body[k], struct.unpack_from("<H", body, k + 1)[0]
            if ident >= len(LOG_VARS) or (typ & 0x0F) not in LOG_TYPES:
                return errno.ENOENT
            ops.append((typ & 0x0F, ident))
        blk = self.blocks.get(bid) or LogBlock()
        if sum(len(b.ops) for b in self.blocks.values()) + len(ops) > LOG_MAX_OPS:
            return errno.ENOMEM
        trial = LogBlock(ops=blk.ops + ops)
        if trial.size() > LOG_MAX_PAYLOAD:
            return errno.E2BIG
        blk.ops = trial.ops
        self.blocks[bid] = blk
        return 0

    def due(self, now: float, values: Callable[[int], float], ms: Callable[[float], int]) -> Iterator[bytes]:
        """The data packet of every running block whose period is due (``now``, s monotonic):
        ``[id, ms timestamp (24 bit), values]``, the timestamp ``ms`` of the time the block was due
        (the values are those of ``now``)."""
        for bid, blk in self.blocks.items():
            if not blk.running or now + 1e-4 < blk.next_due:
                continue
            # stamped when its period was due, as the firmware's periodic log timer stamps it: a
            # loop that ran late sends late, but never two stamps closer than a period (no burst)
            stamp = min(blk.next_due, now)
            blk.next_due += blk.period_s
            if blk.next_due < now:  # late by more than a period: skip the missed ones, stamp now
                blk.next_due = now + blk.period_s
                stamp = now
            yield blk.data(bid, ms(stamp), values)
            blk.sent += 1

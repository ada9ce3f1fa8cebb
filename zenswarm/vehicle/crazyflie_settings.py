"""The Crazyflie bridge's settings: the scenario's ``[crazyflie]`` table with command-line
overrides, and the check of each UAV's cflib link URI (docs/crazyflie.md).

URIs are cflib's: ``radio://DONGLE/CHANNEL/RATE[/ADDRESS]`` (a Crazyradio: dongle index,
channel 0-125, data rate 250K, 1M or 2M, a 5-byte address in 10 hex digits, e.g.
``radio://0/80/2M/E7E7E7E701``), ``udp://HOST:PORT`` (a simulated Crazyflie, or Bitcraze's
software-in-the-loop firmware), ``usb://N`` (a Crazyflie on USB). Every UAV needs its own URI:
two UAVs on one URI would fly one vehicle.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from zenswarm.errors import ScenarioError
from zenswarm.schema import CrazyflieTable, ScenarioTables, convert, to_builtins

_RADIO = re.compile(r"^radio://(\d+)/(\d+)/(250K|1M|2M)(/[0-9A-Fa-f]{10})?$")
_UDP = re.compile(r"^udp://([A-Za-z0-9.\-]+|\[[0-9A-Fa-f:]+\]):(\d+)$")
_USB = re.compile(r"^usb://\d+$")


def check_uri(flag: str, uri: str) -> str:
    """``uri`` if cflib can open it (see the module's text), else :class:`ScenarioError` naming ``flag``."""
    if not isinstance(uri, str):
        raise ScenarioError(flag, f"expected a cflib link URI, got {uri!r}")
    m = _RADIO.match(uri)
    if m:
        if int(m.group(2)) > 125:
            raise ScenarioError(flag, f"radio channel must be 0..125, got {m.group(2)} in {uri!r}")
        return uri
    m = _UDP.match(uri)
    if m:
        if not 1 <= int(m.group(2)) <= 65535:
            raise ScenarioError(flag, f"UDP port must be 1..65535, got {m.group(2)} in {uri!r}")
        return uri
    if _USB.match(uri):
        return uri
    raise ScenarioError(flag, f"not a Crazyflie link URI: {uri!r} (expected radio://0/80/2M/E7E7E7E701, udp://HOST:PORT or usb://0)")


@dataclass(frozen=True)
class CrazyflieSettings:
    """The bridge's settings (durations s, rates Hz; the table's keys, see :class:`zenswarm.schema.CrazyflieTable`)."""

    n: int
    uris: tuple[str, ...]
    rate_hz: float
    takeoff: bool
    takeoff_duration_s: float
    takeoff_tolerance_m: float
    takeoff_timeout_s: float
    connect_timeout_s: float
    link_timeout_s: float
    cmd_timeout_s: float
    land_duration_s: float
    land_timeout_s: float
    start_timeout_s: float
    yaw_gain: float
    positioning: str


_KEYS = {
    "uris": "cflib link URI of each UAV (default udp://HOST:BASE_PORT+i-1, the simulated Crazyflies)",
    "host": "host of the default URIs",
    "base_port": "first UDP port of the default URIs (19850, where cflib scans)",
    "rate_hz": "setpoint rate, Hz (default the control rate, at least 10)",
    "takeoff": "take off with the high-level commander to the initial positions before the mission",
    "takeoff_duration_s": "the takeoff's duration, s",
    "takeoff_tolerance_m": "the takeoff is done within this distance of the initial position, m",
    "takeoff_timeout_s": "give the takeoff up after this long, s",
    "connect_timeout_s": "give a vehicle up if cflib has not connected (TOCs, parameters) after this long, s",
    "link_timeout_s": "a vehicle whose log blocks stop this long is unhealthy (its state no longer published), s",
    "cmd_timeout_s": "an agent command older than this is replaced by a level hover, s",
    "land_duration_s": "the high-level commander's landing duration, s",
    "land_timeout_s": "how long to wait for the vehicles to land, s",
    "start_timeout_s": "start the mission after this long even if some UAV is not ready, s",
    "yaw_gain": "the bridge's yaw loop, 1/s: yaw rate = gain * (yaw* - yaw) (the legacy setpoint flies a yaw rate)",
    "positioning": "onboard (the vehicle positions itself: Lighthouse, or a feed of its own) or extpos (the bridge forwards "
    "swarm/<name>/mocap/<i> to it)",
}


def crazyflie_settings(sc: ScenarioTables, cli: dict[str, Any] | None = None) -> CrazyflieSettings:
    """The scenario's ``[crazyflie]`` table with command-line overrides (``uri``: {uav: URI},
    1-based; other keys as the table's, None ignored). Errors are :class:`ScenarioError` naming
    the field or flag: a malformed URI, two UAVs on one URI, a URI for a UAV that does not exist,
    a list whose length is not N. Keys of the table:

    """
    cli = dict(cli or {})
    uri_over: dict[int, str] = cli.pop("uri", None) or {}
    t = sc.crazyflie or CrazyflieTable()
    over = {k: v for k, v in cli.items() if v is not None}
    for k in over:
        if k not in _KEYS:
            raise ScenarioError(f"--{k}", "unknown setting")
    if over:
        t = convert({**to_builtins(t, omit_defaults=True), **over}, CrazyflieTable, "crazyflie")
    n = sc.n
    if t.uris is not None and len(t.uris) != n:
        raise ScenarioError("crazyflie.uris", f"expected {n} URIs (one per UAV), got {len(t.uris)}")
    if t.base_port > 65535 - n + 1:
        raise ScenarioError("crazyflie.base_port", f"expected an integer in 1..{65535 - n + 1} ({n} UAVs), got {t.base_port}")
    uris = [check_uri(f"crazyflie.uris[{i}]", u) for i, u in enumerate(t.uris)] if t.uris else [
        f"udp://{t.host}:{t.base_port + i}" for i in range(n)
    ]  # fmt: skip
    for i, u in uri_over.items():
        if not 1 <= i <= n:
            raise ScenarioError("--uri", f"UAV {i} does not exist (the scenario has UAVs 1..{n})")
        uris[i - 1] = check_uri("--uri", u)
    seen: dict[str, int] = {}
    for i, u in enumerate(uris):
        key = u.upper() if u.startswith("radio://") else u
        if key in seen:
            where = "--uri" if uri_over else "crazyflie.uris"
            raise ScenarioError(where, f"UAVs {seen[key] + 1} and {i + 1} have the same URI {u!r}: each UAV needs its own Crazyflie")
        seen[key] = i
    return CrazyflieSettings(
        n=n,
        uris=tuple(uris),
        rate_hz=t.rate_hz if t.rate_hz is not None else max(10.0, sc.timing.control_rate_hz),
        **{k: getattr(t, k) for k in _KEYS if k not in ("uris", "host", "base_port", "rate_hz")},
    )


crazyflie_settings.__doc__ = (crazyflie_settings.__doc__ or "") + "".join(f"    ``{k}``: {v}\n" for k, v in _KEYS.items())

"""MAVLink bridge: fly the swarm's agents on PX4 or ArduPilot vehicles (or the simulated ones of
:mod:`zenswarm.plant.mavlink_vehicle`) without changing a line of the agents.

``zenswarm bridge mavlink``: its flags (:func:`add_mavlink_parser`), their
:class:`zenswarm.bridge.vehicles.settings.MavlinkBridgeSettings` (:func:`bridge_settings`), and
the bridge run with them (:func:`run`; also what ``zenswarm up`` starts, the settings on stdin)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from zenswarm.bridge.vehicles.mavlink.loop import _run
from zenswarm.bridge.vehicles.settings import MavlinkBridgeSettings, bridge_main, run_bridge
from zenswarm.errors import ScenarioError
from zenswarm.vehicle.autopilot import mavlink_settings

__all__ = ["bridge_settings", "run", "add_mavlink_parser", "add_parsers"]


def _cli_overrides(args: argparse.Namespace) -> dict[str, Any]:
    def pairs(items: list[str] | None, flag: str, conv: Callable[[str], Any]) -> dict[int, Any]:
        out: dict[int, Any] = {}
        for s in items or []:
            i, sep, val = s.partition("=")
            if not sep or not i.strip().isdigit() or not val:
                raise ScenarioError(flag, f"expected I=VALUE (I = UAV number), got {s!r}")
            try:
                out[int(i)] = conv(val)
            except ValueError:
                raise ScenarioError(flag, f"bad value in {s!r}") from None
        return out

    return {
        "conn": pairs(getattr(args, "conn", None), "--conn", str),
        "sysid": pairs(getattr(args, "sysid", None), "--sysid", int),
        "origin": pairs(getattr(args, "origin", None), "--origin", lambda v: tuple(float(c) for c in v.split(","))),
        "base_port": getattr(args, "base_port", None),
        "host": getattr(args, "mav_host", None),
        "setpoint": getattr(args, "setpoint", None),
        "rate_hz": getattr(args, "rate", None),
        "autopilot": getattr(args, "autopilot", None),
        "hover_throttle": getattr(args, "hover_throttle", None),
        "takeoff": False if getattr(args, "no_takeoff", False) else None,
        "link_timeout_s": getattr(args, "link_timeout", None),
        "land_timeout_s": getattr(args, "land_timeout", None),
        "stream_s": getattr(args, "stream_s", None),
        "start_timeout_s": getattr(args, "start_timeout", None),
    }


def bridge_settings(args: argparse.Namespace) -> MavlinkBridgeSettings:
    """``zenswarm bridge mavlink``'s flags as :class:`MavlinkBridgeSettings`: the scenario file
    parsed (none given: fetched from the leader's mission), realtime; a bad file or flag is a
    ScenarioError naming it."""
    from zenswarm.bridge.args import process_settings
    from zenswarm.scenario.config import load_scenario

    path = args.scenario_path if getattr(args, "scenario_path", None) is not None else args.scenario
    sc = None if path is None else load_scenario(path)
    return MavlinkBridgeSettings(process=process_settings(args, "bridge", sc, realtime=True), no_wait_alive=bool(args.no_wait_alive),
                                 **_cli_overrides(args))  # fmt: skip


def run(s: MavlinkBridgeSettings) -> int:
    """Run the bridge with these settings (its command's flags, or ``zenswarm up``'s on its
    standard input). Bad ``[mavlink]`` settings or overrides (ids, timeouts): exit 2 naming the
    field before any work (no Zenoh session, no MAVLink link opened); the process checks again
    with the scenario it runs (fetched from the leader if none is given)."""
    return run_bridge(s, mavlink_settings, _run)


_main_args = bridge_main(bridge_settings, run)


def _configure(p: argparse.ArgumentParser) -> None:
    from zenswarm.bridge.args import add_process_args

    p.add_argument(
        "scenario_path", nargs="?", type=Path, metavar="SCENARIO", help="scenario TOML (its [mavlink] table configures the links)"
    )
    add_process_args(p)
    g = p.add_argument_group("MAVLink")
    g.add_argument(
        "--conn", action="append", metavar="I=URL",
        help="pymavlink connection string of UAV I, e.g. 1=udpout:127.0.0.1:14540, 2=udpin:0.0.0.0:14541, "
        "3=tcp:127.0.0.1:5762, 4=/dev/ttyUSB0,921600 (repeatable; overrides mavlink.connections)",
    )
    g.add_argument("--sysid", action="append", metavar="I=ID", help="MAVLink system id of UAV I's vehicle (repeatable)")
    g.add_argument(
        "--origin", action="append", metavar="I=X,Y,Z",
        help="where UAV I's local NED origin is in the swarm's ENU frame, m (repeatable; overrides mavlink.origins)",
    )
    g.add_argument("--base-port", type=int, help="default connections udpout:HOST:P+i-1 (overrides mavlink.base_port)")
    g.add_argument("--mav-host", help="host of the default connections (overrides mavlink.host)")
    g.add_argument(
        "--setpoint",
        choices=("attitude", "position"),
        help="SET_ATTITUDE_TARGET from uav/<i>/cmd, or SET_POSITION_TARGET_LOCAL_NED from uav/<i>/ref",
    )
    g.add_argument("--rate", type=float, metavar="HZ", help="minimum setpoint rate, >= 20 Hz")
    g.add_argument("--autopilot", choices=("auto", "px4", "ardupilot"), help="mode numbering (default: from the vehicle's heartbeat)")
    g.add_argument("--hover-throttle", type=float, metavar="U", help="normalised throttle at hover (PX4 MPC_THR_HOVER)")
    g.add_argument("--no-takeoff", action="store_true", help="do not fly to the initial positions before the mission")
    g.add_argument("--link-timeout", type=float, metavar="S", help="silence after which a vehicle is unhealthy (default 1 s)")
    g.add_argument("--land-timeout", type=float, metavar="S", help="wait at most S for the vehicles to land and disarm")
    g.add_argument("--stream-s", type=float, metavar="S", help="setpoints streamed before asking for the offboard mode")
    g.add_argument("--start-timeout", type=float, metavar="S", help="start the mission after S even if some UAV is not ready")
    g.add_argument("--no-wait-alive", action="store_true", help="start the mission clock without waiting for the leader and agents")
    g.add_argument(
        "--expect", action="append", metavar="PROCESS",
        help="also wait for this process (e.g. recorder) to announce itself before starting the mission clock",
    )
    p.set_defaults(func=_main_args)


def add_mavlink_parser(bridge_sub: argparse._SubParsersAction) -> None:
    """Add the ``mavlink`` subcommand to an existing ``bridge`` subcommand's subparsers (for a
    ``bridge`` command that also has other subcommands, e.g. record/replay)."""
    m = bridge_sub.add_parser(
        "mavlink",
        help="fly the swarm's agents on MAVLink vehicles (PX4, ArduPilot, or `mavlink-vehicle`)",
        description=(__doc__ or "").split("\n\n")[0],
    )
    _configure(m)


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register ``bridge`` with its ``mavlink`` subcommand (``zenswarm bridge mavlink ...``)."""
    p = sub.add_parser(
        "bridge",
        help="connect the swarm bus to the outside (MAVLink vehicles)",
        description="Bridges between the swarm bus and the outside world.",
    )
    bsub = p.add_subparsers(dest="bridge_cmd", metavar="{mavlink}", required=True)
    add_mavlink_parser(bsub)

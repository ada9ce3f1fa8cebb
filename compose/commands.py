"""What each process of ``zenswarm up`` is started with, both ways: the supervisor asks
:func:`command` for a role's (command line, settings), and the child's ``--settings`` entry
(:func:`run_edge` for the edges; :func:`zenswarm.compose.roles.run_role` for the roles) reads them back.

Every process gets its part of the flight's :class:`zenswarm.process.settings.FlightSettings` as
one typed value, msgpack on its standard input: the plant, the leader and the agents a
:class:`zenswarm.process.settings.RoleSettings`; the recorder a
:class:`zenswarm.bridge.recording.recorder.RecorderSettings`; the MAVLink or Crazyflie bridge a
:class:`zenswarm.bridge.vehicles.settings.MavlinkBridgeSettings` /
:class:`~zenswarm.bridge.vehicles.settings.CrazyflieBridgeSettings`; their simulated vehicles a
:class:`zenswarm.compose.roles.MavlinkFleetSettings` / :class:`~zenswarm.compose.roles.CrazyflieFleetSettings`.
The command line only names the process: its command, ``--swarm NAME`` (how
:func:`zenswarm.compose.launch.processes_of` finds the processes of a swarm in the process
table), ``--settings -`` and ``--supervisor PID``. The edges' own commands (``zenswarm record``,
``zenswarm bridge mavlink``, ...) build the same settings from their flags.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from zenswarm import bus
from zenswarm.errors import ScenarioError
from zenswarm.process.settings import FlightSettings, RoleSettings, decode_as, encode, read_settings
from zenswarm.vehicle.autopilot import SITL_SEND_OFFSET

__all__ = ["role_names", "swarm_roles", "Launch", "ROLES_BY_SETTINGS", "EDGES", "command", "role_settings", "edge_settings", "run_edge"]

def role_names(n: int) -> list[str]:
    """Process names of a swarm of n UAVs, in start order."""
    return ["plant", "leader"] + [f"agent:{i}" for i in range(1, n + 1)]


def swarm_roles(n: int, plant: str = "sim") -> list[str]:
    """The roles ``zenswarm up --plant PLANT`` runs for n UAVs, in start order (the recorder,
    started first with ``--record``, aside): with ``mavlink`` the simulated vehicles and the
    bridge take the plant's place (also with ``crazyflie``: simulated Crazyflies and the Crazyflie bridge)."""
    names = role_names(n)
    return ["vehicles", "bridge"] + names[1:] if plant in ("mavlink", "crazyflie") else names


def vehicle_ports(flight: FlightSettings, n: int) -> tuple[int, int | None]:
    """The simulated vehicles' UDP base ports (:class:`Launch`), those given or free ones: MAVLink
    vehicle i on P+i and its send port P+40+i (:data:`SITL_SEND_OFFSET`); with ``--plant
    crazyflie``, Crazyflie i on P+i (else None)."""
    mav = flight.mavlink_base_port or bus.free_udp_block(n, also=(SITL_SEND_OFFSET,))
    cf = (flight.crazyflie_base_port or bus.free_udp_block(n)) if flight.plant == "crazyflie" else None
    return mav, cf


ROLES_BY_SETTINGS = ("plant", "leader", "agent")
"""The roles (:func:`zenswarm.compose.roles.run_role` reads their settings)."""


@dataclass(frozen=True)
class Launch:
    """What the supervisor knows of its flight once its router listens: the flight, the router's
    endpoints its processes join (``connect``), the credentials directory of a secured router
    (``keys``; None: an open one), the simulated vehicles' UDP ports (``mav_base_port``: MAVLink
    vehicle i on P+i-1; ``cf_base_port``: Crazyflie i, or None without ``--plant crazyflie``) and
    the supervisor's pid (a label in its children's command lines)."""

    flight: FlightSettings
    connect: tuple[str, ...]
    keys: Path | None
    mav_base_port: int
    cf_base_port: int | None
    supervisor: int

    @property
    def tls(self) -> bool:
        """Mutual TLS: asked for, and a secured router."""
        return self.flight.tls and self.keys is not None


def role_settings(role: str, at: Launch, kill_at_tick: int | None = None) -> RoleSettings:
    """plant, leader, agent:<i>: the role's part of the flight; the plant waits for the recorder
    with ``--record``; ``kill_at_tick``: lockstep, the role kills itself just before that tick."""
    expect = ("recorder",) if role == "plant" and at.flight.record is not None else ()
    return at.flight.role(role, at.connect, at.keys, kill_at_tick=kill_at_tick, expect=expect)


def edge_settings(role: str, at: Launch) -> Any:
    """The settings of an edge process of the flight: ``recorder``, ``bridge`` (MAVLink or
    Crazyflie), ``vehicles`` (their simulation)."""
    a = at.flight
    if role == "recorder":
        from zenswarm.bridge.recording.recorder import RecorderSettings

        if a.record is None:
            raise ValueError("no recorder without --record")
        return RecorderSettings(
            out=a.record, swarm=a.swarm, connect=at.connect, scenario=a.scenario, scenario_source=f"file:{a.scenario_file}",
            mode=a.mode, keys=at.keys, tls=at.tls, faults=a.faults,
        )  # fmt: skip
    if role == "bridge":
        return _bridge_settings(at)
    if role == "vehicles":
        return _vehicles_settings(at)
    raise ValueError(f"not a process of this swarm: {role!r}")


def _vehicles_settings(at: Launch) -> Any:
    """The simulated vehicles (no Zenoh: the bridge talks to them over UDP). MAVLink: as PX4 SITL
    and real autopilots, each vehicle's NED about where it booted, and vehicle i sending from
    P+40+i to P+i where the bridge listens (udpin). Crazyflies (CRTP over UDP): with
    ``positioning = "extpos"`` they are the mocap system too, on the swarm's bus (a secured one:
    as its own user, :data:`zenswarm.process.security.MOCAP_FEEDER`, allowed the mocap keys only)."""
    from zenswarm.compose.roles import CrazyflieFleetSettings, MavlinkFleetSettings

    a, sc = at.flight, at.flight.scenario
    if at.cf_base_port is not None:
        mocap = sc.crazyflie is not None and sc.crazyflie.positioning == "extpos"
        return CrazyflieFleetSettings(scenario=sc, base_port=at.cf_base_port, swarm=a.swarm, mocap=mocap,
                                      connect=at.connect if mocap else (), rt_priority=a.rt_priority,
                                      keys=at.keys if mocap else None, tls=at.tls and mocap)  # fmt: skip
    return MavlinkFleetSettings(scenario=sc, swarm=a.swarm, base_port=at.mav_base_port, telemetry_hz=100.0, own_origin=True,
                                sitl_ports=True, rt_priority=a.rt_priority)  # fmt: skip


def _bridge_settings(at: Launch) -> Any:
    """The MAVLink bridge to the simulated vehicles (own origins, SITL ports: it listens where
    vehicle i sends, and puts its origin where it boots, on the ground under its initial
    position; with ``--external vehicles`` too when ``--mavlink-base-port`` says where they are,
    else the scenario's ``[mavlink]`` table), or the Crazyflie bridge (to the simulated ones
    unless they are external and ``--crazyflie-base-port`` does not say where they are); both
    wait for the recorder with ``--record``."""
    from zenswarm.bridge.vehicles.settings import CrazyflieBridgeSettings, MavlinkBridgeSettings

    a, sc = at.flight, at.flight.scenario
    expect = ("recorder",) if a.record is not None else ()
    process = RoleSettings(role="bridge", scenario=sc, swarm=a.swarm, connect=at.connect, realtime=True, keys=at.keys, tls=at.tls,
                           faults=a.faults, rt_priority=a.rt_priority, expect=expect)  # fmt: skip
    if at.cf_base_port is not None:
        # external vehicles: the scenario's [crazyflie] uris, unless --crazyflie-base-port says where they are
        own = "vehicles" not in a.external or a.crazyflie_base_port is not None
        uri = {i + 1: f"udp://127.0.0.1:{at.cf_base_port + i}" for i in range(sc.n)} if own else {}
        return CrazyflieBridgeSettings(process=process, uri=uri)
    if "vehicles" in a.external and a.mavlink_base_port is None:
        # vehicles of the user's own (PX4/ArduPilot SITL, real ones): the scenario's [mavlink]
        # table says where they are (connections, sysids, origins), as `zenswarm bridge mavlink`
        return MavlinkBridgeSettings(process=process)
    gz = sc.mavlink.ground_z if sc.mavlink is not None else 0.0
    return MavlinkBridgeSettings(
        process=process, base_port=at.mav_base_port,
        conn={i + 1: f"udpin:127.0.0.1:{at.mav_base_port + i}" for i in range(sc.n)},
        origin={i + 1: (float(q[0]), float(q[1]), float(gz)) for i, q in enumerate(sc.initial_positions)},
    )  # fmt: skip


def _words(role: str, at: Launch) -> list[str]:
    """The command of ``role``: its subcommand's words (``agent --id I``, ``record``, ...)."""
    if role.startswith("agent:"):
        return ["agent", "--id", role.split(":", 1)[1]]
    if role in ("plant", "leader"):
        return [role]
    if role == "recorder":
        return ["record"]
    if role == "bridge":
        return ["bridge", "crazyflie" if at.cf_base_port is not None else "mavlink"]
    if role == "vehicles":
        return ["crazyflie-vehicle" if at.cf_base_port is not None else "mavlink-vehicle"]
    raise ValueError(f"not a process of this swarm: {role!r}")


def command(role: str, at: Launch, kill_at_tick: int | None = None) -> tuple[list[str], bytes]:
    """What ``role`` (a swarm role, or ``recorder``, ``vehicles``, ``bridge``) is started with:
    its command line (this interpreter's; the process's name, ``--swarm``, ``--settings -``,
    ``--supervisor PID``) and its settings, msgpack for its standard input."""
    argv = [sys.executable, "-m", "zenswarm", *_words(role, at), "--swarm", at.flight.swarm, "--settings", "-",
            "--supervisor", str(at.supervisor)]  # fmt: skip
    edge = role.partition(":")[0] not in ROLES_BY_SETTINGS  # the recorder, the vehicles, the bridge
    settings = edge_settings(role, at) if edge else role_settings(role, at, kill_at_tick)
    return argv, encode(settings)


# ----------------------------------------------------------------------------- the child's side
def _recorder() -> tuple[type, Callable[[Any], int]]:
    from zenswarm.bridge.recording.recorder import RecorderSettings, run_settings

    return RecorderSettings, run_settings


def _mavlink_bridge() -> tuple[type, Callable[[Any], int]]:
    from zenswarm.bridge.vehicles.mavlink import run
    from zenswarm.bridge.vehicles.settings import MavlinkBridgeSettings

    return MavlinkBridgeSettings, run


def _crazyflie_bridge() -> tuple[type, Callable[[Any], int]]:
    from zenswarm.bridge.vehicles.crazyflie import run
    from zenswarm.bridge.vehicles.settings import CrazyflieBridgeSettings

    return CrazyflieBridgeSettings, run


def _mavlink_vehicles() -> tuple[type, Callable[[Any], int]]:
    from zenswarm.compose.roles import MavlinkFleetSettings, run_mavlink_fleet

    return MavlinkFleetSettings, run_mavlink_fleet


def _crazyflie_vehicles() -> tuple[type, Callable[[Any], int]]:
    from zenswarm.compose.roles import CrazyflieFleetSettings, run_crazyflie_fleet

    return CrazyflieFleetSettings, run_crazyflie_fleet


EDGES: dict[tuple[str, ...], Callable[[], tuple[type, Callable[[Any], int]]]] = {
    ("record",): _recorder,
    ("bridge", "mavlink"): _mavlink_bridge,
    ("bridge", "crazyflie"): _crazyflie_bridge,
    ("mavlink-vehicle",): _mavlink_vehicles,
    ("crazyflie-vehicle",): _crazyflie_vehicles,
}
"""The edge commands that take ``--settings``: their words -> (their settings' type, what runs them), imported when asked."""


def edge_of(argv: list[str]) -> tuple[str, ...] | None:
    """The edge command ``argv`` starts with, if it is one of :data:`EDGES` and carries ``--settings``."""
    if "--settings" not in argv:
        return None
    return next((words for words in EDGES if argv[: len(words)] == list(words)), None)


def run_edge(argv: list[str]) -> int:
    """``COMMAND --swarm NAME --settings FILE [--supervisor PID]`` (what the supervisor starts):
    run the edge with the settings in FILE (``-``: standard input), which must be this swarm's."""
    words = edge_of(argv)
    if words is None:
        raise ValueError(f"not an edge's settings command line: {argv[:2]!r}")
    from zenswarm.compose.roles import settings_words

    kind, run = EDGES[words]()
    ns = settings_words(f"zenswarm {' '.join(words)}", argv[len(words) :])
    settings: Any = decode_as(read_settings(ns.settings), kind)
    if settings.swarm != ns.swarm:
        raise ScenarioError("--settings", f"the settings of swarm {settings.swarm!r}, not of swarm {ns.swarm!r}")
    return run(settings)

"""Simulated quadrotors exposed as MAVLink vehicles over UDP: the subset of a PX4 multicopter
that the MAVLink bridge (:mod:`zenswarm.bridge.vehicles.mavlink`) uses, so the whole chain agents -> bridge ->
MAVLink/UDP -> vehicles runs on one machine and in CI.

Each UAV i of the scenario is a vehicle with its own system id (default i) listening on its own
UDP port (``udpin:HOST:BASE_PORT + i - 1``; it answers whoever talks to it), or with
``sitl_ports`` sending as PX4 SITL does from ``BASE_PORT + 40 + i - 1`` to ``BASE_PORT + i - 1``
(a ground station listens with ``udpin``). Physics is :func:`zenswarm.plant.quadrotor.step` (eqs 1-5 with
the onboard attitude PID) for all UAVs at once, ``timing.physics_rate_hz`` sub-steps (1 kHz) in
chunks of ``timing.substeps`` (10) at ``timing.control_rate_hz`` (100 Hz) on the wall clock, plus
the scenario's disturbances and a flat ground at ``ground_z`` (vehicles spawn on it below their
scenario initial position).

Spoken (PX4 flavour by default; ``autopilot = "ardupilot"`` switches to ArduCopter's mode numbers,
heartbeat and behaviours; each behaviour cites its autopilot source next to its code):

* HEARTBEAT 1 Hz: MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4 / ARDUPILOTMEGA, base_mode =
  CUSTOM_MODE_ENABLED (| SAFETY_ARMED), custom_mode = PX4 ``main << 16 | sub << 24`` or the
  ArduCopter mode number; SYS_STATUS 1 Hz with the sensor, GPS and MAV_SYS_STATUS_PREARM_CHECK
  health bits; EXTENDED_SYS_STATE (landed state) and HOME_POSITION 1 Hz;
* LOCAL_POSITION_NED and ATTITUDE (PX4: and ATTITUDE_QUATERNION) at ``telemetry_hz`` (50 Hz),
  GLOBAL_POSITION_INT at a fifth of it (a simulated GPS about PX4 SITL's default home);
  local NED about the swarm origin, or with ``own_origin`` about where each vehicle booted;
* the parameter protocol with each autopilot's parameters (:mod:`zenswarm.plant.mavlink.params`),
  which the vehicle follows (COM_OF_LOSS_T, MIS_TAKEOFF_ALT, MPC_TKO_SPEED, MPC_LAND_SPEED,
  COM_DISARM_LAND, RTL_RETURN_ALT; GUID_OPTIONS, GUID_TIMEOUT, WPNAV_SPEED_UP/DN, LAND_SPEED,
  DISARM_DELAY, RTL_ALT);
* COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_DO_SET_MODE (and SET_MODE),
  MAV_CMD_NAV_TAKEOFF, MAV_CMD_NAV_LAND, MAV_CMD_NAV_RETURN_TO_LAUNCH, MAV_CMD_REQUEST_MESSAGE
  (HOME_POSITION, AUTOPILOT_VERSION), each answered with COMMAND_ACK; other commands get
  MAV_RESULT_UNSUPPORTED; messages for another system or another component are ignored;
* SET_ATTITUDE_TARGET (quaternion, or body rates when the attitude is ignored; PX4: normalised
  thrust through :class:`zenswarm.vehicle.frames.ThrustMap`; ArduCopter: a climb rate unless GUID_OPTIONS
  bit 3) and SET_POSITION_TARGET_LOCAL_NED (position/velocity/yaw in MAV_FRAME_LOCAL_NED; the
  vehicle then runs its own PD position loop producing thrust and attitude).

PX4 modes: OFFBOARD (main 6) follows the setpoints; it is refused (MAV_RESULT_TEMPORARILY_REJECTED)
unless a setpoint arrived in the last COM_OF_LOSS_T; HOLD (AUTO.LOITER, POSCTL, ALTCTL) holds the
position where it was entered; AUTO.TAKEOFF climbs to MIS_TAKEOFF_ALT (or param7 AMSL) then
holds; AUTO.RTL climbs to RTL_RETURN_ALT, returns over home and lands; AUTO.LAND descends at
MPC_LAND_SPEED and disarms COM_DISARM_LAND after touchdown. Offboard-loss failsafe: no setpoint
for COM_OF_LOSS_T -> HOLD; still none ``failsafe_land_s`` later -> LAND. Arming in OFFBOARD needs
fresh setpoints; disarming needs the vehicle on the ground unless forced (param2 = 21196).

ArduCopter modes: GUIDED / GUIDED_NOGPS stay in the mode without setpoints; their sub-modes
(TakeOff, Pos, PosVelAccel, VelAccel, Angle) follow ArduCopter ``mode_guided.cpp``: landed,
only MAV_CMD_NAV_TAKEOFF or a positive climb rate lifts off (position targets do not), and
velocity/angle targets older than GUID_TIMEOUT are dropped (stop, or level and hold altitude);
LOITER, BRAKE, POSHOLD, ALT_HOLD, STABILIZE hold; LAND descends at LAND_SPEED and disarms on
touchdown; RTL climbs to RTL_ALT, returns and lands; landed for DISARM_DELAY -> disarm.

Test hooks (also what a faulty vehicle looks like): :meth:`MavlinkFleet.silence` drops all
traffic of one vehicle both ways for a while (physics goes on); ``mode_override`` makes a vehicle
accept mode requests but keep reporting (and flying) another mode;
:meth:`MavlinkFleet.set_prearm_failure` makes it fail its pre-arm checks.

Not simulated: PX4's RTL_DESCEND_ALT loiter and COM_DISARM_PRFLT, ArduCopter's RTL_LOIT_TIME,
the auto_armed / throttle-zero subtleties of ArduCopter's auto-disarm,
MAV_CMD_SET_MESSAGE_INTERVAL (answered UNSUPPORTED), missions, geofence, RC.

``zenswarm mavlink-vehicle SCENARIO --base-port P`` (or ``zenswarm plant --mavlink --scenario
SCENARIO --base-port P``) runs the fleet until
SIGTERM/SIGINT (:func:`run_fleet`). Importing this module sets ``MAVLINK20=1`` (see bridge.vehicles.mavlink).

This module is the simulated MAVLink vehicles' front door: :func:`run_fleet`, and every name of
its parts, which live one idea a module: :mod:`zenswarm.plant.mavlink.options` (what a vehicle is
configured with, :class:`VehicleOptions`; the mode kinds), :mod:`zenswarm.plant.mavlink.params`
(the autopilots' parameters), :mod:`zenswarm.plant.mavlink.link` (the UDP endpoint, the messages
in and out, the GPS about :data:`REF_LLA`), :mod:`zenswarm.plant.mavlink.autopilot` (one vehicle's
autopilot, :class:`SimVehicle`), :mod:`zenswarm.plant.mavlink.fleet` (:class:`MavlinkFleet`); the
position loop is :mod:`zenswarm.plant.position_control`'s, shared with the simulated Crazyflies,
and the run until a signal :mod:`zenswarm.plant.fleet`'s. The wire is MAVLink's local NED (body
FRD); the plant and the autopilot's state the swarm's ENU (body FLU).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from zenswarm.plant.fleet import run_until_signal
from zenswarm.plant.mavlink.autopilot import (  # noqa: F401 - the parts' names, importable here as before they moved
    _FORCE_MAGIC,
    _GUID_THRUST_AS_THRUST,
    SUB_ANGLE,
    SUB_POS,
    SUB_POSVEL,
    SUB_TAKEOFF,
    SUB_VEL,
    SimVehicle,
)
from zenswarm.plant.mavlink.fleet import MavlinkFleet
from zenswarm.plant.mavlink.link import _EARTH_R, REF_LLA, mavlink, mavutil  # noqa: F401
from zenswarm.plant.mavlink.options import HOLD, LAND, OFFBOARD, RTL, TAKEOFF, VehicleOptions, vehicle_options  # noqa: F401

__all__ = ["VehicleOptions", "SimVehicle", "MavlinkFleet", "run_fleet"]


def run_fleet(
    sc: Any,
    *,
    base_port: int | None = None,
    autopilot: str | None = None,
    telemetry_hz: float | None = None,
    duration: float | None = None,
    own_origin: bool = False,
    sitl_ports: bool = False,
    rt_priority: int | None = None,
) -> int:
    """Run the fleet of scenario ``sc`` in the calling thread until SIGTERM/SIGINT (or
    ``duration`` s). ``base_port``: vehicle i listens on UDP base_port + i - 1 (None: the
    scenario's ``mavlink.base_port``); ``autopilot`` (``px4`` or ``ardupilot``) and
    ``telemetry_hz`` override the scenario's vehicle options; ``own_origin`` and ``sitl_ports`` set
    the options of the same names (:class:`VehicleOptions`); ``rt_priority``: run under
    ``SCHED_FIFO`` at this priority once the fleet is built (:mod:`zenswarm.process.rtsched`; checked
    first, exit 2 if not permitted). The command line (``zenswarm
    mavlink-vehicle``, ``zenswarm plant --mavlink``) is parsed in :mod:`zenswarm.compose.roles`."""
    from zenswarm.process import rtsched
    from zenswarm.process.runtime import gc_policy, gc_startup_done

    gc_policy()  # a bad ZENSWARM_GC: exit 2 before any work
    rtsched.set_requested(rtsched.validate(rt_priority, realtime=True))  # out of range or not permitted: exit 2 now
    opts = vehicle_options(sc)
    opts = replace(
        opts,
        autopilot=autopilot or opts.autopilot,
        telemetry_hz=telemetry_hz or opts.telemetry_hz,
        own_origin=own_origin or opts.own_origin,
        sitl_ports=sitl_ports or opts.sitl_ports,
    )
    # one fleet, its ports bound once (a busy port: ScenarioError naming it, exit 2)
    fleet = MavlinkFleet.from_scenario(sc, base_port=base_port, opts=opts)
    ready = (
        f"{fleet.n} vehicle(s) ({fleet.opts.autopilot}) "
        + ", ".join(f"sysid {v.sysid} on udp {fleet.opts.host}:{v.port}" for v in fleet.vehicles)
        + f"; physics {1 / fleet.h:g} Hz in chunks of {fleet.chunk}, telemetry {fleet.loop_hz / fleet.tel_every:g} Hz"
    )
    # once ready (sockets open, vehicles built) the GC's start-up is done: see zenswarm.process.gcpolicy.GcPolicy (safe
    # points: WallClock.wait); its counters end the stopped line
    return run_until_signal(
        fleet, "mavlink-vehicle", ready, duration, on_ready=gc_startup_done, counters=lambda: str(gc_policy().counters())
    )

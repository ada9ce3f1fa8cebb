"""MAVLink bridge: fly the swarm's agents on PX4 or ArduPilot vehicles (or the simulated ones of
:mod:`zenswarm.plant.mavlink_vehicle`) without changing a line of the agents.

``zenswarm bridge mavlink SCENARIO --swarm S --connect EP [--conn I=URL ...]`` takes the plant's place on the swarm bus in realtime
mode. For each UAV i it opens (or shares) a MAVLink connection (pymavlink connection string:
``udpout:host:port``, ``udpin:host:port``, ``tcp:host:port``, ``/dev/ttyUSB0,921600``) to the
vehicle with system id ``sysid_i`` and then:

1. sends its own HEARTBEAT at 1 Hz (MAV_TYPE_ONBOARD_CONTROLLER) and waits for the vehicle's;
   then reads the autopilot's parameters (PX4 ``MPC_THR_HOVER``, ``COM_OF_LOSS_T``; ArduCopter
   ``GUID_OPTIONS``, ``GUID_TIMEOUT``, ``MOT_THST_HOVER``): the hover throttle of the thrust map,
   the check that ``link_timeout_s`` is below the vehicle's loss timeout, and on ArduCopter with
   attitude setpoints ``GUID_OPTIONS`` bit 3 set (thrust as thrust, not a climb rate); a missing
   or bad parameter refuses the UAV (:func:`zenswarm.vehicle.autopilot.vehicle_params`);
2. streams setpoints (a position hold at the current position) for ``stream_s`` seconds before
   asking for the offboard mode, as PX4 requires (it refuses OFFBOARD unless setpoints arrive at
   more than 2 Hz, and leaves it after ``COM_OF_LOSS_T`` without them);
3. asks for the mode with MAV_CMD_DO_SET_MODE (PX4: OFFBOARD = main mode 6; ArduPilot copter:
   GUIDED = 4 for position setpoints or a takeoff, GUIDED_NOGPS = 20 for attitude only) and waits
   until the vehicle's heartbeat reports it. It never arms a vehicle whose heartbeat reports a
   mode it did not ask for: if the vehicle acknowledges the request but keeps reporting another
   mode, the UAV is *refused* (reason in the diag message) and left alone. Nor one whose
   SYS_STATUS reports a present, enabled subsystem unhealthy or failing pre-arm checks
   (:func:`health_problem`);
4. arms (MAV_CMD_COMPONENT_ARM_DISARM) and, with ``takeoff = true``, flies to the UAV's initial
   position of the scenario with position setpoints (ArduCopter: MAV_CMD_NAV_TAKEOFF first, and
   no position target until its altitude is reached, see ``_ardupilot_climb``);
5. once every UAV is ready (or ``start_timeout_s`` passed) and, unless ``--no-wait-alive``, the
   leader and the agents hold liveliness tokens, starts the mission clock: every control tick it
   publishes ``clock`` and each ready UAV's ``uav/<i>/state`` (from LOCAL_POSITION_NED and
   ATTITUDE/ATTITUDE_QUATERNION, converted to ENU/FLU by :mod:`zenswarm.vehicle.frames`; stamped ``ts``
   with the vehicle's ``time_boot_ms`` on the mission clock once TIMESYNC gave its clock offset,
   :meth:`Bridge.sample_time`), as the realtime
   plant does (mission time is wall time since the start: a tick the loop missed on an overloaded
   host is skipped and counted in ``ticks_skipped``, never caught up in a burst), and forwards
   each agent's ``uav/<i>/cmd`` as SET_ATTITUDE_TARGET
   (quaternion + normalised thrust through :class:`zenswarm.vehicle.frames.ThrustMap`) at
   ``max(rate_hz, 20)`` Hz, re-sending the latest command if the agent is slower; with
   ``setpoint = "position"`` it forwards ``uav/<i>/ref`` as SET_POSITION_TARGET_LOCAL_NED
   (position + velocity) instead and lets the vehicle run its own position loop. A command older
   than ``cmd_timeout_s`` is replaced by a position hold;
6. a vehicle silent for more than ``link_timeout_s`` is marked unhealthy in ``diag/bridge``
   (its state is no longer published; the other UAVs keep flying); when it talks again it is
   marked healthy and, if it left the offboard mode during the silence (offboard-loss failsafe)
   but is still armed, the bridge asks for the mode again. If the mode changes while the link
   is healthy (a pilot took over), the UAV is *released* and no longer commanded;
7. at the end of the mission (``timing.time_limit_s``) or on SIGTERM/SIGINT it switches every
   vehicle it armed to the land mode (PX4 AUTO.LAND, ArduPilot LAND), waits (at most
   ``land_timeout_s``) until the vehicles report disarmed (auto-disarm after landing) and sends a
   (non-forced) disarm to any that did not.

Unknown and malformed MAVLink traffic (bad CRC/garbage, unknown message ids, non-finite fields,
other system ids) is ignored and counted (``mav_bad``, ``mav_unknown``, ``mav_malformed``,
``mav_other_system``, ``mav_unhandled`` in the bridge's diag counters).

Configuration: the scenario's ``[mavlink]`` table (see :func:`mavlink_settings` for every key),
overridden by command-line flags. All frames conversions are in :mod:`zenswarm.vehicle.frames`.

The package, one idea a module: :mod:`.link` (pymavlink, a UAV's link, telemetry and endpoint,
its frames), :mod:`.core` (the bridge's links, commands and what it knows of each vehicle),
:mod:`.receive` (what it reads), :mod:`.phases` (the per-UAV phase machine, steps 1-4 and 6),
:mod:`.setpoints` (setpoints, TIMESYNC, states out), :mod:`.landing` (step 7), :mod:`.bridge`
(:class:`Bridge`: all of them), :mod:`.loop` (the process and its loop), :mod:`.cli` (the command,
its settings). Every name of the module it was (``Bridge``, ``_BridgeLoop``, ``mavlink``,
``mavutil``, the phases, ...) is still importable from here.

Importing this package sets ``MAVLINK20=1`` in the environment before importing pymavlink, so all
connections of the process speak MAVLink 2 (PX4 and ArduPilot both do).
"""

from __future__ import annotations

from zenswarm.bridge.vehicles.mavlink.bridge import Bridge
from zenswarm.bridge.vehicles.mavlink.cli import _cli_overrides, _main_args, add_mavlink_parser, add_parsers, bridge_settings, run
from zenswarm.bridge.vehicles.mavlink.core import _AIRBORNE_STATES, _PENDING, _STALL_S, BridgeCore
from zenswarm.bridge.vehicles.mavlink.landing import Landing
from zenswarm.bridge.vehicles.mavlink.link import (
    _TIMESYNC_WINDOW,
    ARM,
    CONNECTING,
    DONE,
    GROUNDED,
    LANDING,
    MODE,
    PARAMS,
    READY,
    REFUSED,
    RELEASED,
    STREAM,
    TAKEOFF,
    Endpoint,
    Telemetry,
    UavLink,
    mavlink,
    mavutil,
    swarm_to_vehicle,
    vehicle_to_swarm,
)
from zenswarm.bridge.vehicles.mavlink.loop import _BridgeLoop, _make_bridge, _run
from zenswarm.bridge.vehicles.mavlink.phases import (
    _ARM_ATTEMPTS,
    _ARM_RETRY_S,
    _MISMATCH_HEARTBEATS,
    _MODE_ATTEMPTS,
    _MODE_RETRY_S,
    _PARAM_RETRY_S,
    _SYS_STATUS_WAIT_S,
    _TAKEOFF_RETRY_S,
    PhaseMachine,
    health_problem,
)
from zenswarm.bridge.vehicles.mavlink.receive import Receiver, _finite
from zenswarm.bridge.vehicles.mavlink.setpoints import _TIMESYNC_S, ATT_MASK, POS_MASK, Setpoints
from zenswarm.vehicle.autopilot import (  # re-exported: the mode tables and settings are the bridge's vocabulary
    AP_COPTER_MODES,
    PX4_AUTO_SUB,
    PX4_HOLD,
    PX4_LAND,
    PX4_MAIN,
    PX4_OFFBOARD,
    PX4_POSCTL,
    MavlinkSettings,
    autopilot_name,
    mavlink_settings,
    mode_name,
    mode_request_params,
    px4_custom_mode,
    px4_decode,
)

__all__ = [
    "Bridge",
    "vehicle_to_swarm",
    "swarm_to_vehicle",
    "health_problem",
    "add_parsers",
    "add_mavlink_parser",
    "bridge_settings",
    "run",
    # the modules' parts
    "BridgeCore",
    "Receiver",
    "PhaseMachine",
    "Setpoints",
    "Landing",
    "Telemetry",
    "Endpoint",
    "UavLink",
    "mavlink",
    "mavutil",
    "ATT_MASK",
    "POS_MASK",
    "CONNECTING",
    "PARAMS",
    "STREAM",
    "MODE",
    "ARM",
    "TAKEOFF",
    "READY",
    "REFUSED",
    "RELEASED",
    "GROUNDED",
    "LANDING",
    "DONE",
    # what the module it was named, kept importable from here
    "_AIRBORNE_STATES",
    "_ARM_ATTEMPTS",
    "_ARM_RETRY_S",
    "_BridgeLoop",
    "_MISMATCH_HEARTBEATS",
    "_MODE_ATTEMPTS",
    "_MODE_RETRY_S",
    "_PARAM_RETRY_S",
    "_PENDING",
    "_STALL_S",
    "_SYS_STATUS_WAIT_S",
    "_TAKEOFF_RETRY_S",
    "_TIMESYNC_S",
    "_TIMESYNC_WINDOW",
    "_cli_overrides",
    "_finite",
    "_main_args",
    "_make_bridge",
    "_run",
    # re-exported from zenswarm.vehicle.autopilot: the bridge's vocabulary (modes, settings)
    "AP_COPTER_MODES",
    "PX4_AUTO_SUB",
    "PX4_HOLD",
    "PX4_LAND",
    "PX4_MAIN",
    "PX4_OFFBOARD",
    "PX4_POSCTL",
    "MavlinkSettings",
    "autopilot_name",
    "mavlink_settings",
    "mode_name",
    "mode_request_params",
    "px4_custom_mode",
    "px4_decode",
]

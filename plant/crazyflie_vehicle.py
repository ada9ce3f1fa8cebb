"""Simulated Crazyflie 2.1 quadrotors that speak CRTP over UDP as cflib's ``udp://`` driver
expects (the transport of Bitcraze's software-in-the-loop firmware): one CRTP packet per UDP
datagram, byte 0 the header ``port << 4 | 0x0C | channel``, then up to 30 bytes of payload.
Vehicle i of the scenario listens on ``udp://HOST:BASE_PORT + i - 1`` (cflib's SITL base port
is 19850) and answers whoever talks to it. Physics is :func:`zenswarm.plant.quadrotor.step`
(eqs 1-5 with the onboard attitude PID) for all vehicles at once, as in
:mod:`zenswarm.plant.mavlink_vehicle`, with a flat ground at z = 0 (vehicles spawn on it below
their initial positions) and positions in the swarm's ENU frame (a positioning system set up
so).

What it answers, from bitcraze's crazyflie-firmware (``src/modules/src``; CRTP protocol version
12, ``crtp.h``), so that unmodified cflib connects, logs, sets parameters and flies it:

* link control (port 15): echo (channel 0), source (1: "Bitcraze Crazyflie"), sink (2), and the
  UDP driver's scan probe (a null packet, 0xFF) answered with an empty link packet
  (``crtpservice.c``);
* platform (port 13): the protocol version (channel 1, command 0) and firmware name (command 1);
  the legacy arming request (channel 0, command 1) (``platformservice.c``);
* log (port 5): the TOC v2 (channel 0: info = count, CRC32, LOG_MAX_OPS, LOG_MAX_BLOCKS; items
  = id, type, group, name), block create/append v2, delete, start (period in 10 ms), stop,
  reset (channel 1, answers ``[cmd, id, errno]``: EEXIST, ENOMEM, E2BIG, ENOENT), data on
  channel 2 as ``[id, 24-bit ms timestamp, values]`` at each block's period (``log.c``);
* param (port 2): the TOC v2, read (channel 1, ``[id, status, value]``), write (channel 2,
  echoed), set by name (channel 3) (``param_logic.c``); read-only parameters refuse writes;
* memory (port 4): no memories (count 0), which ends cflib's memory scan;
* supervisor (port 9, protocol >= 12): the state bitfield (channel 0, ``0x0C``), arm/disarm,
  crash recovery, emergency stop (channel 1; answers ``[cmd | 0x80, success, armed]``)
  (``crtp_supervisor.c``); the state machine of ``supervisor_state_machine.c`` reduced to what a
  flight meets: pre-flight checks passed -> armed (ReadyToFly) -> flying (a motor above idle
  within 2 s) -> landed -> reset (disarmed after LANDING_TIMEOUT 3 s); armed but not flying for
  PREFLIGHT_TIMEOUT 30 s -> disarmed; the motors run only when armed;
* commander (port 3): the legacy RPYT setpoint ``<fffH`` (roll, pitch in degrees; yaw *rate* in
  deg/s, inverted; thrust 0..65535, below MIN_THRUST 1000 -> 0, clamped to MAX_THRUST 60000;
  thrust locked at 0 until a setpoint with thrust 0 arrives, ``crtp_commander_rpyt.c``); the
  firmware's attitude is in the legacy frame where pitch is inverted
  (:mod:`zenswarm.vehicle.crazyflie` has every sign); ``flightmode.stabModeYaw`` = 1 makes the
  yaw absolute;
* generic setpoint (port 7): STOP, POSITION (x, y, z m, yaw deg), VELOCITY_WORLD (m/s, yaw rate
  deg/s), and the meta command notify-setpoint-stop (``crtp_commander_generic.c``);
* high-level commander (port 8): set group mask, takeoff and land (v2: height, yaw, use current
  yaw, duration), go to (v2), stop; takeoff only from a stopped planner, land unless already
  landing, both from the vehicle's state when the planner is stopped; a finished landing stops
  the planner, and a stopped planner sends the null setpoint (motors off)
  (``crtp_commander_high_level.c``, ``planner.c``). Its setpoints have priority 1 and the CRTP
  setpoints 2: a CRTP setpoint stops the planner, and the high-level commander is heard again
  only after notify-setpoint-stop relaxes the priority (``commander.c``): the clean handover back
  is land (or take off), then notify-setpoint-stop;
* the commander watchdog (``supervisor.c``): a flying vehicle that has heard no setpoint for
  COMMANDER_WDT_TIMEOUT_STABILIZE (500 ms) levels out (roll = pitch = 0, yaw rate 0, thrust
  kept); after COMMANDER_WDT_TIMEOUT_SHUTDOWN (2 s) its motors stop and it is *locked* (a
  reboot is needed: :meth:`CrazyflieFleet.reboot`).

Log variables (names, types and units as the firmware's): ``stateEstimate.{x,y,z,vx,vy,vz}``
(m, m/s, float), ``stateEstimate.{roll,pitch,yaw}`` (deg, pitch inverted), ``gyro.{x,y,z}``
(deg/s, body), ``stabilizer.thrust``, ``motor.m1..m4`` (uint16), ``pm.vbat`` (V),
``pm.batteryLevel`` (%), ``pm.state``, ``radio.rssi``, ``supervisor.info``. Parameters: see
:data:`PARAMS`.

* localization (port 6): external position (channel 0 EXT_POSITION ``<fff``, the generic
  channel's EXT_POSE, channel 2 EXT_POSITION_PACKED for this vehicle's id = its number i)
  (``crtp_localization_service.c``). The estimator: the true state until the first external
  position; from then on the last measurement dead-reckoned on the velocity with a small bias
  (:data:`ESTIMATOR_DRIFT_M_S`), so a silent feed drifts. The logged ``stateEstimate.x/y/z``, the
  high-level commander and the position controller use that estimate (the motion is the
  plant's true one).

Not simulated: memories, trajectories in memory, tumble detection, the Kalman filter (the
estimate is the true state, or the external positions as above), the quaternion of EXT_POSE,
radio link statistics (the UDP driver has none), console text.

Test hooks: :meth:`CrazyflieFleet.silence` drops one vehicle's traffic both ways for a while
(physics goes on: a lost link), :meth:`CrazyflieFleet.status`.

``zenswarm crazyflie-vehicle SCENARIO --base-port P`` runs the fleet until SIGTERM/SIGINT
(:func:`run_fleet`); with ``--mocap --swarm S --connect EP`` it is also the motion-capture
system: :class:`MocapFeeder` publishes the true positions on ``swarm/S/mocap/<i>``.

This module is the simulated Crazyflies' front door: :func:`run_fleet`, and every name of its
parts, which live one idea a module: :mod:`zenswarm.plant.crazyflie.crtp` (the protocol's numbers and
encodings: ports, header, TOC, log blocks), :mod:`zenswarm.plant.crazyflie.log` (the log service,
:data:`LOG_VARS`), :mod:`zenswarm.plant.crazyflie.params` (the parameter service, :data:`PARAMS`),
:mod:`zenswarm.plant.crazyflie.planner` (the high-level commander's segments, :class:`HlPlan`),
:mod:`zenswarm.plant.crazyflie.firmware` (one vehicle, :class:`SimCrazyflie`),
:mod:`zenswarm.plant.crazyflie.fleet` (:class:`CrazyflieFleet`), :mod:`zenswarm.plant.crazyflie.mocap_feeder`
(:class:`MocapFeeder`); the position controller is :mod:`zenswarm.plant.position_control`'s, shared
with the simulated MAVLink vehicles, and the run until a signal :mod:`zenswarm.plant.fleet`'s.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from zenswarm.plant.crazyflie.crtp import *  # noqa: F403 - the protocol's names, importable here as before they moved
from zenswarm.plant.crazyflie.crtp import DEFAULT_BASE_PORT, header, toc_crc, toc_item
from zenswarm.plant.crazyflie.firmware import (  # noqa: F401 - the parts' names, importable here as before they moved
    ESTIMATOR_DRIFT_M_S,
    FIRMWARE_NAME,
    IS_FLYING_HYSTERESIS_S,
    LANDING_TIMEOUT_S,
    PREFLIGHT_TIMEOUT_S,
    PRIORITY_CRTP,
    PRIORITY_DISABLE,
    PRIORITY_HIGHLEVEL,
    PRIORITY_LOWEST,
    WDT_SHUTDOWN_S,
    WDT_STABILIZE_S,
    SimCrazyflie,
)
from zenswarm.plant.crazyflie.fleet import CrazyflieFleet
from zenswarm.plant.crazyflie.log import LOG_VARS  # noqa: F401
from zenswarm.plant.crazyflie.mocap_feeder import MocapFeeder
from zenswarm.plant.crazyflie.params import PARAMS  # noqa: F401
from zenswarm.plant.crazyflie.planner import HlPlan  # noqa: F401
from zenswarm.plant.fleet import run_until_signal

# the protocol helpers' names before they moved to zenswarm.plant.crazyflie.crtp
_toc_crc, _toc_item, _header = toc_crc, toc_item, header


def run_fleet(
    sc: Any, *, base_port: int = DEFAULT_BASE_PORT, host: str = "127.0.0.1", duration: float | None = None,
    mocap: tuple[str, list[str]] | None = None, mocap_hz: float = 100.0, rt_priority: int | None = None,
    mocap_security: Mapping[str, Any] | None = None,
) -> int:  # fmt: skip
    """Run the fleet of scenario ``sc`` in the calling thread until SIGTERM/SIGINT (or
    ``duration`` s). A port that cannot be bound: :class:`~zenswarm.errors.ScenarioError` naming it (exit 2).
    ``mocap`` = (swarm name, Zenoh connect endpoints): also publish the vehicles' true positions
    as a motion-capture feed (:class:`MocapFeeder`) at ``mocap_hz``, its session configured with
    ``mocap_security`` (:func:`zenswarm.process.security.client_fragments`: a secured router's
    credentials; None: an open one). ``rt_priority``: run under
    ``SCHED_FIFO`` at this priority once the fleet is up (:mod:`zenswarm.process.rtsched`; checked
    first, exit 2 if not permitted)."""
    from zenswarm.process import rtsched

    rtsched.set_requested(rtsched.validate(rt_priority, realtime=True))  # out of range or not permitted: exit 2 now
    fleet = CrazyflieFleet.from_scenario(sc, base_port=base_port, host=host)
    if mocap is None:
        return _run_fleet(fleet, duration)
    from zenswarm import bus
    from zenswarm.bus.wire import Keys

    try:
        with bus.open_session(bus.client_config(mocap[1], settings=mocap_security), handle_signals=False) as session:
            feeder = MocapFeeder(fleet, session, Keys(mocap[0]).prefix, mocap_hz)
            fleet.on_tick = feeder
            try:
                return _run_fleet(fleet, duration, f"; mocap on swarm/{mocap[0]}/mocap/<i> at {mocap_hz:g} Hz")
            finally:
                fleet.on_tick = None
                feeder.close()
    finally:
        fleet.close()


def _run_fleet(fleet: CrazyflieFleet, duration: float | None, extra: str = "") -> int:
    """Run ``fleet`` until SIGTERM/SIGINT (or ``duration`` s) and close it
    (:func:`zenswarm.plant.fleet.run_until_signal`); ``extra`` ends the ready line."""
    return run_until_signal(fleet, "crazyflie-vehicle", f"{fleet.n} Crazyflie(s) at " + ", ".join(fleet.uris()) + extra, duration)

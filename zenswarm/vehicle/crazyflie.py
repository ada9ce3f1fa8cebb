"""Crazyflie 2.1 firmware units: the thrust map (N <-> the 16-bit thrust command) and the legacy
roll/pitch/yaw-rate/thrust (RPYT) setpoint's angles, signs and limits (pure: numpy and math only).

Thrust map. The firmware's thrust command is a 16-bit motor duty (0..65535 = 0..100 % PWM). The
collective thrust it gives is Bitcraze's own thrust-stand measurement of a Crazyflie 2.x
("PWM to Thrust", crazyflie-firmware ``docs/functional-areas/pwm-to-thrust.md``, "Old
measurements (2015)": thrust in grams at 0, 6.25, ..., 93.75 % PWM). Between the measured points
the map is linear; above 93.75 % it extends the last segment to 100 %. It is monotone, so it
inverts exactly. The legacy commander (``crtp_commander_rpyt.c``) takes commands below
``MIN_THRUST`` = 1000 as 0 and clamps above ``MAX_THRUST`` = 60000: :func:`thrust_to_command`
clamps to that range and says so.

Angles. The legacy setpoint carries roll and pitch in degrees and the yaw *rate* in deg/s
(``flightmode.stabModeYaw`` = 0, RATE, the default). Signs, from the firmware source:

* roll: right-handed about the body x axis (forward), as the paper's phi;
* pitch: the firmware's attitude is in the "legacy CF2 body coordinate system, where pitch is
  inverted" (``stabilizer_types.h``; ``stateEstimate.pitch`` is logged so), and cflib's
  ``Commander.send_setpoint`` sends ``-pitch`` on the wire. So the paper's theta (right-handed
  about the body y axis, nose down positive, accelerating towards +x) is cflib's ``pitch``
  argument, the wire's ``-theta`` and the logged ``stateEstimate.pitch``'s ``-theta``;
* yaw rate: "legacy rate input is inverted" (``crtp_commander_rpyt.c``: ``attitudeRate.yaw =
  -values->yaw``): a counter-clockwise rate r (rad/s, about z up) is ``-degrees(r)`` on the wire;
* yaw (logged ``stateEstimate.yaw``): degrees, counter-clockwise about z up, the paper's psi.

Frames: the Crazyflie's world frame is whatever its positioning system gives (Lighthouse,
motion capture: set it up as x east, y north, z up, the swarm's ENU frame) and its body frame is
x forward, y left, z up (FLU), the paper's.
"""

from __future__ import annotations

import math

import numpy as np

G_STD = 9.81
"""m/s^2, the conversion of the thrust stand's grams to newtons."""

PWM_PERCENT = np.array([0.0, 6.25, 12.5, 18.75, 25.0, 31.25, 37.5, 43.25, 50.0, 56.25, 62.5, 68.75, 75.0, 81.25, 87.5, 93.75])
"""PWM duty of the thrust-stand measurement, % (crazyflie-firmware pwm-to-thrust.md, 2015 table)."""
THRUST_GRAMS = np.array([0.0, 1.6, 4.8, 7.9, 10.9, 13.9, 17.3, 21.0, 24.4, 28.6, 32.8, 37.3, 41.7, 46.0, 51.9, 57.9])
"""Collective thrust measured at each PWM duty, g (the same table)."""

CMD_FULL = 65535
"""The 16-bit thrust command at 100 % PWM."""
MIN_THRUST = 1000
"""Below this the legacy commander sends thrust 0 (``crtp_commander_rpyt.c`` MIN_THRUST)."""
MAX_THRUST = 60000
"""The legacy commander clamps the thrust command to this (``crtp_commander_rpyt.c`` MAX_THRUST)."""

_CMD = np.append(PWM_PERCENT / 100.0 * CMD_FULL, CMD_FULL)
_slope = (THRUST_GRAMS[-1] - THRUST_GRAMS[-2]) / (PWM_PERCENT[-1] - PWM_PERCENT[-2])
_N = np.append(THRUST_GRAMS, THRUST_GRAMS[-1] + _slope * (100.0 - PWM_PERCENT[-1])) * 1e-3 * G_STD


def command_to_thrust(cmd: float) -> float:
    """Collective thrust, N, that the 16-bit motor command ``cmd`` (0..65535) gives (the thrust
    map, piecewise linear through Bitcraze's measurement)."""
    return float(np.interp(min(max(float(cmd), 0.0), CMD_FULL), _CMD, _N))


def thrust_to_command(force_n: float) -> tuple[int, bool]:
    """The legacy setpoint's thrust command for a collective thrust ``force_n`` (N), and whether
    it was clamped: a thrust above what ``MAX_THRUST`` gives becomes ``MAX_THRUST``; a positive
    thrust below what ``MIN_THRUST`` gives becomes ``MIN_THRUST`` (the lowest that spins the
    motors); zero or less (or NaN) is 0, not a clamp."""
    f = float(force_n)
    if not f > 0.0:
        return 0, False
    cmd = float(np.interp(f, _N, _CMD))
    if cmd > MAX_THRUST:
        return MAX_THRUST, True
    if cmd < MIN_THRUST:
        return MIN_THRUST, True
    return int(round(cmd)), False


def max_thrust_n() -> float:
    """The largest collective thrust the legacy commander can ask for, N (at ``MAX_THRUST``)."""
    return command_to_thrust(MAX_THRUST)


def rpyt_wire(roll: float, pitch: float, yaw_rate: float) -> tuple[float, float, float]:
    """The legacy setpoint's (roll, pitch, yaw) wire floats for the paper's phi, theta (rad) and a
    counter-clockwise yaw rate (rad/s): (deg(phi), -deg(theta), -deg(rate))."""
    return math.degrees(roll), -math.degrees(pitch), -math.degrees(yaw_rate)


def rpyt_from_wire(roll_deg: float, pitch_deg: float, yaw_deg_s: float) -> tuple[float, float, float]:
    """Inverse of :func:`rpyt_wire`: the paper's phi, theta (rad) and the counter-clockwise yaw
    rate (rad/s) that the firmware flies for the wire's floats."""
    return math.radians(roll_deg), -math.radians(pitch_deg), -math.radians(yaw_deg_s)


def attitude_from_log(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """The paper's (phi, theta, psi), rad, from the logged ``stateEstimate.roll/pitch/yaw`` (deg,
    legacy pitch inverted)."""
    return np.array([math.radians(roll_deg), -math.radians(pitch_deg), math.radians(yaw_deg)])


def attitude_to_log(rpy: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`attitude_from_log`: ``stateEstimate.roll/pitch/yaw`` in degrees."""
    return math.degrees(float(rpy[0])), -math.degrees(float(rpy[1])), math.degrees(float(rpy[2]))


def yaw_rate_command(yaw_ref: float, yaw: float, gain: float = 4.0, limit: float = 3.0) -> float:
    """A yaw *rate* (rad/s, counter-clockwise) that turns ``yaw`` (rad) to ``yaw_ref`` (rad): the
    legacy setpoint has no absolute yaw in its default mode, so the bridge closes this
    proportional loop (gain 1/s, limited to ``limit`` rad/s) on the logged yaw."""
    e = (yaw_ref - yaw + math.pi) % (2.0 * math.pi) - math.pi
    return max(-limit, min(limit, gain * e))

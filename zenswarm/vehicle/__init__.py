"""Vehicle math and autopilot facts: what a quadrotor is, in numbers.

- :mod:`zenswarm.vehicle.params`: Crazyflie 2.1 physical parameters and attitude-PID gains (eqs 1-5).
- :mod:`zenswarm.vehicle.inversion`: thrust and attitude from a virtual acceleration, and back (eq. 28).
- :mod:`zenswarm.vehicle.frames`: ENU/FLU and the paper's ZYX Euler angles to MAVLink's NED/FRD.
- :mod:`zenswarm.vehicle.geometry`: clearances to the capped-cylinder obstacles and between UAVs.
- :mod:`zenswarm.vehicle.autopilot`: PX4 and ArduPilot flight modes and the ``[mavlink]`` settings.

Pure (numpy and the standard library), except :func:`zenswarm.vehicle.autopilot.load_mavutil`.
"""

"""The simulated Crazyflies' parts, one idea a module: the CRTP protocol (:mod:`.crtp`), the log and
parameter services (:mod:`.log`, :mod:`.params`), the high-level commander's segments
(:mod:`.planner`), a vehicle's firmware (:mod:`.firmware`), the fleet (:mod:`.fleet`) and the
motion-capture feed (:mod:`.mocap_feeder`). Their front door and command is
:mod:`zenswarm.plant.crazyflie_vehicle`."""

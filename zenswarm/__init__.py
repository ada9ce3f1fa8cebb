"""zenswarm: hierarchical distributed formation flight for quadrotor swarms over Zenoh.

Shared, small: scenario configuration and validation (:mod:`zenswarm.config`), the wire
protocol (:mod:`zenswarm.wire`), metrics, the in-process simulator and the CLI.
"""

__version__ = "0.1.0"

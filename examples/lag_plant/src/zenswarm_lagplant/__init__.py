"""Example zenswarm plant model plug-in: point mass, first-order attitude lag, linear drag."""

from zenswarm_lagplant.model import LagParams, LagPlant

__all__ = ["LagPlant", "LagParams"]

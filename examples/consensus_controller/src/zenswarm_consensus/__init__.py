"""Example zenswarm controller plug-in: first-order consensus formation with PD tracking."""

from zenswarm_consensus.controller import ConsensusController, ConsensusParams

__all__ = ["ConsensusController", "ConsensusParams"]

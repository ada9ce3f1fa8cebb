"""The project's one exception hierarchy."""

from __future__ import annotations


class ZenswarmError(Exception):
    """Base class of every error zenswarm raises on purpose."""


class ScenarioError(ZenswarmError):
    """A scenario file or value is invalid. ``field`` names the offending field (dotted path)."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")


class DecodeError(ZenswarmError):
    """A payload on the bus could not be decoded or failed validation."""


class ProcessFailure(ZenswarmError):
    """A swarm process died or the mission failed."""


class RecordingError(ZenswarmError):
    """An MCAP recording is missing, truncated or corrupted."""


class CampaignError(ZenswarmError):
    """A campaign directory (``zenswarm sweep --out DIR``) is missing, unreadable or malformed."""

"""argparse ``type=`` functions shared by the commands: a bad value is a usage error (exit 2)
naming the flag, before any work. The seed's is :func:`zenswarm.config.seed_arg`."""

from __future__ import annotations

import argparse
import math

__all__ = ["positive_float"]


def positive_float(text: str) -> float:
    """A finite number > 0 (``--fixed-gain``, ``--lockstep-timeout``, ``--external-timeout``,
    ``scenario generate --spacing``): 0, negatives, nan and inf are refused."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0 (positive), got {text!r}")
    return v

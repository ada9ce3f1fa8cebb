"""argparse ``type=`` functions shared by the commands: a bad value is a usage error (exit 2)
naming the flag, before any work. The seed's is :func:`zenswarm.config.seed_arg`. Also the flag set
every swarm process takes (:func:`add_process_args`)."""

from __future__ import annotations

import argparse
import math

__all__ = ["positive_float", "add_process_args"]


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


def add_process_args(p: argparse.ArgumentParser) -> None:
    """The flags every swarm process takes (read back with
    :meth:`zenswarm.runtime.ProcessOptions.of`): ``--scenario``, ``--swarm``, ``--connect``,
    ``--realtime``, the credentials (:func:`zenswarm.security.add_security_args`), the link
    faults (:func:`zenswarm.linkfaults.add_fault_args`) and ``--lockstep-timeout``."""
    from pathlib import Path

    from . import security
    from .linkfaults import add_fault_args
    from .runtime import DEFAULT_LOCKSTEP_TIMEOUT_S

    p.add_argument("--scenario", type=Path, help="scenario TOML; if omitted, fetched from the leader's mission key")
    p.add_argument("--swarm", default="default", help="swarm name: the key prefix swarm/<name> (default: default)")
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh router endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--realtime", action="store_true", help="run on the wall clock (latest value wins) instead of lockstep")
    security.add_security_args(p)
    add_fault_args(p)
    p.add_argument(
        "--lockstep-timeout",
        type=positive_float,
        default=DEFAULT_LOCKSTEP_TIMEOUT_S,
        metavar="S",
        help=f"lockstep: wall seconds to wait for an input before it counts as a drop (default {DEFAULT_LOCKSTEP_TIMEOUT_S})",
    )

"""TRANSITIONAL (issue 14): the flag helpers that :mod:`zenswarm.runtime` and the role processes
still import from the base, re-exported from their home at the edge, :mod:`zenswarm.bridge.args`.

Nothing below the edges should see argparse; this module (and the ``add_fault_args`` /
``add_security_args`` wrappers of :mod:`zenswarm.linkfaults` and :mod:`zenswarm.security`) goes
once runtime.py and the roles take typed options. pyproject's import contracts name the imports
that still point upwards because of it (``ignore_imports``, marked TRANSITIONAL).
"""

from __future__ import annotations

from zenswarm.bridge.args import (
    add_fault_args,
    add_security_args,
    positive_float,
    seed_arg,
)

__all__ = ["positive_float", "seed_arg", "add_fault_args", "add_security_args"]

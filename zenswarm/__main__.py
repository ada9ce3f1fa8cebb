"""The ``zenswarm`` command (``[project.scripts]``, ``python -m zenswarm``).

``zenswarm sweep ...`` is :mod:`zenswarm.sweep` (it flies through :mod:`zenswarm.api`, above
the edges); every other subcommand is :func:`zenswarm.compose.cli.main`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``zenswarm ARGV`` (default: sys.argv[1:]) and return its exit status."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] == "sweep":
        from zenswarm.sweep import main as sweep_main

        return sweep_main(args[1:])
    from zenswarm.compose.cli import main as cli_main

    return cli_main(args)


if __name__ == "__main__":
    sys.exit(main())

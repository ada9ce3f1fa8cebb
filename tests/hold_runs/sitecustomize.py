"""Test-only: hold a sweep's runs after the first while a gate file exists (tests/test_sweep.py).

Python imports ``sitecustomize`` at start-up from ``sys.path``. The interrupt test puts this folder
on ``PYTHONPATH`` and sets ``ZENSWARM_TEST_RUN_GATE=<file>`` for one ``zenswarm sweep`` only; in
its process and its pool's workers, :func:`zenswarm.sweep.run_one` then waits, for every run but
run 0, until the file is gone. So the sweep is interrupted with exactly one run finished however
loaded the machine is (it raced the sweep before: under CPU load all four runs had finished when
the test's Ctrl-C came). Without the variable nothing is changed.
"""

from __future__ import annotations

import os

_GATE = os.environ.get("ZENSWARM_TEST_RUN_GATE")
if _GATE:
    import time
    from typing import Any

    import zenswarm.sweep as _sweep

    _run_one = _sweep.run_one

    def run_one(task: Any) -> Any:
        while task["run"] > 0 and os.path.exists(_GATE):
            time.sleep(0.02)
        return _run_one(task)

    run_one.__module__, run_one.__qualname__ = _sweep.__name__, "run_one"  # pickled by reference to the pool
    _sweep.run_one = run_one

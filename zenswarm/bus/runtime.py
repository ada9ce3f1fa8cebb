"""zenoh's thread layout: the ``ZENOH_RUNTIME`` of the swarm's processes and of the router, and
which zenoh threads a process has (for diagnostics).

The standard library only; zenoh reads the variable when a process opens its first session.
"""

from __future__ import annotations

import os
from typing import Final

__all__ = ["ZENOH_RUNTIME_DEFAULT", "ZENOH_RUNTIME_ROUTER", "use_swarm_runtime", "zenoh_threads"]

ZENOH_RUNTIME_DEFAULT: Final = (
    "(rx: (handover: app), tx: (handover: app), net: (handover: app), acc: (handover: app), app: (worker_threads: 1))"
)
"""zenoh's thread layout in the swarm's plant, leader and agent processes (see :func:`use_swarm_runtime`)."""


def use_swarm_runtime() -> None:
    """Run this process's zenoh on one thread, unless ``ZENOH_RUNTIME`` is already set.

    By default zenoh runs five tokio runtimes (``app``, ``acc``, ``tx``, ``rx``, ``net``; ``rx``
    with two worker threads), so one message crosses several threads in each process: read by
    an ``rx`` thread, queued to a ``tx`` thread, and so on, each hand-over a thread wake-up.
    :data:`ZENOH_RUNTIME_DEFAULT` hands every runtime over to one ``app`` runtime with a single
    worker thread. On the 2-core machine that, with :func:`~zenswarm.bus.callbacks.direct_callback`
    (and the router's ``tx`` apart), took the lockstep swarm from 2.54 to 1.39 ms per tick on paper
    example 1 (3 UAVs) and from 13.15 to 6.77 ms on gen16 (BENCHMARKS.md, "What made the swarm
    faster": the ablation's "+ supervisor queue" row against "as committed").

    zenoh reads the variable once, when it creates its runtimes (the first session of the
    process), so call this before opening one; child processes inherit it. The supervisor's
    router does not use it: a router blocked on one slow receiver (congestion control ``BLOCK``)
    must not stop forwarding everything else, which one worker thread would
    (:data:`ZENOH_RUNTIME_ROUTER`). Set
    ``ZENOH_RUNTIME`` yourself (RON syntax, zenoh's ``zenoh-runtime`` crate) to override it.
    """
    os.environ.setdefault("ZENOH_RUNTIME", ZENOH_RUNTIME_DEFAULT)


ZENOH_RUNTIME_ROUTER: Final = (
    "(rx: (handover: app), net: (handover: app), acc: (handover: app), app: (worker_threads: 1), tx: (worker_threads: 1))"
)
"""zenoh's thread layout in the supervisor (the router): one ``app`` thread, and ``tx`` on its own.

A router forwarding a ``BLOCK`` message into a full queue waits, inside the task that read it,
until the sending task of that queue has drained it. With ``tx`` handed over to the single ``app``
thread too, that sending task could never run: the wait would end only when zenoh closes the link
(seconds later), and one slow receiver would stall the whole swarm. Measured: with everything on
one thread, a flood of 64 KiB garbage messages froze example 1 every time (4 of 4 runs); with
``tx`` apart, it flew (0 of 4 froze, ``tests/test_garbage.py``), and at nearly the same speed."""


def zenoh_threads() -> str:
    """Names of this process's zenoh threads, sorted and comma-separated (e.g. ``"app-0"``), as
    Linux names them; ``""`` where /proc is not readable. For diagnostics."""
    names = []
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return ""
    for tid in tids:
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                name = f.read().strip()
        except OSError:  # a thread that ended since the listing: not one of them any more
            continue
        if name.split("-")[0] in ("app", "acc", "tx", "rx", "net"):
            names.append(name)
    return ",".join(sorted(names))

"""Real-time scheduling of a realtime flight's control loops (issue 16, item 5).

On a machine whose cores are busy (a whole swarm on a laptop, or a companion computer that also
runs a camera pipeline), a control loop that wakes for its deadline waits for the kernel's fair
scheduler to give it a core: with the 11 processes of an 8-UAV swarm on 2 cores (about 90 % busy)
the agents' worst loop jitter in 3-minute flights was 22.7 and 101.4 ms (two runs), and a bare
100 Hz loop beside the swarm was late by up to 17 ms. A loop under ``SCHED_FIFO`` preempts every
normally scheduled thread the moment it wakes: 6.4 and 9.7 ms in the runs beside them
(BENCHMARKS.md, "Real-time priority").

``--rt-priority P`` (1-99; :func:`check_priority`) runs a process's threads under
``SCHED_FIFO`` priority P, once its start-up is over (:func:`apply_after_startup`, the same
moment the managed collector freezes: :class:`zenswarm.process.gcpolicy.GcPolicy`). Start-up (imports,
scenario, session) stays under the fair scheduler, so a process that is still importing numpy
cannot hold a core against loops that already fly: ``SCHED_FIFO`` threads of one priority are
never preempted by each other, only by a higher priority or by blocking. Every thread of the
process is raised, zenoh's included (its receiving thread runs the subscriber callbacks, and a
control loop waiting for the GIL that thread holds must not wait for the fair scheduler too);
threads started later inherit the policy of the thread that starts them.

Linux only (``os.sched_setscheduler``). Needs ``CAP_SYS_NICE`` (root) or an ``RLIMIT_RTPRIO`` of
at least P (``ulimit -r``; ``/etc/security/limits.conf``: ``@realtime - rtprio 99``). The
kernel keeps 5 % of every second for the fair scheduler (``/proc/sys/kernel/sched_rt_runtime_us``),
so a loop that spins by mistake cannot lock the machine.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from zenswarm.errors import ScenarioError

__all__ = ["RT_PRIORITY_MIN", "RT_PRIORITY_MAX", "RtPriorityError", "check_priority", "probe", "validate", "apply_to_process",
           "apply_after_startup", "current_policy", "set_requested", "requested", "process_policy", "counters"]

RT_PRIORITY_MIN = 1
"""Lowest ``SCHED_FIFO`` priority accepted (Linux's range is 1-99)."""

RT_PRIORITY_MAX = 99
"""Highest ``SCHED_FIFO`` priority accepted."""


class RtPriorityError(ScenarioError):
    """``--rt-priority`` is out of range, or this process may not use real-time scheduling."""


def check_priority(value: object, field: str = "--rt-priority") -> int:
    """``value`` as a ``SCHED_FIFO`` priority (an int in 1-99); :class:`RtPriorityError` naming
    ``field`` otherwise."""
    if isinstance(value, bool):
        raise RtPriorityError(field, f"must be an integer {RT_PRIORITY_MIN}-{RT_PRIORITY_MAX}, got {value!r}")
    try:
        p = int(str(value).strip()) if not isinstance(value, int) else value
    except ValueError:
        raise RtPriorityError(field, f"must be an integer {RT_PRIORITY_MIN}-{RT_PRIORITY_MAX}, got {value!r}") from None
    if not RT_PRIORITY_MIN <= p <= RT_PRIORITY_MAX:
        raise RtPriorityError(field, f"must be {RT_PRIORITY_MIN}-{RT_PRIORITY_MAX} (SCHED_FIFO priority), got {p}")
    return p


def _supported() -> bool:
    return sys.platform.startswith("linux") and hasattr(os, "sched_setscheduler") and hasattr(os, "SCHED_FIFO")


def probe(priority: int, field: str = "--rt-priority") -> None:
    """Check that this process may run threads under ``SCHED_FIFO`` ``priority``, changing
    nothing: the calling thread is raised and put back to what it was. Raises
    :class:`RtPriorityError` naming ``field`` and saying how to get the privilege."""
    if not _supported():
        raise RtPriorityError(field, "real-time scheduling (SCHED_FIFO) is only available on Linux")
    try:
        old_policy = os.sched_getscheduler(0)
        old_param = os.sched_getparam(0)
    except OSError as e:
        raise RtPriorityError(field, f"cannot read this process's scheduling policy: {e}") from None
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        raise RtPriorityError(
            field,
            f"SCHED_FIFO priority {priority} is not permitted for this user: run as root (CAP_SYS_NICE), "
            "or allow it with an RLIMIT_RTPRIO of at least that (`ulimit -r`; /etc/security/limits.conf: "
            "'<user> - rtprio 99'), or leave --rt-priority out",
        ) from None
    except OSError as e:
        raise RtPriorityError(field, f"SCHED_FIFO priority {priority} refused by the kernel: {e}") from None
    os.sched_setscheduler(0, old_policy, old_param)


def validate(value: object, *, realtime: bool, how: str = "--realtime", field: str = "--rt-priority") -> int | None:
    """What a process checks of ``--rt-priority`` before any work: None stays None; otherwise an
    integer 1-99 (:func:`check_priority`), a realtime flight (``how`` says how to ask for one) and
    permitted to this user (:func:`probe`). Returns the priority; :class:`RtPriorityError` naming
    ``field`` otherwise."""
    if value is None:
        return None
    p = check_priority(value, field)
    if not realtime:
        raise RtPriorityError(field, f"only for realtime flights ({how}): lockstep has no deadline")
    probe(p, field)
    return p


def _thread_ids() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [os.getpid()]


def apply_to_process(priority: int) -> int:
    """Put every thread of this process under ``SCHED_FIFO`` ``priority``; returns how many
    threads were raised (a thread that ended meanwhile is skipped). Raises
    :class:`RtPriorityError` if not permitted (see :func:`probe`)."""
    if not _supported():
        raise RtPriorityError("--rt-priority", "real-time scheduling (SCHED_FIFO) is only available on Linux")
    raised = 0
    param = os.sched_param(priority)
    for tid in _thread_ids():
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, param)
        except ProcessLookupError:
            continue  # the thread ended
        except PermissionError:
            probe(priority)  # says why, with the remedy
            raise
        raised += 1
    return raised


def current_policy(tid: int = 0) -> tuple[str, int]:
    """(policy name, priority) of thread/process ``tid`` (0: the calling thread), e.g. ``("fifo", 20)``
    or ``("other", 0)``."""
    names = {getattr(os, n): n[6:].lower() for n in ("SCHED_OTHER", "SCHED_FIFO", "SCHED_RR", "SCHED_BATCH", "SCHED_IDLE")
             if hasattr(os, n)}
    pol = os.sched_getscheduler(tid)
    return names.get(pol, str(pol)), os.sched_getparam(tid).sched_priority


def process_policy(pid: int) -> list[tuple[str, int]]:
    """(policy, priority) of every thread of process ``pid`` (Linux ``/proc``)."""
    out = []
    for t in sorted(os.listdir(f"/proc/{pid}/task")):
        try:
            out.append(current_policy(int(t)))
        except (ProcessLookupError, FileNotFoundError):
            continue
    return out


_REQUESTED: int | None = None
_RAISED = 0


def set_requested(priority: int | None) -> None:
    """This process runs its loops under ``SCHED_FIFO`` ``priority`` once start-up is over (None: no)."""
    global _REQUESTED
    _REQUESTED = priority


def requested() -> int | None:
    """The priority :func:`set_requested` asked for (None: the fair scheduler)."""
    return _REQUESTED


def apply_after_startup(log: Callable[[str], None] | None = None) -> int:
    """Start-up is over: apply the requested priority (:func:`set_requested`) to every thread.
    Returns the number of threads raised (0 if none was requested)."""
    global _RAISED
    p = _REQUESTED
    if p is None:
        return 0
    n = _RAISED = apply_to_process(p)
    if log is not None:
        log(f"real-time scheduling: {n} threads under SCHED_FIFO priority {p}")
    return n


def counters() -> dict[str, float]:
    """``rt.priority`` (0: the fair scheduler) and ``rt.threads`` (threads raised) for the diagnostics."""
    return {"rt.priority": float(_REQUESTED or 0), "rt.threads": float(_RAISED)}

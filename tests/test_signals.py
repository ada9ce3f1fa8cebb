"""Stop signals (zenswarm.process.signals.SignalRelay; the recorder's and replay's stop request).

A Python signal handler runs in the main thread between two of its bytecodes. One that set a
``threading.Event`` took the event's lock, and if the main thread was inside that event's
``wait()`` at that moment (the recorder waits on its stop event in the main thread all the
time), it held the lock already: the handler waited for it forever, and the recorder never
exited after SIGTERM (test_record_synthetic_traffic_every_payload_in_order, once, in CI). Here
the main thread holds the lock on purpose while the signal arrives; each case runs in a child
interpreter (signal handlers are per process), killed if it hangs.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from swarmtest import ROOT

HELD = """
import os, signal, threading
{setup}
with {event}._cond:  # the lock Event.wait() and Event.set() hold, as the main loop's wait does
    os.kill(os.getpid(), signal.SIGTERM)
    for _ in range(100_000):  # the handler runs in this thread, between these bytecodes
        pass
print("handler returned", flush=True)
assert {event}.wait(10), "the stop event was never set"
{after}
print("stopped", flush=True)
"""


def _child(code: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    try:
        return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as e:  # run() killed it
        pytest.fail(f"the child hung on its stop signal (killed after {timeout:g} s): {e.stdout!r} {e.stderr!r}")


def test_recorder_stop_signal_while_the_main_thread_holds_the_stop_events_lock() -> None:
    cp = _child(HELD.format(
        setup="from zenswarm.bridge.recording.recorder import _Stop\nstop = _Stop()\nstop.install()",
        event="stop.event",
        after="assert stop.why == 'received SIGTERM', stop.why\nstop.close()",
    ))  # fmt: skip
    assert cp.returncode == 0 and cp.stdout.split() == ["handler", "returned", "stopped"], (cp.stdout, cp.stderr)


def test_relay_hands_signals_on_outside_the_handler_and_restores_the_handlers() -> None:
    cp = _child(HELD.format(
        setup=(
            "from zenswarm.process.signals import SignalRelay\n"
            "ev = threading.Event(); got = []\n"
            "def on(signum):\n"
            "    got.append((signum, threading.current_thread() is threading.main_thread()))\n"
            "    ev.set()\n"
            "before = [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)]\n"
            "relay = SignalRelay(on)"
        ),
        event="ev",
        after=(
            "assert got == [(signal.SIGTERM, False)], got  # once, in the relay's thread\n"
            "relay.close()\n"
            "assert [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)] == before\n"
            "assert not relay._thread.is_alive()\n"
            "relay.close()  # idempotent"
        ),
    ))  # fmt: skip
    assert cp.returncode == 0 and cp.stdout.split() == ["handler", "returned", "stopped"], (cp.stdout, cp.stderr)

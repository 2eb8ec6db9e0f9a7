"""A Ctrl-C that lands in a finaliser: Python prints and drops it; the sweep raises it again."""

from __future__ import annotations

import signal
import subprocess
import sys

SCRIPT = """
import os, signal, time
from physmend.sweep.ctrl_c import kept, check
from physmend.sweep.report import Reporter

class Finaliser:
    def __del__(self):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.5)  # the handler runs here, inside the finaliser

def dropped(where):
    Finaliser()
    print(where, 'went on', flush=True)

dropped('plain')
check()  # outside kept(): nothing remembered
with kept():
    dropped('kept')
    try:
        Reporter(None, None, '')(0, {'val.rmse': 1.0})
    except KeyboardInterrupt as exc:
        print('report raised:', exc, flush=True)
print('after kept:', signal.getsignal(signal.SIGINT) is signal.default_int_handler, flush=True)
check()
print('nothing pending after', flush=True)
"""


def _as_from_a_shell() -> None:
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_a_ctrl_c_dropped_in_a_finaliser_is_raised_at_the_next_epoch_report() -> None:
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120,
                          preexec_fn=_as_from_a_shell)
    assert done.returncode == 0, done.stderr
    # Python dropped both (the case this module exists for), and went on
    assert done.stderr.count("KeyboardInterrupt") >= 2 and "Exception ignored" in done.stderr, done.stderr
    assert done.stdout.splitlines() == [
        "plain went on",
        "kept went on",
        "report raised: Ctrl-C (raised again: Python had dropped it in a finaliser)",
        "after kept: True",
        "nothing pending after",
    ], done.stdout + done.stderr

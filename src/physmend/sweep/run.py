"""Running a sweep's loop in this process: the progress bar, the worker processes it waits for, the
summary, and the error when no trial finished. Imports :mod:`physmend.sweep.loop`.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from typing import Any

from physmend.exceptions import PhysmendError
from physmend.redact import redact
from physmend.sweep.loop import Sweep
from physmend.sweep.parent import _finish_parent
from physmend.sweep.report import _say, summary
from physmend.sweep.workers import _join_workers


class NoTrialCompleted(PhysmendError, RuntimeError):
    """A sweep ended without one trial that finished training: nothing is selected (exit status 2)."""


def _drive(sweep: Sweep, helpers: Sequence[Any] = ()) -> str:
    """Run this worker's loop, then wait for the ``helpers`` (worker processes) before the summary."""
    from tqdm import tqdm

    bar = tqdm(total=sweep.n_trials, desc=f"sweep {sweep.study.study_name}", unit="trial",
               file=sys.stderr, disable=not sweep.settings.progress, dynamic_ncols=True)
    status = "FINISHED"
    try:
        sweep.loop(bar)
        _join_workers(list(helpers))
    except KeyboardInterrupt:
        status = "KILLED"
        _say(bar, "interrupted: the running trial is recorded FAIL (interrupted); rerun the same command to resume")
        for proc in helpers:  # a Ctrl-C reaches them too: they record their own running trials
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:  # only this process was interrupted: pass it on
                proc.send_signal(signal.SIGINT)
                proc.wait()
        raise
    except BaseException as exc:
        status = "FAILED"
        for proc in helpers:  # their running trials are marked FAIL (interrupted) once their heartbeats go stale
            proc.terminate()
        from physmend.tracking import ERROR_TAG

        sweep.store.client.set_tag(sweep.parent_run_id, ERROR_TAG, redact(f"{type(exc).__name__}: {exc}")[:5000])
        raise
    finally:
        bar.close()
        if status == "FINISHED":
            counts = _finish_parent(sweep, status)
            print(summary(sweep, counts))
        else:
            try:
                _finish_parent(sweep, status)
            except Exception as exc:  # noqa: BLE001 - never mask the error that ended the sweep
                sys.stderr.write(f"could not record the end of sweep run {sweep.parent_run_id}: {exc}\n")
    if counts.best_value is None and not counts.running:  # the command did not do its job: say so, non-zero
        raise NoTrialCompleted(f"sweep {sweep.study.study_name!r}: none of its {counts.counted} trials finished "
                               f"training ({counts.failed} failed, {counts.pruned} pruned); `physmend runs` lists why")
    return sweep.parent_run_id



def _trainer() -> Callable[..., Any]:
    from physmend.ude import train

    return train

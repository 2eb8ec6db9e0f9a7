"""A standby worker told its sweep ahead (:func:`physmend.sweep.standby.brief`) prepares its first
trial while it waits: the model compiled and the records smoothed in that process, the training
after it the same as one without; a preparation that fails costs nothing but time, and the command
line handed afterwards runs. Real processes, real training."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import physmend.ude.warmstart as warmstart
from physmend import prestart
from physmend import problem as problem_module
from physmend.config import compose
from physmend.problem import load_problem
from physmend.sweep import standby
from physmend.ude import train

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=10",
        "train.eval_every=5", "simulate.rtol=1e-6", "simulate.atol=1e-7", "ude.depth=1"]


def test_the_preparation_keeps_what_the_first_training_needs_and_changes_nothing(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import scipy.interpolate

    cfg = compose(TINY)
    problem_module._COMPILED.clear()
    warmstart._SMOOTHED.clear()
    warmstart.forget_warm_starts()
    alone = train(cfg, load_problem(cfg))  # empty caches: everything computed in the training
    problem_module._COMPILED.clear()
    warmstart._SMOOTHED.clear()

    warmstart.forget_warm_starts()  # the second training fits its own warm start, as a new process would
    standby._prepare({"overrides": TINY, "config_dir": None})
    assert len(problem_module._COMPILED) == 1 and warmstart._SMOOTHED  # compiled and smoothed, kept
    fits: list[int] = []
    real = scipy.interpolate.make_smoothing_spline
    monkeypatch.setattr(scipy.interpolate, "make_smoothing_spline", lambda *a, **k: fits.append(1) or real(*a, **k))
    after = train(cfg, load_problem(cfg))
    assert fits == []  # the training smoothed nothing again
    assert after.val_rmse == alone.val_rmse
    np.testing.assert_equal(after.history, alone.history)  # every checkpoint's numbers (NaN where no loss yet)


def test_a_preparation_that_fails_costs_nothing_and_the_command_line_still_runs() -> None:
    standby._prepare({"overrides": ["no_such_group=1"], "config_dir": None})  # swallowed: the command reports it
    procs = prestart.spawn(1)
    try:
        standby.brief(procs, ["no_such_group=1"], "/nonexistent/folder")
        standby.brief(procs, TINY, None)  # several briefs: each prepared in turn
        assert standby.hand(procs[0], ["--version"], {}) is procs[0]
        assert procs[0].wait(timeout=300) == 0
    finally:
        standby.release(procs)
    released = prestart.spawn(1)
    standby.brief(released, TINY, None)
    standby.release(released)  # briefed, never handed a command line: ended
    assert released[0].poll() is not None


def test_a_standby_process_runs_the_command_line_after_its_brief() -> None:
    proc = subprocess.Popen([sys.executable, "-m", "physmend.sweep.standby"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    standby.brief([proc], TINY, None)
    standby.hand(proc, ["--version"], {})
    assert proc.stdout is not None
    out = proc.stdout.read()
    proc.wait(timeout=300)
    from physmend import __version__

    assert proc.returncode == 0 and out.strip() == __version__

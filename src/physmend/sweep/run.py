"""Running a sweep: :func:`run_sweep` checks what was given, opens the study and the parent run,
starts the worker processes, and drives this process's loop (the progress bar, the workers it
waits for, the summary, and the error when no trial finished).
"""

from __future__ import annotations

import gc
import os
import signal
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from physmend.config import ConfigError
from physmend.exceptions import PhysmendError
from physmend.redact import redact
from physmend.sweep.configs import TrialConfigs, _override_key, check_keys, check_overrides, probe_space
from physmend.sweep.ctrl_c import kept as kept_ctrl_c
from physmend.sweep.loop import Sweep
from physmend.sweep.parent import _create_parent, _finish_parent, _parent_run, _parent_tags
from physmend.sweep.report import _say
from physmend.sweep.settings import Settings
from physmend.sweep.space import load_space
from physmend.sweep.summary import summary
from physmend.sweep.storage import _retry, _study, default_study_name, open_storage, study_fingerprint
from physmend.sweep.workers import GIVEN_WINS_ENV, PROBED_ENV, _join_workers, _start_workers


class NoTrialCompleted(PhysmendError, RuntimeError):
    """A sweep ended without one trial that finished training: nothing is selected (exit status 2)."""


def run_sweep(
    cfg: DictConfig,
    source_run_id: str | None = None,
    *,
    overrides: Sequence[str] | None = None,
    config_dir: str | Path | None = None,
    given_wins: bool = False,
    standby: Sequence[Any] = (),
    meanwhile: Callable[[], None] | None = None,
) -> str:
    """Run (or resume, or join as a worker) the sweep configured by ``cfg.sweep``; returns the parent run ID.

    ``overrides``/``config_dir`` are what ``cfg`` was composed from (the CLI passes them): each
    trial's config is composed from them plus the trial's values. Without them (a call from
    Python), the trial's values are patched into a copy of ``cfg``. A key both given in ``overrides``
    and searched by the space is an error, or with ``given_wins`` (``physmend discover``, whose user did
    not pick the space) no longer searched, said in one line. ``standby``: processes started early
    (:mod:`physmend.sweep.standby`) that become the extra workers; the caller ends those not used.
    ``meanwhile``: the caller's work for after the sweep, run once in this process where it only
    waits for other workers' trials (none: it is not run; :meth:`Sweep.idle`).

    Everything the user gave (space, settings, model, data, source run) is checked before any run
    is written. A diverging trial is restarted (``sweep.restarts``, :mod:`physmend.sweep.restart`), and
    recorded FAIL where no restart finishes it; the sweep goes on. Ctrl-C records the
    running trial FAIL (its run KILLED) and re-raises ``KeyboardInterrupt``.
    """
    from physmend.cpus import side_by_side
    from physmend.problem import load_problem
    from physmend.settings import group_settings
    from physmend.tracking import get_run, open_store

    settings = Settings.from_cfg(cfg.sweep)
    given_wins = given_wins or os.environ.get(GIVEN_WINS_ENV) == "1"  # a worker of such a sweep (workers.py)
    if settings.workers > 1 and overrides is None:
        raise ConfigError(f"sweep.workers={settings.workers} starts worker processes from the command line "
                          "(physmend sweep … sweep.workers=N); from Python, start several processes with the same "
                          "configuration yourself (they share the study)")
    space = load_space(settings.space)
    if overrides is not None and given_wins:
        both = sorted({_override_key(o) for o in overrides} & set(space.params))
        if both:
            print(f"sweep: {', '.join(both)} given on the command line: {space.label} does not search "
                  f"{'it' if len(both) == 1 else 'them'} in this sweep")
            space = space.without(both)
    if overrides is not None:
        check_overrides(space, overrides)
        if os.environ.get(PROBED_ENV) != "1":  # a worker whose sweep composed these already: seconds saved
            probe_space(space, overrides, config_dir)
    else:
        check_keys(space, cfg)
    # this process trains beside settings.workers - 1 others: threads: auto is its share of the CPUs,
    # also where a trial's configuration loads its problem again
    with side_by_side(settings.workers):
        problem = load_problem(cfg)
        storage = open_storage(group_settings(cfg, "tracking").optuna_storage)
        store = _retry(lambda: open_store(cfg.tracking))
        if source_run_id:
            get_run(store, source_run_id)
        study_name = settings.study_name or default_study_name(problem, cfg, space)
        # everything checked: the other workers start now and set themselves up while this one opens the
        # study (whichever process gets there first creates it, its first trials and the parent run)
        helpers = _start_workers(settings.workers - 1, source_run_id, overrides or [], config_dir, given_wins, standby)
        try:
            study, created = _study(storage, study_name, settings, space, study_fingerprint(cfg, space))
            tags = _parent_tags(cfg, space, study_name, storage.url, source_run_id)
            parent = _parent_run(study, created, store, lambda: _create_parent(store, cfg, space, settings, tags))
            _settle_run_context()
            configs = TrialConfigs(cfg, problem, overrides, config_dir)
            if str(problem.device).startswith("cpu"):
                from physmend.ude.adjoint import warm

                # the training loops compiled (a fresh install) or read from numba's cache here, not inside
                # the first trial: a Ctrl-C that lands in an import there is an ImportError, not an interrupt
                warm(problem.dtype)
        except BaseException:
            for proc in helpers:  # they would meet the same trouble
                proc.terminate()
                proc.wait()
            raise
        return _drive(Sweep(cfg, settings, space, study, storage, store, parent, configs, _trainer(),
                            meanwhile=meanwhile), helpers)


def _drive(sweep: Sweep, helpers: Sequence[Any] = ()) -> str:
    """Run this worker's loop, then wait for the ``helpers`` (worker processes) before the summary."""
    from tqdm import tqdm

    bar = tqdm(total=sweep.n_trials, desc=f"sweep {sweep.study.study_name}", unit="trial",
               file=sys.stderr, disable=not sweep.settings.progress, dynamic_ncols=True)
    status = "FINISHED"
    try:
        with kept_ctrl_c():  # a Ctrl-C that Python drops in a finaliser is raised again (physmend.sweep.ctrl_c)
            sweep.loop(bar)
        if helpers:
            sweep.idle()
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
        from physmend.tracking import ERROR_TAG, write_tags

        write_tags(sweep.store.client, sweep.parent_run_id, {ERROR_TAG: redact(f"{type(exc).__name__}: {exc}")[:5000]})
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


def _settle_run_context() -> None:
    """Read MLflow's run context (the git repository around the program, once per process) and
    collect its garbage now, before any trial: the GitPython objects it makes sit in reference cycles
    until a later collection, and a Ctrl-C that lands in their finaliser during a trial is printed
    and dropped by Python. :mod:`physmend.sweep.ctrl_c` raises any dropped Ctrl-C again at the next
    epoch; this keeps the commonest one from being dropped at all, so that it acts at once."""
    from mlflow.tracking.context.registry import resolve_tags

    resolve_tags()
    gc.collect()

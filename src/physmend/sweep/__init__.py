"""The architecture sweep: an Optuna study over UDE architectures and training settings.

Each trial is a child MLflow run (``trial-NNNN``) under the sweep's parent run; the best finished
trial by ``val.rmse`` is recorded on the parent as the automatic choice and the selection (see
:mod:`physmend.tracking.selection`). physmend owns the study loop (ask → compose → train → tell)
so that it can prune from intermediate validation errors, resume, and run as many workers.

Search spaces
    ``sweeps/<name>.yaml`` (shipped) or a path to your own YAML file::

        description: what the space explores
        params:
          ude.width: {choice: [16, 32, 64]}
          train.lr: {log_uniform: [0.001, 0.03]}
          train.weight_decay: {uniform: [0.0, 1.0e-3]}
          ude.depth: {int: [1, 3]}                  # optional: step: 1, log: false
        first_trials:                                # optional: tried before the sampler proposes
          - {ude.width: 32, train.lr: 0.01}

    Each trial's values become Hydra overrides (``key=value``) composed on top of the sweep's
    own overrides, so every trial's config is a real composed config.

Resume and workers
    The study lives in ``tracking.optuna_storage`` under ``sweep.study_name`` (default
    ``<model>-<data>-<space>``). Running the same command again continues it: it runs only the
    trials still missing from ``sweep.n_trials``, under the same parent run (its ID is a study user
    attribute). Any number of processes may run the same command on one storage: before each
    trial a worker counts the trials that reached a verdict (COMPLETE, PRUNED, FAIL) plus those
    running, and stops when ``n_trials`` is reached; a trial asked in a race beyond ``n_trials`` is
    closed at once as FAIL with ``fail_reason=surplus``, and its worker counts again (it waits while
    ``sweep.budget``'s decision, which may ask for more trials, is still to come).

Interrupted trials
    A trial whose worker stopped (killed, machine lost) stays RUNNING in the storage. Each
    running trial records its worker (host, PID) and a heartbeat (every
    ``sweep.heartbeat_interval`` s). A worker about to ask for a trial marks stale ones FAIL with
    ``fail_reason=interrupted`` (and their child runs KILLED): trials of a dead process on the same
    host at once, others after ``sweep.stale_after`` s without a heartbeat. Interrupted trials
    (and Ctrl-C'd ones) reached no verdict, so they do not count towards ``n_trials``: resuming
    runs a fresh trial in their place. They are not re-enqueued — a configuration that crashed
    its worker is not retried blindly. A Ctrl-C that lands in a finaliser, where Python prints
    and drops it, is raised again at the trial's next epoch (:mod:`physmend.sweep.ctrl_c`).

Divergence and budget
    A trial whose training diverges is restarted (``sweep.restarts``, each time with the learning
    rate /3 and segments /2) before it counts as failed; the summary states the divergence rate
    (:mod:`physmend.sweep.restart`). With ``sweep.budget`` (s of wall time) the sweep runs
    ``n_trials`` trials, then as many more as the budget allows at what those cost, ``max_trials``
    at most (:mod:`physmend.sweep.budget`; ``physmend discover`` sweeps this way).

Modules (nothing here imports :mod:`physmend.stages`)
    ``space``     search-space files, parsing, sampling into Hydra overrides
    ``restart``   which errors restart a trial, and with which settings
    ``budget``    how many trials a budget allows
    ``settings``  the checked ``sweep.*`` options, sampler and pruner, the keys that shape a stack,
                  the first trials proposed together
    ``configs``   each trial's composed configuration and problem
    ``storage``   the Optuna storage and study: open, fingerprint, tally
    ``workers``   worker processes, identity, heartbeats, stale trials
    ``standby``   worker processes started early (importing) that wait for their command line
    ``report``    per-epoch reporter, logged results, progress lines
    ``outcome``   how one trial ended
    ``ctrl_c``    a Ctrl-C that Python dropped in a finaliser, raised again
    ``child``     a trial's child run: opened, tagged on a restart, marked FAIL or KILLED
    ``group``     trials asked as a group and trained as one stack
    ``loop``      the study loop (one trial or a group at a time)
    ``parent``    the sweep's parent MLflow run
    ``summary``   the closing summary and the divergence rate
    ``run``       :func:`run_sweep`: everything checked, study and parent run opened, workers
                  started, the loop driven to the summary
The stage, ``physmend.stages.sweep.run(cfg, source_run_id) -> run_id``, calls :func:`run_sweep`.
"""

from __future__ import annotations

from physmend.sweep.configs import TrialConfigs, check_overrides, probe_space
from physmend.sweep.loop import Sweep
from physmend.sweep.outcome import Outcome
from physmend.sweep.run import NoTrialCompleted, run_sweep
from physmend.sweep.settings import PRUNERS, SAMPLERS, Settings, shape_keys
from physmend.sweep.space import KINDS, Param, SearchSpace, available_spaces, hydra_value, load_space, parse_space, trial_overrides
from physmend.sweep.storage import (
    CONFIG_ATTR,
    HEARTBEAT_ATTR,
    PARENT_ATTR,
    REASON_ATTR,
    RUN_ID_ATTR,
    UNCOUNTED,
    WORKER_ATTR,
    Tally,
    open_storage,
    study_fingerprint,
    tally,
)
from physmend.sweep.workers import is_stale, this_worker

__all__ = [
    "CONFIG_ATTR", "HEARTBEAT_ATTR", "KINDS", "PARENT_ATTR", "PRUNERS", "REASON_ATTR", "RUN_ID_ATTR", "SAMPLERS",
    "UNCOUNTED", "WORKER_ATTR", "NoTrialCompleted", "Outcome", "Param", "SearchSpace", "Settings", "Sweep", "Tally", "TrialConfigs",
    "available_spaces", "check_overrides", "hydra_value", "is_stale", "load_space", "open_storage", "parse_space",
    "probe_space", "run_sweep", "shape_keys", "study_fingerprint", "tally", "this_worker", "trial_overrides",
]

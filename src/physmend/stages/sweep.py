"""``physmend sweep``: an Optuna study over UDE architectures and training settings, one MLflow child
run per trial under the sweep's parent run (see :mod:`physmend.sweep` for how it works and where).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from omegaconf import DictConfig

from physmend.config import ConfigError
from physmend.sweep.configs import TrialConfigs, _override_key, check_keys, check_overrides, probe_space
from physmend.sweep.loop import Sweep
from physmend.sweep.run import _drive, _trainer
from physmend.sweep.parent import _create_parent, _parent_run, _parent_tags
from physmend.sweep.settings import Settings
from physmend.sweep.space import load_space
from physmend.sweep.storage import _retry, _study, default_study_name, open_storage, study_fingerprint
from physmend.sweep.workers import _start_workers

STAGE = "sweep"


def run(
    cfg: DictConfig,
    source_run_id: str | None = None,
    *,
    overrides: Sequence[str] | None = None,
    config_dir: str | Path | None = None,
    given_wins: bool = False,
) -> str:
    """Run (or resume, or join as a worker) the sweep configured by ``cfg.sweep``; returns the parent run ID.

    ``overrides``/``config_dir`` are what ``cfg`` was composed from (the CLI passes them): each
    trial's config is composed from them plus the trial's values. Without them (a call from
    Python), the trial's values are patched into a copy of ``cfg``. A key both given in ``overrides``
    and searched by the space is an error, or with ``given_wins`` (``physmend discover``, whose user did
    not pick the space) no longer searched, said in one line.

    Everything the user gave (space, settings, model, data, source run) is checked before any run
    is written. A diverging trial is restarted (``sweep.restarts``, :mod:`physmend.sweep.restart`), and
    recorded FAIL where no restart finishes it; the sweep goes on. Ctrl-C records the
    running trial FAIL (its run KILLED) and re-raises ``KeyboardInterrupt``.
    """
    from physmend.problem import load_problem
    from physmend.tracking import get_run, open_store

    settings = Settings.from_cfg(cfg.sweep)
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
        probe_space(space, overrides, config_dir)
    else:
        check_keys(space, cfg)
    problem = load_problem(cfg)
    storage = open_storage(str(cfg.tracking.optuna_storage))
    store = _retry(lambda: open_store(cfg.tracking))
    if source_run_id:
        get_run(store, source_run_id)
    study_name = settings.study_name or default_study_name(problem, cfg, space)
    study, created = _study(storage, study_name, settings, space, study_fingerprint(cfg, space))
    tags = _parent_tags(cfg, space, study_name, storage.url, source_run_id)
    parent = _parent_run(study, created, store, lambda: _create_parent(store, cfg, space, settings, tags))
    configs = TrialConfigs(cfg, problem, overrides, config_dir)
    helpers = _start_workers(settings.workers - 1, source_run_id, overrides or [], config_dir)
    return _drive(Sweep(cfg, settings, space, study, storage, store, parent, configs, _trainer()), helpers)

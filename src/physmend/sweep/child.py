"""A trial's child MLflow run under the sweep's parent run: opened, tagged on a restart, marked when
its trial fails or was interrupted.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from physmend.redact import redact
from physmend.sweep.report import _say
from physmend.sweep.storage import RUN_ID_ATTR

if TYPE_CHECKING:
    import optuna
    from physmend.tracking import Store


@contextlib.contextmanager
def child_run(store: Store, study_name: str, parent_run_id: str, trial: optuna.Trial, values: dict[str, Any],
              cfg: DictConfig, holder: dict[str, str], extra_tags: dict[str, str] | None = None) -> Iterator[Any]:
    """The trial's child run under the sweep's parent, its ID recorded in ``holder`` and the trial."""
    from physmend.tracking import stage_run
    from physmend.tracking import selection as sel

    tags = {sel.STUDY_TAG: study_name, sel.TRIAL_NUMBER_TAG: str(trial.number), **(extra_tags or {})}
    with stage_run(
        store, cfg, stage=sel.TRIAL_STAGE, source_run_id=parent_run_id,
        run_name=f"trial-{trial.number:04d}", parent_run_id=parent_run_id, tags=tags,
    ) as run_:
        holder["run_id"] = run_.run_id
        trial.set_user_attr(RUN_ID_ATTR, run_.run_id)
        run_.log_params(values)
        yield run_


def record_restart(trial: optuna.Trial, attempts: Any, run_: Any, bar: Any, restarts: int) -> None:
    """A restart of ``trial`` (:class:`physmend.sweep.restart.Attempts`) on its Optuna trial and child
    run (tags, and the ``config.yaml`` later stages load), and one line on the terminal above ``bar``
    (``restarts``: ``sweep.restarts``)."""
    from physmend.sweep.restart import OVERRIDES_TAG, REASONS_TAG, RESTARTS_ATTR, RESTARTS_TAG, describe

    n = attempts.restarts
    trial.set_user_attr(RESTARTS_ATTR, n)
    run_.set_tags({RESTARTS_TAG: str(n), REASONS_TAG: " | ".join(attempts.reasons)[:5000],
                   OVERRIDES_TAG: describe(attempts.changes)})
    run_.log_text(OmegaConf.to_yaml(attempts.current, resolve=True), "config.yaml")
    _say(bar, f"trial {trial.number} diverged ({attempts.reasons[-1]}); restart {n} of "
              f"{restarts} with {describe(attempts.changes)}")


def mark_child(store: Store, run_id: str | None, state: str, *, error: str | None = None) -> None:
    """Tag a trial's child run with the trial's ``state`` (and ``error``); quietly, the study is the record."""
    from physmend.tracking import ERROR_TAG
    from physmend.tracking import selection as sel

    if run_id is None:
        return
    try:
        store.client.set_tag(run_id, sel.TRIAL_STATE_TAG, state)
        if error:
            store.client.set_tag(run_id, ERROR_TAG, redact(error))
    except Exception:  # noqa: BLE001 - the trial's FAIL in the study is what counts
        pass


def kill_child(store: Store, run_id: str | None, reason: str) -> None:
    """A trial's child run whose trial was interrupted: FAIL with ``reason``, ended KILLED if still running."""
    from physmend.tracking import ERROR_TAG
    from physmend.tracking import selection as sel

    if not run_id:
        return
    try:
        run = store.client.get_run(run_id)
        store.client.set_tag(run_id, sel.TRIAL_STATE_TAG, "FAIL")
        if run.info.status == "RUNNING" or ERROR_TAG not in run.data.tags:
            store.client.set_tag(run_id, ERROR_TAG, redact(reason))
        if run.info.status == "RUNNING":
            store.client.set_terminated(run_id, "KILLED")
    except Exception:  # noqa: BLE001 - the run may be gone; the study is the record
        pass

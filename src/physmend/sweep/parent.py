"""The sweep's parent MLflow run: its tags, its creation by the study's first worker, how other
workers find it, and its closing tags (best trial, selection).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from physmend.redact import redact
from physmend.sweep.settings import Settings
from physmend.sweep.space import SearchSpace
from physmend.sweep.storage import PARENT_ATTR, PARENT_WAIT_S, RUN_ID_ATTR, Tally, tally

if TYPE_CHECKING:
    from physmend.sweep.loop import Sweep
    from physmend.tracking import Store


def _parent_tags(cfg: DictConfig, space: SearchSpace, study_name: str, storage_url: str, source_run_id: str | None) -> dict[str, str]:
    from physmend.tracking import DATA_TAG, MODEL_TAG, SOURCE_TAG, STAGE_TAG
    from physmend.tracking import selection as sel

    return {
        STAGE_TAG: "sweep",
        SOURCE_TAG: source_run_id or "",
        MODEL_TAG: str(OmegaConf.select(cfg, "model.builder", default="")),
        DATA_TAG: str(OmegaConf.select(cfg, "data.name", default="")),
        sel.STUDY_TAG: study_name,
        sel.SPACE_TAG: space.name if space.label.startswith("sweeps/") else space.label,
        sel.STORAGE_TAG: redact(storage_url),
    }



def _create_parent(store: "Store", cfg: DictConfig, space: SearchSpace, settings: Settings, tags: dict[str, str]) -> str:
    import yaml

    run = store.client.create_run(store.experiment_id, run_name=f"sweep-{tags['physmend.study']}", tags=tags)
    run_id = run.info.run_id
    store.client.log_text(run_id, redact(OmegaConf.to_yaml(cfg, resolve=True)), "config.yaml")
    store.client.log_text(run_id, yaml.safe_dump(space.spec(), sort_keys=False), "space.yaml")
    for key, value in {"space": tags["physmend.space"], "sampler": settings.sampler, "pruner": settings.pruner,
                       "seed": settings.seed, "study": tags["physmend.study"]}.items():
        store.client.log_param(run_id, key, redact(str(value)))
    from physmend.tracking.marks import save_view

    save_view(store)  # "Views" in the MLflow UI: the trials ranked by val.rmse
    return run_id



def _parent_run(study: Any, created: bool, store: "Store", make: Callable[[], str]) -> str:
    """The sweep's parent run ID: created by the study's creator, looked up (and resumed) by others."""
    from physmend.tracking import TrackingError

    if created:
        run_id = make()
        study.set_user_attr(PARENT_ATTR, run_id)
        return run_id
    deadline = time.monotonic() + PARENT_WAIT_S
    run_id = study.user_attrs.get(PARENT_ATTR)
    while run_id is None and time.monotonic() < deadline:  # the creator is writing it right now
        time.sleep(0.5)
        run_id = study.user_attrs.get(PARENT_ATTR)
    if run_id is None:  # the creator died before writing it
        run_id = make()
        study.set_user_attr(PARENT_ATTR, run_id)
        return run_id
    try:
        run = store.client.get_run(run_id)
    except Exception:  # noqa: BLE001 - MlflowException: not in this store
        run = None
    if run is None or run.info.lifecycle_stage != "active" or run.info.experiment_id != store.experiment_id:
        raise TrackingError(
            f"study {study.study_name!r} belongs to sweep run {run_id!r}, which is not an active run of experiment "
            f"{store.experiment_name!r} in {store.uri}; pass sweep.study_name=NEW_NAME to start a new study"
        )
    if run.info.status != "RUNNING":
        store.client.update_run(run_id, status="RUNNING")
    return run_id



def _finish_parent(sweep: Sweep, status: str) -> Tally:
    """Record counts and the best trial on the parent; end it when no other worker still runs trials."""
    from physmend.tracking import selection as sel
    from physmend.tracking import write_tags

    client = sweep.store.client
    trials = sweep.study.get_trials(deepcopy=False)
    counts = tally(trials)
    parent = sweep.parent_run_id
    metrics = {"trials.complete": counts.complete, "trials.pruned": counts.pruned,
               "trials.failed": counts.failed, "trials.interrupted": counts.uncounted}
    if counts.best_value is not None:
        metrics["best.val.rmse"] = counts.best_value
        metrics["val.rmse"] = counts.best_value  # the sweep's own, so a val.rmse column ranks sweeps too
        best = next(t for t in trials if t.number == counts.best_number)
        best_run = best.user_attrs.get(RUN_ID_ATTR)
        if best_run:
            sel.record_auto_selection(sweep.store, parent, best_run)
    ts = int(time.time() * 1000)
    from mlflow.entities import Metric

    client.log_batch(parent, metrics=[Metric(k, float(v), ts, 0) for k, v in metrics.items()])
    write_tags(client, parent, {"physmend.n_trials": str(sweep.n_trials)})
    if counts.running == 0:  # otherwise the last worker to finish ends it
        client.set_terminated(parent, status)
    return counts

"""Sweeps, trials and the selected trial: tags on the sweep's parent run, never copies.

A sweep is a parent run (``physmend.stage=sweep``); each trial a child run (``physmend.stage=trial``,
``mlflow.parentRunId`` = the sweep). The parent run records

- ``physmend.best_run_id``: the automatic choice (the finished trial with the lowest ``val.rmse``);
- ``physmend.selected_run_id``: the current choice, with ``physmend.selected_by`` (``auto`` or the
  OS user who ran ``physmend select``) and ``physmend.selected_at`` (UTC, ISO 8601).

"The currently selected run" without an ID is the ``physmend.selected_run_id`` of the sweep whose
selection was made most recently (:func:`current_selection`): a new sweep's automatic choice, or a
later ``physmend select`` on any sweep.
"""

from __future__ import annotations

import datetime as _dt
import getpass
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

from omegaconf import DictConfig, OmegaConf

from physmend.tracking.runs import STAGE_TAG, get_run
from physmend.tracking.store import Store, TrackingError, write_tags

SWEEP_STAGE = "sweep"
TRIAL_STAGE = "trial"
PARENT_TAG = "mlflow.parentRunId"
STUDY_TAG = "physmend.study"
SPACE_TAG = "physmend.space"
STORAGE_TAG = "physmend.optuna_storage"
TRIAL_NUMBER_TAG = "physmend.trial_number"
TRIAL_STATE_TAG = "physmend.trial_state"
BEST_TAG = "physmend.best_run_id"
#: on a trial run: "true" for its sweep's automatic best (shown in the MLflow UI's runs table)
MARK_TAG = "physmend.best"
SELECTED_TAG = "physmend.selected_run_id"
SELECTED_BY_TAG = "physmend.selected_by"
SELECTED_AT_TAG = "physmend.selected_at"
AUTO = "auto"
MODEL_FILES = ("model/hybrid.json", "model/weights.pt")


class Selection(NamedTuple):
    """A selection recorded on a sweep run: which trial run, by whom, when."""

    sweep_run_id: str
    run_id: str
    by: str
    at: str
    previous_run_id: str | None


class LoadedTrial(NamedTuple):
    """A trial rebuilt from its run's artifacts: resolved config, problem, hybrid model."""

    cfg: DictConfig
    problem: Any
    hybrid: Any


def utc_now() -> str:
    """The current time as UTC ISO 8601 with microseconds (sorts as text)."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="microseconds")


def os_user() -> str:
    """The name of the OS user (``"unknown"`` where it cannot be found)."""
    try:
        return getpass.getuser()
    except Exception:  # noqa: BLE001 - no passwd entry, no env: still record something
        return "unknown"


def search_all(store: Store, filter_string: str, order_by: Sequence[str] | None = None) -> list[Any]:
    """Every active run of the store's experiment matching ``filter_string`` (all pages)."""
    runs: list[Any] = []
    token = None
    while True:
        page = store.client.search_runs(
            [store.experiment_id], filter_string, max_results=1000, order_by=list(order_by or []), page_token=token
        )
        runs.extend(page)
        token = page.token
        if not token:
            return runs


def sweep_runs(store: Store) -> list[Any]:
    """All sweep parent runs of the experiment, oldest first."""
    return search_all(store, f"tags.`{STAGE_TAG}` = '{SWEEP_STAGE}'", ["attributes.start_time ASC"])


def trial_runs(store: Store, sweep_run_id: str) -> list[Any]:
    """The trial runs of one sweep, ordered by trial number."""
    runs = search_all(store, f"tags.`{PARENT_TAG}` = '{sweep_run_id}'")
    runs = [r for r in runs if r.data.tags.get(STAGE_TAG) == TRIAL_STAGE]
    return sorted(runs, key=lambda r: int(r.data.tags.get(TRIAL_NUMBER_TAG, "-1")))


def trial_state(run: Any) -> str:
    """COMPLETE / PRUNED / FAIL from the trial's tag; RUNNING while its run is still running."""
    state = run.data.tags.get(TRIAL_STATE_TAG)
    if state:
        return state
    return "RUNNING" if run.info.status == "RUNNING" else "FAIL"


def check_trial(store: Store, run_id: str) -> Any:
    """The run ``run_id`` if it is a finished trial with model artifacts; a clear error otherwise."""
    run = get_run(store, run_id)
    stage = run.data.tags.get(STAGE_TAG)
    if stage != TRIAL_STAGE:
        kind = f"a {stage!r} run" if stage else "not a physmend run (no physmend.stage tag)"
        raise TrackingError(
            f"run {run_id!r} is {kind}, not a sweep trial; only trial runs can be selected "
            "(`physmend runs` lists them)"
        )
    number = run.data.tags.get(TRIAL_NUMBER_TAG, "?")
    state = trial_state(run)
    if run.info.status != "FINISHED" or state != "COMPLETE":
        reason = run.data.tags.get("physmend.error", "")
        raise TrackingError(
            f"trial {number} (run {run_id!r}) must have finished training to be selected, but its run is "
            f"{run.info.status} and the trial {state}" + (f" ({reason})" if reason else "")
        )
    present = {f.path for f in store.client.list_artifacts(run_id, "model")}
    missing = [p for p in MODEL_FILES if p not in present]
    if missing:
        raise TrackingError(f"trial {number} (run {run_id!r}) has no model artifacts {missing}; it cannot be loaded")
    parent = run.data.tags.get(PARENT_TAG)
    if not parent:
        raise TrackingError(f"trial run {run_id!r} has no parent sweep run (tag {PARENT_TAG} missing)")
    return run


def _sweep_of(store: Store, trial_run: Any) -> Any:
    parent_id = trial_run.data.tags[PARENT_TAG]
    return get_run(store, parent_id, stage=SWEEP_STAGE)


def select(store: Store, run_id: str, *, by: str | None = None) -> Selection:
    """Make trial ``run_id`` the selection of its sweep (tags on the sweep run only).

    Raises:
        TrackingError: unknown run, run of another experiment, not a trial, a failed or pruned
            trial, or a trial without model artifacts. Nothing is written then.
    """
    run = check_trial(store, run_id)
    sweep = _sweep_of(store, run)
    return _write_selection(store, sweep, run_id, by=by or os_user())


def record_auto_selection(store: Store, sweep_run_id: str, best_run_id: str) -> Selection:
    """Record the automatic best on the sweep run; it becomes the selection unless a person chose one."""
    write_tags(store.client, sweep_run_id, {BEST_TAG: best_run_id})
    # visible in the MLflow UI: a tag on the trial itself (the runs table can show and filter it) and the
    # sweep run's description
    for other in store.client.search_runs([store.experiment_id], filter_string=f"tags.`{MARK_TAG}` = 'true' "
                                          f"and tags.`{PARENT_TAG}` = '{sweep_run_id}'"):
        if other.info.run_id != best_run_id:
            write_tags(store.client, other.info.run_id, {MARK_TAG: "false"})
    write_tags(store.client, best_run_id, {MARK_TAG: "true"})
    best = store.client.get_run(best_run_id)
    val = best.data.metrics.get("val.rmse")
    number = best.data.tags.get(TRIAL_NUMBER_TAG, "?")
    write_tags(store.client, sweep_run_id, {"mlflow.note.content":
                         f"Best trial: [trial {number}](#/experiments/{store.experiment_id}/runs/{best_run_id}) "
                         f"(run {best_run_id})" + (f", val.rmse {val:.4g}" if val is not None else "")
                         + f". Trials are this run's children; the best carries the tag {MARK_TAG}=true and "
                         "a ★ in its name; this run's own val.rmse is the best's."})
    sweep = store.client.get_run(sweep_run_id)
    tags = sweep.data.tags
    if tags.get(SELECTED_TAG) and tags.get(SELECTED_BY_TAG, AUTO) != AUTO:
        from physmend.tracking.marks import mark

        mark(store, sweep_run_id, best_run_id, tags[SELECTED_TAG])
        return Selection(sweep_run_id, tags[SELECTED_TAG], tags[SELECTED_BY_TAG], tags.get(SELECTED_AT_TAG, ""), None)
    return _write_selection(store, sweep, best_run_id, by=AUTO)


def _write_selection(store: Store, sweep: Any, run_id: str, *, by: str) -> Selection:
    previous = sweep.data.tags.get(SELECTED_TAG)
    at = utc_now()
    sweep_id = sweep.info.run_id
    write_tags(store.client, sweep_id, {SELECTED_TAG: run_id, SELECTED_BY_TAG: by, SELECTED_AT_TAG: at})
    from physmend.tracking.marks import mark

    best = store.client.get_run(sweep_id).data.tags.get(BEST_TAG)
    mark(store, sweep_id, best, run_id)  # the names the MLflow UI's runs table shows
    return Selection(sweep_id, run_id, by, at, previous)


def current_selection(store: Store) -> str:
    """The run ID selected most recently on any sweep of the experiment.

    Raises:
        TrackingError: no sweep has a selection yet.
    """
    sweeps = [r for r in sweep_runs(store) if r.data.tags.get(SELECTED_TAG)]
    if not sweeps:
        raise TrackingError(
            f"no trial is selected in experiment {store.experiment_name!r} of {store.uri}: "
            "run `physmend sweep` first, or pass a run ID"
        )
    latest = max(sweeps, key=lambda r: (r.data.tags.get(SELECTED_AT_TAG, ""), r.info.start_time))
    return latest.data.tags[SELECTED_TAG]


def _apply_overrides(cfg: DictConfig, overrides: Sequence[str] | dict[str, Any] | None) -> DictConfig:
    if not overrides:
        return cfg
    if isinstance(overrides, dict):
        patch = OmegaConf.create({})
        for key, value in overrides.items():
            OmegaConf.update(patch, key, value, force_add=True)
    else:
        bad = [o for o in overrides if "=" not in o]
        if bad:
            raise TrackingError(f"problem_cfg_overrides must look like key=value, but got {bad}")
        patch = OmegaConf.from_dotlist(list(overrides))
    return OmegaConf.merge(cfg, patch)  # type: ignore[return-value]


def load_trial(
    store: Store, run_id: str | None = None, problem_cfg_overrides: Sequence[str] | dict[str, Any] | None = None,
    *, current: DictConfig | None = None,
) -> LoadedTrial:
    """Rebuild a trial from its run: resolved ``config.yaml``, the problem, the hybrid model.

    ``run_id=None`` loads the current selection. ``problem_cfg_overrides`` (``key=value`` strings
    or a mapping) patch the stored config before the problem is loaded, e.g. a moved
    ``data.root``. ``current``: the user's composed configuration, whose model and data are used
    (see :func:`physmend.tracking.stored_config.read_stored_config`); without it the caller trusts
    the store's ``model.builder``. A stored interpolation is refused either way.

    Raises:
        TrackingError: the run is not a finished trial with model artifacts, or they do not fit.
    """
    from physmend.problem import load_problem
    from physmend.tracking.fingerprint import check_same_model
    from physmend.tracking.stored_config import read_stored_config
    from physmend.ude import ArtifactError, load_hybrid

    run_id = run_id or current_selection(store)
    check_trial(store, run_id)
    with tempfile.TemporaryDirectory(prefix="physmend-trial-") as tmp:
        folder = Path(tmp)
        try:
            store.client.download_artifacts(run_id, "config.yaml", str(folder))
            store.client.download_artifacts(run_id, "model", str(folder))
        except Exception as exc:  # noqa: BLE001 - any store/IO failure is "cannot load this run"
            raise TrackingError(f"could not download the artifacts of run {run_id!r}: {exc}") from None
        cfg = read_stored_config(folder / "config.yaml", run_id, current)  # data: never resolved
        cfg = _apply_overrides(cfg, problem_cfg_overrides)
        problem = load_problem(cfg)
        if current is not None:
            check_same_model(store, store.client.get_run(run_id), cfg)
        try:
            hybrid = load_hybrid(cfg, problem, folder)
        except ArtifactError as exc:
            raise TrackingError(f"run {run_id!r}: {exc}") from None
    return LoadedTrial(cfg, problem, hybrid)


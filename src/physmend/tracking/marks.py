"""What MLflow's runs table shows without configuration: names that carry ``val.rmse`` and mark the
sweep's best and selected trial, and a saved view of the trials ranked by ``val.rmse``.

MLflow 3.17's runs table shows, in a browser that never changed it, only attribute columns (run
name, created, dataset, duration, source, models): metrics hide behind "Columns" and trials sit
collapsed under their sweep run. Its column choice lives in the browser (local storage), never in
the store, so the one field physmend can make speak in the default view is the run name:

- a finished trial is named ``trial-0003 val.rmse=0.0412``;
- the sweep's automatic best ``★ trial-0002 val.rmse=0.0387 (best, selected)``; a trial a person
  selected with ``physmend select`` ``▶ trial-0005 val.rmse=0.0431 (selected)``;
- the sweep run itself (the row shown while its trials are collapsed)
  ``★ #2 0.0387 val.rmse · trial-0002 · sweep <study>``; it also carries ``val.rmse`` (the best's) as
  its own metric, the best trial's run ID as a tag and a link to it in its description.

The saved view :data:`VIEW_KEY` (an experiment tag ``mlflow.sharedViewState.<key>``, MLflow's own
format for "Views" → saved view) lists the trials alone, sorted by ``val.rmse``, with the
``val.rmse`` column shown; ``physmend ui`` prints its address. Where MLflow decides by itself:
its home page opens an experiment in the view chosen by the browser's GenAI / Model training
switch (GenAI's "Traces" on a fresh browser; its "Training runs" tab then lists the runs); the tag
``mlflow.experimentKind`` no longer chooses it (3.17 reads only the switch and the address's
``workflowType``), and a saved view cannot expand a sweep's trials (MLflow leaves expansion out of
shared views).
"""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Any

from physmend.tracking.store import write_tags

if TYPE_CHECKING:
    from physmend.tracking.store import Store

BEST_MARK = "★"
SELECTED_MARK = "▶"
#: the saved view's key (``?viewStateShareKey=`` in the runs table's address)
VIEW_KEY = "physmend-trials"
VIEW_TAG = f"mlflow.sharedViewState.{VIEW_KEY}"
#: on a trial run: "true" while its name carries a mark (so the next marking can clear it)
MARKED_TAG = "physmend.marked"
RUN_NAME_TAG = "mlflow.runName"
# as in physmend.tracking.selection, which imports this module
_PARENT_TAG = "mlflow.parentRunId"
_STUDY_TAG = "physmend.study"
_NUMBER_TAG = "physmend.trial_number"


def trial_name(number: int, value: float | None, *, best: bool = False, selected: bool = False) -> str:
    """A trial's run name: ``trial-0003``, with ``val.rmse=…`` once finished, marked when best/selected."""
    name = f"trial-{int(number):04d}" + (f" val.rmse={value:.4g}" if value is not None else "")
    roles = [role for role, on in (("best", best), ("selected", selected)) if on]
    if not roles:
        return name
    return f"{BEST_MARK if best else SELECTED_MARK} {name} ({', '.join(roles)})"


def sweep_name(study: str, best: tuple[int, float | None] | None, selected: int | None = None) -> str:
    """The sweep run's name: ``★ #2 0.0387 val.rmse · trial-0002 · sweep study`` (``best``: its number
    and value; ``selected``: the number of a selected trial other than the best). The best trial's
    number and value come first: the runs table's name column shows about 17 characters before it
    cuts (``★ #2 0.0387 val.r…``)."""
    if best is None:
        return f"sweep-{study}"
    number, value = best
    text = f"{BEST_MARK} #{number} " + (f"{value:.4g} val.rmse · " if value is not None else "") + f"trial-{number:04d}"
    if selected is not None and selected != number:
        text += f" · {SELECTED_MARK} trial-{selected:04d} selected"
    return f"{text} · sweep {study}"


def _number(run: Any) -> int:
    try:
        return int(run.data.tags.get(_NUMBER_TAG, "-1"))
    except ValueError:
        return -1


def _value(run: Any) -> float | None:
    return run.data.metrics.get("val.rmse")


def mark(store: "Store", sweep_run_id: str, best_run_id: str | None, selected_run_id: str | None) -> None:
    """Name the sweep's best and selected trials and the sweep run after them; a trial marked
    before and now neither gets its plain name back. Writes names and tags only."""
    client = store.client
    wanted = {r for r in (best_run_id, selected_run_id) if r}
    earlier = client.search_runs([store.experiment_id], f"tags.`{MARKED_TAG}` = 'true' and "
                                 f"tags.`{_PARENT_TAG}` = '{sweep_run_id}'")
    for run in earlier:
        if run.info.run_id not in wanted:
            write_tags(client, run.info.run_id, {RUN_NAME_TAG: trial_name(_number(run), _value(run)),
                                                 MARKED_TAG: "false"})
    runs = {r: client.get_run(r) for r in wanted}
    for run_id, run in runs.items():
        name = trial_name(_number(run), _value(run), best=run_id == best_run_id, selected=run_id == selected_run_id)
        write_tags(client, run_id, {RUN_NAME_TAG: name, MARKED_TAG: "true"})
    sweep = client.get_run(sweep_run_id)
    study = sweep.data.tags.get(_STUDY_TAG, sweep_run_id)
    best = runs.get(best_run_id) if best_run_id else None
    chosen = runs.get(selected_run_id) if selected_run_id else None
    write_tags(client, sweep_run_id, {RUN_NAME_TAG: sweep_name(
        study, (_number(best), _value(best)) if best is not None else None,
        _number(chosen) if chosen is not None else None)})


def view_state() -> dict[str, Any]:
    """The saved view's state (MLflow's search facets and runs-table UI state): trials only,
    sorted by ``val.rmse`` (lowest first), columns ``val.rmse``, the trial's state and its number."""
    return {
        "searchFilter": "tags.`physmend.stage` = 'trial'",
        "orderByKey": "metrics.`val.rmse`",
        "orderByAsc": True,
        "startTime": "ALL",
        "lifecycleFilter": "Active",
        "selectedColumns": ["metrics.`val.rmse`", "metrics.`train.rmse`", "tags.`physmend.trial_state`",
                            "tags.`physmend.study`", "attributes.`Duration`"],
    }


def view_address(experiment_id: str) -> str:
    """The saved view's address relative to the MLflow UI's root (``#/experiments/…``)."""
    return f"#/experiments/{experiment_id}/runs?workflowType=machine_learning&viewStateShareKey={VIEW_KEY}"


#: the start of the description physmend gives its experiment (a user's own is never replaced)
NOTE_START = "physmend:"


def save_view(store: "Store") -> None:
    """Write the saved view :data:`VIEW_KEY` on the store's experiment ("Views" in the runs table),
    and put its link first in the experiment's description (shown above every page of it, the GenAI
    overview MLflow opens by default included) unless a person wrote that description."""
    now = int(time.time() * 1000)
    envelope = {"name": "physmend: trials by val.rmse", "createdAt": now, "updatedAt": now,
                "state": json.dumps(view_state())}
    client = store.client
    client.set_experiment_tag(store.experiment_id, VIEW_TAG, json.dumps(envelope))
    note = client.get_experiment(store.experiment_id).tags.get("mlflow.note.content", "")
    if not note or note.startswith(NOTE_START):
        client.set_experiment_tag(store.experiment_id, "mlflow.note.content", experiment_note(store.experiment_id))


def experiment_note(experiment_id: str) -> str:
    """The experiment's description (markdown): the runs table's link first."""
    return (f"{NOTE_START} [runs table: trials ranked by val.rmse]({view_address(experiment_id)}) · "
            "diagnose, sweep (each trial a child run; the best marked ★ in its name and tagged physmend.best), "
            "mask, sensitivity, symbolic and propose runs")

"""Stage runs: tags that chain a stage to its source run, config and artifacts as plain files.

Every text written to a run (config, parameters, tags, texts, errors) is :func:`~physmend.redact.redact`-ed."""

from __future__ import annotations

import json
import tempfile
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from physmend.redact import redact
from physmend.tracking.store import Store, TrackingError

STAGE_TAG = "physmend.stage"
SOURCE_TAG = "physmend.source_run_id"
MODEL_TAG = "physmend.model"
DATA_TAG = "physmend.data"
ERROR_TAG = "physmend.error"
#: MLflow's run description (shown on the run's page)
NOTE_TAG = "mlflow.note.content"


class StageRun:
    """A thin handle on an active MLflow run with helpers for plain-file artifacts."""

    def __init__(self, store: Store, run_id: str) -> None:
        self.store = store
        self.run_id = run_id

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        import mlflow

        clean = {k: float(v) for k, v in metrics.items() if v is not None}
        if clean:
            mlflow.log_metrics(clean, step=step)

    def log_params(self, params: dict[str, Any]) -> None:
        import mlflow

        mlflow.log_params({k: redact(str(v))[:6000] for k, v in params.items()})

    def set_tags(self, tags: dict[str, str]) -> None:
        import mlflow

        mlflow.set_tags({k: redact(str(v)) for k, v in tags.items()})

    def describe(self, text: str) -> None:
        """The run's description in the MLflow UI (Markdown): what the stage found."""
        import mlflow

        mlflow.set_tag(NOTE_TAG, redact(text)[:5000])

    def log_text(self, text: str, path: str) -> None:
        import mlflow

        mlflow.log_text(redact(text), path)

    def log_json(self, obj: Any, path: str) -> None:
        self.log_text(json.dumps(obj, indent=2, sort_keys=True, default=float), path)

    def log_figure(self, fig: Any, path: str) -> None:
        import mlflow

        mlflow.log_figure(fig, path)

    def log_file(self, local: str | Path, folder: str | None = None) -> None:
        import mlflow

        mlflow.log_artifact(str(local), folder)


@contextmanager
def stage_run(
    store: Store,
    cfg: DictConfig,
    *,
    stage: str,
    source_run_id: str | None,
    run_name: str | None = None,
    parent_run_id: str | None = None,
    tags: dict[str, str] | None = None,
) -> Iterator[StageRun]:
    """Start an MLflow run for ``stage`` tagged with its source run; log the resolved config.

    A failure inside the block marks this run FAILED with the error as a tag and re-raises;
    earlier runs are never touched.
    """
    import mlflow

    all_tags = {
        STAGE_TAG: stage,
        SOURCE_TAG: source_run_id or "",
        MODEL_TAG: str(OmegaConf.select(cfg, "model.builder", default="")),
        DATA_TAG: str(OmegaConf.select(cfg, "data.name", default="")),
    }
    if source_run_id:  # until the stage describes what it found
        all_tags[NOTE_TAG] = f"physmend {stage}, from run {source_run_id}"
    from physmend.tracking.fingerprint import STRUCTURE_FILE, fingerprint_tags

    model_tags, structure = fingerprint_tags(cfg)
    all_tags.update(model_tags)
    all_tags.update(tags or {})
    with mlflow.start_run(
        experiment_id=store.experiment_id,
        run_name=run_name or stage,
        parent_run_id=parent_run_id,
        nested=parent_run_id is not None,
        tags={k: redact(str(v)) for k, v in all_tags.items()},
    ) as active:
        handle = StageRun(store, active.info.run_id)
        handle.log_text(OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
        if structure is not None:
            handle.log_text(structure, STRUCTURE_FILE)
        try:
            yield handle
        except BaseException as exc:
            # a Ctrl-C that lands inside a store write can leave that write's session broken: the
            # error tag and traceback are best effort, the run's end is always attempted
            try:
                mlflow.set_tag(ERROR_TAG, redact(f"{type(exc).__name__}: {exc}")[:5000])
                mlflow.log_text(redact("".join(traceback.format_exception(exc))), "error.txt")
            except Exception:  # noqa: BLE001 - never mask the error that ended the stage
                pass
            finally:
                try:
                    mlflow.end_run(status="KILLED" if isinstance(exc, KeyboardInterrupt) else "FAILED")
                except Exception:  # noqa: BLE001 - as above; the caller may still end it by ID
                    pass
            raise


def get_run(store: Store, run_id: str, *, stage: str | None = None) -> Any:
    """Fetch a run by ID, checking it exists, belongs to the store's experiment and (optionally) its stage."""
    from mlflow.exceptions import MlflowException

    try:
        run = store.client.get_run(run_id)
    except MlflowException:
        raise TrackingError(f"run ID {run_id!r} does not exist in the tracking store {store.uri}") from None
    if run.info.experiment_id != store.experiment_id:
        raise TrackingError(
            f"run {run_id!r} belongs to another MLflow experiment (id {run.info.experiment_id}), "
            f"not to {store.experiment_name!r}"
        )
    actual = run.data.tags.get(STAGE_TAG)
    if stage is not None and actual != stage:
        raise TrackingError(f"run {run_id!r} must be a {stage!r} run, but is a {actual!r} run")
    return run


def download_artifact(store: Store, run_id: str, path: str) -> Path:
    """Download one artifact of a run into a temporary folder and return its local path."""
    from mlflow.exceptions import MlflowException

    dest = Path(tempfile.mkdtemp(prefix="physmend-"))
    try:
        return Path(store.client.download_artifacts(run_id, path, str(dest)))
    except (MlflowException, OSError):
        raise TrackingError(f"run {run_id!r} has no artifact {path!r}; was it written by physmend?") from None

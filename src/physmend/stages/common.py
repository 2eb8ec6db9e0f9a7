"""What stages share: finding the source run, rebuilding its model, logging a trained model."""

from __future__ import annotations

import math

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from physmend.tracking import STAGE_TAG, Store, StageRun, TrackingError, get_run


@dataclass
class Source:
    """A source run and what it carries: its resolved config, the problem, and (if any) its hybrid."""

    run: Any
    cfg: DictConfig
    problem: Any
    hybrid: Any


def stage_of(run: Any) -> str:
    return run.data.tags.get(STAGE_TAG, "")


def resolve(store: Store, run_id: str | None, *, stages: tuple[str, ...], latest: bool = False) -> Any:
    """The run ``run_id`` checked to be one of ``stages``; without an ID the current selection
    (``trial``) or, with ``latest``, the newest finished run of the first of ``stages``."""
    if run_id is None:
        if latest:
            runs = store.client.search_runs(
                [store.experiment_id],
                filter_string=f"tags.`{STAGE_TAG}` = '{stages[0]}' and attributes.status = 'FINISHED'",
                order_by=["attributes.start_time DESC"],
                max_results=1,
            )
            if not runs:
                raise TrackingError(
                    f"no finished {stages[0]!r} run in experiment {store.experiment_name!r} of {store.uri}; "
                    f"run `physmend {stages[0]}` first or pass a run ID"
                )
            return runs[0]
        from physmend.tracking.selection import current_selection

        run_id = current_selection(store)
    run = get_run(store, run_id)
    if stage_of(run) not in stages:
        raise TrackingError(
            f"run {run_id!r} must be a {' or '.join(repr(s) for s in stages)} run, but is a {stage_of(run) or 'non-physmend'!r} run"
        )
    if run.info.status != "FINISHED":
        raise TrackingError(f"run {run_id!r} did not finish (status {run.info.status}); choose a finished run")
    return run


def load_source(store: Store, run: Any, current: DictConfig | None, *, with_model: bool = True) -> Source:
    """Rebuild the config, problem and (``with_model``) hybrid model from a run's plain-file artifacts.

    ``current``: the user's composed configuration; the model and data are built from it, after
    checking the run was made with the same (:mod:`physmend.tracking.stored_config`)."""
    from physmend.problem import load_problem
    from physmend.tracking.fingerprint import check_same_model
    from physmend.tracking.stored_config import read_stored_config
    from physmend.ude import ArtifactError, load_hybrid

    run_id = run.info.run_id
    with tempfile.TemporaryDirectory(prefix="physmend-src-") as tmp:
        folder = Path(tmp)
        try:
            store.client.download_artifacts(run_id, "config.yaml", str(folder))
            if with_model:
                store.client.download_artifacts(run_id, "model", str(folder))
        except Exception as exc:  # noqa: BLE001 - any store/IO failure means "cannot load this run"
            raise TrackingError(f"run {run_id!r} lacks the artifacts physmend needs (config.yaml, model/): {exc}") from None
        cfg = read_stored_config(folder / "config.yaml", run_id, current)
        problem = load_problem(cfg)
        if current is not None:
            check_same_model(store, run, cfg)
        hybrid = None
        if with_model:
            try:
                hybrid = load_hybrid(cfg, problem, folder)
            except ArtifactError as exc:
                raise TrackingError(f"run {run_id!r}: {exc}") from None
            kept = run.data.tags.get("physmend.kept")
            if kept:
                names = kept.split(",")
                stray = [n for n in names if n not in hybrid.spec.corrected]
                if stray:
                    from physmend.modeling.safe_parse import quoted

                    raise TrackingError(f"run {run_id!r}: its tag physmend.kept names {quoted(stray[0])}, which is not "
                                        f"a state its network corrects ({', '.join(hybrid.spec.corrected)[:100]})")
                hybrid.keep_only(names)
    return Source(run, cfg, problem, hybrid)


def log_training(run_: StageRun, result: Any) -> None:
    """Log a :class:`physmend.ude.TrainResult`: metrics, history, model files, figures."""
    import matplotlib.pyplot as plt

    for row in result.history:  # a failed checkpoint (inf) is in history.json and checkpoints.failed
        run_.log_metrics({k: v for k, v in row.items() if k != "epoch" and math.isfinite(v)}, step=int(row["epoch"]))
    run_.log_metrics({k: v for k, v in result.metrics.items() if math.isfinite(v)})
    log_artifacts(run_, result.artifacts)
    for rel, fig in result.figures.items():
        run_.log_figure(fig, rel)
        plt.close(fig)


def log_artifacts(run_: StageRun, artifacts: dict[str, str | bytes]) -> None:
    """Log plain-file artifacts given as ``relative path -> content``."""
    for rel, content in artifacts.items():
        if isinstance(content, bytes):
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / Path(rel).name
                path.write_bytes(content)
                run_.log_file(path, str(Path(rel).parent))
        else:
            run_.log_text(content, rel)


def merged(trial_cfg: DictConfig, stage_cfg: DictConfig, *keys: str) -> DictConfig:
    """The source's resolved config with the current command's ``tracking`` and stage groups."""
    out = OmegaConf.create(OmegaConf.to_container(trial_cfg, resolve=True))
    for key in ("tracking", *keys):
        if key in stage_cfg:
            out[key] = OmegaConf.create(OmegaConf.to_container(stage_cfg[key], resolve=True))
    return out  # type: ignore[return-value]

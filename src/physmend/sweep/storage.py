"""The Optuna storage and study: opening (with retries), the study's fingerprint compared on
resume, and the tally of trials that count towards ``sweep.n_trials``.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from physmend.config import ConfigError
from physmend.sweep.settings import Settings
from physmend.sweep.space import SearchSpace

if TYPE_CHECKING:
    import optuna
    from physmend.problem import Problem


RUN_ID_ATTR = "mlflow_run_id"  # Optuna trial user attr: the trial's MLflow run ID

PARENT_ATTR = "mlflow_parent_run_id"  # Optuna study user attr: the sweep's parent run ID

CONFIG_ATTR = "physmend_config"  # Optuna study user attr: what the study was started with

WORKER_ATTR = "worker"

HEARTBEAT_ATTR = "heartbeat"

REASON_ATTR = "fail_reason"

UNCOUNTED = ("interrupted", "surplus")  # FAIL reasons that are no verdict on the trial's parameters

PARENT_WAIT_S = 20.0  # how long a worker waits for the study's creator to write the parent run ID

# config groups whose values make trials comparable: resuming a study with others is refused
_COMPARED = ("model", "data", "simulate", "ude", "train", "seed")



def open_storage(url: str) -> "optuna.storages.RDBStorage":
    """The Optuna RDB storage at ``url`` (``sqlite:///`` paths resolve against the working directory).

    A database server is probed first, within seconds whatever its driver: one that accepts the
    connection and never answers is one line, not a sweep that hangs (``tracking.store.probe_store``).
    """
    import optuna

    from physmend.tracking import TrackingError, sqlite_path
    from physmend.tracking.store import SERVER_TIMEOUT_S, probe_store

    kwargs: dict[str, Any] = {}
    db = sqlite_path(url)
    if db is not None:
        if not db.parent.is_dir():
            raise TrackingError(f"tracking.optuna_storage {url!r}: the folder {str(db.parent)!r} for the database does not exist")
        url = f"sqlite:///{db}"
        kwargs["engine_kwargs"] = {"connect_args": {"timeout": 60}}
    else:
        probe_store(url, timeout=SERVER_TIMEOUT_S, key="tracking.optuna_storage")
    try:
        return _retry(lambda: optuna.storages.RDBStorage(url, **kwargs))
    except (ImportError, ValueError, optuna.exceptions.OptunaError) as exc:
        raise TrackingError(f"tracking.optuna_storage {url!r} cannot be opened: {exc}") from None



@contextlib.contextmanager
def asking(storage: Any) -> Iterator[None]:
    """Around ``study.ask()``: one process at a time where ``storage`` is a sqlite file.

    Optuna hands an enqueued (WAITING) trial to the process that sets it RUNNING, reading it with
    ``SELECT … FOR UPDATE``; sqlite has no row lock, so two workers asking at once both read it
    WAITING and both train it (seen: discover's two workers, ready at the same moment, both ran
    trial 0, and its other trials then ran one after another). A database server locks the row:
    no lock is taken there. The lock is :func:`physmend.tracking.store.folder_lock` on the
    database's folder (no file is created), held for the ask only."""
    from physmend.tracking import sqlite_path
    from physmend.tracking.store import folder_lock

    db = sqlite_path(str(getattr(storage, "url", "")))
    with folder_lock(db.parent if db is not None else None, required=False):  # no lock: as Optuna alone
        yield


def _retry(fn: Callable[[], Any], attempts: int = 4) -> Any:
    """Call ``fn``, retrying transient failures (two workers creating one database at once)."""
    from physmend.tracking import TrackingError

    for i in range(attempts):
        try:
            return fn()
        except (TrackingError, ImportError, KeyboardInterrupt):
            raise
        except Exception:  # noqa: BLE001 - table/migration races; re-raised on the last attempt
            if i == attempts - 1:
                raise
            time.sleep(0.5 + 0.5 * i + (os.getpid() % 7) / 10)
    raise AssertionError("unreachable")



def study_fingerprint(cfg: DictConfig, space: SearchSpace) -> dict[str, Any]:
    """What a study was started with: the config values that shape trials (``_COMPARED``), and the space.

    ``sweep.*`` settings (n_trials, sampler, pruner, timeout …) may change when resuming.
    """
    data = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(data, dict)
    keep = {k: data[k] for k in _COMPARED if k in data}
    flat: dict[str, Any] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        else:
            flat[prefix] = node

    walk("", keep)
    return {"config": flat, "space": space.spec()}



def check_fingerprint(study_name: str, stored: dict[str, Any] | None, current: dict[str, Any]) -> None:
    """Resuming a study with another configuration would mix incomparable trials: refuse."""
    if not stored:
        return
    old, new = stored.get("config", {}), current["config"]
    diffs = [f"{k}: {old.get(k, '<unset>')!r} -> {new.get(k, '<unset>')!r}" for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    if stored.get("space") != current["space"]:
        diffs.append("the search space changed")
    if diffs:
        shown = "; ".join(diffs[:6]) + (f"; … ({len(diffs) - 6} more)" if len(diffs) > 6 else "")
        raise ConfigError(
            f"study {study_name!r} was started with another configuration ({shown}); rerun the original command "
            "to resume it, or pass sweep.study_name=NEW_NAME to start a new study"
        )



def default_study_name(problem: "Problem", cfg: DictConfig, space: SearchSpace) -> str:
    """``<model>-<data>-<space>``."""
    return f"{problem.model.name}-{cfg.data.name}-{space.name}"



def _open_study(storage: Any, name: str, settings: Settings) -> tuple["optuna.Study", bool]:
    """``(study, created)``: create the study, or load it if it exists (exactly one creator wins)."""
    import optuna

    try:
        study = optuna.create_study(storage=storage, study_name=name, direction="minimize", pruner=settings.make_pruner())
        return study, True
    except optuna.exceptions.DuplicatedStudyError:
        return optuna.load_study(study_name=name, storage=storage, pruner=settings.make_pruner()), False



@dataclass
class Tally:
    """Trials of a study by what they mean for ``n_trials``."""

    complete: int = 0
    pruned: int = 0
    failed: int = 0
    running: int = 0
    uncounted: int = 0
    best_value: float | None = None
    best_number: int | None = None

    @property
    def counted(self) -> int:
        """Trials that reached a verdict (COMPLETE, PRUNED, FAIL other than interrupted/surplus)."""
        return self.complete + self.pruned + self.failed



def _uncounted(t: Any) -> bool:
    from optuna.trial import TrialState

    return t.state == TrialState.FAIL and t.user_attrs.get(REASON_ATTR) in UNCOUNTED



def tally(trials: Sequence[Any]) -> Tally:
    """Count ``trials`` (FrozenTrials) and find the best complete one."""
    from optuna.trial import TrialState

    out = Tally()
    for t in trials:
        if t.state == TrialState.COMPLETE:
            out.complete += 1
            if t.value is not None and (out.best_value is None or t.value < out.best_value):
                out.best_value, out.best_number = t.value, t.number
        elif t.state == TrialState.PRUNED:
            out.pruned += 1
        elif t.state == TrialState.RUNNING:
            out.running += 1
        elif t.state == TrialState.FAIL:
            if _uncounted(t):
                out.uncounted += 1
            else:
                out.failed += 1
    return out



def _study(storage: Any, name: str, settings: Settings, space: SearchSpace, fingerprint: dict[str, Any]) -> tuple[Any, bool]:
    """Create the study (recording what it was started with, enqueuing ``first_trials``) or load and check it.

    A budgeted sweep of single trials (``sweep.budget``, ``sweep.group: 1``) enqueues its whole
    minimum instead (and every one of ``first_trials``), proposed together as one group of
    ``sweep.n_trials`` would be
    (:func:`physmend.sweep.settings.proposed_together`): the trials the budget measures are then the
    same however many workers run them and whichever asks first, and the same as a stack of them."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study, created = _retry(lambda: _open_study(storage, name, settings))
    if created:
        study.set_user_attr(CONFIG_ATTR, fingerprint)
        first: list[dict[str, Any]] = list(space.first_trials)
        if settings.budgeted is not None and settings.group == 1:
            from physmend.sweep.settings import proposed_together

            first = proposed_together(space, settings, max(settings.n_trials, len(space.first_trials)))
        for values in first:
            study.enqueue_trial(values, skip_if_exists=True)
    else:
        check_fingerprint(name, study.user_attrs.get(CONFIG_ATTR), fingerprint)
    return study, created

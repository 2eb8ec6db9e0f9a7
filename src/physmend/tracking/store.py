"""The MLflow store: tracking URI, experiment, artifact location beside an sqlite database."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mlflow.tracking import MlflowClient


class TrackingError(ValueError):
    """A run ID or the tracking store is not what a stage needs; the message names the run."""


@dataclass
class Store:
    """An opened tracking store: ``client`` and the id of the physmend experiment in it."""

    uri: str
    client: "MlflowClient"
    experiment_id: str
    experiment_name: str


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI (relative paths resolve against the working directory)."""
    if not uri.startswith("sqlite:///"):
        return None
    return Path(uri[len("sqlite:///") :]).expanduser().resolve()


@contextlib.contextmanager
def _folder_lock(folder: Path | None) -> Iterator[None]:
    """Exclusive lock on ``folder`` (POSIX ``flock`` on the directory itself: no file is created).

    MLflow creates and migrates a new sqlite database on first use; two processes doing that at
    once (sweep workers started together) collide. Elsewhere (no folder, no ``fcntl``) a no-op.
    """
    try:
        import fcntl
    except ImportError:  # Windows
        fcntl = None  # type: ignore[assignment]
    if folder is None or fcntl is None:
        yield
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def open_store(tracking_cfg: Any) -> Store:
    """Open (creating if needed) the MLflow store and experiment named by ``tracking.uri/experiment``.

    With an sqlite store, artifacts live in ``mlartifacts/`` beside the database file.
    """
    import mlflow
    from mlflow.tracking import MlflowClient

    uri = str(tracking_cfg.uri)
    name = str(tracking_cfg.experiment)
    db = sqlite_path(uri)
    if db is not None:
        if not db.parent.is_dir():
            raise TrackingError(
                f"tracking.uri {uri!r}: the folder {str(db.parent)!r} for the database does not exist"
            )
        uri = f"sqlite:///{db}"
    mlflow.set_tracking_uri(uri)
    with _folder_lock(db.parent if db is not None else None):  # workers starting together: one creates
        client = MlflowClient(tracking_uri=uri)
        exp = client.get_experiment_by_name(name)
        if exp is None:
            artifact_location = (db.parent / "mlartifacts" / name).as_uri() if db is not None else None
            exp_id = client.create_experiment(name, artifact_location=artifact_location)
    if exp is not None:
        if exp.lifecycle_stage != "active":
            raise TrackingError(
                f"tracking.experiment {name!r} is deleted in {uri}; restore it or choose another name"
            )
        exp_id = exp.experiment_id
    return Store(uri=uri, client=client, experiment_id=exp_id, experiment_name=name)

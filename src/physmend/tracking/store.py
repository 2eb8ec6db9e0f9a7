"""The MLflow store: tracking URI, experiment, artifact location beside an sqlite database."""

from __future__ import annotations

import contextlib
import os
import random
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from physmend.exceptions import PhysmendError
from physmend.redact import redact
from physmend.settings import TrackingSettings
from physmend.tracking.probe import scheme_of

if TYPE_CHECKING:
    from mlflow.tracking import MlflowClient


class TrackingError(PhysmendError, ValueError):
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
def folder_lock(folder: Path | None, *, required: bool = True) -> Iterator[None]:
    """Exclusive lock on ``folder`` (POSIX ``flock`` on the directory itself: no file is created).

    MLflow creates and migrates a new sqlite database on first use; two processes doing that at
    once (sweep workers started together) collide; two sweep workers asking for the same waiting
    trial of a sqlite study both get it (:func:`physmend.sweep.storage.asking`). Elsewhere (no
    folder, no ``fcntl``) a no-op; ``required=False``: also where the folder cannot be locked (a
    file system without ``flock``), instead of raising ``OSError``. Never nested in one process (a
    second descriptor's lock would wait for the first).
    """
    try:
        import fcntl
    except ImportError:  # Windows
        fcntl = None  # type: ignore[assignment]
    if folder is None or fcntl is None:
        yield
        return
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        if required:
            raise
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            if required:
                raise
        yield
    finally:
        os.close(fd)  # releases the lock


#: what opening the stores imports (MLflow, its SQL store and migrations; Optuna's RDB storage's
#: tables): seconds where nothing is byte-compiled yet
STORE_MODULES = ("mlflow", "mlflow.tracking", "mlflow.store.tracking.sqlalchemy_store", "alembic.command",
                 "optuna.storages._rdb.models")


def preload() -> None:
    """Import :data:`STORE_MODULES` ahead of opening a store, touching no store (a process that
    waits for its work does it: :mod:`physmend.sweep.standby`). A module another version lays
    out differently is skipped: opening the store imports what it needs then."""
    import importlib

    quiet_mlflow()
    for name in STORE_MODULES:
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001 - only time is at stake; open_store reports real trouble
            continue


def quiet_mlflow() -> None:
    """Keep MLflow's own console lines off physmend's output: with a tracking server MLflow writes
    "🏃 View run … / 🧪 View experiment …" to stdout at every run's end (two lines per trial;
    ``MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT`` turns it off, read at each run's end), and its loggers
    print INFO notices (new tables, new experiments) on stderr. A user's own setting of the variable
    or of ``MLFLOW_LOGGING_LEVEL`` wins; warnings and errors still show."""
    import logging

    os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")
    if not os.environ.get("MLFLOW_LOGGING_LEVEL"):
        logging.getLogger("mlflow").setLevel(logging.WARNING)


#: seconds a database server may take to accept a connection and list its tables before a stage gives
#: up (MLflow itself would retry for about 100 s, and wait forever on one that accepts and never answers)
SERVER_TIMEOUT_S = 5
#: the same for an sqlite file (no network; a writer's lock may hold it a few seconds)
SQLITE_TIMEOUT_S = 10


def probe_store(uri: str, *, timeout: float = SQLITE_TIMEOUT_S, key: str = "tracking.uri",
                shown: str | None = None) -> None:
    """Raise :class:`TrackingError` (one line naming ``key`` and the URI as the user wrote it,
    ``shown``, redacted) when the database store ``uri`` cannot be opened within ``timeout`` seconds,
    whatever its driver (a server that accepts connections and never answers included:
    :mod:`physmend.tracking.probe`); other stores (a server, a folder) are not probed."""
    from physmend.tracking.probe import probe_database

    try:
        probe_database(uri, timeout)
    except Exception as exc:  # noqa: BLE001 - any failure to open the store is one line naming it
        raise TrackingError(f"{key} {redact(shown or uri)!r} cannot be opened: {_reason(exc)}") from None


def _reason(exc: BaseException) -> str:
    """The first line of what a store library said, without its SQL, links and stack."""
    from physmend.tracking.probe import DRIVER_PACKAGES

    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    for noise in ("(sqlite3.OperationalError) ", "(sqlite3.DatabaseError) "):
        text = text.replace(noise, "")
    if isinstance(exc, KeyError):
        text = f"unknown scheme {text}"
    if isinstance(exc, ModuleNotFoundError):  # SQLAlchemy's driver for the scheme is not installed
        module = (exc.name or text).split(".")[0]
        todo = DRIVER_PACKAGES.get(module, f"pip install the package that provides {module!r}")
        text = f"its database driver {module!r} is not installed ({todo})"
    return redact(text[:300])


#: tracking URI schemes of a database that MLflow reaches directly (no server in between)
DATABASE_SCHEMES = ("postgresql", "mysql", "mssql")


def _artifact_location(tracking_cfg: TrackingSettings, uri: str, db: Path | None, name: str) -> str | None:
    """Where a new experiment's artifacts go: ``tracking.artifact_location`` when set; beside an sqlite
    database; the server's choice behind an ``http(s)://`` URI. A database reached directly with no
    location set is an error: MLflow would write ``./mlruns`` in whichever folder each stage ran."""
    chosen = tracking_cfg.artifact_location
    if chosen:
        return str(chosen)
    if db is not None:
        return (db.parent / "mlartifacts" / name).as_uri()
    if scheme_of(uri) in DATABASE_SCHEMES:
        raise TrackingError(
            f"tracking.uri {redact(uri)!r} is a database reached directly: set tracking.artifact_location to a folder "
            "or URI every machine can reach (e.g. s3://bucket/physmend or /shared/mlartifacts), or run an MLflow "
            "tracking server on it (mlflow server --backend-store-uri … --artifacts-destination …) and set "
            "tracking.uri=http://HOST:PORT (docs/many-machines.md)")
    return None


#: tries of a tag write that met another writer's insert of the same key (then it finds the key and updates it)
TAG_ATTEMPTS = 5


def write_tags(client: "MlflowClient", run_id: str, tags: dict[str, str]) -> None:
    """Set ``tags`` on the run ``run_id`` in one batch, also while other workers write the same run.

    A sweep's parent run and its marked trials are written by every worker that finishes (their
    selection, names, best): MLflow's database store reads that a tag is absent and then inserts it,
    so two writers setting the same new key at once collide on the tags table's unique key
    (``UNIQUE constraint failed`` in sqlite, ``duplicate key`` in PostgreSQL). A batch write retries
    within the store; a write that still collides is tried again here, up to ``TAG_ATTEMPTS`` times.
    """
    from mlflow.entities import RunTag
    from mlflow.exceptions import MlflowException

    batch = [RunTag(key, str(value)) for key, value in tags.items()]
    for attempt in range(TAG_ATTEMPTS):
        try:
            client.log_batch(run_id, tags=batch)
            return
        except MlflowException as exc:
            text = str(exc).lower()
            collided = any(word in text for word in ("unique", "duplicate key", "integrity", "failed to set tags"))
            if not collided or attempt == TAG_ATTEMPTS - 1:
                raise
            time.sleep(0.1 * (attempt + 1) + 0.2 * random.random())


def open_store(tracking_cfg: Any) -> Store:
    """Open (creating if needed) the MLflow store and experiment named by ``tracking.uri/experiment``.

    With an sqlite store, artifacts live in ``mlartifacts/`` beside the database file.
    """
    tracking_cfg = TrackingSettings.build(tracking_cfg)  # checked; missing keys: conf/tracking/default.yaml
    uri = tracking_cfg.uri
    name = tracking_cfg.experiment
    db = sqlite_path(uri)
    if db is not None:
        if not db.parent.is_dir():
            raise TrackingError(
                f"tracking.uri {redact(uri)!r}: the folder {str(db.parent)!r} for the database does not exist"
            )
        uri = f"sqlite:///{db}"
    # a server that does not answer is reported in seconds, not after minutes of retries (the
    # user's own settings of these win)
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "1")
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "20")
    quiet_mlflow()
    # a database that does not answer: one line within seconds (before MLflow's import, another second)
    probe_store(uri, timeout=SQLITE_TIMEOUT_S if db is not None else SERVER_TIMEOUT_S, key="tracking.uri",
                shown=str(tracking_cfg.uri))
    import mlflow
    from mlflow.exceptions import MlflowException
    from mlflow.tracking import MlflowClient

    try:
        mlflow.set_tracking_uri(uri)
        with folder_lock(db.parent if db is not None else None):  # workers starting together: one creates
            client = MlflowClient(tracking_uri=uri)
            exp = client.get_experiment_by_name(name)
            if exp is None:
                artifact_location = _artifact_location(tracking_cfg, uri, db, name)
                # a classic ML experiment (MLflow 3's UI still chooses its GenAI or model-training view by a
                # browser setting or the address's workflowType: `physmend ui` prints the runs table's address)
                try:
                    exp_id = client.create_experiment(name, artifact_location=artifact_location, tags={
                        "mlflow.experimentKind": "custom_model_development",
                        "mlflow.note.content": "physmend: diagnose, sweep trials (val.rmse), mask, sensitivity, "
                                              "symbolic and propose runs; a sweep's best trial is tagged physmend.best"})
                except MlflowException as exc:
                    # workers on other machines starting together against one server (no shared folder to
                    # lock): another created it between the lookup and the creation — use theirs
                    exists = "RESOURCE_ALREADY_EXISTS" in f"{exc.error_code} {exc}"
                    exp = client.get_experiment_by_name(name) if exists else None
                    if exp is None:
                        raise
                    exp_id = exp.experiment_id
    except TrackingError:
        raise
    except Exception as exc:  # noqa: BLE001 - any failure to open the store is one line naming it
        raise TrackingError(f"tracking.uri {redact(str(tracking_cfg.uri))!r} cannot be opened: {_reason(exc)}") from None
    if exp is not None:
        if exp.lifecycle_stage != "active":
            raise TrackingError(
                f"tracking.experiment {name!r} is deleted in {redact(uri)}; restore it or choose another name"
            )
        exp_id = exp.experiment_id
    return Store(uri=uri, client=client, experiment_id=exp_id, experiment_name=name)

"""MLflow conventions: the store, stage runs and their lineage tags, plain-file artifacts."""

from __future__ import annotations

from physmend.tracking.runs import (
    DATA_TAG,
    ERROR_TAG,
    MODEL_TAG,
    SOURCE_TAG,
    STAGE_TAG,
    StageRun,
    download_artifact,
    get_run,
    stage_run,
)
from physmend.tracking.store import Store, TrackingError, open_store, sqlite_path

__all__ = [
    "DATA_TAG",
    "ERROR_TAG",
    "MODEL_TAG",
    "SOURCE_TAG",
    "STAGE_TAG",
    "StageRun",
    "Store",
    "TrackingError",
    "download_artifact",
    "get_run",
    "open_store",
    "sqlite_path",
    "stage_run",
]

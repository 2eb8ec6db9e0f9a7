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
from physmend.tracking.selection import (
    BEST_TAG,
    SELECTED_AT_TAG,
    SELECTED_BY_TAG,
    SELECTED_TAG,
    LoadedTrial,
    Selection,
    check_trial,
    current_selection,
    load_trial,
    select,
)
from physmend.tracking.store import Store, TrackingError, open_store, sqlite_path, write_tags

__all__ = [
    "BEST_TAG",
    "DATA_TAG",
    "ERROR_TAG",
    "MODEL_TAG",
    "SELECTED_AT_TAG",
    "SELECTED_BY_TAG",
    "SELECTED_TAG",
    "SOURCE_TAG",
    "STAGE_TAG",
    "LoadedTrial",
    "Selection",
    "StageRun",
    "Store",
    "TrackingError",
    "check_trial",
    "current_selection",
    "download_artifact",
    "get_run",
    "load_trial",
    "open_store",
    "select",
    "sqlite_path",
    "stage_run",
    "write_tags",
]

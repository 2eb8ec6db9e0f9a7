"""``physmend ui``: the MLflow UI on the configured store, its secret kept off every command line.

A store URI may carry a password (``postgresql://user:secret@host/db``). A process's command line
can be read by every user of the machine (``ps``, ``/proc/PID/cmdline``), its environment only by
the user who started it: so the MLflow child gets the store in ``MLFLOW_BACKEND_STORE_URI`` (the
variable ``mlflow ui --backend-store-uri`` reads), and what is printed is redacted. Before the
server starts, the store is probed once with a short timeout: a store that does not answer is one
line, not minutes of MLflow's own retries, and one that accepts connections but never answers is
given up after :data:`PROBE_TIMEOUT` seconds whatever its driver (:mod:`physmend.tracking.probe`).
The server stops with physmend on SIGTERM and SIGHUP as on Ctrl-C (:mod:`physmend.tracking.child`).
A tracking server (``http(s)://``) is its own UI: its address is printed and nothing is started.
"""

from __future__ import annotations

import os
import sys
from typing import Any

from physmend.redact import redact
from physmend.settings import TrackingSettings
from physmend.tracking.child import run_server
from physmend.tracking.store import TrackingError, probe_store, sqlite_path

#: seconds the store may take to answer before ``physmend ui`` gives up (MLflow itself retries ~100 s)
PROBE_TIMEOUT = 5
#: the environment variable ``mlflow ui`` reads its ``--backend-store-uri`` from
STORE_VARIABLE = "MLFLOW_BACKEND_STORE_URI"


def server_command(uri: str, host: str, port: int) -> tuple[list[str], dict[str, str]]:
    """The MLflow UI child's argv and environment: the store ``uri`` only in the environment."""
    cmd = [sys.executable, "-m", "mlflow", "ui", "--host", host, "--port", str(port), "--workers", "1"]
    # MLflow 3's job runner (GenAI judges, 7 processes) is nothing physmend uses: off unless the user set it
    return cmd, {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false", **os.environ, STORE_VARIABLE: uri}


def ui(cfg: Any, *, host: str, port: int) -> int:
    """Start the MLflow UI on ``cfg.tracking`` (blocks until it stops); returns its exit status
    (``128 + signal`` when physmend was told to stop: the server's processes are ended too).

    Raises:
        TrackingError: the store's folder is missing or the store does not answer within
            :data:`PROBE_TIMEOUT` seconds (one line, the URI redacted).
    """
    tc = TrackingSettings.build(cfg.tracking)
    uri = tc.uri
    if uri.lower().startswith(("http://", "https://")):  # a tracking server is its own UI
        print(f"tracking.uri is an MLflow tracking server: open {redact(page(uri.rstrip('/'), uri, cfg))} "
              f"in a browser (experiment {tc.experiment!r})")
        return 0
    db = sqlite_path(uri)
    if db is not None:
        uri = f"sqlite:///{db}"
        if not db.parent.is_dir():
            raise TrackingError(f"tracking.uri {redact(uri)!r}: the folder {str(db.parent)!r} for the database does not exist")
    if db is None or db.exists():  # a new sqlite file is created by the server
        probe_store(uri, timeout=PROBE_TIMEOUT)
    cmd, env = server_command(uri, host, port)
    print(f"running: {' '.join(cmd)} (store {redact(uri)}, passed in the environment as {STORE_VARIABLE})")
    print(f"open: {redact(page(f'http://{host}:{port}', uri if db is None or db.exists() else None, cfg))}")
    return run_server(cmd, env)


def page(base: str, store_uri: str | None, cfg: Any) -> str:
    """The experiment's runs table in the MLflow UI (``workflowType=machine_learning``: MLflow 3's UI
    otherwise opens its GenAI view, whatever the experiment), in the saved view of the trials ranked
    by ``val.rmse`` once a sweep wrote it (:mod:`physmend.tracking.marks`); ``base`` alone when the
    experiment cannot be looked up (no store yet, a server that does not answer)."""
    if store_uri is None:
        return base
    try:
        os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
        os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "5")
        from mlflow.tracking import MlflowClient

        exp = MlflowClient(tracking_uri=store_uri).get_experiment_by_name(TrackingSettings.build(cfg.tracking).experiment)
    except Exception:  # noqa: BLE001 - the URL is a convenience; the UI starts regardless
        return base
    if exp is None:
        return base
    from physmend.tracking.marks import VIEW_TAG, view_address

    if VIEW_TAG in exp.tags:
        return f"{base}/{view_address(exp.experiment_id)}"
    return f"{base}/#/experiments/{exp.experiment_id}/runs?workflowType=machine_learning"

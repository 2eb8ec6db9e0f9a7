"""A finished sweep trial in a real MLflow sqlite store, written in about a second: a sweep run, a
trial run under it with the user's configuration, the model's fingerprint and a real (untrained)
hybrid model's ``model/hybrid.json`` and ``model/weights.pt`` — what a sweep leaves, without the
training. Tests tamper with its artifacts as anyone with write access to a shared store could. Also: a
TCP server that accepts connections and never answers (a stalled database), and the ``physmend``
command of this environment for tests that run it as a process."""

from __future__ import annotations

import socket
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest


@dataclass
class StoredTrial:
    """The user's project, the opened store and the trial's run ID."""

    project: Path
    store: Any
    run_id: str

    def artifact(self, rel: str) -> Path:
        """The file of the trial's artifact ``rel`` inside the store (sqlite: artifacts on disk)."""
        folder = Path(self.store.client.get_run(self.run_id).info.artifact_uri.removeprefix("file://"))
        return folder / rel

    def args(self) -> list[str]:
        """The user's own options for a stage loading the trial."""
        return ["--config-dir", str(self.project / "my_conf"), "model=oscillator", "data=oscillator"]

    def proposal(self, corrections: dict[str, Any]) -> str:
        """A finished propose run beside the trial (its config, model fingerprint and structure) whose
        ``corrections.yaml`` is ``corrections``: its run ID."""
        import yaml

        from physmend.tracking.fingerprint import STRUCTURE_FILE

        client = self.store.client
        tags = {k: v for k, v in client.get_run(self.run_id).data.tags.items() if k.startswith("physmend.model.")}
        run_id = client.create_run(self.store.experiment_id, tags={"physmend.stage": "propose", **tags}).info.run_id
        client.log_text(run_id, self.artifact("config.yaml").read_text(), "config.yaml")
        client.log_text(run_id, self.artifact(STRUCTURE_FILE).read_text(), STRUCTURE_FILE)
        client.log_text(run_id, yaml.safe_dump(corrections), "corrections.yaml")
        client.set_terminated(run_id)
        return run_id


@pytest.fixture
def stored_trial(user_project: Path, monkeypatch: pytest.MonkeyPatch, reset_mlflow: None) -> StoredTrial:
    """A finished trial of the oscillator (tests/conftest.py's ``user_project``) in ``mlflow.db``."""
    from omegaconf import OmegaConf

    from physmend.config import compose
    from physmend.problem import load_problem
    from physmend.tracking import open_store
    from physmend.tracking.fingerprint import STRUCTURE_FILE, fingerprint_tags
    from physmend.tracking.runs import STAGE_TAG
    from physmend.tracking.selection import PARENT_TAG, TRIAL_NUMBER_TAG, TRIAL_STATE_TAG
    from physmend.ude.artifacts import artifacts_of
    from physmend.ude.hybrid import HybridModel, HybridSpec

    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator"], user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    spec = HybridSpec(corrected=["cart.v"], in_states=["cart.x", "cart.v"], in_observed=[], in_inputs=["motor.F"],
                      in_parameters=[], widths=[4, 4], activation="tanh", mean=[0.0, 0.0, 0.0], std=[1.0, 1.0, 1.0],
                      out_scale=[1.0], estimated=["damper.c"], units="equation", rate_scale=[0.5],
                      state_low=[-1.0, -2.0], state_high=[1.0, 2.0])
    files = artifacts_of(HybridModel(problem.compiled, spec, problem.dtype), {"val.rmse": 0.1})
    store = open_store(cfg.tracking)
    client = store.client
    sweep = client.create_run(store.experiment_id, tags={STAGE_TAG: "sweep"})
    tags, structure = fingerprint_tags(cfg)
    trial = client.create_run(store.experiment_id, tags={
        STAGE_TAG: "trial", PARENT_TAG: sweep.info.run_id, TRIAL_NUMBER_TAG: "0", TRIAL_STATE_TAG: "COMPLETE", **tags})
    run_id = trial.info.run_id
    client.log_text(run_id, OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
    client.log_text(run_id, structure or "", STRUCTURE_FILE)
    for rel, content in files.items():
        if isinstance(content, bytes):
            client.log_text(run_id, "", rel)  # the folder, then the bytes in place
            StoredTrial(user_project, store, run_id).artifact(rel).write_bytes(content)
        else:
            client.log_text(run_id, content, rel)
    client.set_terminated(run_id)
    client.set_terminated(sweep.info.run_id)
    return StoredTrial(user_project, store, run_id)


@pytest.fixture
def run_cli(capsys: pytest.CaptureFixture[str]) -> Callable[..., tuple[int, str]]:
    """``main(argv)`` -> (exit status, stderr)."""
    from physmend.cli import main

    def call(*argv: str) -> tuple[int, str]:
        capsys.readouterr()
        rc = main(list(argv))
        return rc, capsys.readouterr().err

    return call


def physmend_command() -> list[str]:
    """The installed ``physmend`` command of this interpreter's environment (a real process)."""
    script = Path(sys.executable).with_name("physmend")
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "import sys; from physmend.cli import main; sys.exit(main())"]


@pytest.fixture
def silent_server() -> Iterator[int]:
    """A real TCP server on 127.0.0.1 that accepts every connection and never sends a byte (a stalled
    database, a tarpit, the wrong service): yields its port; closed at the end."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(64)
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        listener.settimeout(0.2)
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except OSError:
                continue
            held.append(conn)  # kept open, never answered

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield int(listener.getsockname()[1])
    finally:
        stop.set()
        thread.join(2)
        for conn in held:
            conn.close()
        listener.close()

"""A stage's run is ended whatever happens inside it: a Ctrl-C that lands inside a store write can
leave the write's session broken, so the error tag fails too — the run must still end KILLED (seen
as a trial left RUNNING under a loaded CI machine)."""

from __future__ import annotations

from pathlib import Path

import pytest
from omegaconf import OmegaConf


def _store(tmp_path: Path):  # noqa: ANN202
    from physmend.tracking import open_store

    return open_store(OmegaConf.create({"uri": f"sqlite:///{tmp_path / 'mlflow.db'}", "experiment": "physmend"}))


def test_interrupted_stage_ends_killed_even_when_the_error_tag_cannot_be_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import mlflow

    from physmend.tracking import stage_run

    store = _store(tmp_path)
    cfg = OmegaConf.create({"model": {"builder": "m"}, "data": {"name": "d"}})
    real_set_tag = mlflow.set_tag

    def broken(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - the session a Ctrl-C broke
        raise RuntimeError("This session's transaction has been rolled back due to a previous exception")

    holder: dict[str, str] = {}
    with pytest.raises(KeyboardInterrupt):
        with stage_run(store, cfg, stage="diagnose", source_run_id=None) as run_:
            holder["id"] = run_.run_id
            monkeypatch.setattr(mlflow, "set_tag", broken)
            raise KeyboardInterrupt
    monkeypatch.setattr(mlflow, "set_tag", real_set_tag)
    assert store.client.get_run(holder["id"]).info.status == "KILLED"
    assert mlflow.active_run() is None

    with pytest.raises(ZeroDivisionError):
        with stage_run(store, cfg, stage="diagnose", source_run_id=None) as run_:
            holder["id"] = run_.run_id
            1 / 0  # noqa: B018
    run = store.client.get_run(holder["id"])
    assert run.info.status == "FAILED" and run.data.tags["physmend.error"].startswith("ZeroDivisionError")

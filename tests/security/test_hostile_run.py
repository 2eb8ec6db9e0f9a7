"""A run in a real MLflow store is data written by someone else. A later stage that loads it by ID
builds the model only from the user's own configuration: a run whose config names a builder that
would write a file, or reads the environment, or a run made with another model (its fingerprint
differs) is refused in one line, exit 2; nothing runs, nothing the user owns changes."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import pytest
from omegaconf import OmegaConf

from physmend.cli import main

TINY = ["model=oscillator", "data=oscillator", "train.epochs=2", "train.eval_every=2", "train.step=0.1",
        "train.segment_length=5", "simulate.method=bosh3", "simulate.rtol=1e-3", "simulate.atol=1e-3",
        "sweep.progress=false", "sweep.space=small", "sweep.n_trials=1"]


pytestmark = pytest.mark.usefixtures("reset_mlflow")  # tests/conftest.py


@pytest.fixture
def swept(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Any, str]:
    """The user's project after one real (tiny) sweep trial: (project, store, trial run ID)."""
    from physmend.tracking import open_store

    monkeypatch.chdir(user_project)
    assert main(["sweep", "--config-dir", str(user_project / "my_conf"), *TINY]) == 0
    store = open_store(OmegaConf.create({"uri": f"sqlite:///{user_project / 'mlflow.db'}", "experiment": "physmend"}))
    (trial,) = store.client.search_runs([store.experiment_id], "tags.`physmend.stage` = 'trial'")
    return user_project, store, trial.info.run_id


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _mask(project: Path, run_id: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    capsys.readouterr()
    rc = main(["mask", run_id, "--config-dir", str(project / "my_conf"), "model=oscillator", "data=oscillator"])
    return rc, capsys.readouterr().err


def _rewrite_config(store: Any, run_id: str, change: Any) -> None:
    """Overwrite the run's config.yaml artifact in the store, as anyone with write access could."""
    from physmend.tracking import download_artifact

    raw = OmegaConf.to_container(OmegaConf.load(download_artifact(store, run_id, "config.yaml")), resolve=False)
    change(raw)
    folder = Path(store.client.get_run(run_id).info.artifact_uri.removeprefix("file://"))
    (folder / "config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(raw)))


def test_the_fingerprint_is_recorded_on_the_run(swept: tuple[Path, Any, str]) -> None:
    from physmend.tracking import download_artifact

    _, store, run_id = swept
    tags = store.client.get_run(run_id).data.tags
    assert len(tags["physmend.model.structure"]) == 64 and len(tags["physmend.model.source"]) == 64
    text = download_artifact(store, run_id, "model_structure.txt").read_text()
    assert hashlib.sha256(text.encode()).hexdigest() == tags["physmend.model.structure"]
    assert '"eq", "spring"' in text and '"var", "damper.c", "parameter"' in text


def test_a_stored_builder_that_would_write_a_file_is_never_imported(swept: tuple[Path, Any, str],
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    project, store, run_id = swept
    marker = project / "pwned"
    evil = project / "evil.py"
    evil.write_text(f"import pathlib\npathlib.Path({str(marker)!r}).write_text('x')\ndef build():\n    return None\n")
    _rewrite_config(store, run_id, lambda raw: raw["model"].__setitem__("builder", f"{evil}:build"))
    before = _digest(project)
    rc, err = _mask(project, run_id, capsys)
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "was made with another model configuration (model.builder" in err and "evil.py" in err
    assert not marker.exists()
    assert _digest(project) == before  # the store gained no run, the user's files are as they were


def test_a_stored_environment_interpolation_is_never_resolved(swept: tuple[Path, Any, str],
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    project, store, run_id = swept
    _rewrite_config(store, run_id, lambda raw: raw["train"].__setitem__("lr", "${oc.env:HOME}"))
    before = _digest(project)
    rc, err = _mask(project, run_id, capsys)
    assert rc == 2, err
    assert "holds an interpolation at train.lr ('${oc.env:HOME}')" in err and "never resolved" in err
    assert len(err.strip().splitlines()) == 1
    import os

    assert os.environ.get("HOME", "/") not in err.replace("${oc.env:HOME}", "")
    assert _digest(project) == before


def test_a_run_made_with_another_model_is_refused_by_its_fingerprint(swept: tuple[Path, Any, str],
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    project, store, run_id = swept
    model_file = project / "oscillator.py"
    original = model_file.read_text()
    model_file.write_text(original.replace("m.equation(f_spring, k * x", "m.equation(f_spring, k * x + 0.1 * x**3"))
    before = _digest(project)
    rc, err = _mask(project, run_id, capsys)
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert f"run {run_id!r} was made with another model" in err and "equation 4 (of spring)" in err
    assert _digest(project) == before


def test_an_edited_comment_is_a_note_not_an_error(swept: tuple[Path, Any, str], capsys: pytest.CaptureFixture[str]) -> None:
    from physmend.config import compose
    from physmend.problem import load_problem
    from physmend.tracking.fingerprint import check_same_model

    project, store, run_id = swept
    model_file = project / "oscillator.py"
    model_file.write_text(model_file.read_text() + "\n# calibrated on the spring bench, 2026\n")
    cfg = compose(["model=oscillator", "data=oscillator"], user_config_dir=project / "my_conf")
    load_problem(cfg)
    capsys.readouterr()
    check_same_model(store, store.client.get_run(run_id), cfg)  # no error: the same equations
    assert "the model file changed since run" in capsys.readouterr().err
    model_file.write_text(model_file.read_text().replace('unit="N/m"', 'unit="kN/m"'))
    load_problem(cfg)
    from physmend.tracking import TrackingError

    with pytest.raises(TrackingError, match=r"variable 'spring\.k' is declared differently"):
        check_same_model(store, store.client.get_run(run_id), cfg)

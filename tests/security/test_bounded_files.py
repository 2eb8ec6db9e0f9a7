"""Small hostile files that used to hang physmend, exhaust its memory or end in a traceback: each is
refused within seconds in one short line, and ``accept`` writes only inside ``decide.output_dir``."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import yaml

from physmend.config import compose
from physmend.modeling import ModelError, apply_corrections, load_model, read_corrections
from physmend.modeling.safe_yaml import loads_bounded
from physmend.tracking import TrackingError

BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{b}: &{b} [*{a}, *{a}, *{a}, *{a}, *{a}, *{a}, *{a}, *{a}, *{a}]\n" for a, b in zip("abcdefgh", "bcdefghi"))

TERMS = {
    "tower": "0*((((((9**64)**64)**64)**64)**64)**64)",
    "symbolic exponent": "zone1.air.T**exp(exp(exp(100)))",
    "unary minus": "-" * 1500 + "zone1.air.T",
    "long chain": "zone1.air.T+" * 1200 + "zone1.air.T",
    "parentheses": "(" * 5000 + "zone1.air.T" + ")" * 5000,
    "one megabyte": "zone1.air.T+" * 90_000 + "1",
}


def _corrections(tmp_path: Path, term_yaml: str, constants: str = "{}") -> Path:
    path = tmp_path / "corrections.yaml"
    path.write_text("physmend_corrections: 1\nmodel: cargo_box\ncorrections:\n"
                    f"  - state: zone1.air.T\n    term: {term_yaml}\n    unit: W\n    constants: {constants}\n")
    return path


@pytest.mark.parametrize("name", list(TERMS))
def test_a_hostile_term_is_one_short_line_within_seconds(tmp_path: Path, name: str) -> None:
    model = load_model(str(compose([]).model.builder))
    path = _corrections(tmp_path, repr(TERMS[name]))
    start = time.perf_counter()
    with pytest.raises(ModelError) as err:
        items, _ = read_corrections(path)
        apply_corrections(model, items, where=str(path))
    message = str(err.value)
    assert time.perf_counter() - start < 10
    assert "\n" not in message and len(message) <= 300, message


def test_a_yaml_alias_bomb_is_refused_before_it_expands(tmp_path: Path) -> None:
    path = tmp_path / "corrections.yaml"
    path.write_text("physmend_corrections: 1\nmodel: cargo_box\n" + BOMB
                    + "corrections:\n  - state: zone1.air.T\n    term: *i\n")
    start = time.perf_counter()
    with pytest.raises(ModelError, match="alias"):
        read_corrections(path)
    assert time.perf_counter() - start < 2
    with pytest.raises(TrackingError, match="aliases are refused"):
        loads_bounded(BOMB, TrackingError, where="run 'x': config.yaml")


def test_constants_that_are_not_numbers_are_one_line(tmp_path: Path) -> None:
    path = _corrections(tmp_path, "'c1*zone1.air.T'", "{c1: abc}")
    with pytest.raises(ModelError, match=r"constants\.'c1' must be a number, but is 'abc'"):
        read_corrections(path)


def test_a_python_tag_in_a_stored_config_is_one_line(tmp_path: Path) -> None:
    from physmend.tracking.stored_config import read_stored_config

    path = tmp_path / "config.yaml"
    path.write_text("seed: !!python/object/apply:os.system ['touch pwned']\n")
    with pytest.raises(TrackingError) as err:
        read_stored_config(path, "abc123")
    assert "\n" not in str(err.value) and "run 'abc123': config.yaml" in str(err.value)
    assert not (tmp_path / "pwned").exists()


@pytest.mark.parametrize("name", ["/elsewhere/evil", "../../x", "a/b"])
def test_accept_never_writes_outside_its_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str,
                                                reset_mlflow: None) -> None:
    """A proposal in a real store whose corrections.yaml names a path as its model."""
    import mlflow
    from omegaconf import OmegaConf

    from physmend.stages.decide import accept
    from physmend.tracking import open_store

    monkeypatch.chdir(tmp_path)
    store = open_store(OmegaConf.create({"uri": f"sqlite:///{tmp_path / 'mlflow.db'}", "experiment": "physmend"}))
    run = store.client.create_run(store.experiment_id, tags={"physmend.stage": "propose"})
    folder = tmp_path / "upload"
    folder.mkdir()
    (folder / "corrections.yaml").write_text(yaml.safe_dump(
        {"physmend_corrections": 1, "model": name, "corrections": [{"state": "zone1.air.T", "term": "1.0"}]}))
    store.client.log_artifact(run.info.run_id, str(folder / "corrections.yaml"))
    store.client.set_terminated(run.info.run_id)
    cfg = compose([f"tracking.uri=sqlite:///{tmp_path / 'mlflow.db'}", f"decide.output_dir={tmp_path / 'accepted'}"])
    before = {p for p in tmp_path.parent.rglob("*")}
    with pytest.raises(TrackingError, match="never a path"):
        accept(cfg, run.info.run_id)
    assert not (tmp_path / "accepted").exists()
    assert {p for p in tmp_path.parent.rglob("*")} - before <= {p for p in tmp_path.rglob("*")}
    assert "physmend.decision" not in store.client.get_run(run.info.run_id).data.tags
    mlflow.set_tracking_uri(None)


def test_a_password_with_quotes_is_redacted_and_store_text_cannot_drive_the_terminal() -> None:
    from physmend.redact import printable, redact

    assert "se'cretQ" not in redact("store postgresql://bob:se'cretQ@db.example/physmend is unreachable")
    assert "bob:***@db.example" in redact("postgresql://bob:se'cretQ@db.example/physmend")
    shown = printable("trial 3 \x1b]0;owned\x07\x1b[2J failed\tnext\n")
    assert "\x1b" not in shown and "\x07" not in shown and "\\x1b" in shown and "\tnext\n" in shown

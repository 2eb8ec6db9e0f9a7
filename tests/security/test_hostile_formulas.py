"""Formulas from corrections files, stored Pareto fronts and catalogues are data: hostile text is
refused in one clear line and nothing in it runs (the tests check that the file it would write was
not written)."""

from __future__ import annotations

from pathlib import Path

import pytest

from physmend.config import compose
from physmend.explain.catalogue import CatalogueError, load_catalogue
from physmend.modeling import ModelError, apply_corrections, load_model, read_corrections
from physmend.symbolic import SymbolicError
from physmend.symbolic._front import Candidate

HOSTILE = [
    "__import__('os').system('touch {marker}')",
    "(lambda: __import__('os').system('touch {marker}'))()",
    "().__class__.__base__.__subclasses__()",
    "open('{marker}', 'w').write('x')",
    "9**9**9",
    "zone1.air.T**(10**10)",
    "[c for c in ()]",
]


@pytest.mark.parametrize("text", HOSTILE)
def test_a_hostile_corrections_file_is_refused_and_runs_nothing(tmp_path: Path, text: str) -> None:
    marker = tmp_path / "pwned"
    term = text.format(marker=marker)
    path = tmp_path / "corrections.yaml"
    path.write_text("physmend_corrections: 1\nmodel: cargo_box\ncorrections:\n"
                    f"  - state: zone1.air.T\n    term: {term!r}\n    unit: W\n    constants: {{}}\n")
    model = load_model(str(compose([]).model.builder))
    with pytest.raises(ModelError) as err:
        items, _ = read_corrections(path)
        apply_corrections(model, items, where=str(path))
    message = str(err.value)
    assert "\n" not in message and ("not allowed in a formula" in message or "not a known variable" in message
                                    or "not a valid formula" in message), message
    assert not marker.exists()


@pytest.mark.parametrize("text", HOSTILE)
def test_a_hostile_stored_front_is_refused(tmp_path: Path, text: str) -> None:
    marker = tmp_path / "pwned"
    with pytest.raises(SymbolicError, match="candidate 'expr' must be a sympy srepr string"):
        Candidate.from_dict({"expr": text.format(marker=marker), "complexity": 3, "mse": 0.1, "r2": 0.9, "text": "x"})
    assert not marker.exists()


def test_a_hostile_catalogue_template_is_refused(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "mechanisms.yaml"
    path.write_text("version: 1\nmechanisms:\n  - id: evil\n    name: evil\n"
                    f"    template: \"__import__('os').system('touch {marker}')\"\n    explanation: x\n")
    with pytest.raises(CatalogueError, match="template must be a sympy expression"):
        load_catalogue(path)
    assert not marker.exists()


def test_stored_formulas_still_read_back() -> None:
    import sympy as sp

    x, y = sp.Symbol("zone1.air.T"), sp.Symbol("zone2.air.T")
    expr = sp.Float(1.02) * (x - y) * sp.sqrt(sp.Abs(x - y)) + sp.Max(x, 3) - sp.sign(y) * sp.exp(-x)
    back = Candidate.from_dict({"expr": sp.srepr(expr), "complexity": 9, "mse": 0.1, "r2": 0.9, "text": "t"}).expr
    assert sp.simplify(back - expr) == 0


def test_a_stored_config_is_data(tmp_path: Path) -> None:
    """A run's config.yaml naming a builder that would write a file, or reading the environment:
    the user's own model configuration is used (or the difference is a clear error), nothing runs,
    and an interpolation is refused, not resolved."""
    from omegaconf import OmegaConf

    from physmend.tracking import TrackingError
    from physmend.tracking.stored_config import read_stored_config

    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.py"
    evil.write_text(f"import pathlib\npathlib.Path({str(marker)!r}).write_text('x')\ndef build():\n    return None\n")
    current = compose([])
    stored = OmegaConf.to_container(current, resolve=True)
    stored["model"]["builder"] = f"{evil}:build"
    path = tmp_path / "config.yaml"
    path.write_text(OmegaConf.to_yaml(OmegaConf.create(stored)))
    with pytest.raises(TrackingError, match=r"run 'r1' was made with another model configuration \(model.builder: "):
        read_stored_config(path, "r1", current)
    assert not marker.exists()
    stored["model"] = OmegaConf.to_container(current.model, resolve=True)
    stored["train"]["lr"] = "${oc.env:HOME}"
    path.write_text(OmegaConf.to_yaml(OmegaConf.create(stored)))
    with pytest.raises(TrackingError, match=r"holds an interpolation at train.lr \('\$\{oc.env:HOME\}'\); a stored "
                                           r"configuration is data and is never resolved"):
        read_stored_config(path, "r1", current)
    stored["train"]["lr"] = 0.01
    path.write_text(OmegaConf.to_yaml(OmegaConf.create(stored)))
    assert read_stored_config(path, "r1", current).model.builder == current.model.builder

"""A model built again with the same equations is not simplified and compiled again; an edited
model file is (every stage of ``physmend discover`` loads the user's model)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physmend.config import compose
from physmend.problem import load_problem


def test_the_same_model_is_compiled_once_and_an_edited_one_again(user_project: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator"], user_config_dir=user_project / "my_conf")
    first = load_problem(cfg)
    again = load_problem(cfg)
    assert again.compiled is first.compiled and again.model is first.model
    assert again.experiments is not first.experiments  # the data are read again: only the model is kept
    source = user_project / "oscillator.py"
    text = source.read_text()
    assert "m.equation(f_spring, k * x" in text
    source.write_text(text.replace("m.equation(f_spring, k * x", "m.equation(f_spring, 2 * k * x"))  # the user edits an equation
    edited = load_problem(cfg)
    assert edited.compiled is not first.compiled
    u = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
    x = torch.zeros(1, len(first.compiled.input_names), dtype=torch.float64)
    p = first.compiled.default_parameters()[None]
    assert not torch.equal(edited.compiled.rhs(u, x, p), first.compiled.rhs(u, x, p))
    source.write_text(text)  # back as it was: the first compilation again, with its numbers
    back = load_problem(cfg)
    assert torch.equal(back.compiled.rhs(u, x, p), first.compiled.rhs(u, x, p))

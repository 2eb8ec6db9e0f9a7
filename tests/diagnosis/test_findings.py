"""The diagnosis as a library call (:func:`physmend.diagnosis.diagnose`): what it finds on a user's
model, without a store, and its small rules on their own."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sympy as sp

from physmend.config import compose
from physmend.diagnosis import Diagnosis, diagnose
from physmend.diagnosis.analysis import interval, redundant_observed
from physmend.problem import load_problem


def test_the_diagnosis_of_a_user_model_is_found_without_writing_anything(user_project: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator"], user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    shown: list[str] = []

    def progress(what: str):  # noqa: ANN202
        from contextlib import nullcontext

        shown.append(what)
        return nullcontext()

    found = diagnose(problem, cfg, progress=progress)
    assert isinstance(found, Diagnosis) and not found.diverged
    assert shown == ["diagnose: simulating 3 experiments as written", "diagnose: locating the mismatch"]
    fits = found.analysis["fits"]
    assert [(f["experiment"], f["output"]) for f in fits] == [(e.id, o) for e in problem.experiments
                                                              for o in problem.model.output_names]
    assert found.analysis["fit_experiments"] == [e.id for e in problem.experiments if e.role in ("train", "validation")]
    assert found.summary.startswith("# physmend diagnose — model `oscillator`, data `oscillator`")
    assert "The model misses the recordings" in found.summary
    metrics = found.metrics()
    assert metrics["max_rmse_to_noise"] == max(f["ratio_to_noise"] for f in fits) and all(np.isfinite(list(metrics.values())))
    assert found.description().startswith("The model as written misses by up to ")  # type: ignore[union-attr]
    assert found.t.shape[0] == found.traj.outputs.shape[0]
    assert not (user_project / "mlflow.db").exists()


def test_the_sampling_interval_is_the_median_gap() -> None:
    assert interval(np.array([0.0, 1.0, 2.0, 4.0])) == 1.0
    assert interval(np.array([3.0])) == 0.0


def test_observed_variables_that_repeat_another_are_not_correlates() -> None:
    from types import SimpleNamespace

    x, u, k, q = sp.symbols("x u k q")
    model = SimpleNamespace(states=[SimpleNamespace(symbol=x)], inputs=[SimpleNamespace(symbol=u)],
                            parameters=[SimpleNamespace(symbol=k)],
                            observed={"a": x, "b": -u, "c": 2 * k, "d": k * x * q, "e": -k * x * q, "f": x + u})
    assert redundant_observed(model) == {"a", "b", "c", "e"}

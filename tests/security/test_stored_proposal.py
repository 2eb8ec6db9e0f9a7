"""A proposal read back from a shared store is data: ``physmend export`` and ``physmend accept`` of a
proposal whose ``corrections.yaml`` holds a term that would hang sympy (the 9**64 tower) refuse it in
one line naming the proposal's run and file — not a temporary copy of it — exit 2, within seconds,
and write nothing."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import pytest

from .conftest import StoredTrial
from .test_bounded_files import TERMS

Cli = Callable[..., tuple[int, str]]
TOWER = {"physmend_corrections": 1, "model": "oscillator",
         "corrections": [{"state": "cart.v", "term": TERMS["tower"], "unit": "N", "constants": {}}]}


@pytest.mark.parametrize("stage", ["export", "accept"])
def test_a_hostile_proposal_is_one_line_naming_its_run(stage: str, stored_trial: StoredTrial, tmp_path: Path,
                                                       run_cli: Cli) -> None:
    run_id = stored_trial.proposal(TOWER)
    out = tmp_path / "out"
    start = time.perf_counter()
    rc, err = run_cli(stage, run_id, *stored_trial.args(), f"export.output_dir={out}", f"decide.output_dir={out}")
    assert time.perf_counter() - start < 10
    assert rc == 2, err
    line = err.strip()
    assert "\n" not in line and "Traceback" not in line and len(line) <= 300, line
    assert f"proposal {run_id!r}: corrections.yaml" in line, line
    assert "is not allowed in a formula" in line and "/tmp" not in line.split("corrections.yaml")[0], line
    assert not out.exists()
    assert "physmend.decision" not in stored_trial.store.client.get_run(run_id).data.tags

"""Writing a proposal's files (:mod:`physmend.proposal.files`): never over an existing file, nothing
of a failing call left behind, and the printed list of what was written."""

from __future__ import annotations

from pathlib import Path

import pytest

from physmend.modeling.errors import ModelError
from physmend.proposal.files import report, write_new


def test_files_are_written_beside_each_other_and_never_over_an_existing_one(tmp_path: Path) -> None:
    out = tmp_path / "out"
    targets = {"python": out / "m.py", "petab": out / "m.petab", "network": out / "m.network.json"}
    write_new({"python": "x = 1\n", "petab": {"problem.yaml": "a: 1\n"},
               "network": {"m.network.json": "{}", "m.network.safetensors": b"\0"}}, targets, out)
    assert (out / "m.py").read_text() == "x = 1\n" and (out / "m.petab" / "problem.yaml").is_file()
    assert (out / "m.network.safetensors").read_bytes() == b"\0"
    other = {"latex": tmp_path / "out2" / "m.tex", "python": out / "m.py"}
    with pytest.raises(ModelError, match="export.output_dir: cannot write"):
        write_new({"latex": "doc", "python": "y = 2\n"}, other, tmp_path / "out2")
    assert not (tmp_path / "out2" / "m.tex").exists() and (out / "m.py").read_text() == "x = 1\n"


def test_the_report_lists_each_format_and_how_to_use_the_module(tmp_path: Path) -> None:
    targets = {"python": tmp_path / "m.py", "network": tmp_path / "m.network.json"}
    text = report("RUN", "box", ["box.T"], ["python", "network"], targets, "m")
    lines = text.splitlines()
    assert lines[0] == "# physmend export — proposal RUN, model box: box.T corrected"
    assert lines[1] == f"  python  {tmp_path / 'm.py'}"
    assert lines[2] == f"  network {tmp_path / 'm.network.json'} + m.network.safetensors"
    assert lines[3].startswith("use: import m; scipy.integrate.solve_ivp(")

"""examples/quickstart.ipynb runs top to bottom (nbclient, a real kernel, a real store in a temporary
folder) and shows the formula, the fit table and a plot; its outputs are not committed."""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[2] / "examples" / "quickstart.ipynb"


def _outputs(nb) -> list[dict]:  # noqa: ANN001
    return [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]


def test_the_notebook_is_committed_without_outputs() -> None:
    import nbformat

    nb = nbformat.read(NOTEBOOK, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code)


@pytest.mark.slow
def test_the_quickstart_notebook_runs_and_shows_formula_fit_and_plot(tmp_path: Path) -> None:
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(NOTEBOOK, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = _outputs(nb)
    errors = [o for o in outputs if o.output_type == "error"]
    assert not errors, errors
    data = [o.get("data", {}) for o in outputs if o.output_type in ("execute_result", "display_data")]
    html = "\n".join(d.get("text/html", "") for d in data)
    text = "\n".join(d.get("text/plain", "") for d in data)
    assert "reactor.A*reactor.B" in text and "reactor.A*reactor.B" in html  # the formula, both equations
    assert "<table" in html and "improvement" in html  # the fit table
    assert "data:image/png;base64," in html and any("image/png" in d for d in data)  # plots, inline and a figure
    assert list((tmp_path / "corrections").glob("cstr-*.yaml")) and list((tmp_path / "exports").glob("cstr_*.tex"))
    assert (tmp_path / "mlflow.db").is_file()

"""What ``physmend export`` writes for a reviewer, from a corrected model built here (no store, no
training): a standalone LaTeX document with the found term marked, readable names and constants
with units and standard errors (compiled where ``pdflatex`` exists); ``sympy.json`` constants with
units; a PEtab problem that PEtab's own linter accepts; the network in PEtab-SciML's layout with
safetensors weights that reproduce the network's output."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import sympy as sp

from physmend.modeling import Model
from physmend.modeling.constant_units import constant_unit
from physmend.modeling.corrections import Correction, apply_corrections
from physmend.modeling.export import sympy_json
from physmend.modeling.latex import found_terms, latex_document, tex_name, tex_unit

CORRECTION = Correction(state="cart.v", term="c1*cart.v*Abs(cart.v)", constants={"c1": -0.9}, unit="N")


def _model() -> Model:
    m = Model("oscillator", description="mass on a spring with a viscous damper")
    x = m.state("cart.x", start=m.parameter("cart.x0", 0.0, unit="m"), unit="m")
    v = m.state("cart.v", start=0.0, unit="m/s")
    mass = m.parameter("cart.mass", 2.0, unit="kg")
    k = m.parameter("spring.k", 8.0, unit="N/m")
    c = m.parameter("damper.c", 0.4, unit="N.s/m", uncertain=True, bounds=(0.0, 5.0))
    force = m.input("motor.F", unit="N")
    f_net = m.variable("cart.F_net", unit="N")
    m.equation(m.der(x), v, owner="cart")
    m.equation(mass * m.der(v), f_net, owner="cart")
    m.equation(f_net, force - k * x - c * v, owner="cart")
    m.output("cart.x", x, unit="m")
    return m


@pytest.fixture
def corrected() -> tuple[object, dict[str, sp.Expr], dict[str, dict[str, object]]]:
    sm = apply_corrections(_model(), [CORRECTION]).simplify()
    terms = found_terms(sm, [CORRECTION])
    units = {v.name: v.unit for v in sm.states + sm.inputs + sm.parameters if v.unit}
    symbol = next(v.symbol for v in sm.parameters if v.name == "cart.v_c1")
    constants = {"cart.v_c1": {"state": "cart.v", "name": "c1", "value": -0.9, "stderr": 0.012,
                               "unit": constant_unit(terms["cart.v"], symbol, "N", units)}}
    return sm, terms, constants


def test_names_and_units_read_as_in_a_paper() -> None:
    assert tex_name("cart.v") == r"v_{\mathrm{cart}}"
    assert tex_name("zone1.air.Q_flow") == r"Q_{\mathrm{flow},\mathrm{zone1},\mathrm{air}}"
    assert tex_name("pendulum.theta") == r"\theta_{\mathrm{pendulum}}" and tex_name("cart.x0") == r"x_{0,\mathrm{cart}}"
    assert tex_name("walls.UA") == r"\mathrm{UA}_{\mathrm{walls}}"
    assert tex_unit("J/(kg.K)") == r"\mathrm{J/(kg\cdot K)}" and tex_unit("m3/s") == r"\mathrm{m^{3}/s}"


def test_the_latex_export_is_a_standalone_document_with_the_found_term_marked(corrected) -> None:  # noqa: ANN001
    sm, terms, constants = corrected
    assert constants["cart.v_c1"]["unit"] == "kg/m"  # N / (m/s)^2: the drag coefficient's unit
    doc = latex_document(sm, terms, constants, {"source_run_id": "abc123", "time_unit": "s"})
    body = [line for line in doc.splitlines() if not line.startswith("%")]
    assert body[0].startswith(r"\documentclass") and r"\begin{document}" in doc and body[-1] == r"\end{document}"
    for env in ("document", "align*", "tabular", "longtable"):
        assert doc.count(rf"\begin{{{env}}}") == doc.count(rf"\end{{{env}}}") >= 1, env
    assert doc.count("{") == doc.count("}")
    # the found term, coloured and marked, added to the equation as the user wrote it
    row = next(line for line in doc.splitlines() if r"\text{found term}" in line)
    assert row.lstrip().startswith(r"\mathrm{mass}_{\mathrm{cart}} \cdot \frac{d\,v_{\mathrm{cart}}}{dt} &=")
    found = row.split(r"\underbrace{\textcolor{found}{", 1)[1].split(r"}}_{\text{found term}}")[0]
    assert sorted(found.split(r" \cdot ")) == sorted([r"c_{1}", r"v_{\mathrm{cart}}", r"\left|{v_{\mathrm{cart}}}\right|"]), found
    assert r"F_{\mathrm{net},\mathrm{cart}}" in row  # the original right-hand side, kept
    # readable names, never a dotted name set upright
    assert not re.search(r"\\mathrm\{[a-z]+\.[a-z]", doc.split(r"\subsection*{Symbols}")[0]), doc
    # the constant with its standard error and unit
    assert r"$c_{1}$ & $-0.9 \pm 0.012$ & $\mathrm{kg/m}$ & $v_{\mathrm{cart}}$ \\" in doc
    assert r"\texttt{cart.v\_c1}" in doc  # the symbol table maps it back to the model's name


@pytest.mark.skipif(shutil.which("pdflatex") is None, reason="pdflatex is not installed (the structure is checked above)")
def test_the_latex_export_compiles(corrected, tmp_path: Path) -> None:  # noqa: ANN001
    sm, terms, constants = corrected
    doc = latex_document(sm, terms, constants, {"source_run_id": "abc123", "time_unit": "s"})
    (tmp_path / "model.tex").write_text(doc)
    done = subprocess.run(["pdflatex", "-interaction=nonstopmode", "-halt-on-error", "model.tex"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and (tmp_path / "model.pdf").stat().st_size > 1000, done.stdout[-3000:]


def test_sympy_json_constants_carry_units(corrected) -> None:  # noqa: ANN001
    sm, _, constants = corrected
    doc = json.loads(sympy_json(sm, ["cart.v"], {"source_run_id": "abc123"}, constants))
    assert doc["constants"]["cart.v_c1"] == {"state": "cart.v", "name": "c1", "value": -0.9, "stderr": 0.012, "unit": "kg/m"}
    assert next(p for p in doc["parameters"] if p["name"] == "cart.v_c1")["unit"] == "kg/m"


def test_the_petab_export_passes_petabs_own_linter(corrected, tmp_path: Path) -> None:  # noqa: ANN001
    pytest.importorskip("libsbml", reason="python-libsbml is part of the test extra")
    petab = pytest.importorskip("petab", reason="petab is part of the test extra (pip install -e '.[test]')")
    from petab import lint

    from physmend.modeling.petab import petab_files

    sm, _, _ = corrected
    t = np.linspace(0.0, 10.0, 21)
    records = [{"id": f"run{k}", "role": role, "initial": {"cart.x": x0, "cart.v": 0.0}, "parameters": {"cart.x0": x0},
                "obs_time": t, "obs": np.sin(t + k)[:, None], "inputs": {"motor.F": (t, np.cos(t))}}
               for k, (x0, role) in enumerate([(0.5, "train"), (-0.3, "test")], 1)]
    files = petab_files(sm, records, {"damper.c": (0.0, 5.0), "cart.v_c1": (-9.0, 9.0)}, {"cart.x": 0.01})
    folder = tmp_path / "problem.petab"
    folder.mkdir()
    for name, text in files.items():
        (folder / name).write_text(text)
    # petab 0.1 (the last without an ANTLR 4.13 runtime, which omegaconf's 4.9 pin excludes) reads its
    # tables with the string type pandas had before 3.0
    with pd.option_context("future.infer_string", False):
        problem = petab.Problem.from_yaml(str(folder / "problem.yaml"))
        assert lint.lint_problem(problem) is False  # False: no error found
        # the linter is no formality: a measurement of an observable nobody defined is an error
        broken = problem.measurement_df.copy()
        broken.loc[0, "observableId"] = "nobody"
        problem.measurement_df = broken
        assert lint.lint_problem(problem) is True

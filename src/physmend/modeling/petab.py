"""A corrected model and its recordings as a PEtab problem (format version 1): an SBML model,
condition, measurement, observable and parameter tables, and the YAML file that ties them.

PEtab is the exchange format of parameter-estimation tools (AMICI, pyPESTO, PEtab.jl, COPASI,
Data2Dynamics); an accepted model written as one can be re-fitted, simulated or profiled there.
How physmend's pieces map onto it:

- **states** are SBML species (amounts in a unit compartment) whose derivative is an SBML rate rule:
  the model's explicit derivative with the corrections in it. Each experiment's initial states are
  its condition's species values, as physmend simulates them.
- **recorded inputs** are SBML parameters set by assignment rules: the linear interpolation of
  each experiment's samples (the end values held outside them), exactly as physmend drives the
  model, written as a balanced tree of ``piecewise`` so a solver finds the interval in
  ``log₂(samples)`` comparisons. A constant parameter ``physmend_experiment`` (the experiment's
  number, set by its condition) picks the experiment's series.
- **parameters**: those that differ between experiments are condition-table columns; the rest are
  in the parameter table — the declared uncertain ones and the corrections' constants estimated
  (bounds: the declared ones; a constant's ±10× its value), every other fixed.
- **measurements**: every finite recorded sample of every output, ``datasetId`` the experiment's
  role (train, validation, test); each output's noise σ from the records' second differences.

SBML identifiers are the model's names with every character that is not a letter, digit or
underscore replaced by ``_`` (the original name is each element's ``name``). Times are in the
model's time unit, from each record's start. Writing needs ``python-libsbml`` (``pip install
'physmend[petab]'``); a model function SBML cannot express is a clear error naming it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import sympy as sp

from physmend.modeling.errors import ModelError

#: files of an exported problem, inside its folder
FILES = {"yaml": "problem.yaml", "sbml": "model.xml", "conditions": "conditions.tsv",
         "measurements": "measurements.tsv", "observables": "observables.tsv", "parameters": "parameters.tsv"}
#: the condition parameter that picks an experiment's recorded inputs
EXPERIMENT_PARAMETER = "physmend_experiment"


def unavailable_reason() -> str | None:
    """Why PEtab cannot be written here (``None`` where ``python-libsbml`` imports)."""
    try:
        import libsbml  # noqa: F401
    except ImportError:
        return ("export.format=petab needs python-libsbml, which is not installed: pip install 'physmend[petab]' "
                "(the other formats need nothing more)")
    return None


def sbml_id(name: str) -> str:
    """An SBML/PEtab identifier for ``name`` (letters, digits, underscores; not starting with a digit)."""
    out = re.sub(r"\W", "_", name, flags=re.ASCII)
    return f"_{out}" if not out or out[0].isdigit() else out


def _num(x: float) -> str:
    if not math.isfinite(x):
        raise ModelError(f"export.format=petab: a value {x!r} is not a finite number")
    return repr(float(x))


def l3(expr: sp.Basic, ids: Mapping[str, str]) -> str:
    """``expr`` in SBML's Level 3 infix syntax (``libsbml.parseL3Formula``), symbols renamed by ``ids``."""

    def go(e: sp.Basic) -> str:
        if isinstance(e, sp.Symbol):
            if e.name not in ids:
                raise ModelError(f"export.format=petab: {e.name!r} is neither a state, an input nor a parameter")
            return ids[e.name]
        if isinstance(e, sp.Integer):
            return str(int(e))
        if isinstance(e, sp.Rational):
            return f"({int(e.p)}/{int(e.q)})"
        if isinstance(e, (sp.Float, sp.Number)):
            return _num(float(e))
        if e == sp.pi:
            return "pi"
        if e == sp.E:
            return "exponentiale"
        if isinstance(e, sp.Add):
            return "(" + " + ".join(go(a) for a in e.args) + ")"
        if isinstance(e, sp.Mul):
            return "(" + " * ".join(go(a) for a in e.args) + ")"
        if isinstance(e, sp.Pow):
            base, exp = e.args
            if exp == sp.Rational(1, 2):
                return f"sqrt({go(base)})"
            if exp == -1:
                return f"(1 / {go(base)})"
            return f"pow({go(base)}, {go(exp)})"
        if isinstance(e, sp.exp):
            return f"exp({go(e.args[0])})"
        if isinstance(e, sp.log):
            return f"ln({go(e.args[0])})"
        if isinstance(e, sp.Abs):
            return f"abs({go(e.args[0])})"
        if isinstance(e, sp.sign):
            a = go(e.args[0])
            return f"piecewise(1, {a} > 0, -1, {a} < 0, 0)"
        if isinstance(e, sp.Heaviside):
            a = go(e.args[0])
            return f"piecewise(1, {a} > 0, 0)"
        if isinstance(e, (sp.Min, sp.Max)):
            return f"{'min' if isinstance(e, sp.Min) else 'max'}({', '.join(go(a) for a in e.args)})"
        if isinstance(e, sp.Piecewise):
            parts = []
            for value, cond in e.args:
                if cond == sp.true:
                    parts.append(go(value))
                    break
                parts += [go(value), go(cond)]
            else:
                parts.append("0")
            return f"piecewise({', '.join(parts)})"
        if isinstance(e, sp.core.relational.Relational):
            return f"({go(e.lhs)} {e.rel_op} {go(e.rhs)})"
        named = {sp.sin: "sin", sp.cos: "cos", sp.tan: "tan", sp.tanh: "tanh", sp.sinh: "sinh", sp.cosh: "cosh",
                 sp.atan: "arctan", sp.asin: "arcsin", sp.acos: "arccos"}
        for fn, text in named.items():
            if isinstance(e, fn):
                return f"{text}({go(e.args[0])})"
        raise ModelError(f"export.format=petab: SBML has no function for {type(e).__name__} (in {e}); "
                         "choose another export.format")

    return go(expr)


def interpolation(t: np.ndarray, v: np.ndarray, time: str = "time") -> str:
    """Linear interpolation of samples ``v (n,)`` at times ``t (n,)`` (increasing), end values held,
    as a balanced tree of SBML ``piecewise`` (Level 3 infix)."""
    keep = [0]  # knots on the line through their neighbours add nothing: left out (exactly the same function)
    for i in range(1, t.size - 1):
        a = keep[-1]
        on_line = v[a] + (v[i + 1] - v[a]) * (t[i] - t[a]) / (t[i + 1] - t[a])
        if abs(v[i] - on_line) > 1e-12 * max(1.0, abs(v[i])):
            keep.append(i)
    keep.append(t.size - 1)
    t, v = t[keep], v[keep]
    if t.size == 1:
        return _num(v[0])

    def segment(k: int) -> str:
        slope = (v[k + 1] - v[k]) / (t[k + 1] - t[k])
        return f"({_num(v[k])} + {_num(slope)} * ({time} - {_num(t[k])}))" if slope != 0 else _num(v[k])

    def tree(lo: int, hi: int) -> str:  # segments lo..hi-1 (segment k spans t[k]..t[k+1])
        if hi - lo == 1:
            return segment(lo)
        mid = (lo + hi) // 2
        return f"piecewise({tree(lo, mid)}, {time} < {_num(t[mid])}, {tree(mid, hi)})"

    inner = tree(0, t.size - 1)
    return f"piecewise({_num(v[0])}, {time} < {_num(t[0])}, {_num(v[-1])}, {time} >= {_num(t[-1])}, {inner})"


def _math(formula: str, what: str) -> Any:
    import libsbml

    ast = libsbml.parseL3Formula(formula)
    if ast is None:
        raise ModelError(f"export.format=petab: the {what} cannot be written in SBML: {libsbml.getLastParseL3Error()}")
    return ast


def sbml_text(sm: Any, experiments: Sequence[Mapping[str, Any]], ids: Mapping[str, str]) -> str:
    """The SBML (Level 3 Version 2) document of corrected model ``sm`` with the recorded inputs of
    ``experiments`` (each: ``inputs`` name -> (time, values)), identifiers ``ids``."""
    import libsbml

    doc = libsbml.SBMLDocument(3, 2)
    model = doc.createModel()
    model.setId(sbml_id(sm.name))
    model.setName(sm.name)
    comp = model.createCompartment()
    comp.setId("physmend_box")
    comp.setConstant(True)
    comp.setSize(1.0)
    comp.setSpatialDimensions(3)
    values = {v.name: float(v.value) for v in sm.parameters}
    for v in sm.parameters:
        p = model.createParameter()
        p.setId(ids[v.name])
        p.setName(v.name)
        p.setValue(values[v.name])
        p.setConstant(True)
    p = model.createParameter()
    p.setId(EXPERIMENT_PARAMETER)
    p.setName("number of the experiment whose recorded inputs drive the model (set by its condition)")
    p.setValue(1.0)
    p.setConstant(True)
    for v in sm.inputs:
        p = model.createParameter()
        p.setId(ids[v.name])
        p.setName(v.name)
        p.setConstant(False)
        p.setValue(0.0)
        branches = []
        for k, e in enumerate(experiments, 1):
            t, u = e["inputs"][v.name]
            branches += [interpolation(np.asarray(t, float), np.asarray(u, float)), f"{EXPERIMENT_PARAMETER} == {k}"]
        rule = model.createAssignmentRule()
        rule.setVariable(ids[v.name])
        rule.setMath(_math(f"piecewise({', '.join(branches)}, 0)", f"recorded input {v.name!r}"))
    first = experiments[0]["initial"] if experiments else {}
    for v in sm.states:
        s = model.createSpecies()
        s.setId(ids[v.name])
        s.setName(v.name)
        s.setCompartment("physmend_box")
        s.setHasOnlySubstanceUnits(True)
        s.setBoundaryCondition(False)
        s.setConstant(False)
        s.setInitialAmount(float(first.get(v.name, 0.0)))
        rule = model.createRateRule()
        rule.setVariable(ids[v.name])
        rule.setMath(_math(l3(sm.rhs[v.name], ids), f"derivative of {v.name!r}"))
    errors = [doc.getError(i) for i in range(doc.checkInternalConsistency())]
    errors = [e for e in errors if e.getSeverity() >= libsbml.LIBSBML_SEV_ERROR]
    if errors:
        raise ModelError(f"export.format=petab: the SBML written is not valid: {errors[0].getMessage().strip()}")
    return libsbml.writeSBMLToString(doc)


def tables(sm: Any, experiments: Sequence[Mapping[str, Any]], ids: Mapping[str, str],
           estimated: Mapping[str, tuple[float, float]], sigmas: Mapping[str, float]) -> dict[str, str]:
    """The PEtab tables (TSV text) and the YAML file, keyed like :data:`FILES` (without ``sbml``).

    ``experiments``: each ``id``, ``role``, ``initial`` (state -> value), ``parameters`` (name ->
    value, those that differ from the declared), ``obs_time (T,)``, ``obs (T, k)`` (outputs in
    ``sm.outputs`` order, NaN = not measured). ``estimated``: parameter -> (lower, upper) bounds
    of those to estimate. ``sigmas``: output -> noise σ (its unit; 1 where missing)."""

    varying = sorted({n for e in experiments for n in e["parameters"]})
    cond_cols = ["conditionId", "conditionName", EXPERIMENT_PARAMETER, *[ids[n] for n in varying],
                 *[ids[v.name] for v in sm.states]]
    values = {v.name: float(v.value) for v in sm.parameters}
    rows = ["\t".join(cond_cols)]
    for k, e in enumerate(experiments, 1):
        row = [sbml_id(f"experiment_{e['id']}"), str(e["id"]), str(k), *[_num(e["parameters"].get(n, values[n])) for n in varying],
               *[_num(e["initial"][v.name]) for v in sm.states]]
        rows.append("\t".join(row))
    conditions = "\n".join(rows) + "\n"

    outputs = list(sm.outputs)
    obs_rows = ["observableId\tobservableName\tobservableFormula\tobservableTransformation\tnoiseFormula\tnoiseDistribution"]
    meas_rows = ["observableId\tsimulationConditionId\tmeasurement\ttime\tdatasetId"]
    for j, out in enumerate(outputs):
        sigma = float(sigmas.get(out, 1.0))
        sigma = sigma if math.isfinite(sigma) and sigma > 0 else 1.0
        oid = sbml_id(f"y_{out}")
        obs_rows.append(f"{oid}\t{out}\t{l3(sm.outputs[out], ids)}\tlin\t{_num(sigma)}\tnormal")
        for e in experiments:
            cid = sbml_id(f"experiment_{e['id']}")
            col = np.asarray(e["obs"])[:, j]
            for t, y in zip(np.asarray(e["obs_time"]), col):
                if math.isfinite(y):
                    meas_rows.append(f"{oid}\t{cid}\t{_num(y)}\t{_num(t)}\t{sbml_id(str(e['role']))}")
    par_rows = ["parameterId\tparameterName\tparameterScale\tlowerBound\tupperBound\tnominalValue\testimate"]
    for v in sm.parameters:
        if v.name in varying:
            continue  # a condition-table column must not be in the parameter table
        lo, hi = estimated.get(v.name, (values[v.name], values[v.name]))
        est = int(v.name in estimated)
        par_rows.append(f"{ids[v.name]}\t{v.name}\tlin\t{_num(lo)}\t{_num(hi)}\t{_num(values[v.name])}\t{est}")
    yaml_text = ("format_version: 1\n"
                 f"parameter_file: {FILES['parameters']}\n"
                 "problems:\n"
                 f"  - sbml_files: [{FILES['sbml']}]\n"
                 f"    condition_files: [{FILES['conditions']}]\n"
                 f"    measurement_files: [{FILES['measurements']}]\n"
                 f"    observable_files: [{FILES['observables']}]\n")
    return {"yaml": yaml_text, "conditions": conditions, "measurements": "\n".join(meas_rows) + "\n",
            "observables": "\n".join(obs_rows) + "\n", "parameters": "\n".join(par_rows) + "\n"}


def identifiers(sm: Any) -> dict[str, str]:
    """Model name -> SBML identifier for every state, input and parameter; a clash (two names that
    become one identifier) is a clear error."""
    ids: dict[str, str] = {}
    taken: dict[str, str] = {}
    for v in [*sm.states, *sm.inputs, *sm.parameters]:
        i = sbml_id(v.name)
        if i in taken or i in (EXPERIMENT_PARAMETER, "physmend_box", "time"):
            raise ModelError(f"export.format=petab: {v.name!r} and {taken.get(i, i)!r} both become the SBML "
                             f"identifier {i!r}; rename one in the model")
        taken[i] = v.name
        ids[v.name] = i
    return ids


def petab_files(sm: Any, experiments: Sequence[Mapping[str, Any]], estimated: Mapping[str, tuple[float, float]],
                sigmas: Mapping[str, float]) -> dict[str, str]:
    """Every file of the PEtab problem (name in :data:`FILES` -> text); arguments as :func:`tables`."""
    ids = identifiers(sm)
    texts = tables(sm, experiments, ids, estimated, sigmas)
    texts["sbml"] = sbml_text(sm, experiments, ids)
    return {FILES[k]: v for k, v in texts.items()}

"""A corrected model written out for use outside physmend: LaTeX, sympy (JSON of ``srepr``) and a
plain Python module whose right-hand side works with ``scipy.integrate.solve_ivp``.

Every writer takes the :class:`~physmend.modeling.simplify.SimplifiedModel` of the model *with*
its corrections applied (their constants are parameters, at their re-fitted values) and returns
text. Names are the model's own (``zone1.air.T``); times are in the model's time unit.
"""

from __future__ import annotations

import json
import keyword
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import sympy as sp
from sympy.printing.pycode import pycode

from physmend.modeling.errors import ModelError
from physmend.modeling.simplify import SimplifiedModel

#: what ``export.format`` may name (besides ``petab``, a folder), and the file suffix each writes;
#: ``network`` writes ``.network.json`` (architecture) and ``.network.safetensors`` (weights)
FORMATS: dict[str, str] = {"latex": ".tex", "sympy": ".sympy.json", "python": ".py", "network": ".network.json"}
SYMPY_FORMAT = "physmend-sympy 1"


def module_name(model: str, run_id: str) -> str:
    """A Python identifier for the exported module of ``model`` from run ``run_id``."""
    name = re.sub(r"\W", "_", f"{model}_{run_id[:8]}")
    return f"m_{name}" if name[0].isdigit() or keyword.iskeyword(name) else name


def _tex_name(name: str) -> str:
    return r"\mathrm{" + name.replace("\\", "").replace("_", r"\_").replace("{", "").replace("}", "") + "}"


def _tex(expr: sp.Expr, sm: SimplifiedModel) -> str:
    names: dict[sp.Symbol, str] = {}
    for s in expr.free_symbols:
        n = str(s)
        if n.startswith("der(") and n.endswith(")"):
            names[s] = r"\frac{d\," + _tex_name(n[4:-1]) + "}{dt}"
        else:
            names[s] = _tex_name(n)
    return sp.latex(expr, symbol_names=names, mul_symbol="dot")


def latex_text(sm: SimplifiedModel, corrected: Sequence[str], constants: Mapping[str, float], meta: Mapping[str, Any]) -> str:
    """A LaTeX fragment (``amsmath``'s ``align*``, names as written): the corrected equations, the
    re-fitted constants, every state's explicit derivative. ``physmend export`` writes the
    standalone document of :func:`physmend.modeling.latex.latex_document` instead."""
    lines = [f"% corrected model {sm.name}, exported by physmend from proposal {meta.get('source_run_id', '?')}",
             f"% time in {meta.get('time_unit', 's')}; every variable in the unit the model declares", "",
             "% the corrected equations, as written, with the discovered terms", r"\begin{align*}"]
    rows = []
    for state in corrected:
        eq = sm.equations.get(state)
        if eq is not None:
            der = next((x for x in eq.lhs.free_symbols if str(x) == f"der({state})"), None)
            coef = eq.lhs.coeff(der) if der is not None and sp.expand(eq.lhs - eq.lhs.coeff(der) * der) == 0 else None
            lhs = (_tex(der, sm) if coef == 1 else f"{_tex(coef, sm)} \\cdot {_tex(der, sm)}") if coef is not None else _tex(eq.lhs, sm)
            rows.append(f"  {lhs} &= {_tex(eq.rhs, sm)}")
    lines += [" \\\\\n".join(rows), r"\end{align*}"]
    if constants:
        lines += ["", "% re-fitted constants", r"\begin{align*}"]
        lines += [" \\\\\n".join(f"  {_tex_name(k)} &= {sp.latex(sp.Float(v, 6))}" for k, v in constants.items()),
                  r"\end{align*}"]
    lines += ["", "% every state's derivative, explicit (states, inputs and parameters only)", r"\begin{align*}"]
    lines += [" \\\\\n".join(f"  \\frac{{d\\,{_tex_name(n)}}}{{dt}} &= {_tex(sm.rhs[n], sm)}" for n in sm.state_names),
              r"\end{align*}", ""]
    return "\n".join(lines)


def _start(sm: SimplifiedModel) -> dict[str, sp.Expr]:
    return {v.name: (v.start if v.start is not None else sp.Integer(0)) for v in sm.states}


def sympy_json(sm: SimplifiedModel, corrected: Sequence[str], meta: Mapping[str, Any],
               constants: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    """JSON with each expression as ``sympy.srepr`` (load one with ``sympy.sympify(text)``):
    ``rhs`` (state -> derivative), ``outputs``, ``start`` (state -> start value), ``equations``
    (the corrected equations as written: ``lhs``, ``rhs``), the declared variables, and
    ``constants``: each correction's re-fitted constant (parameter name -> ``state``, ``name``,
    ``value``, ``unit`` — ``""`` where not known — and ``stderr`` where the re-fit gave one)."""
    constants = dict(constants or {})
    doc = {
        "format": SYMPY_FORMAT,
        **{k: v for k, v in meta.items() if isinstance(v, (str, int, float))},
        "states": [{"name": v.name, "unit": v.unit} for v in sm.states],
        "inputs": [{"name": v.name, "unit": v.unit} for v in sm.inputs],
        "parameters": [{"name": v.name, "unit": v.unit or str(constants.get(v.name, {}).get("unit") or ""),
                        "value": v.value} for v in sm.parameters],
        "constants": {k: {key: (None if isinstance(val, float) and not math.isfinite(val) else val)  # JSON has no inf
                          for key, val in info.items()} for k, info in constants.items()},
        "rhs": {n: sp.srepr(sm.rhs[n]) for n in sm.state_names},
        "outputs": {n: sp.srepr(e) for n, e in sm.outputs.items()},
        "start": {n: sp.srepr(e) for n, e in _start(sm).items()},
        "equations": {n: {"lhs": sp.srepr(sm.equations[n].lhs), "rhs": sp.srepr(sm.equations[n].rhs)}
                      for n in corrected if n in sm.equations},
    }
    return json.dumps(doc, indent=1) + "\n"


def _code(exprs: Sequence[sp.Expr], sm: SimplifiedModel, what: str) -> tuple[list[str], list[str]]:
    """Python statements (common subexpressions) and one expression per item of ``exprs``, in
    ``x[i]`` (states), ``u[j]`` (inputs) and ``p['name']`` (parameters)."""
    names = {v.symbol: sp.Symbol(f"x[{i}]") for i, v in enumerate(sm.states)}
    names |= {v.symbol: sp.Symbol(f"u[{j}]") for j, v in enumerate(sm.inputs)}
    names |= {v.symbol: sp.Symbol(f"p[{v.name!r}]") for v in sm.parameters}
    renamed = [sp.sympify(e).xreplace(names) for e in exprs]
    stray = set().union(*(e.free_symbols for e in renamed)) - set(names.values()) if renamed else set()
    if stray:
        raise ModelError(f"export: the {what} use symbols that are neither states, inputs nor parameters: "
                         f"{sorted(map(str, stray))}")
    repl, reduced = sp.cse(renamed, symbols=sp.numbered_symbols("_c"))
    body = [f"    {s} = {pycode(v)}" for s, v in repl]
    out = [pycode(r) for r in reduced]
    bad = [line for line in body + out if "Not supported" in line]
    if bad:
        raise ModelError(f"export: the {what} use a function plain Python cannot express: {bad[0].strip()}")
    return body, out


def python_module(sm: SimplifiedModel, experiments: Mapping[str, Mapping[str, Any]], meta: Mapping[str, Any]) -> str:
    """A plain Python module (``math`` only): ``STATES``, ``INPUTS``, ``OUTPUTS``, ``PARAMETERS``
    (declared values, the corrections' constants re-fitted), ``EXPERIMENTS`` (each record's
    parameters that differ and its initial states), ``initial_state(p)``, ``rhs(t, x, u, p)`` and
    ``outputs(x, u, p)``."""
    rhs_body, rhs_out = _code([sm.rhs[n] for n in sm.state_names], sm, "derivatives")
    out_body, out_out = _code(list(sm.outputs.values()), sm, "outputs")
    start_body, start_out = _code(list(_start(sm).values()), sm, "start values")
    units = {v.name: v.unit for v in sm.states + sm.inputs + sm.parameters if v.unit}
    tu = meta.get("time_unit", "s")
    doc = (f'"""Corrected model {sm.name!r}, exported by physmend from proposal {meta.get("source_run_id", "?")}.\n\n'
           f"Time in {tu}; each variable in its unit (UNITS). With scipy, for one experiment of EXPERIMENTS:\n\n"
           "    p = {**PARAMETERS, **EXPERIMENTS[exp]['parameters']}\n"
           "    x0 = [EXPERIMENTS[exp]['initial'][s] for s in STATES]\n"
           "    sol = solve_ivp(lambda t, x: rhs(t, x, inputs(t), p), (t0, t1), x0, method='LSODA')\n\n"
           "where ``inputs(t)`` returns the inputs (INPUTS order) at time t.\n"
           '"""\n')
    lines = [doc, "from __future__ import annotations", "", "import math", "",
             f"STATES = {sm.state_names!r}", f"INPUTS = {sm.input_names!r}", f"OUTPUTS = {list(sm.outputs)!r}",
             "PARAMETERS = {" + ", ".join(f"{v.name!r}: {float(v.value)!r}" for v in sm.parameters) + "}",
             f"UNITS = {units!r}", f"EXPERIMENTS = {json.loads(json.dumps(experiments))!r}", "", "",
             "def initial_state(p=PARAMETERS):",
             '    """Start values of STATES from the parameters (the model\'s own start expressions)."""',
             *start_body, f"    return [{', '.join(start_out)}]", "", "",
             "def rhs(t, x, u, p=PARAMETERS):",
             f'    """d(STATES)/dt per {tu} at states ``x`` and inputs ``u`` (INPUTS order); ``t`` unused: the inputs carry time."""',
             *rhs_body, f"    return [{', '.join(rhs_out)}]", "", "",
             "def outputs(x, u, p=PARAMETERS):", '    """The measured OUTPUTS at states ``x`` and inputs ``u``."""',
             *out_body, f"    return [{', '.join(out_out)}]", ""]
    return "\n".join(lines)

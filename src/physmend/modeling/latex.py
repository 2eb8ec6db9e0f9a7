"""The corrected model as a standalone LaTeX document a reviewer can compile (``pdflatex``; only
``amsmath``, ``xcolor``, ``geometry`` and ``longtable``, all in every standard TeX distribution).

Names read as in a paper: ``cart.v`` is :math:`v_{\\mathrm{cart}}`, ``zone1.air.Q_flow`` is
:math:`Q_{\\mathrm{flow},\\mathrm{zone1},\\mathrm{air}}`, a Greek word is its letter, a correction's
constant ``cart.v_c1`` is :math:`c_{1}` (with the corrected state as a superscript where several
equations are corrected); a table maps every symbol back to the model's name and unit. The term
physmend found is coloured and marked (``\\underbrace{…}_{\\text{found term}}``); each re-fitted
constant is listed with its standard error and unit where they are known.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import sympy as sp

from physmend.modeling.simplify import SimplifiedModel

GREEK = {"alpha", "beta", "gamma", "delta", "epsilon", "zeta", "eta", "theta", "iota", "kappa", "lambda", "mu",
         "nu", "xi", "pi", "rho", "sigma", "tau", "upsilon", "phi", "chi", "psi", "omega", "Gamma", "Delta", "Theta",
         "Lambda", "Xi", "Pi", "Sigma", "Upsilon", "Phi", "Psi", "Omega"}
_TEXT_SPECIAL = {"\\": r"\textbackslash{}", "_": r"\_", "%": r"\%", "&": r"\&", "#": r"\#", "$": r"\$",
                 "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}
_UNIT_SYMBOLS = {"µ": r"\mu ", "Ω": r"\Omega ", "°": r"^{\circ}", "%": r"\%", "·": r"\cdot ", "*": r"\cdot "}


def text(s: str) -> str:
    """``s`` safe in LaTeX text mode."""
    return "".join(_TEXT_SPECIAL.get(ch, ch) for ch in str(s)).encode("ascii", "replace").decode()


def _roman(word: str) -> str:
    """A word upright in math mode (letters, digits; anything else escaped)."""
    return r"\mathrm{" + "".join(ch if ch.isalnum() and ch.isascii() else text(ch) for ch in word) + "}"


def _head(word: str) -> str:
    if word in GREEK:
        return "\\" + word
    if len(word) == 1 and word.isascii() and word.isalpha():
        return word
    return _roman(word)


def tex_name(name: str) -> str:
    """A readable math symbol for a model variable: the last part of the dotted name is the symbol,
    its own ``_suffix`` and trailing digits and the components it belongs to the subscript."""
    *owners, base = name.split(".")
    head, *subs = base.split("_")
    m = re.fullmatch(r"([A-Za-z]+?)(\d+)", head)
    if m:
        head, subs = m.group(1), [m.group(2), *subs]
    subs = [s for s in subs if s] + [o for o in owners if o]
    if not head:
        return _roman(name)
    sub = ",".join(s if s.isdigit() or (len(s) == 1 and s.isalpha()) else _roman(s) for s in subs)
    return _head(head) + (f"_{{{sub}}}" if sub else "")


def tex_names(names: Iterable[str], constants: Mapping[str, tuple[str, str]]) -> dict[str, str]:
    """Symbol for every name (``constants``: parameter name -> (corrected state, constant name));
    names that would look alike are written out in full."""
    states = sorted({state for state, _ in constants.values()})
    out: dict[str, str] = {}
    for name in names:
        if name in constants:
            state, const = constants[name]
            sym = tex_name(const)
            out[name] = sym if len(states) == 1 else f"{{{sym}}}^{{({tex_name(state)})}}"
        else:
            out[name] = tex_name(name)
    seen: dict[str, list[str]] = {}
    for name, sym in out.items():
        seen.setdefault(sym, []).append(name)
    for sym, alike in seen.items():
        if len(alike) > 1:
            for name in alike:
                out[name] = _roman(name)
    return out


def tex_unit(unit: str) -> str:
    """A unit string (``J/(kg.K)``, ``m3/s``, ``kg·m^2/s^3``) in upright math."""
    if not unit:
        return ""
    s = re.sub(r"(?<=[A-Za-zµΩ)])(-?\d+(?:\.\d+)?)", r"^{\1}", unit)  # Modelica m3 -> m^{3}
    s = re.sub(r"\^(-?\d+(?:\.\d+)?)", r"^{\1}", s).replace("^{{", "^{").replace("}}", "}")
    s = re.sub(r"(?<=[A-Za-z}])\.(?=[A-Za-z])", r"\\cdot ", s)
    for ch, tex in _UNIT_SYMBOLS.items():
        s = s.replace(ch, tex)
    return r"\mathrm{" + s + "}"


def _expr(expr: sp.Expr, names: Mapping[str, str]) -> str:
    symbols: dict[sp.Symbol, str] = {}
    for s in expr.free_symbols:
        n = str(s)
        if n.startswith("der(") and n.endswith(")"):
            symbols[s] = r"\frac{d\," + names.get(n[4:-1], tex_name(n[4:-1])) + "}{dt}"
        else:
            symbols[s] = names.get(n, tex_name(n))
    return sp.latex(expr, symbol_names=symbols, mul_symbol="dot")


def _lhs(sm: SimplifiedModel, state: str, names: Mapping[str, str]) -> str:
    eq = sm.equations[state]
    der = next((x for x in eq.lhs.free_symbols if str(x) == f"der({state})"), None)
    if der is None:
        return _expr(eq.lhs, names)
    coef = eq.lhs.coeff(der)
    if sp.expand(eq.lhs - coef * der) != 0:
        return _expr(eq.lhs, names)
    return _expr(der, names) if coef == 1 else f"{_expr(coef, names)} \\cdot {_expr(der, names)}"


def _value(info: Mapping[str, Any]) -> str:
    shown = sp.latex(sp.Float(float(info["value"]), 4))
    se = info.get("stderr")
    if se is None:
        return shown
    if not math.isfinite(float(se)):
        return shown + r" \;(\text{not pinned down by the data})"
    return f"{shown} \\pm {sp.latex(sp.Float(float(se), 2))}"


def latex_document(sm: SimplifiedModel, terms: Mapping[str, sp.Expr], constants: Mapping[str, Mapping[str, Any]],
                   meta: Mapping[str, Any]) -> str:
    """The document. ``terms``: corrected state -> the found term in ``sm``'s symbols (the equation's
    right-hand side is the original plus it); ``constants``: parameter name -> ``state``, ``name``
    (``c1``), ``value``, and where known ``stderr`` and ``unit``; ``meta``: ``source_run_id``,
    ``time_unit``."""
    const_of = {k: (str(v["state"]), str(v["name"])) for k, v in constants.items()}
    all_names = [v.name for v in sm.states + sm.inputs + sm.parameters] + list(sm.observed)
    names = tex_names(all_names, const_of)
    tu = str(meta.get("time_unit", "s"))
    lines = [
        f"% corrected model {sm.name}, exported by physmend from proposal {meta.get('source_run_id', '?')}",
        r"\documentclass[11pt]{article}", r"\usepackage{amsmath}", r"\usepackage{xcolor}",
        r"\usepackage[margin=2cm]{geometry}", r"\usepackage{longtable}",
        r"\definecolor{found}{rgb}{0.75,0.1,0.1}", r"\begin{document}",
        rf"\section*{{Corrected model \texttt{{{text(sm.name)}}}}}",
        rf"Exported by physmend from proposal \texttt{{{text(str(meta.get('source_run_id', '?')))}}}. "
        rf"Time in {text(tu)}; every variable in the unit the model declares (table at the end). "
        r"The terms physmend found are \textcolor{found}{coloured} and marked ``found term''.", "",
        r"\subsection*{Corrected equations}", r"\begin{align*}",
    ]
    rows = []
    for state, term in terms.items():
        if state not in sm.equations:
            continue
        original = sm.equations[state].rhs - term  # the equation as the user wrote it
        found = r"\underbrace{\textcolor{found}{" + _expr(term, names) + r"}}_{\text{found term}}"
        rhs = found if original == 0 else f"{_expr(original, names)} + {found}"
        rows.append(f"  {_lhs(sm, state, names)} &= {rhs}")
    lines += [" \\\\\n".join(rows) or r"  \text{(no correction)}", r"\end{align*}"]
    if constants:
        lines += ["", r"\subsection*{Re-fitted constants}", r"\begin{tabular}{llll}",
                  r"symbol & value & unit & in the correction of \\ \hline"]
        for pname, info in constants.items():
            unit = str(info.get("unit") or "")
            lines.append(f"${names[pname]}$ & ${_value(info)}$ & "
                         f"{'$' + tex_unit(unit) + '$' if unit else 'not known'} & ${names.get(str(info['state']), '')}$ \\\\")
        lines += [r"\end{tabular}", ""]
        lines.append(r"Standard errors from the re-fit through the simulator; a unit follows from the term's "
                     r"unit where the constant enters it linearly.")
    lines += ["", r"\subsection*{Every state's derivative, explicit}", r"\begin{align*}",
              " \\\\\n".join(f"  \\frac{{d\\,{names[n]}}}{{dt}} &= {_expr(sm.rhs[n], names)}" for n in sm.state_names),
              r"\end{align*}", "", r"\subsection*{Symbols}", r"\begin{longtable}{lll}",
              r"symbol & name in the model & unit \\ \hline"]
    units = {v.name: v.unit for v in sm.states + sm.inputs + sm.parameters} | dict(sm.units or {})
    for pname, info in constants.items():
        units[pname] = str(info.get("unit") or "")
    for name in all_names:
        unit = units.get(name) or ""
        lines.append(f"${names[name]}$ & \\texttt{{{text(name)}}} & {'$' + tex_unit(unit) + '$' if unit else ''} \\\\")
    lines += [r"\end{longtable}", r"\end{document}", ""]
    return "\n".join(lines)


def found_terms(sm: SimplifiedModel, corrections: Sequence[Any]) -> dict[str, sp.Expr]:
    """Each correction's term in ``sm``'s symbols (its constants as the parameters ``<state>_<name>``)."""
    from physmend.modeling.corrections import constant_parameter_name
    from physmend.modeling.expressions import parse_expression

    symbols = {v.name: v.symbol for v in sm.states + sm.inputs + sm.parameters}
    symbols |= {n: sp.Symbol(n) for n in sm.observed}
    out = {}
    for c in corrections:
        consts = {k: symbols[constant_parameter_name("", c.state, k)] for k in c.constants
                  if constant_parameter_name("", c.state, k) in symbols}
        out[c.state] = parse_expression(c.term, {**symbols, **consts}, where=f"correction of {c.state}")
    return out

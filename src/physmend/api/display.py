"""HTML pieces of a result's notebook view: a heading, equations, tables and inline PNG plots."""

from __future__ import annotations

import base64
import html
from collections.abc import Iterable, Mapping
from typing import Any

#: rows of a table shown in a notebook at most (the DataFrame itself holds them all)
MAX_ROWS = 20


def heading(title: str, run_id: str, note: str = "") -> str:
    extra = f" — {html.escape(note)}" if note else ""
    return f"<h4>{html.escape(title)}</h4><p>run <code>{html.escape(run_id)}</code>{extra}</p>"


def rounded(expr: Any, digits: int = 4) -> Any:
    """``expr`` with its numbers shown to ``digits`` significant digits (for display only)."""
    import sympy as sp

    return expr.evalf(digits) if isinstance(expr, sp.Basic) else expr


def signed(expr: Any) -> str:
    """``+ term`` or ``- term`` (never ``+ -term``), numbers to 4 significant digits."""
    text = str(rounded(expr))
    return f"- {text[1:]}" if text.startswith("-") else f"+ {text}"


def terms(formulas: Mapping[str, Any]) -> str:
    """``state: + term; …`` in one line."""
    return "; ".join(f"{state}: {signed(expr)}" for state, expr in formulas.items())


def equations(formulas: Mapping[str, Any]) -> str:
    """One line per corrected state: ``d(state)/dt = … + term`` in LaTeX (Jupyter typesets ``$…$``),
    and the term as text."""
    import sympy as sp

    if not formulas:
        return "<p>(no formulas)</p>"
    lines = []
    for state, expr in formulas.items():
        shown = rounded(expr)
        tex = sp.latex(shown, mul_symbol="dot") if isinstance(shown, sp.Basic) else html.escape(str(shown))
        tex = tex if tex.startswith("-") else "+ " + tex
        lines.append(f"<li>$\\frac{{d\\,\\mathrm{{{_tex_name(state)}}}}}{{dt}} = \\ldots {tex}$ "
                     f"&nbsp; <code>{html.escape(state)}: {html.escape(signed(expr))}</code></li>")
    return "<ul>" + "".join(lines) + "</ul>"


def _tex_name(name: str) -> str:
    return name.replace("\\", "").replace("_", "\\_").replace("{", "").replace("}", "")


def table(frame: Any, *, caption: str = "", floats: str = "{:.4g}") -> str:
    """``frame`` (a pandas DataFrame) as an HTML table of at most :data:`MAX_ROWS` rows."""
    if frame is None or len(frame) == 0:
        return ""
    shown = frame.head(MAX_ROWS)
    more = f"<p>({len(frame) - MAX_ROWS} more rows in the DataFrame)</p>" if len(frame) > MAX_ROWS else ""
    cap = f"<p><b>{html.escape(caption)}</b></p>" if caption else ""
    return cap + shown.to_html(index=False, float_format=floats.format, border=0) + more


def images(pngs: Iterable[tuple[str, bytes]], *, width: int = 480) -> str:
    """Inline ``<img>`` tags (PNG as base64 data) with the artifact path as their title."""
    out = []
    for name, data in pngs:
        src = "data:image/png;base64," + base64.b64encode(data).decode("ascii")
        out.append(f'<img src="{src}" title="{html.escape(name)}" alt="{html.escape(name)}" '
                   f'style="max-width:{width}px;display:inline-block;margin:2px"/>')
    return "<div>" + "".join(out) + "</div>" if out else ""


def short(value: float) -> str:
    return f"{value:.4g}"

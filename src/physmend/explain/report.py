"""A report in Markdown rendered as one self-contained HTML page.

Markdown goes through markdown-it-py (CommonMark with tables); images the report names by their
artifact path are embedded as ``data:`` URIs, so the page shows them wherever it is opened (the
MLflow UI's artifact view, a browser from a download, an e-mail); formulas written as code spans
whose text has a MathML rendering are shown as MathML (browsers draw it natively; no script, no
network), with the plain text kept as the element's title.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping

STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; max-width: 72rem; margin: 2rem auto;
       padding: 0 1rem; line-height: 1.45; color: #1b1b1b; }
table { border-collapse: collapse; margin: 0.8rem 0; font-size: 0.92rem; }
th, td { border: 1px solid #ccc; padding: 0.25rem 0.6rem; text-align: left; }
th { background: #f2f2f2; }
code { background: #f5f5f5; padding: 0 0.2rem; border-radius: 3px; }
img { max-width: 100%; height: auto; display: block; margin: 0.6rem 0; }
math { font-size: 1.05rem; }
"""


def mathml(expr: object) -> str:
    """Presentation MathML of a sympy expression, as an inline ``<math>`` element."""
    import sympy as sp

    return f'<math xmlns="http://www.w3.org/1998/Math/MathML">{sp.mathml(expr, printer="presentation", mul_symbol="dot")}</math>'


def to_html(md: str, title: str, images: Mapping[str, bytes] | None = None,
            math: Mapping[str, str] | None = None) -> str:
    """``md`` as a standalone HTML page: ``images`` (artifact path -> PNG bytes) embedded where the
    Markdown links them; each code span whose text is a key of ``math`` shown as that MathML."""
    from markdown_it import MarkdownIt

    parser = MarkdownIt("commonmark", {"html": False}).enable("table")
    tokens = parser.parse(md)
    images = images or {}
    math = math or {}
    for token in tokens:
        for child in token.children or []:
            if child.type == "image":
                src = str(child.attrGet("src") or "")
                if src in images:
                    child.attrSet("src", "data:image/png;base64," + base64.b64encode(images[src]).decode("ascii"))
            elif child.type == "code_inline" and child.content in math:
                child.type = "html_inline"
                child.content = f'<span title="{html.escape(child.content)}">{math[child.content]}</span>'
    body = parser.renderer.render(tokens, parser.options, {})
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{STYLE}</style></head>\n<body>\n{body}</body></html>\n")

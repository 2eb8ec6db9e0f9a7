"""Pareto fronts of formulas (accuracy vs complexity) and the rules that choose one."""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field
from typing import Any

import sympy

from physmend.symbolic._errors import SymbolicError
from physmend.modeling.evaluate import n_constants

FORMAT = "physmend.pareto_front/1"
RULES = ("score", "knee", "best", "bic")


@dataclass
class Candidate:
    """One formula of a Pareto front.

    Attributes:
        expr: the formula, in sympy Symbols named exactly like the inputs (full-precision constants).
        complexity: the back end's size measure (operon: tree length; sindy: number of terms;
            pysr: PySR complexity). ``sympy.count_ops(expr)`` gives a back-end-neutral one.
        mse: mean squared error on the data it was fitted on (target units²).
        r2: coefficient of determination on the same data.
        text: readable string, constants rounded to 4 significant digits (display only).
        terms: sindy only: library term (as text) -> coefficient.
    """

    expr: sympy.Expr
    complexity: int
    mse: float
    r2: float
    text: str
    terms: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict; ``expr`` is ``sympy.srepr`` (exact), ``str`` the plain sympy text."""
        return {
            "expr": sympy.srepr(self.expr),
            "str": str(self.expr),
            "complexity": int(self.complexity),
            "mse": float(self.mse),
            "r2": float(self.r2),
            "text": self.text,
            "terms": {k: float(v) for k, v in self.terms.items()},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Candidate:
        _require(d, ("expr", "complexity", "mse", "r2", "text"), "candidate")
        from physmend.modeling.errors import ModelError
        from physmend.modeling.safe_parse import parse_safe

        try:  # stored data: parsed by the restricted parser, never evaluated
            expr = parse_safe(d["expr"], where="candidate 'expr'", new_symbols=True)
        except ModelError as exc:
            raise SymbolicError(f"candidate 'expr' must be a sympy srepr string, but got {d['expr']!r} ({exc})") from exc
        return cls(
            expr=expr,
            complexity=int(d["complexity"]),
            mse=float(d["mse"]),
            r2=float(d["r2"]),
            text=str(d["text"]),
            terms={str(k): float(v) for k, v in d.get("terms", {}).items()},
        )


@dataclass
class ParetoFront:
    """Non-dominated formulas for one target, complexity ascending and MSE strictly descending.

    Attributes:
        backend: the back end that produced it (``"operon"``, ``"sindy"``, ``"pysr"``).
        target: name of the target (e.g. the corrected state).
        inputs: input names, in the column order of ``X``.
        candidates: the front.
        units: input name -> unit string, as given to ``fit``.
        n_points: number of points the metrics were computed on (used by the ``"bic"`` rule).
        info: JSON-ready details of the run (settings, seconds, points used for the search).
    """

    backend: str
    target: str
    inputs: list[str]
    candidates: list[Candidate]
    units: dict[str, str] = field(default_factory=dict)
    n_points: int = 0
    info: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict that round-trips through :meth:`from_dict`."""
        return {
            "format": FORMAT,
            "backend": self.backend,
            "target": self.target,
            "inputs": list(self.inputs),
            "units": dict(self.units),
            "n_points": int(self.n_points),
            "info": self.info,
            "candidates": [c.to_dict() for c in self.candidates],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ParetoFront:
        if not isinstance(d, dict):
            raise SymbolicError(f"a Pareto front must be a dict, but got {type(d).__name__}")
        _require(d, ("backend", "target", "inputs", "candidates"), "Pareto front")
        return cls(
            backend=str(d["backend"]),
            target=str(d["target"]),
            inputs=[str(x) for x in d["inputs"]],
            candidates=[Candidate.from_dict(c) for c in d["candidates"]],
            units={str(k): str(v) for k, v in (d.get("units") or {}).items()},
            n_points=int(d.get("n_points", 0)),
            info=dict(d.get("info") or {}),
        )

    def __len__(self) -> int:
        return len(self.candidates)

    def table(self) -> str:
        """The front as an aligned text table (index, complexity, MSE, R², formula)."""
        rows = [f"{'#':>3}  {'complexity':>10}  {'MSE':>11}  {'R2':>9}  formula for {self.target}"]
        for i, c in enumerate(self.candidates):
            rows.append(f"{i:>3}  {c.complexity:>10d}  {c.mse:>11.4g}  {c.r2:>9.6f}  {c.text}")
        return "\n".join(rows)


def _require(d: dict[str, Any], keys: tuple[str, ...], what: str) -> None:
    missing = [k for k in keys if k not in d]
    if missing:
        raise SymbolicError(f"a {what} dict must have the keys {list(keys)}, but {missing} are missing (got {sorted(d)})")


def pareto_filter(candidates: list[Candidate]) -> list[Candidate]:
    """Keep the non-dominated candidates: complexity ascending, each with a strictly lower MSE."""
    out: list[Candidate] = []
    for c in sorted(candidates, key=lambda c: (c.complexity, c.mse)):
        if not out or c.mse < out[-1].mse:
            if out and c.complexity == out[-1].complexity:
                continue
            out.append(c)
    return out


def _describe(front: ParetoFront, i: int) -> str:
    c = front.candidates[i]
    return f"index {i} (complexity {c.complexity}, MSE {c.mse:.4g}, R² {c.r2:.5f}): {c.text}"


def _knee(front: ParetoFront, tol: float) -> tuple[int, str]:
    best = min(range(len(front)), key=lambda i: front.candidates[i].mse)
    limit = front.candidates[best].mse * (1.0 + tol)
    i = next(i for i, c in enumerate(front.candidates) if c.mse <= limit)
    why = (
        f"rule 'knee': the simplest formula whose MSE is within {tol:.0%} of the best MSE on the front "
        f"({front.candidates[best].mse:.4g} at index {best}), i.e. MSE <= {limit:.4g}; chose {_describe(front, i)}"
    )
    if i > 0:
        worst = min(c.mse for c in front.candidates[:i])
        why += f"; {'the simpler formula has' if i == 1 else f'the {i} simpler formulas have'} MSE >= {worst:.4g}"
    return i, why


def _n_params(c: Candidate) -> int:
    """Fitted constants of a candidate: its library terms (sindy) or its floating-point constants."""
    return len(c.terms) if c.terms else n_constants(c.expr)


def _bic(front: ParetoFront) -> tuple[int, str]:
    n = front.n_points
    if n <= 0:
        raise SymbolicError(f"rule 'bic' needs the number of points of the front (n_points > 0), but got n_points={n}")
    tiny = 1e-300
    scores = [n * math.log(max(c.mse, tiny)) + _n_params(c) * math.log(n) for c in front.candidates]
    i = min(range(len(scores)), key=lambda j: (scores[j], front.candidates[j].complexity))
    k = _n_params(front.candidates[i])
    why = (
        f"rule 'bic': the lowest Bayesian information criterion n·ln(MSE) + k·ln(n), with n = {n} points "
        f"and k = the number of fitted constants; chose {_describe(front, i)} (k = {k}, BIC = {scores[i]:.6g})"
    )
    return i, why


def _score(front: ParetoFront, loss_factor: float = 1.5) -> tuple[int, str]:
    """PySR's selection: among formulas with MSE <= ``loss_factor`` × the best MSE, the one with the
    steepest drop of ln(MSE) per unit of complexity from its simpler neighbour on the front."""
    cands = front.candidates
    best = min(c.mse for c in cands)
    scores = []
    for i, c in enumerate(cands):
        if i == 0:
            s = 0.0
        else:
            p = cands[i - 1]
            dc = max(c.complexity - p.complexity, 1)
            s = -(math.log(max(c.mse, 1e-300)) - math.log(max(p.mse, 1e-300))) / dc
        scores.append(s)
    ok = [i for i, c in enumerate(cands) if c.mse <= loss_factor * best]
    picked = max(ok, key=lambda i: (scores[i], -cands[i].complexity))
    why = (f"rule 'score': among formulas with MSE <= {loss_factor}× the best ({best:.4g}), the steepest drop of "
           f"ln(MSE) per unit of complexity ({scores[picked]:.3g}); chose {_describe(front, picked)}")
    return picked, why


def choose(front: ParetoFront, rule: str = "knee", index: int | None = None, *, tol: float = 0.05) -> tuple[int, str]:
    """Choose one formula of ``front`` by a stated rule; returns ``(index, sentence saying why)``.

    Args:
        front: a non-empty Pareto front.
        rule: ``"score"``: PySR's rule (steepest ln(MSE) drop per complexity among formulas within
            1.5× of the best MSE); ``"knee"``: the simplest formula whose MSE is within ``1 + tol`` of the best
            MSE on the front; ``"best"``: the lowest MSE; ``"bic"``: the lowest
            ``n·ln(MSE) + k·ln(n)`` (k = fitted constants).
        index: choose this index instead of applying the rule (the sentence still says what the
            rule would have picked).
        tol: relative MSE tolerance of the knee rule (0.05 = 5 %).

    Raises:
        SymbolicError: empty front, unknown rule, ``tol < 0`` or ``index`` out of range.
    """
    if not front.candidates:
        raise SymbolicError(f"cannot choose from an empty Pareto front (target {front.target!r}, back end {front.backend!r})")
    if rule not in RULES:
        raise SymbolicError(f"Pareto rule must be one of {list(RULES)}, but got {rule!r}")
    if not (tol >= 0 and math.isfinite(tol)):
        raise SymbolicError(f"knee tolerance must be a finite number >= 0, but got {tol!r}")
    if rule == "knee":
        picked, why = _knee(front, tol)
    elif rule == "score":
        picked, why = _score(front)
    elif rule == "best":
        picked = min(range(len(front)), key=lambda i: (front.candidates[i].mse, front.candidates[i].complexity))
        why = f"rule 'best': the lowest MSE on the front; chose {_describe(front, picked)}"
    else:
        picked, why = _bic(front)
    if index is None:
        return picked, why[0].upper() + why[1:]
    last = len(front.candidates) - 1
    try:
        if isinstance(index, bool):
            raise TypeError
        index = operator.index(index)
    except TypeError:
        raise SymbolicError(f"Pareto index must be an integer in [0, {last}], but got {index!r}") from None
    if not 0 <= index <= last:
        raise SymbolicError(f"Pareto index must be in [0, {last}], but got {index}")
    return index, f"Chosen by index: {_describe(front, index)} (the {why})"

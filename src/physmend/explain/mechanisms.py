"""Mechanism catalogue: which physical mechanism a discovered formula's form suggests.

The catalogue (``mechanisms.yaml`` beside this file, or a user's own file, read by
:mod:`physmend.explain.catalogue`) is data: generic templates such as ``c*(a - b)*sqrt(Abs(a - b))``
with unit rules for their placeholders and an explanation. :func:`classify` is numerical, so algebraically different but equivalent forms of a
formula match the same template: the formula is evaluated on sample values of its variables
(e.g. trajectories), and for every template and every admissible assignment of variables to
placeholders the coefficient ``c`` is fitted by least squares; the R² of that fit ranks the
matches.

A form is never used with a quantity on an interval scale (a unit with an offset: ``degC``,
``degF``, a unit the model declares affine) other than linearly or as a difference
(:mod:`physmend.modeling.interval`): ``c·√|u|`` (Torricelli) or ``c·sign(u)`` of a temperature in
°C is not admissible, ``c·(a − b)·√|a − b|`` of two is. A threshold form's constant ``k`` (a
quantile of its variable) lies on the variable's own scale and moves with its zero, so
``c·Max(u − k, 0)`` stays admissible; a scale or an exponent does not move, so ``u/(k + u)`` and
``u·|u|^(k−1)`` of a °C quantity are not.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sympy

from physmend.explain.catalogue import COEFFICIENT, SECOND, Mechanism, MechanismError, load_catalogue, shape_function
from physmend.modeling.evaluate import abs_bars, evaluate, mse_r2


@dataclass
class MechanismMatch:
    """How well one catalogue template, with variables assigned, reproduces a formula.

    Attributes:
        id, name: the catalogue entry.
        explanation: the entry's explanation with the actual variable names filled in.
        variables: placeholder -> variable name.
        coefficient: fitted ``c`` (units of the formula divided by the template's).
        r2: R² of ``c * template`` against the formula on the samples.
        formula: the template with ``c`` and the variables filled in (``c`` to 4 significant digits).
        k: the template's second constant (a threshold, scale or exponent), where it has one.
    """

    id: str
    name: str
    explanation: str
    variables: dict[str, str]
    coefficient: float
    r2: float
    formula: str = ""
    complexity: int = field(default=0, repr=False)
    k: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)


def k_grid(kind: str, values: np.ndarray) -> np.ndarray:
    """The values tried for a template's second constant (:data:`~physmend.explain.catalogue.K_GRIDS`)
    given the samples of its variable ``values (n,)``: thresholds at the 10th…90th percentiles (the kink inside the data,
    where it can be told from a straight line), scales from 1/100 to 100 times the typical size,
    exponents 0.25…4 in steps of 0.05."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if kind == "threshold":
        return np.unique(np.quantile(v, np.linspace(0.1, 0.9, 41))) if v.size else np.zeros(0)
    if kind == "scale":
        size = float(np.median(np.abs(v))) if v.size else 0.0
        size = size if size > 0 else float(np.mean(np.abs(v))) if v.size else 0.0
        return size * np.logspace(-2, 2, 81) if size > 0 else np.zeros(0)
    return np.round(np.arange(0.25, 4.0 + 1e-9, 0.05), 10)


def fit_with_k(m: Mechanism, f: Any, columns: list[np.ndarray], y: np.ndarray) -> tuple[float, float | None, float, np.ndarray] | None:
    """``c`` (least squares) and, for a template with a second constant, the ``k`` of its grid that
    fits ``y`` best: ``(c, k, R², form values)``; None where the form is zero or not finite.
    ``f(*columns[, k])`` evaluates the template's shape on the samples ``(n,)`` of the variables
    assigned to its placeholders (in :attr:`Mechanism.placeholders` order); the grid of ``k`` comes
    from the column of :attr:`Mechanism.k_of`."""
    column = columns[m.placeholders.index(m.k_of)] if m.k else columns[0]

    def at(k: float | None) -> tuple[float, float | None, float, np.ndarray] | None:
        with np.errstate(all="ignore"):
            t = np.array(np.broadcast_to(np.asarray(f(*columns) if k is None else f(*columns, k), dtype=float), y.shape))
        tt = float(t @ t)
        if not np.isfinite(t).all() or tt == 0.0:
            return None
        c = float(t @ y) / tt
        return c, None if k is None else float(k), mse_r2(y, c * t)[1], t

    if not m.k:
        return at(None)
    grid = k_grid(m.k, column)
    fits = [at(float(k)) for k in grid]
    scored = [i for i, fit in enumerate(fits) if fit is not None]
    if not scored:
        return None
    i = max(scored, key=lambda j: fits[j][2])  # type: ignore[index]
    best = fits[i]
    lo, hi = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
    if hi > lo:  # refined between the grid's neighbours of the best
        from scipy.optimize import minimize_scalar

        def loss(k: float) -> float:  # 1 - R² (finite: a k where the form fails counts as no fit)
            fit = at(k)
            return 1.0 - fit[2] if fit is not None and np.isfinite(fit[2]) else 2.0

        res = minimize_scalar(loss, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6 * max(abs(lo), abs(hi), 1e-12)})
        refined = at(float(res.x))
        if refined is not None and refined[2] > best[2]:  # type: ignore[index]
            best = refined
    return best



#: classification fits every template (and its second constant on a grid) to at most this many of
#: the samples, evenly spaced: long records (tens of thousands of rows) would otherwise make the
#: catalogue's search seconds per formula, for the same ranking
MAX_SAMPLES = 2000


def _samples(expr: sympy.Expr, samples: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    names = sorted(s.name for s in expr.free_symbols)
    missing = [n for n in names if n not in samples]
    if missing:
        raise MechanismError(
            f"every variable of the formula needs sample values, but none were given for {missing} (given: {sorted(samples)})"
        )
    arrays = {n: np.asarray(samples[n], dtype=float).ravel() for n in names}
    sizes = {n: a.size for n, a in arrays.items() if a.size != 1}
    if len(set(sizes.values())) > 1:
        raise MechanismError(f"sample arrays must have one length, but got {sizes}")
    n = next(iter(sizes.values()), None)
    if n is None:  # only scalars or a constant formula: take the length of any given sample
        n = next((np.size(v) for v in samples.values() if np.size(v) > 1), 2)
    arrays = {k: np.broadcast_to(a, (n,)) if a.size == 1 else a for k, a in arrays.items()}
    y = evaluate(expr, arrays, n=n)
    ok = np.isfinite(y)
    for a in arrays.values():
        ok &= np.isfinite(a)
    if ok.sum() < 2:
        raise MechanismError(f"classification needs at least 2 samples where the formula is finite, but got {int(ok.sum())}")
    keep = np.flatnonzero(ok)
    if keep.size > MAX_SAMPLES:  # evenly spaced: a shape is told apart on a few thousand points
        keep = keep[np.unique(np.linspace(0, keep.size - 1, MAX_SAMPLES).round().astype(int))]
    return {k: np.asarray(a[keep], dtype=float) for k, a in arrays.items()}, y[keep]


def _formula(m: Mechanism, assignment: Mapping[str, str], coefficient: float, k: float | None = None) -> str:
    """The template's text with ``c`` (and ``k``; 4 significant digits) and the variable names filled in."""
    values = {**assignment, COEFFICIENT: f"{coefficient:.4g}", **({SECOND: f"{k:.4g}"} if k is not None else {})}
    return abs_bars(re.sub(r"[A-Za-z_]\w*", lambda mt: values.get(mt.group(0), mt.group(0)), m.text))


def classify(
    expr: sympy.Expr,
    samples: Mapping[str, np.ndarray],
    units: Mapping[str, str],
    *,
    catalogue_path: str | Path | None = None,
    top: int = 3,
    tie_tol: float = 1e-4,
) -> list[MechanismMatch]:
    """Rank the catalogue's mechanisms by how well each reproduces ``expr`` on ``samples``.

    Args:
        expr: the formula (sympy, Symbols named like the variables).
        samples: variable name -> values ``(n,)`` (e.g. trajectories; scalars are broadcast);
            must cover every variable of ``expr``. Points where anything is non-finite are dropped.
        units: variable name -> unit string; a variable without a unit is never paired with
            another (no difference is formed from it) and never counts as kelvin.
        catalogue_path: a catalogue file; default the shipped ``mechanisms.yaml``.
        top: how many matches to return.
        tie_tol: matches whose R² is within ``tie_tol`` of the best count as tied with it and are
            ordered simplest template first.

    Only the variables of ``expr`` are assigned to placeholders (injectively, obeying the unit
    rules); each template's ``c`` is fitted by least squares, and assignments that differ only by
    the sign of ``c`` (e.g. ``a - b`` vs ``b - a``) are reported once, with ``c >= 0``.

    Returns:
        Up to ``top`` matches, best first.

    Raises:
        MechanismError: a variable of ``expr`` has no samples, lengths differ, too few finite points.
        CatalogueError: the catalogue is malformed.
    """
    if isinstance(top, bool) or not isinstance(top, int) or top < 1:
        raise MechanismError(f"top must be an integer >= 1, but got {top!r}")
    if isinstance(expr, str):
        from physmend.modeling.safe_parse import parse_safe

        expr = parse_safe(expr, where="formula", new_symbols=True)
    catalogue = load_catalogue(catalogue_path)
    cols, y = _samples(expr, samples)
    names = sorted(cols)
    n = y.size

    found: list[tuple[Mechanism, dict[str, str], float, float, float | None]] = []
    for m in catalogue:
        f = shape_function(m)
        for combo in itertools.permutations(names, len(m.placeholders)):
            assignment = dict(zip(m.placeholders, combo))
            if not m.admissible(assignment, units):
                continue
            if m.k:  # a second constant searched on its grid
                fitted = fit_with_k(m, f, [cols[v] for v in combo], y)
                if fitted is not None:
                    found.append((m, assignment, fitted[0], fitted[2], fitted[1]))
                continue
            with np.errstate(all="ignore"):
                t = np.array(np.broadcast_to(np.asarray(f(*[cols[v] for v in combo]), dtype=float), (n,)))
            tt = float(t @ t)
            if not np.isfinite(t).all() or tt == 0.0:
                continue
            c = float(t @ y) / tt
            _, r2 = mse_r2(y, c * t)
            found.append((m, assignment, c, r2, None))

    # One report per mechanism and set of variables (a - b and b - a differ only in the sign of c).
    found.sort(key=lambda x: (-round(x[3], 9), x[2] < 0, x[0].complexity))
    unique: dict[tuple[str, frozenset[str]], tuple[Mechanism, dict[str, str], float, float, float | None]] = {}
    for item in found:
        unique.setdefault((item[0].id, frozenset(item[1].values())), item)
    ranked = sorted(unique.values(), key=lambda x: -x[3])
    if ranked:
        best = ranked[0][3]
        tied = sorted((x for x in ranked if x[3] >= best - tie_tol), key=lambda x: (x[0].complexity, -x[3]))
        ranked = tied + [x for x in ranked if x[3] < best - tie_tol]
    return [
        MechanismMatch(
            id=m.id,
            name=m.name,
            explanation=m.describe(assignment),
            variables=assignment,
            coefficient=c,
            r2=r2,
            formula=_formula(m, assignment, c, k),
            complexity=m.complexity,
            k=k,
        )
        for m, assignment, c, r2, k in ranked[:top]
    ]

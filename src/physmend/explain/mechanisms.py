"""Mechanism catalogue: which physical mechanism a discovered formula's form suggests.

The catalogue (``mechanisms.yaml`` beside this file, or a user's own file) is data: generic
templates such as ``c*(a - b)*sqrt(Abs(a - b))`` with unit rules for their placeholders and an
explanation. :func:`classify` is numerical, so algebraically different but equivalent forms of a
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
import string
from collections.abc import Mapping
from functools import lru_cache
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sympy
import yaml

from physmend.exceptions import PhysmendError
from physmend.modeling.evaluate import abs_bars, evaluate, mse_r2
from physmend.modeling.units import is_affine

DEFAULT_CATALOGUE = Path(__file__).with_name("mechanisms.yaml")

#: function names a template may use; every other identifier is a placeholder (or ``c``).
TEMPLATE_FUNCTIONS: dict[str, Any] = {
    "sqrt": sympy.sqrt,
    "Abs": sympy.Abs,
    "abs": sympy.Abs,
    "sign": sympy.sign,
    "exp": sympy.exp,
    "log": sympy.log,
    "tanh": sympy.tanh,
    "Max": sympy.Max,
    "Min": sympy.Min,
}
COEFFICIENT = "c"
#: a template's second constant (a threshold, a scale or an exponent), searched on a grid (``k:`` of an entry)
SECOND = "k"
#: how the second constant is searched: over the quantiles of the variable (a threshold inside its
#: range), over multiples of its typical size (a scale), or over exponents from 1/4 to 4
K_GRIDS = ("threshold", "scale", "exponent")
_ENTRY_KEYS = {"id", "name", "template", "explanation", "same_unit", "units", "different_unit", "k", "k_of"}
_REQUIRED = ("id", "name", "template", "explanation")
_ID = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


class MechanismError(PhysmendError, ValueError):
    """Bad input to :func:`classify` (missing samples, mismatched lengths); states rule and value."""


class CatalogueError(MechanismError):
    """A mechanism catalogue file is malformed; the message names the file and the entry."""


@dataclass(frozen=True)
class Mechanism:
    """One catalogue entry, validated.

    Attributes:
        shape: the template divided by ``c`` (an expression of the placeholders only).
        text: the template as written in the catalogue.
        placeholders: the template's placeholder names, sorted.
        complexity: ``sympy.count_ops`` of the template: lower is simpler (breaks ties).
    """

    id: str
    name: str
    template: sympy.Expr
    shape: sympy.Expr
    placeholders: tuple[str, ...]
    same_unit: tuple[tuple[str, ...], ...]
    units: dict[str, str]
    different_unit: tuple[tuple[str, ...], ...]
    explanation: str
    complexity: int
    text: str = ""
    k: str | None = None
    k_of: str | None = None  # the placeholder whose samples set the grid of ``k`` (the only one, or named)

    def admissible(self, assignment: Mapping[str, str], units: Mapping[str, str]) -> bool:
        """Whether mapping placeholders to variables (``assignment``) obeys the unit rules, and uses
        every variable on an interval scale (°C) only linearly or as a difference (:meth:`interval_reason`)."""
        unit = {p: (units.get(v) or "").strip() or None for p, v in assignment.items()}
        for p, required in self.units.items():
            if unit[p] != required:
                return False
        for group in self.same_unit:
            found = {unit[p] for p in group}
            if None in found or len(found) != 1:
                return False
        for group in self.different_unit:
            known = [unit[p] for p in group if unit[p] is not None]
            if len(known) != len(set(known)):
                return False
        return self.interval_reason(assignment, units) is None

    def interval_reason(self, assignment: Mapping[str, str], units: Mapping[str, str]) -> str | None:
        """Why this form may not take the variables of ``assignment`` whose units have an offset
        (``degC``): the reason naming the template's offending part, or None. Placeholders stand for
        the variables; a threshold ``k`` moves with its variable's zero."""
        scales = tuple(sorted((p, (units.get(v) or "").strip()) for p, v in assignment.items()
                              if is_affine(units.get(v))))
        if not scales:
            return None
        if self.k == "threshold" and len(scales) == 1:  # the threshold is a value on the variable's scale
            scales = scales + ((SECOND, scales[0][1]),)
        return _shape_reason(self.shape, scales)

    def describe(self, assignment: Mapping[str, str]) -> str:
        """The explanation with the variable names filled in."""
        return " ".join(self.explanation.format_map(dict(assignment)).split())


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


@lru_cache(maxsize=1024)
def _shape_reason(shape: sympy.Expr, scales: tuple[tuple[str, str], ...]) -> str | None:
    """:func:`physmend.modeling.interval.shift_violation` of a template's shape with the placeholders
    ``scales`` (name -> affine unit) shifting; the verdict depends on the form only, so it is kept."""
    from physmend.modeling.interval import shift_violation

    return shift_violation(shape, {sympy.Symbol(p): unit for p, unit in scales})


def _parse_template(text: str, where: str) -> sympy.Expr:
    from physmend.modeling.errors import ModelError
    from physmend.modeling.safe_parse import parse_safe

    try:  # a catalogue is data: the restricted parser, never sympify
        expr = parse_safe(str(text), where=f"{where}: template", new_symbols=True)
    except ModelError as exc:
        raise CatalogueError(f"{where}: template must be a sympy expression, but got {text!r} ({exc})") from exc
    if not isinstance(expr, sympy.Expr):
        raise CatalogueError(f"{where}: template must be a sympy expression, but got {text!r}")
    return expr


def _groups(value: Any, key: str, placeholders: tuple[str, ...], where: str, *, size: int | None = None) -> tuple[tuple[str, ...], ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(g, list) for g in value):
        raise CatalogueError(f"{where}: {key} must be a list of placeholder lists, but got {value!r}")
    out = []
    for g in value:
        if len(g) < 2 or (size is not None and len(g) != size):
            need = f"exactly {size}" if size else "at least 2"
            raise CatalogueError(f"{where}: each {key} group must name {need} placeholders, but got {g!r}")
        unknown = [p for p in g if p not in placeholders]
        if unknown:
            raise CatalogueError(f"{where}: {key} names {unknown}, which are not placeholders of the template {list(placeholders)}")
        out.append(tuple(str(p) for p in g))
    return tuple(out)


def _entry(raw: Any, k: int, path: Path) -> Mechanism:
    label = f"mechanism entry {k}"
    if isinstance(raw, dict) and isinstance(raw.get("id"), str):
        label += f" (id {raw['id']!r})"
    where = f"{path}: {label}"
    if not isinstance(raw, dict):
        raise CatalogueError(f"{where}: must be a mapping, but got {type(raw).__name__}")
    missing = [key for key in _REQUIRED if key not in raw]
    if missing:
        raise CatalogueError(f"{where}: must have the keys {list(_REQUIRED)}, but {missing} are missing")
    unknown = sorted(set(raw) - _ENTRY_KEYS)
    if unknown:
        raise CatalogueError(f"{where}: keys must be among {sorted(_ENTRY_KEYS)}, but got unknown {unknown}")
    if not isinstance(raw["id"], str) or not _ID.match(raw["id"]):
        raise CatalogueError(f"{where}: id must be letters, digits and underscores starting with a letter, but got {raw['id']!r}")
    for key in ("name", "template", "explanation"):
        if not isinstance(raw[key], str) or not raw[key].strip():
            raise CatalogueError(f"{where}: {key} must be a non-empty string, but got {raw[key]!r}")

    template = _parse_template(raw["template"], where)
    c = sympy.Symbol(COEFFICIENT)
    if c not in template.free_symbols:
        raise CatalogueError(f"{where}: template must contain the coefficient {COEFFICIENT!r}, but got {raw['template']!r}")
    shape = template.subs(c, 1)
    if sympy.expand(template - c * shape) != 0:
        raise CatalogueError(f"{where}: template must be {COEFFICIENT!r} times an expression of the placeholders, but got {raw['template']!r}")
    kind = raw.get("k")
    if kind is not None and kind not in K_GRIDS:
        raise CatalogueError(f"{where}: k must be one of {list(K_GRIDS)} (how the second constant {SECOND!r} is searched), "
                             f"but got {kind!r}")
    placeholders = tuple(sorted(s.name for s in shape.free_symbols if kind is None or s.name != SECOND))
    k_of = raw.get("k_of")
    if kind is not None and (sympy.Symbol(SECOND) not in shape.free_symbols or not placeholders):
        raise CatalogueError(f"{where}: a template with k: {kind} must hold the constant {SECOND!r} and a "
                             f"placeholder, but got {raw['template']!r}")
    if kind is None and k_of is not None:
        raise CatalogueError(f"{where}: k_of names the placeholder that sizes the grid of k, so it needs k, but the "
                             "entry has no k")
    if kind is not None:
        if k_of is None and len(placeholders) != 1:
            raise CatalogueError(f"{where}: a template with k: {kind} and several placeholders {list(placeholders)} "
                                 f"needs k_of: the placeholder whose samples set the grid of {SECOND!r}")
        k_of = placeholders[0] if k_of is None else k_of
        if k_of not in placeholders:
            raise CatalogueError(f"{where}: k_of must be one of the placeholders {list(placeholders)}, but got {k_of!r}")

    units = raw.get("units") or {}
    if not isinstance(units, dict) or not all(isinstance(v, str) for v in units.values()):
        raise CatalogueError(f"{where}: units must map placeholders to unit strings, but got {units!r}")
    bad = [p for p in units if p not in placeholders]
    if bad:
        raise CatalogueError(f"{where}: units names {bad}, which are not placeholders of the template {list(placeholders)}")

    fields = {f for _, f, _, _ in string.Formatter().parse(raw["explanation"]) if f is not None}
    bad = sorted(f for f in fields if f not in placeholders)
    if bad:
        raise CatalogueError(
            f"{where}: explanation may only use the placeholders {list(placeholders)} as {{fields}}, but uses {bad}"
        )
    return Mechanism(
        id=raw["id"],
        name=raw["name"].strip(),
        template=template,
        shape=shape,
        placeholders=placeholders,
        same_unit=_groups(raw.get("same_unit"), "same_unit", placeholders, where),
        units={str(p): v.strip() for p, v in units.items()},
        different_unit=_groups(raw.get("different_unit"), "different_unit", placeholders, where, size=2),
        explanation=raw["explanation"].strip(),
        complexity=int(sympy.count_ops(template)),
        text=" ".join(raw["template"].split()),
        k=kind,
        k_of=k_of,
    )


def k_grid(kind: str, values: np.ndarray) -> np.ndarray:
    """The values tried for a template's second constant (:data:`K_GRIDS`) given the samples of its
    variable ``values (n,)``: thresholds at the 10th…90th percentiles (the kink inside the data,
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


def load_catalogue(path: str | Path | None = None) -> list[Mechanism]:
    """Read and validate a mechanism catalogue (default: the one shipped with physmend).

    Raises:
        CatalogueError: the file is missing or not YAML, or an entry breaks a rule (the message
            names the file, the entry's position and id, the rule and the value found).
    """
    path = Path(path) if path is not None else DEFAULT_CATALOGUE
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise CatalogueError(f"{path}: cannot read the mechanism catalogue ({exc.strerror or exc})") from exc
    except yaml.YAMLError as exc:
        raise CatalogueError(f"{path}: the mechanism catalogue is not valid YAML ({exc})") from exc
    if not isinstance(data, dict) or not isinstance(data.get("mechanisms"), list) or not data["mechanisms"]:
        raise CatalogueError(f"{path}: must be a mapping with a non-empty list 'mechanisms', but got {type(data).__name__}")
    entries = [_entry(raw, k, path) for k, raw in enumerate(data["mechanisms"])]
    seen: dict[str, int] = {}
    for k, m in enumerate(entries):
        if m.id in seen:
            raise CatalogueError(f"{path}: mechanism ids must be unique, but entries {seen[m.id]} and {k} are both {m.id!r}")
        seen[m.id] = k
    return entries


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
        dummies = [sympy.Symbol(f"_p{i}") for i in range(len(m.placeholders))]
        extra = [sympy.Symbol(SECOND)] if m.k else []
        f = sympy.lambdify(
            dummies + extra, m.shape.xreplace({sympy.Symbol(p): d for p, d in zip(m.placeholders, dummies)}), modules="numpy"
        )
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

"""The mechanism catalogue: its entries (:class:`Mechanism`: a template, unit rules for its
placeholders, an explanation), their rules for quantities on an interval scale, and the YAML file
they are read from (:func:`load_catalogue`; ``mechanisms.yaml`` beside this file by default).
:mod:`physmend.explain.mechanisms` matches formulas against them.
"""

from __future__ import annotations

import re
import string
from collections.abc import Mapping
from functools import lru_cache
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import sympy
import yaml

from physmend.exceptions import PhysmendError
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



def load_catalogue(path: str | Path | None = None) -> list[Mechanism]:
    """Read and validate a mechanism catalogue (default: the one shipped with physmend).

    A file is read and validated once while it is unchanged (same size and modification time): the
    symbolic stage classifies every candidate formula against it (a new list each call; the entries
    are frozen).

    Raises:
        CatalogueError: the file is missing or not YAML, or an entry breaks a rule (the message
            names the file, the entry's position and id, the rule and the value found).
    """
    path = Path(path) if path is not None else DEFAULT_CATALOGUE
    try:
        stat = path.stat()
    except OSError as exc:
        raise CatalogueError(f"{path}: cannot read the mechanism catalogue ({exc.strerror or exc})") from exc
    return list(_read_catalogue(str(path), stat.st_mtime_ns, stat.st_size))


@lru_cache(maxsize=4)
def _read_catalogue(name: str, mtime_ns: int, size: int) -> tuple[Mechanism, ...]:
    """The entries of the catalogue file ``name`` (its ``mtime_ns`` and ``size`` key the cache)."""
    path = Path(name)
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
    return tuple(entries)


def shape_function(m: Mechanism) -> Any:
    """``m``'s shape as a numpy function of its placeholders' samples (in :attr:`Mechanism.placeholders`
    order) and, for a template with a second constant, ``k`` last; made once per form."""
    return _shape_function(m.shape, m.placeholders, bool(m.k))


@lru_cache(maxsize=256)
def _shape_function(shape: sympy.Expr, placeholders: tuple[str, ...], second: bool) -> Any:
    dummies = [sympy.Symbol(f"_p{i}") for i in range(len(placeholders))]
    extra = [sympy.Symbol(SECOND)] if second else []
    return sympy.lambdify(dummies + extra, shape.xreplace({sympy.Symbol(p): d for p, d in zip(placeholders, dummies)}),
                          modules="numpy")


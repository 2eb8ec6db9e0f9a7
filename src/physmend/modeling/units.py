"""Physical dimensions of declared units, and of formulas built from them.

Units are the strings a model declares (``m.parameter("UA", 20, unit="W/K")``), written in the
Modelica notation the component library uses — ``"J/(kg.K)"``, ``"m3/s"``, ``"N.s/m"``,
``"m2.5/s"``, ``"1/tu"`` — or with ``*`` and ``^`` (``"kg*m^2/s^3"``). :func:`dimension` turns one
into exponents of base dimensions: SI base units and the derived SI units are expanded (a watt is
``kg·m²·s⁻³``, so ``"W"`` and ``"J/s"`` agree), prefixes are dropped (``"mm"`` is a length), a
temperature in ``K`` or ``degC`` is one dimension, and any other word is a dimension of its own
(``"kanimals"``, a model's time unit ``"tu"``). A unit that cannot be read is unknown (``None``),
never an error: the model was accepted with it.

:func:`formula_dimension` infers the dimension of a formula from its symbols' units, with the rule
of dimensional symbolic regression (PySR's): a fitted floating-point constant may carry any unit,
so a product holding one can take any dimension; integers and exponents are pure numbers. It
returns the formula's dimension, :data:`ANY` where constants leave it free, or raises
:class:`UnitMismatch` naming the first operation whose operands cannot agree (``T + Q`` with ``T`` in
K and ``Q`` in W; ``exp(T)``).

Units with an offset (affine units, an interval scale): ``degC``/``°C`` and ``degF``/``°F`` are
built in; a model may declare more (:func:`declare_affine`, through
:meth:`physmend.modeling.Model.affine_unit`), each with its ``offset`` — how far its zero lies
above the absolute zero, in its own steps (273.15 for degC). A quantity in such a unit has a zero
that is a convention, so it may enter a nonlinear operation only as a difference
(:mod:`physmend.modeling.interval` checks formulas). :func:`is_affine` and :func:`affine_offset`
answer for one unit string: the whole string must be the unit (``degC/s``, a rate, is a ratio
scale). This module is extended rather than replaced by ``pint``: pint knows affine units, but it
is not installed here, its registry would not read the Modelica notation models are written in
(``J/(kg.K)``, ``m2.5/s``, a model's own words such as ``kanimals``) and unknown words must stay
dimensions of their own, never errors; the affine knowledge needed is one offset per unit.
"""

from __future__ import annotations

import re
from collections.abc import Mapping

import sympy as sp

#: a dimension: base name -> exponent (zero exponents left out; ``{}`` is a pure number)
Dimension = dict[str, float]


class _Any:
    """A dimension left free by a fitted constant."""

    def __repr__(self) -> str:
        return "ANY"


#: the dimension of a formula part that a fitted constant can give any unit
ANY = _Any()


class UnitMismatch(ValueError):
    """A formula whose parts cannot have consistent units (message: the operation and units)."""


_BASE = {"kg": {"M": 1}, "m": {"L": 1}, "s": {"T": 1}, "K": {"Θ": 1}, "A": {"I": 1}, "mol": {"N": 1},
         "cd": {"J": 1}}
_DERIVED = {
    "g": "kg/1", "degC": "K", "degF": "K", "°C": "K", "°F": "K", "rad": "1", "deg": "1", "degree": "1", "°": "1", "rev": "1", "sr": "1", "%": "1", "1": "1",
    "Hz": "1/s", "N": "kg.m/s2", "Pa": "N/m2", "bar": "Pa", "atm": "Pa", "J": "N.m", "W": "J/s",
    "C": "A.s", "V": "W/A", "F": "C/V", "Ohm": "V/A", "Ω": "V/A", "S": "A/V", "Wb": "V.s", "T": "Wb/m2",
    "H": "Wb/A", "L": "m3", "l": "m3", "min": "s", "h": "s", "d": "s", "day": "s", "Wh": "W.h",
    "Ah": "A.h", "eV": "J", "cal": "J",
}
_PREFIXES = ("da", "Y", "Z", "E", "P", "G", "M", "k", "h", "d", "c", "m", "u", "µ", "n", "p", "f", "a")
#: a unit word (letters), an exponent or a number (``2``, ``-1``, ``2.5``), or one of ``( ) . / * ^``
_TOKEN = re.compile(r"[A-Za-zµΩ°%_]+|[-+]?\d+(?:\.\d+)?|[()./*^]|\s+|.")


#: built-in units on an interval scale -> how far their zero lies above the absolute zero, in their own steps
BUILTIN_AFFINE: dict[str, float] = {"degC": 273.15, "°C": 273.15, "degF": 459.67, "°F": 459.67}
#: affine units declared by models in this process (:func:`declare_affine`): unit -> offset
_USER_AFFINE: dict[str, float] = {}
#: declared affine unit -> the unit whose steps it counts (its dimension), where one was given
_USER_BASE: dict[str, str] = {}
_UNIT_WORD = re.compile(r"[A-Za-zµΩ°%_]+")


class AffineUnitError(ValueError):
    """An affine-unit declaration breaks a rule (the message names the unit, the rule and the value)."""


def declare_affine(unit: str, offset: float | None = None, *, base: str | None = None) -> None:
    """Declare ``unit`` a unit with an offset (an interval scale), for the whole process.

    Args:
        unit: one unit word (letters and ``° µ Ω % _``, e.g. ``"degRe"``): a compound such as
            ``"degC/s"`` is a rate, a ratio scale, and cannot be affine.
        offset: how far the unit's zero lies above the absolute zero, in the unit's own steps
            (273.15 for degC, 459.67 for degF, 1.01325 for a gauge pressure in bar); required,
            finite.
        base: optional unit whose steps ``unit`` counts (``"K"``): its dimension becomes
            ``unit``'s; without it the unit is a dimension of its own.

    Declaring the same unit again with the same offset and base does nothing.

    Raises:
        AffineUnitError: no offset, an offset that is not a finite number, a unit that is not one
            word or is an absolute unit (``K``, ``m``), an unreadable base, or a redeclaration that
            differs.
    """
    if not isinstance(unit, str) or not _UNIT_WORD.fullmatch(unit.strip()):
        raise AffineUnitError(f"an affine unit must be one unit word such as 'degRe' (letters, °, µ, Ω, %, _), "
                              f"but got {unit!r}")
    unit = unit.strip()
    if offset is None:
        raise AffineUnitError(f"affine unit {unit!r} needs offset=: how far its zero lies above the absolute "
                              "zero, in its own steps (273.15 for degC), but none was given")
    if isinstance(offset, bool) or not isinstance(offset, (int, float)) or offset != offset or abs(offset) == float("inf"):
        raise AffineUnitError(f"affine unit {unit!r} needs a finite number as offset, but got {offset!r}")
    if unit in _BASE or (unit in _DERIVED and unit not in BUILTIN_AFFINE) or any(
            unit.startswith(p) and (unit[len(p):] in _BASE or unit[len(p):] in _DERIVED) for p in _PREFIXES):
        raise AffineUnitError(f"unit {unit!r} is an absolute (ratio-scale) unit and cannot be declared affine")
    if base is not None and dimension(base) is None:
        raise AffineUnitError(f"affine unit {unit!r}: base must be a readable unit such as 'K', but got {base!r}")
    known = BUILTIN_AFFINE.get(unit, _USER_AFFINE.get(unit))
    if known is not None and (known != float(offset) or (base is not None and _USER_BASE.get(unit, base) != base)):
        raise AffineUnitError(f"affine unit {unit!r} is already declared with offset {known:g}"
                              f"{f' (base {_USER_BASE[unit]!r})' if unit in _USER_BASE else ''}, "
                              f"but got offset {float(offset):g}{f' (base {base!r})' if base else ''}")
    if unit in BUILTIN_AFFINE:
        return
    _USER_AFFINE[unit] = float(offset)
    if base is not None:
        _USER_BASE[unit] = base.strip()


def affine_offset(unit: str | None) -> float | None:
    """The offset of ``unit`` if it is affine (built in or declared): its zero's height above the
    absolute zero in its own steps; ``None`` for an absolute unit, a compound or no unit."""
    text = (unit or "").strip()
    return BUILTIN_AFFINE.get(text, _USER_AFFINE.get(text))


def is_affine(unit: str | None) -> bool:
    """Whether ``unit`` (the whole string) is a unit with an offset: a quantity on an interval scale."""
    return affine_offset(unit) is not None


def affine_units() -> dict[str, float]:
    """Every affine unit known now (built in and declared): unit -> offset."""
    return {**BUILTIN_AFFINE, **_USER_AFFINE}


def _mul(a: Dimension, b: Dimension, power: float = 1.0) -> Dimension:
    out = dict(a)
    for k, v in b.items():
        out[k] = out.get(k, 0.0) + power * v
    return {k: v for k, v in out.items() if abs(v) > 1e-12}


def _scale(a: Dimension, power: float) -> Dimension:
    return {k: v * power for k, v in a.items() if abs(v * power) > 1e-12}


def _word(word: str, depth: int = 0) -> Dimension:
    """A unit word without exponent: SI base, derived, prefixed, or a dimension of its own."""
    if word in _BASE:
        return dict(_BASE[word])
    if word in _USER_BASE and depth < 8:  # a declared affine unit measured in steps of a known unit
        return _parse(_USER_BASE[word], depth + 1)
    if word in _DERIVED and depth < 8:
        return _parse(_DERIVED[word], depth + 1)
    for p in _PREFIXES:
        rest = word[len(p):]
        if word.startswith(p) and rest and (rest in _BASE or rest in _DERIVED):
            return _word(rest, depth)
    return {word: 1.0}


def _parse(text: str, depth: int = 0) -> Dimension:
    tokens = [t for t in _TOKEN.findall(text) if t.strip()]
    pos = 0

    def peek() -> str | None:
        return tokens[pos] if pos < len(tokens) else None

    def take() -> str:
        nonlocal pos
        pos += 1
        return tokens[pos - 1]

    def number(t: str | None) -> bool:
        return t is not None and re.fullmatch(r"[-+]?\d+(?:\.\d+)?", t) is not None

    def factor() -> Dimension:
        t = take()
        if t == "(":
            inner = quotient()
            if take() != ")":
                raise ValueError(text)
            base = inner
        elif number(t):
            if float(t) != 1.0:
                raise ValueError(text)
            base = {}
        elif re.fullmatch(r"[A-Za-zµΩ°%_]+", t):
            base = _word(t, depth)
        else:
            raise ValueError(text)
        if peek() == "^":
            take()
        if number(peek()):
            base = _scale(base, float(take()))
        return base

    def product() -> Dimension:
        out = factor()
        while peek() in (".", "*"):
            take()
            out = _mul(out, factor())
        return out

    def quotient() -> Dimension:
        out = product()
        while peek() == "/":
            take()
            out = _mul(out, product(), -1.0)
        return out

    result = quotient()
    if pos != len(tokens):
        raise ValueError(text)
    return result


def dimension(unit: str | None) -> Dimension | None:
    """The base-dimension exponents of ``unit`` (``"W/K"`` → ``{M: 1, L: 2, T: -3, Θ: -1}``);
    ``{}`` for a pure number (``"1"``, ``"%"``); ``None`` when the unit is empty or cannot be read."""
    text = (unit or "").strip()
    if not text:
        return None
    try:
        return _parse(text)
    except (ValueError, IndexError, RecursionError):
        return None


def same(a: Dimension, b: Dimension) -> bool:
    """Whether two dimensions are equal (exponents to 1e-9)."""
    return all(abs(a.get(k, 0.0) - b.get(k, 0.0)) <= 1e-9 for k in set(a) | set(b))


def show(d: Dimension | _Any | None) -> str:
    """A dimension as text: ``M·L^2·T^-3`` (``1`` for a pure number, ``any`` for :data:`ANY`)."""
    if d is None:
        return "unknown"
    if d is ANY:
        return "any"
    assert isinstance(d, dict)
    parts = [k if abs(v - 1) < 1e-12 else f"{k}^{v:g}" for k, v in sorted(d.items())]
    return "·".join(parts) or "1"


_PURE_FUNCTIONS = (sp.exp, sp.log, sp.sin, sp.cos, sp.tan, sp.tanh, sp.sinh, sp.cosh, sp.atan, sp.asin, sp.acos,
                   sp.erf, sp.asinh, sp.acosh, sp.atanh)


def formula_dimension(expr: sp.Expr, units: Mapping[str, str]) -> Dimension | _Any:
    """The dimension of ``expr`` given each symbol's unit (``units``: name -> unit string).

    A floating-point constant is free (:data:`ANY`), as is a symbol whose unit is unknown; a number
    added to a sum or compared in ``min``/``max`` is in the sum's unit (``max(x, 0)``); a product
    with a free factor is free; a sum's known terms must agree; a function such as ``exp`` or
    ``tanh`` needs a pure-number (or free) argument and gives a pure number; ``|x|`` and ``min``/
    ``max`` keep their argument's dimension, ``sign`` gives a pure number; a power with a numeric
    exponent scales the exponents, any other exponent must be a pure number with a pure base.

    Raises:
        UnitMismatch: the first operation whose operands cannot agree, with their units.
    """

    def of(e: sp.Basic) -> Dimension | _Any:
        if isinstance(e, sp.Float):
            return ANY
        if isinstance(e, sp.Number) or e in (sp.pi, sp.E):
            return {}
        if isinstance(e, sp.Symbol):
            d = dimension(units.get(e.name))
            return ANY if d is None else d
        if isinstance(e, sp.Add):
            known: list[tuple[sp.Basic, Dimension]] = []
            for term in e.args:
                if isinstance(term, sp.Number):  # an offset or threshold (0 in max(x, 0)): in the sum's unit
                    continue
                d = of(term)
                if d is not ANY:
                    assert isinstance(d, dict)
                    if known and not same(known[0][1], d):
                        raise UnitMismatch(f"{known[0][0]} [{show(known[0][1])}] + {term} [{show(d)}]")
                    known.append((term, d))
            return known[0][1] if known else ANY
        if isinstance(e, sp.Mul):
            out: Dimension = {}
            free = False
            for factor in e.args:
                d = of(factor)
                if d is ANY:
                    free = True
                else:
                    assert isinstance(d, dict)
                    out = _mul(out, d)
            return ANY if free else out
        if isinstance(e, sp.Pow):
            base, exp = e.args
            if isinstance(exp, sp.Number):
                d = of(base)
                return ANY if d is ANY else _scale(d, float(exp))  # type: ignore[arg-type]
            for part, what in ((exp, "exponent"), (base, "base of a power with a variable exponent")):
                d = of(part)
                if d is not ANY and d:
                    raise UnitMismatch(f"{what} {part} has units [{show(d)}], not a pure number")
            return {}
        if isinstance(e, (sp.Abs,)):
            return of(e.args[0])
        if isinstance(e, (sp.sign, sp.Heaviside)):
            of(e.args[0])
            return {}
        if isinstance(e, (sp.Min, sp.Max)):
            return of(sp.Add(*e.args, evaluate=False)) if len(e.args) > 1 else of(e.args[0])
        if isinstance(e, _PURE_FUNCTIONS):
            for arg in e.args:
                d = of(arg)
                if d is not ANY and d:
                    raise UnitMismatch(f"{type(e).__name__}({arg}) of units [{show(d)}], not a pure number")
            return {}
        if isinstance(e, sp.Piecewise):
            return of(sp.Add(*[branch for branch, _ in e.args], evaluate=False))
        return ANY  # a function this check does not know: nothing is claimed about it

    return of(expr)


def mismatch(expr: sp.Expr, units: Mapping[str, str], target_unit: str | None) -> str | None:
    """Why ``expr`` cannot be in ``target_unit`` with its symbols in ``units`` (None: it can).

    Unknown units are never a reason: only declared, readable units are checked."""
    try:
        d = formula_dimension(expr, units)
    except UnitMismatch as exc:
        return f"inconsistent units: {exc}"
    want = dimension(target_unit)
    if d is ANY or want is None:
        return None
    assert isinstance(d, dict)
    if not same(d, want):
        return f"units [{show(d)}] cannot be the equation's {target_unit} [{show(want)}]"
    return None


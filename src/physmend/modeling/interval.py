"""Interval-scale quantities in formulas: a temperature in °C enters a nonlinear term only as a difference.

A quantity in a unit with an offset (``degC``, ``degF``, a unit a model declares with
:meth:`physmend.modeling.Model.affine_unit`) has a zero that is a convention: moving the zero by
``s`` moves every quantity in that unit by ``s`` together. A formula may depend on that convention
only as a model written in that unit already does — linearly (``c·T``, ``c·T·u`` with ``u`` a
flow: the enthalpy carried by a flow): its value must be *affine in s*,
``f(T + s) = f(T) + s·g(T)``. Anything else (``sign(T)``, ``√|T|``, ``T²``, ``T1·T2``,
``exp(T)``, ``(T1 − 0.72·T2)²``) changes its shape with the chosen zero and cannot be physics.

The check is structural and right by construction. Every interval-scale symbol ``T_i`` of one unit
is shifted by one common ``s`` (one shift per affine unit: °C and °F have independent zeros). Each
node's *shift rate* ``∂node/∂s`` is built bottom-up — 1 for a shifted symbol, 0 for any other
atom, the sum for a sum, ``rate(f)·(other factors)`` for a product — and a node is refused where:

* a product has more than one factor whose rate is not zero (``T1·T2``, ``T·(T1 − 0.5·T2)``);
* a power with an exponent other than 1 has a base or exponent whose rate is not zero (``T²``,
  ``√|T|`` — the ``Abs`` inside is refused first —, ``1/T``, ``2**T``);
* ``Min``/``Max`` get arguments whose rates are not one and the same number (``Max(T − 3, 0)``
  refused; ``Min(T1, T2)`` and ``Max(T1 − T2, 0)`` pass: they move with the zero, or not at all);
* any other function or condition (``Abs``, ``sign``, ``Heaviside``, ``exp``, ``log``, ``tanh``,
  ``sin``, ``cos``, ``Piecewise`` …) gets an argument whose rate is not zero.

By induction every node that passes is affine in ``s``, so the whole formula is. A fitted constant
does not move with the zero: ``sign(T − 3.2)`` is refused like ``sign(T)``, as a back end fits the
0.03 of ``√|T + 0.03|`` as readily as a real reference temperature, and a formula that is only
invariant after re-fitting its constants would let every shape through with one constant more. The
mechanism catalogue's threshold forms (``c·Max(u − k, 0)``) are the exception, declared by the
caller: their ``k`` is chosen among the variable's own quantiles, a value on its scale, and is
passed to :func:`shift_violation` as shifting with it. A rate is tested for
zero as sympy leaves it (``1 − 1``, ``c − c``), then expanded where it is small; a formula larger
than :data:`MAX_NODES` nodes is refused unread (symbolic regression's formulas have tens).
"""

from __future__ import annotations

import re
from collections.abc import Hashable, Mapping

import sympy as sp

from physmend.modeling.evaluate import abs_bars
from physmend.modeling.units import is_affine

#: formulas with more nodes than this are refused without being walked (bounded time)
MAX_NODES = 5000
#: a rate with more operations than this is not expanded to test it for zero (it counts as not zero)
MAX_EXPAND_OPS = 200
#: the longest sub-expression quoted in a reason, and the longest reason
_QUOTE = 30
_REASON = 100
_DIGITS = re.compile(r"(\d\.\d{3})\d+|(\d{2,}\.\d)\d+|(\d\.\d{2})\d+")


def _text(e: sp.Basic) -> str:
    """``e`` as short text: unordered (printing is most of a refusal's cost), constants cut to a few digits."""
    text = abs_bars(sp.sstr(e, order="none", full_prec=False))
    return _DIGITS.sub(lambda m: next(g for g in m.groups() if g), text)


def _clip(text: str, size: int) -> str:
    return text if len(text) <= size else text[: size - 1] + "…"


def _zero(r: sp.Expr) -> bool:
    if r == 0:
        return True
    if r.is_number:
        return bool(abs(complex(r)) == 0)
    if sp.count_ops(r) > MAX_EXPAND_OPS:
        return False
    return sp.expand(r) == 0


def shift_violation(expr: sp.Basic, shifted: Mapping[sp.Symbol, Hashable]) -> str | None:
    """Why ``expr`` is not affine in the shifts of its interval-scale symbols (None: it is).

    Args:
        expr: the formula (sympy).
        shifted: each interval-scale symbol -> its scale (symbols of one scale shift together; e.g.
            the unit string); symbols not in it do not shift.

    Returns:
        A reason of at most 100 characters naming the offending sub-expression, or None.
    """
    try:
        if not shifted or not (expr.free_symbols & set(shifted)):
            return None
        size = sum(1 for _ in sp.preorder_traversal(expr))
    except RecursionError:  # nested deeper than Python's stack: no formula a back end returns
        return "too deeply nested to check for interval-scale quantities"
    if size > MAX_NODES:
        return f"too large to check for interval-scale quantities ({size} nodes > {MAX_NODES})"
    scales = sorted({str(g) for g in shifted.values()})
    of = {s: scales.index(str(g)) for s, g in shifted.items()}
    moving = set(shifted)
    zero = [sp.Integer(0)] * len(scales)
    memo: dict[sp.Basic, list[sp.Expr]] = {}

    class _Refused(Exception):
        pass

    def refuse(template: str, parts: tuple[sp.Basic, ...], scale: int) -> None:
        """Raise the reason: ``template`` with the quoted ``parts`` ({0}, {1}), shortened to fit."""
        texts = [_text(p) for p in parts]
        tail = f" depends on the zero of {scales[scale]}"
        for size in (_QUOTE, 20, 12, 6):
            why = template.format(*[_clip(t, size) for t in texts]) + tail
            if len(why) <= _REASON:
                break
        raise _Refused(_clip(why, _REASON))

    def moved(rates: list[sp.Expr]) -> int | None:
        """The first scale whose rate is not zero, or None."""
        return next((k for k, r in enumerate(rates) if not _zero(r)), None)

    def check_args(e: sp.Basic) -> None:
        for a in e.args:
            if isinstance(a, sp.core.relational.Relational):
                a = a.lhs - a.rhs  # a condition T > T2 compares a difference with zero
            elif not isinstance(a, sp.Expr):  # a (value, condition) pair, a tuple, And/Or of conditions
                if isinstance(a, sp.Basic):
                    check_args(a)
                continue
            k = moved(rate(a))
            if k is not None:
                refuse("{0}: the argument {1}", (e, a), k)

    def rate(e: sp.Basic) -> list[sp.Expr]:
        if e in memo:
            return memo[e]
        if not (getattr(e, "free_symbols", set()) & moving):
            out = zero
        elif isinstance(e, sp.Symbol):
            out = [sp.Integer(1) if k == of[e] else sp.Integer(0) for k in range(len(scales))]
        elif isinstance(e, sp.Add):
            parts = [rate(a) for a in e.args]
            out = [sp.Add(*[p[k] for p in parts]) for k in range(len(scales))]
        elif isinstance(e, sp.Mul):
            parts = [(f, rate(f)) for f in e.args]
            dep = [(f, r, moved(r)) for f, r in parts]
            dep = [(f, r, k) for f, r, k in dep if k is not None]
            if len(dep) > 1:
                refuse("product of {0} and {1}: each", (dep[0][0], dep[1][0]), dep[0][2])
            if not dep:
                out = zero
            else:
                f, r, _ = dep[0]
                rest = sp.Mul(*[g for g in e.args if g is not f])
                out = [rk * rest for rk in r]
        elif isinstance(e, sp.Pow):
            base, ex = e.args
            for part in (ex, base):
                k = moved(rate(part))
                if k is not None and ex != 1:
                    refuse("{0}: the " + ("base" if part is base else "exponent") + " {1}", (e, part), k)
            out = zero
        elif isinstance(e, (sp.Min, sp.Max)):
            parts = [rate(a) for a in e.args]
            for k in range(len(scales)):
                first = parts[0][k]
                if not first.is_number or any(not _zero(p[k] - first) for p in parts[1:]):
                    bad = next((a for a, p in zip(e.args, parts) if not _zero(p[k])), e.args[0])
                    refuse("{0} compares {1}, which", (e, bad), k)
            out = parts[0]
        else:  # any other function or condition: every argument must not move with the zero
            check_args(e)
            out = zero
        memo[e] = out
        return out

    try:
        rate(expr)
    except _Refused as exc:
        return str(exc)
    except RecursionError:
        return f"too deeply nested to check for interval-scale quantities ({size} nodes)"
    return None


def interval_symbols(expr: sp.Basic, units: Mapping[str, str]) -> dict[sp.Symbol, str]:
    """The symbols of ``expr`` whose unit (``units``: name -> unit string) has an offset -> that unit."""
    return {s: units[s.name].strip() for s in expr.free_symbols
            if isinstance(s, sp.Symbol) and is_affine(units.get(s.name))}


def interval_violation(expr: sp.Basic, units: Mapping[str, str]) -> str | None:
    """Why ``expr`` uses a quantity on an interval scale (°C, °F, a declared affine unit) other than
    linearly or as a difference (None: it does not). ``units``: symbol name -> unit string; a
    symbol without a unit or in an absolute unit (K) is never a reason. See the module docstring."""
    return shift_violation(expr, interval_symbols(expr, units))

"""Rewrites of sympy expressions into the functions a torch (or numpy) printer can write.

sympy's torch printer knows ``sin cos tan asin acos atan atan2 sinh cosh tanh asinh acosh atanh
exp log sqrt Abs sign floor ceiling Min Max Heaviside Piecewise erf …`` but not the reciprocal
trigonometric and hyperbolic functions and their inverses, ``frac``, ``erfc`` or ``sinc``; a model
written with ``sympy.cot`` would not compile (``Unsupported by TorchPrinter: cot``).
:func:`for_torch` rewrites each into functions the printer has, with the same values on the real
line (sympy's conventions):

==========  ============================  ==========  ============================
``cot(a)``  ``cos(a)/sin(a)``             ``acot(a)`` ``atan(1/a)``
``sec(a)``  ``1/cos(a)``                  ``asec(a)`` ``acos(1/a)``
``csc(a)``  ``1/sin(a)``                  ``acsc(a)`` ``asin(1/a)``
``coth(a)`` ``cosh(a)/sinh(a)``           ``acoth(a)`` ``atanh(1/a)``
``sech(a)`` ``1/cosh(a)``                 ``asech(a)`` ``acosh(1/a)``
``csch(a)`` ``1/sinh(a)``                 ``acsch(a)`` ``asinh(1/a)``
``frac(a)`` ``a - floor(a)``              ``erfc(a)`` ``1 - erf(a)``
``sinc(a)`` ``sin(a)/a`` (1 at 0)         ``log(a, b)`` ``log(a)/log(b)`` (sympy's own)
==========  ============================  ==========  ============================

A function of numbers only (``cot(2)``, ``log(2)``, ``exp(-1)``) becomes its floating-point value
(torch functions take tensors, not Python numbers). Everything else is left as it is, so an
expression without these functions comes back unchanged (the same object).
"""

from __future__ import annotations

from collections.abc import Callable

import sympy as sp

#: function class -> the same function written with functions every printer knows
REWRITES: dict[type, Callable[[sp.Expr], sp.Expr]] = {
    sp.cot: lambda a: sp.cos(a) / sp.sin(a),
    sp.sec: lambda a: 1 / sp.cos(a),
    sp.csc: lambda a: 1 / sp.sin(a),
    sp.acot: lambda a: sp.atan(1 / a),
    sp.asec: lambda a: sp.acos(1 / a),
    sp.acsc: lambda a: sp.asin(1 / a),
    sp.coth: lambda a: sp.cosh(a) / sp.sinh(a),
    sp.sech: lambda a: 1 / sp.cosh(a),
    sp.csch: lambda a: 1 / sp.sinh(a),
    sp.acoth: lambda a: sp.atanh(1 / a),
    sp.asech: lambda a: sp.acosh(1 / a),
    sp.acsch: lambda a: sp.asinh(1 / a),
    sp.frac: lambda a: a - sp.floor(a),
    sp.erfc: lambda a: 1 - sp.erf(a),
    sp.sinc: lambda a: sp.Piecewise((sp.Integer(1), sp.Eq(a, 0)), (sp.sin(a) / a, True)),
}


def _numeric_function(e: sp.Basic) -> bool:
    return isinstance(e, sp.Function) and not e.free_symbols and bool(e.is_number)


def _as_float(e: sp.Expr) -> sp.Expr:
    value = e.evalf(20)
    return sp.Float(value, 20) if value.is_real and value.is_finite else e


def for_torch(expr: sp.Expr) -> sp.Expr:
    """``expr`` with every function of :data:`REWRITES` rewritten and every function of numbers only
    evaluated to a float (see the module docstring); the same values on the real line."""
    expr = sp.sympify(expr)
    if not isinstance(expr, sp.Basic) or not expr.args:
        return expr
    present = {type(f) for f in expr.atoms(sp.Function)}
    for cls in REWRITES:
        if cls in present:
            expr = expr.replace(cls, REWRITES[cls])  # called with the function's argument
    if any(_numeric_function(f) for f in expr.atoms(sp.Function)):
        expr = expr.replace(_numeric_function, _as_float)
    return expr

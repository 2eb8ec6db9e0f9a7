"""A restricted parser for formulas read from files, stores and regression back ends.

Whatever a run's artifacts, a corrections file or a back end's output says is data, never code:
``sympy.sympify`` evaluates Python, so it is never used on such text. This parser walks Python's
syntax tree and accepts only

* numbers (finite, at most 1e300 in size), the constants ``pi`` and ``E``;
* names of known symbols (``symbols``), or any plain name when ``new_symbols`` is true (templates,
  Pareto fronts); dotted model names such as ``zone1.air.T`` are allowed; names starting with an
  underscore never are;
* ``+ - * / **`` (and ``^``, read as ``**``), unary ``-`` and ``+``; numeric exponents up to
  ``MAX_EXPONENT`` in size;
* calls of whitelisted functions (``sqrt exp log Abs/abs sign tanh sin cos cot atan2 Min/min Max/max
  powabs floor …``) and,
  for ``srepr`` text, the constructors ``Add Mul Pow Symbol('name') Float('1.5', precision=53)
  Integer(2) Rational(1, 2)``.

Anything else — attributes, subscripts, lambdas, comprehensions, keyword arguments (but
``precision``), strings outside ``Symbol``/``Float`` — is refused with one :class:`ModelError` line
naming ``where`` and the offending piece.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Mapping

import sympy as sp

from physmend.modeling.errors import ModelError

MAX_LENGTH = 20_000  # characters
MAX_NODES = 5_000
MAX_EXPONENT = 64
MAX_NUMBER = 1e300
MAX_DEPTH = 200  # nesting of the syntax tree: far below Python's recursion limit
QUOTE = 60  # characters of the offending text an error quotes


def quoted(text: str, limit: int = QUOTE) -> str:
    """``repr`` of ``text``, cut to about ``limit`` characters (an error never echoes a whole file)."""
    return repr(text) if len(text) <= limit else repr(text[:limit]) + f"… ({len(text)} characters)"


def _depth(tree: ast.AST) -> int:
    """The nesting depth of ``tree``, found without recursion."""
    deepest, stack = 0, [(tree, 1)]
    while stack:
        node, d = stack.pop()
        deepest = max(deepest, d)
        stack.extend((child, d + 1) for child in ast.iter_child_nodes(node))
    return deepest

FUNCTIONS: dict[str, object] = {
    "sqrt": sp.sqrt, "exp": sp.exp, "log": sp.log, "Abs": sp.Abs, "abs": sp.Abs, "sign": sp.sign,
    "tanh": sp.tanh, "sin": sp.sin, "cos": sp.cos, "tan": sp.tan, "sinh": sp.sinh, "cosh": sp.cosh,
    "atan": sp.atan, "Min": sp.Min, "min": sp.Min, "Max": sp.Max, "max": sp.Max, "Heaviside": sp.Heaviside,
    "cbrt": sp.cbrt, "square": lambda x: x**2, "Add": sp.Add, "Mul": sp.Mul, "asin": sp.asin, "acos": sp.acos,
    "sqrtabs": lambda x: sp.sqrt(sp.Abs(x)), "logabs": lambda x: sp.log(sp.Abs(x)), "log1p": lambda x: sp.log(1 + x),
    "powabs": lambda a, b: sp.Abs(a) ** b, "cot": sp.cot, "sec": sp.sec, "csc": sp.csc, "acot": sp.acot,
    "asec": sp.asec, "acsc": sp.acsc, "coth": sp.coth, "sech": sp.sech, "csch": sp.csch, "asinh": sp.asinh,
    "acosh": sp.acosh, "atanh": sp.atanh, "acoth": sp.acoth, "asech": sp.asech, "acsch": sp.acsch,
    "atan2": sp.atan2, "floor": sp.floor, "ceiling": sp.ceiling, "ceil": sp.ceiling, "erf": sp.erf,
    "erfc": sp.erfc, "frac": sp.frac, "sinc": sp.sinc,
}
CONSTANTS = {"pi": sp.pi, "E": sp.E}
_DOTTED = re.compile(r"(?<![\w.'\"])([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)+)")
_STRING_ARG = re.compile(r"^[A-Za-z_][\w.]*$")


def parse_safe(text: str, symbols: Mapping[str, sp.Symbol] | None = None, *, where: str = "expression",
               new_symbols: bool = False) -> sp.Expr:
    """The sympy expression of ``text`` (see the module docstring for what is accepted).

    ``symbols``: name -> symbol of the known variables (dotted names allowed); with ``new_symbols``
    any other plain name becomes a new symbol of that name.
    """
    if not isinstance(text, str):
        raise ModelError(f"{where}: a formula must be text, but got {type(text).__name__}")
    if len(text) > MAX_LENGTH:
        raise ModelError(f"{where}: a formula may have at most {MAX_LENGTH} characters, but has {len(text)}")
    known = dict(symbols or {})
    tokens: dict[str, str] = {}

    def repl(match: re.Match[str]) -> str:
        token = f"v{len(tokens)}x_dotted"
        tokens[token] = match.group(1)
        return token

    plain = _DOTTED.sub(repl, text).replace("^", "**")  # a power, as back ends write it (never XOR)
    try:
        tree = ast.parse(plain.strip(), mode="eval")
    except SyntaxError as exc:
        raise ModelError(f"{where}: {quoted(text)} is not a valid formula ({exc.msg})") from None
    except (RecursionError, MemoryError):
        raise ModelError(f"{where}: {quoted(text)} is nested too deeply (at most {MAX_DEPTH} levels)") from None
    if sum(1 for _ in ast.walk(tree)) > MAX_NODES:
        raise ModelError(f"{where}: a formula may have at most {MAX_NODES} syntax nodes")
    if _depth(tree) > MAX_DEPTH:
        raise ModelError(f"{where}: {quoted(text)} is nested too deeply (at most {MAX_DEPTH} levels)")

    def refuse(what: str) -> ModelError:
        return ModelError(f"{where}: {quoted(text)} is not allowed in a formula: {what}")

    def symbol(name: str) -> sp.Symbol:
        name = tokens.get(name, name)
        if name.startswith("_") or "__" in name:
            raise refuse(f"the name {name!r}")
        if name in known:
            return known[name]
        if new_symbols:
            return sp.Symbol(name)
        raise ModelError(f"{where}: uses {name!r}, which is not a known variable or constant")

    def number(value: object) -> sp.Expr:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise refuse(f"the constant {value!r}")
        if not math.isfinite(float(value)) or abs(float(value)) > MAX_NUMBER:
            raise refuse(f"the number {value!r} (finite and at most {MAX_NUMBER:g} in size)")
        return sp.Integer(value) if isinstance(value, int) else sp.Float(value)

    def power(base: sp.Expr, exponent: sp.Expr) -> sp.Expr:
        if exponent.is_number:
            # a plain number only: evaluating a symbolic one (exp(exp(exp(100)))) would not end
            if not isinstance(exponent, sp.Number) or not exponent.is_finite:
                raise refuse("an exponent that is not a plain number or a formula of the variables")
            if abs(float(exponent)) > MAX_EXPONENT:
                raise refuse(f"an exponent of size {float(exponent):.4g} (at most {MAX_EXPONENT})")
            if isinstance(base, sp.Number) and base != 0:
                # the size of the result before it is built: 9**64 is fine, (9**64)**64 is not
                size = abs(float(exponent)) * abs(math.log10(abs(float(base))) if abs(float(base)) != math.inf else math.inf)
                if not size <= math.log10(MAX_NUMBER):
                    raise refuse(f"a power of a number whose result exceeds {MAX_NUMBER:g} in size")
        elif base.is_number:
            raise refuse("a number raised to a variable power")
        return sp.Pow(base, exponent)

    def string_arg(node: ast.AST) -> str:
        if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
            raise refuse("a constructor needs one string argument")
        value = tokens.get(node.value, node.value)
        return value

    def visit(node: ast.AST) -> sp.Expr:
        if isinstance(node, ast.Expression):
            return visit(node.body)
        if isinstance(node, ast.Constant):
            return number(node.value)
        if isinstance(node, ast.Name):
            if node.id in CONSTANTS and node.id not in known:
                return CONSTANTS[node.id]
            return symbol(node.id)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            value = visit(node.operand)
            return -value if isinstance(node.op, ast.USub) else value
        if isinstance(node, ast.BinOp):
            a, b = visit(node.left), visit(node.right)
            if isinstance(node.op, ast.Add):
                return a + b
            if isinstance(node.op, ast.Sub):
                return a - b
            if isinstance(node.op, ast.Mult):
                return a * b
            if isinstance(node.op, ast.Div):
                return a / b
            if isinstance(node.op, ast.Pow):
                return power(a, b)
            raise refuse(f"the operator {type(node.op).__name__}")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            name = node.func.id
            kwargs = {k.arg: k.value for k in node.keywords}
            if name == "Symbol" and len(node.args) == 1 and not kwargs:
                text_arg = string_arg(node.args[0])
                if not _STRING_ARG.fullmatch(text_arg):
                    raise refuse(f"the symbol name {text_arg!r}")
                return symbol(text_arg)
            if name == "Float" and len(node.args) == 1 and set(kwargs) <= {"precision"}:
                arg = node.args[0]
                raw = string_arg(arg) if isinstance(arg, ast.Constant) and isinstance(arg.value, str) else None
                try:
                    value = float(raw) if raw is not None else float(visit(arg))
                except (TypeError, ValueError):
                    raise refuse(f"the number {raw!r}") from None
                return number(value)
            if name == "Integer" and len(node.args) == 1 and not kwargs:
                return number(int(visit(node.args[0])))
            if name == "Rational" and len(node.args) == 2 and not kwargs:
                p, q = (visit(a) for a in node.args)
                if not (p.is_Integer and q.is_Integer) or q == 0:
                    raise refuse("Rational needs two integers, the second non-zero")
                return sp.Rational(int(p), int(q))
            if name == "Pow" and len(node.args) == 2 and not kwargs:
                return power(visit(node.args[0]), visit(node.args[1]))
            if name in FUNCTIONS and not kwargs and node.args:
                return FUNCTIONS[name](*[visit(a) for a in node.args])  # type: ignore[operator]
            raise refuse(f"the call {name}(…)")
        raise refuse(f"the syntax {type(node).__name__}")

    try:
        return visit(tree)
    except ModelError:
        raise
    except (TypeError, ValueError, ZeroDivisionError, OverflowError) as exc:
        raise ModelError(f"{where}: {quoted(text)} is not a valid formula ({str(exc)[:QUOTE]})") from None
    except RecursionError:
        raise ModelError(f"{where}: {quoted(text)} is nested too deeply (at most {MAX_DEPTH} levels)") from None

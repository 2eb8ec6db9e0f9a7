"""Sympy expressions to torch functions: one tensor per argument, functions the torch printer lacks
rewritten (:mod:`physmend.modeling.rewrite`), ``Max``/``Min``/``Heaviside``/``sqrt`` with the
values and gradients a solver needs (see :func:`lambdify_torch`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextvars import ContextVar

import sympy as sp
import torch

from physmend.modeling.errors import ModelError
from physmend.modeling.recent import Recent
from physmend.modeling.rewrite import for_torch


def _maximum(*args: object) -> torch.Tensor:
    out = args[0]
    for a in args[1:]:
        out = _pair(out, a, torch.maximum, "min")
    return out  # type: ignore[return-value]


def _minimum(*args: object) -> torch.Tensor:
    out = args[0]
    for a in args[1:]:
        out = _pair(out, a, torch.minimum, "max")
    return out  # type: ignore[return-value]


def _pair(a: object, b: object, both: Callable, clamp_kw: str) -> object:
    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        return both(a, b)
    if isinstance(a, torch.Tensor):
        return torch.clamp(a, **{clamp_kw: b})
    if isinstance(b, torch.Tensor):
        return torch.clamp(b, **{clamp_kw: a})
    return max(a, b) if clamp_kw == "min" else min(a, b)  # type: ignore[type-var]


def _sqrt(x: object) -> torch.Tensor:
    """``sqrt`` whose gradient at 0 is 0 instead of inf (so ``d·sqrt(|d|)`` differentiates to 0,
    not NaN, where ``d = 0``, e.g. two temperatures starting equal); NaN below 0 as usual. Where no
    gradient is taken (solves under ``no_grad``, finite differences) the values are ``torch.sqrt``'s
    and so is the cost (one operation instead of five)."""
    x = torch.as_tensor(x)
    if not (x.requires_grad and torch.is_grad_enabled()):
        return torch.sqrt(x)
    pos = x > 0
    root = torch.sqrt(torch.where(pos, x, torch.ones_like(x)))
    return torch.where(pos, root, torch.where(x == 0, torch.zeros_like(x), torch.full_like(x, float("nan"))))


#: the floating dtype of the arguments of the compiled function being called (see :func:`_where`)
_ARG_DTYPE: ContextVar[torch.dtype | None] = ContextVar("physmend_arg_dtype", default=None)


def _heaviside(x: object, h0: object = 0.5) -> torch.Tensor:
    """sympy's ``Heaviside(x, h0)``: 0 below 0, ``h0`` at 0, 1 above, with gradient 0 (torch's own
    ``heaviside`` has no derivative, so a model holding it could not be trained)."""
    x = torch.as_tensor(x, dtype=_ARG_DTYPE.get() if not isinstance(x, torch.Tensor) else None)
    one, zero = torch.ones_like(x), torch.zeros_like(x)
    return torch.where(x > 0, one, torch.where(x < 0, zero, torch.as_tensor(h0, dtype=x.dtype, device=x.device)))


def _where(cond: object, a: object, b: object) -> object:
    """``torch.where`` for sympy's ``Piecewise``; a choice between two plain numbers (``Piecewise((1.5,
    x > 0), (0, True))``) is made in the arguments' dtype, not torch's default (float32) or int64."""
    if not isinstance(cond, torch.Tensor):
        return a if cond else b
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return torch.where(cond, a, b)  # type: ignore[arg-type]
    dtype = _ARG_DTYPE.get() or torch.get_default_dtype()
    return torch.where(cond, torch.as_tensor(a, dtype=dtype, device=cond.device),
                       torch.as_tensor(b, dtype=dtype, device=cond.device))


_OVERRIDES = {"max": _maximum, "min": _minimum, "heaviside": _heaviside, "sqrt": _sqrt, "where": _where}


def _in_arg_dtype(fn: Callable[..., list]) -> Callable[..., list]:
    """``fn`` run with :data:`_ARG_DTYPE` set to its first floating tensor argument's dtype."""

    def call(*args: object) -> list:
        like = next((a.dtype for a in args if isinstance(a, torch.Tensor) and a.is_floating_point()), None)
        token = _ARG_DTYPE.set(like)
        try:
            return fn(*args)
        finally:
            _ARG_DTYPE.reset(token)

    return call


#: functions lambdified in this process, by their arguments and expressions (most recent last): a
#: corrected model shares its outputs, observed equations, start values and most coefficients with
#: the model as written, and a formula tried after another shares them with the one before
_LAMBDIFIED: Recent[Callable[..., list]] = Recent(256)


def lambdify_torch(
    args: Sequence[sp.Symbol], exprs: Sequence[sp.Expr], what: str
) -> Callable[..., list]:
    """Lambdify ``exprs`` of ``args`` into a function of tensors (one tensor per argument).

    Functions the torch printer lacks (``cot``, ``sech``, ``acsc`` …) are rewritten first
    (:func:`physmend.modeling.rewrite.for_torch`), with the same values. ``what`` names the
    expressions in an error. The function is stateless: the same arguments and expressions give the
    one made before in this process."""
    return _LAMBDIFIED.get((tuple(args), tuple(sp.sympify(e) for e in exprs)), lambda: _lambdify_anew(args, exprs, what))


def _lambdify_anew(args: Sequence[sp.Symbol], exprs: Sequence[sp.Expr], what: str) -> Callable[..., list]:
    safe = {s: sp.Symbol(f"a{i}", real=True) for i, s in enumerate(args)}
    renamed = [for_torch(sp.sympify(e).xreplace(safe)) for e in exprs]
    stray = set().union(*(e.free_symbols for e in renamed)) - set(safe.values()) if renamed else set()
    if stray:
        raise ModelError(f"{what}: expression uses symbols that are not arguments: {sorted(map(str, stray))}")
    try:
        fn = sp.lambdify(list(safe.values()), renamed, modules=[_OVERRIDES, "torch"], cse=True)
    except Exception as exc:  # sympy raises many types for unsupported functions
        raise ModelError(f"{what}: cannot compile to torch ({exc})") from exc
    return _in_arg_dtype(fn) if any(e.has(sp.Piecewise, sp.Heaviside) for e in renamed) else fn


def _stack(values: list, like: torch.Tensor) -> torch.Tensor:
    """``values`` (tensors or numbers) broadcast to ``like``'s shape and stacked on a last axis."""
    if values and all(isinstance(v, torch.Tensor) and v.shape == like.shape for v in values):
        return torch.stack(values, dim=-1)  # the usual case in a solve: no broadcasting to do
    tensors = [
        v if isinstance(v, torch.Tensor) else torch.as_tensor(float(v), dtype=like.dtype, device=like.device)
        for v in values
    ]
    return torch.stack(torch.broadcast_tensors(*tensors, like), dim=-1)[..., :-1] if tensors else like[..., :0]

"""Compilation of a simplified model to batched, differentiable torch functions.

Shapes: ``u`` states ``(..., n_states)``, ``x`` inputs ``(..., n_inputs)``, ``p`` parameters
``(..., n_params)``; any leading dimensions (batch of experiments or segments, time) broadcast.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import sympy as sp
import torch

from physmend.modeling.errors import ModelError
from physmend.modeling.simplify import SimplifiedModel


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


def _heaviside(x: torch.Tensor, h0: float = 0.5) -> torch.Tensor:
    return torch.heaviside(x, torch.as_tensor(h0, dtype=x.dtype, device=x.device))


_OVERRIDES = {"max": _maximum, "min": _minimum, "heaviside": _heaviside}


def lambdify_torch(
    args: Sequence[sp.Symbol], exprs: Sequence[sp.Expr], what: str
) -> Callable[..., list]:
    """Lambdify ``exprs`` of ``args`` into a function of tensors (one tensor per argument)."""
    safe = {s: sp.Symbol(f"a{i}", real=True) for i, s in enumerate(args)}
    renamed = [sp.sympify(e).xreplace(safe) for e in exprs]
    stray = set().union(*(e.free_symbols for e in renamed)) - set(safe.values()) if renamed else set()
    if stray:
        raise ModelError(f"{what}: expression uses symbols that are not arguments: {sorted(map(str, stray))}")
    try:
        return sp.lambdify(list(safe.values()), renamed, modules=[_OVERRIDES, "torch"], cse=True)
    except Exception as exc:  # sympy raises many types for unsupported functions
        raise ModelError(f"{what}: cannot compile to torch ({exc})") from exc


def _stack(values: list, like: torch.Tensor) -> torch.Tensor:
    tensors = [
        v if isinstance(v, torch.Tensor) else torch.as_tensor(float(v), dtype=like.dtype, device=like.device)
        for v in values
    ]
    return torch.stack(torch.broadcast_tensors(*tensors, like), dim=-1)[..., :-1] if tensors else like[..., :0]


@dataclass
class CompiledModel:
    """Torch functions of a :class:`SimplifiedModel` (see module docstring for shapes)."""

    model: SimplifiedModel
    _rhs: Callable[..., list]
    _observed: Callable[..., list]
    _outputs: Callable[..., list]
    _start: Callable[..., list]

    @property
    def state_names(self) -> list[str]:
        return self.model.state_names

    @property
    def input_names(self) -> list[str]:
        return self.model.input_names

    @property
    def parameter_names(self) -> list[str]:
        return self.model.parameter_names

    @property
    def output_names(self) -> list[str]:
        return self.model.output_names

    @property
    def observed_names(self) -> list[str]:
        return list(self.model.observed)

    def _call(self, fn: Callable[..., list], u: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        lead = torch.broadcast_shapes(u.shape[:-1], x.shape[:-1], p.shape[:-1])
        like = torch.zeros(lead, dtype=u.dtype, device=u.device)
        return _stack(fn(*u.unbind(-1), *x.unbind(-1), *p.unbind(-1)), like)

    def rhs(self, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Derivatives ``du/dt``, shape ``(..., n_states)`` in state units per second."""
        return self._call(self._rhs, u, x, p)

    def observed(self, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Algebraic (observed) variables, shape ``(..., n_observed)``."""
        return self._call(self._observed, u, x, p)

    def outputs(self, u: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Measured outputs, shape ``(..., n_outputs)``."""
        return self._call(self._outputs, u, x, p)

    def start(self, p: torch.Tensor) -> torch.Tensor:
        """Default initial states from parameters ``p (..., n_params)``: ``(..., n_states)``."""
        like = torch.zeros(p.shape[:-1], dtype=p.dtype, device=p.device)
        return _stack(self._start(*p.unbind(-1)), like)

    def default_parameters(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Parameter values as declared, shape ``(n_params,)``."""
        return torch.tensor([v.value for v in self.model.parameters], dtype=dtype)


def compile_model(model: SimplifiedModel) -> CompiledModel:
    """Compile the explicit ODE, observed equations, outputs and start values to torch."""
    u = [v.symbol for v in model.states]
    x = [v.symbol for v in model.inputs]
    p = [v.symbol for v in model.parameters]
    args = u + x + p
    starts = []
    for v in model.states:
        start = v.start if v.start is not None else sp.Integer(0)
        bad = start.free_symbols - set(p)
        if bad:
            raise ModelError(
                f"model {model.name!r}: start value of state {v.name!r} may depend on parameters "
                f"only, but uses {sorted(map(str, bad))}"
            )
        starts.append(start)
    return CompiledModel(
        model=model,
        _rhs=lambdify_torch(args, [model.rhs[n] for n in model.state_names], f"model {model.name!r} derivatives"),
        _observed=lambdify_torch(args, list(model.observed.values()), f"model {model.name!r} observed equations"),
        _outputs=lambdify_torch(args, list(model.outputs.values()), f"model {model.name!r} outputs"),
        _start=lambdify_torch(p, starts, f"model {model.name!r} start values"),
    )

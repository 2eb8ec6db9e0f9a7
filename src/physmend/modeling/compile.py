"""Compilation of a simplified model to batched, differentiable torch functions.

Shapes: ``u`` states ``(..., n_states)``, ``x`` inputs ``(..., n_inputs)``, ``p`` parameters
``(..., n_params)``; any leading dimensions (batch of experiments or segments, time) broadcast.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import sympy as sp
import torch

from physmend.modeling.errors import ModelError
from physmend.modeling.lambdify import _stack, lambdify_torch
from physmend.modeling.simplify import SimplifiedModel

__all__ = ["AffineSplit", "BoundRhs", "CompiledModel", "compile_model", "lambdify_torch"]


@dataclass
class AffineSplit:
    """Rows of ``du/dt`` that are affine in states and inputs: ``A(p) u + B(p) x + c(p)``.

    The flat entries are A row-major, then B, then c: ``constant`` holds every entry that does not
    depend on the parameters (most are zeros), ``coeffs(p)`` returns the others, at the flat
    positions ``varying``. Rows listed in ``nonlinear`` also have terms that are not affine in
    states and inputs (``x·y``, ``sqrt(x)``): ``rest`` evaluates those terms only, added to the
    row's affine part (a correction added to a large equation costs the correction, not the
    equation).
    """

    n_states: int
    n_inputs: int
    coeffs: Callable[..., list]
    nonlinear: list[int]
    rest: Callable[..., list] | None
    constant: list[float] = field(default_factory=list)
    varying: list[int] = field(default_factory=list)
    #: the states, inputs and parameters ``rest`` takes, by index (it takes only those its terms use)
    rest_args: tuple[list[int], list[int], list[int]] = ([], [], [])
    _tensors: dict[Any, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict, repr=False)

    def flat(self, p: torch.Tensor) -> torch.Tensor:
        """All entries for parameters ``p (..., n_params)``: ``(..., n² + n·m + n)``."""
        key = (p.dtype, p.device)
        if key not in self._tensors:
            self._tensors[key] = (torch.tensor(self.constant, dtype=p.dtype, device=p.device),
                                  torch.tensor(self.varying, dtype=torch.long, device=p.device))
        const, where = self._tensors[key]
        base = const.expand(*p.shape[:-1], const.shape[0])
        if not self.varying:
            return base.clone()
        like = torch.zeros(p.shape[:-1], dtype=p.dtype, device=p.device)
        return base.index_copy(-1, where, _stack(self.coeffs(*p.unbind(-1)), like))


def _linear_in(term: sp.Expr, ux: set) -> bool:
    """True when ``term`` is ``k(p)·s`` for one state or input ``s`` or a sum of such (``k`` free of ``ux``)."""
    return not any(sp.diff(term, s).free_symbols & ux for s in term.free_symbols & ux)


@functools.lru_cache(maxsize=4096)
def _row_split(rhs: sp.Expr, u: tuple, x: tuple) -> tuple[sp.Expr | None, tuple, tuple, sp.Expr]:
    """One row ``du_i/dt = rhs`` split: its terms not affine in the states ``u`` and inputs ``x``
    (None: every term is), and the affine rest's coefficients of ``u``, of ``x`` and its constant.
    Kept per row: a corrected model (the model as written plus a term or two) or a formula tried
    after another builds the rows it shares with them again (seconds of sympy for tens of states)."""
    ux = set(u) | set(x)
    e = sp.expand(rhs) if rhs.count_ops() < 400 else rhs
    terms = sp.Add.make_args(e)
    rest = [t for t in terms if not _linear_in(t, ux)]
    remainder = None
    if rest:  # the terms affine in states and inputs stay in A, B, c; ``rest`` adds the others
        remainder = sp.Add(*rest)
        e = sp.Add(*[t for t in terms if t not in rest])
    return (remainder, tuple(sp.diff(e, s) for s in u), tuple(sp.diff(e, s) for s in x),
            e.xreplace({s: 0 for s in ux}))


def _affine_split(model: SimplifiedModel, u: list, x: list, p: list) -> AffineSplit:
    n, m = len(u), len(x)
    entries: list[sp.Expr] = [sp.Integer(0)] * (n * n + n * m + n)
    nonlinear: list[int] = []
    remainders: list[sp.Expr] = []
    for i, name in enumerate(model.state_names):
        remainder, by_state, by_input, constant_term = _row_split(model.rhs[name], tuple(u), tuple(x))
        if remainder is not None:
            nonlinear.append(i)
            remainders.append(remainder)
        entries[i * n : (i + 1) * n] = by_state
        entries[n * n + i * m : n * n + (i + 1) * m] = by_input
        entries[n * n + n * m + i] = constant_term
    entries = [sp.sympify(e) for e in entries]
    constant = [float(e) if e.is_number and e.is_real else 0.0 for e in entries]
    varying = [k for k, e in enumerate(entries) if not (e.is_number and e.is_real)]
    coeffs = lambdify_torch(p, [entries[k] for k in varying], f"model {model.name!r} affine coefficients")
    used = set().union(*(r.free_symbols for r in remainders)) if remainders else set()
    picks = ([j for j, s in enumerate(u) if s in used], [k for k, s in enumerate(x) if s in used],
             [k for k, s in enumerate(p) if s in used])
    rest_fn = None
    if nonlinear:
        args = [u[j] for j in picks[0]] + [x[k] for k in picks[1]] + [p[k] for k in picks[2]]
        rest_fn = lambdify_torch(args, remainders, f"model {model.name!r} derivatives")
    return AffineSplit(n, m, coeffs, nonlinear, rest_fn, constant, varying, picks)


class BoundRhs:
    """``du/dt`` for fixed parameters ``p (B, n_params)``: call with ``u (..., B, n)``, ``x (..., B, m)``.

    Affine rows cost one batched matrix product; the coefficients are computed once here.
    Gradients flow to ``p`` through the coefficients. With ``rows (B,)`` (indices into ``p (E,
    n_params)``) batch element ``b`` has the parameters ``p[rows[b]]``: many segments of a few
    experiments share a few matrices, and a step is one plain product with all of them (each
    row keeps its own block) instead of a product per element, whose gradient with respect to the
    matrices is an outer product per element.
    """

    #: the shared-matrix product does ``E`` times a per-element product's arithmetic and a few more
    #: operations: it pays from this many states (measured, one thread: 0.73-0.86 of the per-element
    #: time at 16-28 states and 2-4 experiments; 1.2-1.75 times it at 2-8 states) ...
    SHARED_MIN_STATES = 16
    #: ... up to this many columns ``E·n`` of the shared product
    SHARED_MAX_COLUMNS = 128

    @classmethod
    def pays(cls, n_states: int, n_matrices: int) -> bool:
        """True where one product with ``n_matrices`` shared matrices beats a product per row."""
        return n_states >= cls.SHARED_MIN_STATES and n_matrices * n_states <= cls.SHARED_MAX_COLUMNS

    def __init__(self, split: AffineSplit, p: torch.Tensor, rows: torch.Tensor | None = None) -> None:
        n, m = split.n_states, split.n_inputs
        self._shared: tuple[torch.Tensor, torch.Tensor | None, torch.Tensor] | None = None
        if rows is not None:
            used, rows = torch.unique(rows, return_inverse=True)  # by index, never by value
            p = p[used]
        flat = split.flat(p)
        A = flat[..., : n * n].reshape(*p.shape[:-1], n, n)
        B = flat[..., n * n : n * n + n * m].reshape(*p.shape[:-1], n, m)
        c = flat[..., n * n + n * m :]
        if rows is not None:
            e = p.shape[0]
            if self.pays(n, e):
                pick = rows.view(-1, 1, 1).expand(-1, 1, n)  # (S, 1, n): each row's block
                self._shared = (A.transpose(-1, -2).permute(1, 0, 2).reshape(n, e * n),
                                B.transpose(-1, -2).permute(1, 0, 2).reshape(m, e * n) if m else None, pick)
            A, B, c, p = A[rows], B[rows], c[rows], p[rows]
        self.A, self.B, self.c, self.p = A, B, c, p
        self.split = split
        # the remainder's parameter columns, taken once (per call where they carry a gradient: a
        # bound physics may serve several backward passes, each needing its own graph)
        self._rest_p = p[..., split.rest_args[2]].unbind(-1) if split.rest is not None and not p.requires_grad else None

    def linear(self, u: torch.Tensor) -> torch.Tensor:
        """``A·u`` for ``u (..., B, n)``: ``(..., B, n)``."""
        if self._shared is not None and u.dim() == 2 and u.shape[0] == self.A.shape[0]:
            at, _, pick = self._shared
            return (u @ at).view(u.shape[0], -1, u.shape[1]).gather(1, pick).squeeze(1)
        return _matvec(self.A, u)

    def linear_plus(self, u: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        """``A·u + d`` for ``u``, ``d (B, n)`` (one fused product where the matrices are per row)."""
        if self._shared is None and u.dim() == 2 and self.A.dim() == 3 and self.A.shape[0] == u.shape[0]:
            return torch.baddbmm(d.unsqueeze(-1), self.A, u.unsqueeze(-1)).squeeze(-1)
        return self.linear(u) + d

    def _affine_part(self, u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        shared = self._shared is not None and u.dim() == 2 and x.dim() == 2 and u.shape[0] == self.A.shape[0]
        if shared and self._shared[1] is not None:  # A·u + B·x in one product and one pick
            at, bt, pick = self._shared
            lin = torch.addmm(u @ at, x, bt)
            return lin.view(u.shape[0], -1, u.shape[1]).gather(1, pick).squeeze(1) + self.c
        du = self.linear(u) + self.c
        if self.split.n_inputs:
            du = du + _matvec(self.B, x)
        return du

    def __call__(self, u: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        du = self._affine_part(u, x)
        if self.split.rest is not None:
            su, sx, sp_ = u.shape[:-1], x.shape[:-1], self.p.shape[:-1]
            lead = su if su == sx == sp_ else torch.broadcast_shapes(su, sx, sp_)
            like = u.new_zeros(lead)
            iu, ix, ip = self.split.rest_args
            rest_p = self._rest_p if self._rest_p is not None else self.p[..., ip].unbind(-1)
            vals = _stack(self.split.rest(*u[..., iu].unbind(-1), *x[..., ix].unbind(-1), *rest_p), like)
            du = _scatter_add(du, vals, self.split.nonlinear)
        return du


def _matvec(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``a (B, r, c)`` times ``v (..., B, c)``: ``(..., B, r)``. One ``bmm`` when ``v`` is ``(B, c)``
    (a solver step: per-call overhead dominates small models); einsum otherwise (it folds leading
    dimensions into one product instead of copying ``a`` for each)."""
    if v.dim() == 2 and a.dim() == 3 and v.shape[0] == a.shape[0]:
        return torch.bmm(a, v.unsqueeze(-1)).squeeze(-1)
    return torch.einsum("...ij,...j->...i", a, v)


def _scatter_add(du: torch.Tensor, vals: torch.Tensor, rows: list[int]) -> torch.Tensor:
    du = du.expand(*vals.shape[:-1], du.shape[-1]).clone() if du.shape[:-1] != vals.shape[:-1] else du.clone()
    du[..., rows] += vals
    return du


@dataclass
class CompiledModel:
    """Torch functions of a :class:`SimplifiedModel` (see module docstring for shapes)."""

    model: SimplifiedModel
    _rhs: Callable[..., list]
    _observed: Callable[..., list]
    _outputs: Callable[..., list]
    _start: Callable[..., list]
    _affine: AffineSplit | None = None

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

    def bind(self, p: torch.Tensor, rows: torch.Tensor | None = None) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
        """``rhs`` with parameters ``p (B, n_params)`` fixed: ``f(u, x) -> du/dt``, fast for affine models.

        ``rows (S,)``: batch element ``s`` has the parameters ``p[rows[s]]`` (segments of a few
        experiments, :class:`BoundRhs`); the same numbers as ``bind(p[rows])``.
        """
        if self._affine is None:
            pr = p if rows is None else p[rows]
            return lambda u, x: self.rhs(u, x, pr)
        return BoundRhs(self._affine, p, rows)

    def shares_matrices(self, n_matrices: int) -> bool:
        """True where :meth:`bind` with ``rows`` over ``n_matrices`` distinct parameter rows shares
        the physics' matrices (:meth:`BoundRhs.pays`); elsewhere callers bind per row, as before."""
        return self._affine is not None and BoundRhs.pays(self._affine.n_states, n_matrices)

    @property
    def affine(self) -> bool:
        """True when every row of ``du/dt`` is ``A(p)·u + B(p)·x + c(p)`` (no nonlinear rows)."""
        return self._affine is not None and self._affine.rest is None

    def jacobian(self, p: torch.Tensor) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None:
        """``J(u, x) = d(du/dt)/du (B, n, n)`` for parameters ``p (B, n_params)`` where every
        equation is affine in the states (then ``J = A(p)``); None otherwise."""
        if self._affine is None or self._affine.rest is not None:
            return None
        bound = BoundRhs(self._affine, p)
        return lambda u, x: bound.A.expand(*u.shape[:-1], u.shape[-1], u.shape[-1])

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
        _affine=_affine_split(model, u, x, p),
    )

"""The hybrid right-hand side of a fixed-step solve on a known input grid, with everything that does
not depend on the state computed once per solve instead of once per evaluation.

For an affine physics ``A(p)·u + B(p)·x + c(p)`` and a network whose features are states, inputs and
parameters (no observed variables), the inputs ``x`` at every half step of the grid are known before
the solve. So the physics' drive ``B·x + c`` and the network's first layer applied to the input and
parameter features (its normalisation folded into the weights) are computed for all half steps in one
product each; an evaluation then costs one batched product for the physics and one per layer for the
network. The function is :meth:`HybridModel.rhs`'s, to rounding; small ODEs are dominated by
per-operation overhead (the cargo box's training solve with its backward pass: 81 k → 56 k
operations, 0.143 → 0.097 s).

A whole-trajectory solve (checkpoints, reports) has no grid, but its inputs are piecewise linear on
their knots, and both drives are affine in the inputs: :func:`drive_table` gives their values at the
knots, which the solver interpolates as it interpolated the inputs.

Shapes: ``p (S, n_params)`` per segment, ``xs (H, S, m)`` inputs at the ``H = 2K+1`` half steps,
states ``u (S, n)``; drives ``physics (H, S, n)``, ``first (H, S, h₁)``.
"""

from __future__ import annotations

from collections.abc import Callable
import torch
from torch import nn

from physmend.modeling.compile import BoundRhs
from physmend.simulate.inputs import PiecewiseLinear
from physmend.ude.hybrid import HybridModel


class Drives:
    """What a solve's evaluation at half step ``k`` needs besides the state: ``drives[k]``.

    ``physics (H, S, n)``: B(p)·x + c(p); ``first (H, S, h1)``: the first layer's input and parameter
    part with its bias. Split once (``unbind``: one gradient ``stack`` in the backward pass, where
    indexing would fill a whole ``(H, …)`` gradient per half step)."""

    def __init__(self, physics: torch.Tensor, first: torch.Tensor) -> None:
        self.physics = physics.unbind(0)
        self.first = first.unbind(0)

    def __getitem__(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.physics[k], self.first[k]


def drivable(hybrid: HybridModel) -> bool:
    """True when :func:`hybrid_drive` applies: affine physics without nonlinear rows, no observed
    features, a corrected equation and a hidden layer."""
    return (hybrid.compiled.affine and not hybrid.observed_idx and bool(hybrid.corrected_idx)
            and len(hybrid.spec.widths) > 0)


#: the most memory a drive table (values and slopes) may take: a longer record, more stacked models or
#: a wider first layer solve with the plain right-hand side instead (the same function; only slower).
#: The table has ``n + h1`` columns per row where the inputs had ``m``: unbounded, a long record of a
#: stack would cost memory in proportion (a 16-model stack of width 64 on 20,000 knots: ~330 MB).
TABLE_MAX_BYTES = 64 * 2**20


def table_fits(rows: int, knots: int, columns: int, dtype: torch.dtype) -> bool:
    """Whether a drive table of ``rows`` rows on ``knots`` knots with ``columns`` columns (the states
    plus the first hidden layer) stays within :data:`TABLE_MAX_BYTES`, counting its values and slopes."""
    itemsize = torch.empty((), dtype=dtype).element_size()
    return 2 * rows * knots * columns * itemsize <= TABLE_MAX_BYTES


def split_first_layer(weight: torch.Tensor, bias: torch.Tensor, mean: torch.Tensor, std: torch.Tensor,
                      n_states: int, n_inputs: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``W·((f − mean)/std) + b`` as ``Wu·u + Wx·x + Wp·p + b'``: the normalisation folded in.

    ``weight (..., h, F)``, ``bias (..., h)``; features ``F`` ordered states, inputs, parameters.
    Returns ``Wu (..., h, n_states)``, ``Wx (..., h, n_inputs)``, ``Wp (..., h, rest)``, ``b' (..., h)``."""
    w = weight / std
    b = bias - (w * mean).sum(-1)
    return w[..., :n_states], w[..., n_states:n_states + n_inputs], w[..., n_states + n_inputs:], b


def physics_drive(hybrid: HybridModel, p: torch.Tensor, xs: torch.Tensor, rows: torch.Tensor | None = None
                  ) -> tuple[Callable[[torch.Tensor, torch.Tensor], torch.Tensor], torch.Tensor]:
    """``(u, d) -> A(p)·u + d`` (:meth:`BoundRhs.linear_plus`) and the drive ``B(p)·x + c(p)`` at
    every half step ``(H, S, n)``; ``rows``: as for :meth:`CompiledModel.bind`."""
    bound = hybrid.compiled.bind(p, rows)
    assert isinstance(bound, BoundRhs)
    physics = bound.c.expand(xs.shape[0], *bound.c.shape)
    if hybrid.compiled.input_names:
        physics = physics + torch.einsum("sij,hsj->hsi", bound.B, xs)
    return bound.linear_plus, physics


def columns(hybrid: HybridModel) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    """The state columns the network reads and the corrected columns (None: all of them, in order)."""
    n = len(hybrid.compiled.state_names)
    reads = None if hybrid._all_states else torch.tensor(hybrid.state_idx, dtype=torch.long)
    idx = hybrid.corrected_idx
    return reads, None if idx == list(range(n)) else torch.tensor(idx, dtype=torch.long)


def with_physics(u: torch.Tensor, d: torch.Tensor, linear_plus: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                 corr: torch.Tensor, index: torch.Tensor | None) -> torch.Tensor:
    """``A·u + d`` (``linear_plus(u, d)``) plus the corrections ``corr`` in the columns ``index`` (None: every column)."""
    du = linear_plus(u, d)
    return du + corr if index is None else du.index_add(-1, index, corr)


def network_parts(hybrid: HybridModel, p: torch.Tensor, xs: torch.Tensor, mask: torch.Tensor | None = None) -> tuple[
        torch.Tensor, torch.Tensor, list[tuple[torch.Tensor, torch.Tensor] | nn.Module], torch.Tensor]:
    """The network of ``hybrid`` split for drives over the inputs ``xs (H, S, m)`` (``p (S, n_params)``):
    the first layer's input and parameter part with its bias ``(H, S, h1)``, its state weights
    transposed ``(n_read, h1)``, the later layers (``(bias, weightᵀ)`` or an activation) and the output
    gain; ``mask (S, k)``: each row's own output mask in place of the hybrid's."""
    layers = list(hybrid.net)
    first = layers[0]
    assert isinstance(first, nn.Linear)
    wu, wx, wp, b1 = split_first_layer(first.weight, first.bias, hybrid.mean, hybrid.std,
                                       len(hybrid.state_idx), len(hybrid.input_idx))
    pre = b1.expand(*xs.shape[:-1], b1.shape[0])
    if hybrid.input_idx:
        pre = pre + xs[..., hybrid.input_idx] @ wx.T
    if hybrid.param_idx:
        pre = pre + (p[:, hybrid.param_idx] @ wp.T)[None]
    rest: list[tuple[torch.Tensor, torch.Tensor] | nn.Module] = [
        (m.bias, m.weight.T) if isinstance(m, nn.Linear) else m for m in layers[1:]]
    gain = hybrid.out_scale * (hybrid.out_mask if mask is None else mask)
    if hybrid.coefficients is not None:
        gain = gain / hybrid.equation_coefficients(p)  # (S, k)
    return pre, wu.T, rest, gain


def hybrid_drive(hybrid: HybridModel, p: torch.Tensor, xs: torch.Tensor, rows: torch.Tensor | None = None
                 ) -> tuple[Callable[[torch.Tensor, tuple[torch.Tensor, torch.Tensor]], torch.Tensor], Drives]:
    """``f(u, drives[k]) -> du/dt`` and the drives of a solve over the half-step inputs ``xs``.

    ``rows (S,)``: segment ``s`` has the parameters ``p[rows[s]]`` (``p`` per experiment; the
    physics then shares one matrix per experiment, :class:`BoundRhs`). Call only where
    :func:`drivable` holds. Gradients reach the network, ``p`` and the estimates."""
    linear_plus, physics = physics_drive(hybrid, p, xs, rows)
    if rows is not None:
        p = p[rows]
    pre, wu_t, rest, gain = network_parts(hybrid, p, xs)
    state_idx, index = columns(hybrid)

    def f(u: torch.Tensor, drive: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        d, h = drive
        h = torch.addmm(h, u if state_idx is None else u[:, state_idx], wu_t)
        for layer in rest:
            h = torch.addmm(layer[0], h, layer[1]) if isinstance(layer, tuple) else layer(h)
        return with_physics(u, d, linear_plus, h * gain, index)

    return f, Drives(physics, pre)


def drive_table(hybrid: HybridModel, p: torch.Tensor, inputs: PiecewiseLinear, mask: torch.Tensor | None = None
                ) -> tuple[Callable[[torch.Tensor, torch.Tensor], torch.Tensor], PiecewiseLinear]:
    """The hybrid's right-hand side for a whole-trajectory solve, ``f(u, d) -> du/dt``, and the drive
    ``d(t)`` it takes in place of the inputs: a :class:`PiecewiseLinear` on the inputs' own knots.

    The physics' drive ``B(p)·x + c(p)`` and the network's first layer on inputs and parameters (its
    normalisation folded in, with its bias) are affine in ``x``, and ``x`` is linear between knots:
    so is the drive, and its values at the knots ``(B, K, n + h1)`` interpolate it exactly. A solver's
    evaluation then looks up the drive (as it looked up the inputs) and costs one product for the
    physics and one per layer — :meth:`HybridModel.rhs`'s function to rounding, without the features,
    the normalisation or the physics' input product at every evaluation. ``p (B, n_params)`` (already
    estimated); ``u (..., B, n)`` with any leading dimensions (finite-difference Jacobians); the
    drive's kinks are the inputs' (a solver's stops should come from the inputs); ``mask (B, k)``:
    each row's own output mask in place of the hybrid's (several masked variants in one solve). Only
    where :func:`drivable` holds; no gradients are meant to pass (whole-trajectory evaluations)."""
    xs = inputs.values.transpose(0, 1)  # (K, B, m): the inputs at their knots
    linear_plus, physics = physics_drive(hybrid, p, xs)
    pre, wu_t, rest, gain = network_parts(hybrid, p, xs, mask)
    n = physics.shape[-1]
    table = PiecewiseLinear(inputs.knots, torch.cat([physics, pre], -1).transpose(0, 1).contiguous())
    state_idx, index = columns(hybrid)

    def f(u: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        physics_d, h = d[..., :n], d[..., n:]
        read = u if state_idx is None else u[..., state_idx]
        if read.dim() == 2:
            h = torch.addmm(h, read, wu_t)
            for layer in rest:
                h = torch.addmm(layer[0], h, layer[1]) if isinstance(layer, tuple) else layer(h)
        else:  # the copies of a finite-difference Jacobian: (..., B, n)
            h = torch.matmul(read, wu_t) + h
            for layer in rest:
                h = torch.matmul(h, layer[1]) + layer[0] if isinstance(layer, tuple) else layer(h)
        return with_physics(u, physics_d, linear_plus, h * gain, index)

    return f, table

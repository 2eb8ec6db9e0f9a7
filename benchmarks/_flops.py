"""FLOP estimate of one hybrid right-hand-side evaluation and of one training epoch.

One RHS evaluation of one batch row (one experiment or one segment) costs the network
(normalise inputs, dense layers, activations, output scaling) plus the physics written in affine
form ``A u + B x + c`` (dense ``A``, ``B``). A multiply-add counts 2 FLOPs, an activation 1 FLOP
per element. Solver arithmetic (stage combinations, error norms, input interpolation) is not
counted. An epoch costs ``rows x rhs_flops x 3`` (forward once, backward about twice).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

BACKWARD_FACTOR = 3.0  # forward + backward ~ 3x the forward FLOPs


def rhs_flops(spec: Any, n_states: int, n_inputs: int) -> dict[str, int]:
    """FLOPs of one hybrid RHS evaluation for one batch row, split into network and physics."""
    sizes = [spec.n_inputs, *spec.widths, len(spec.corrected)]
    dense = sum(2 * a * b + b for a, b in zip(sizes[:-1], sizes[1:]))  # matmul + bias
    activations = sum(spec.widths)
    normalise = 2 * spec.n_inputs  # (z - mean) / std
    scale = 2 * len(spec.corrected) + len(spec.corrected)  # * out_scale * mask, + physics
    network = dense + activations + normalise + scale
    physics = 2 * n_states * n_states + 2 * n_states * n_inputs + n_states  # A u + B x + c
    return {"network": network, "physics": physics, "total": network + physics}


def epoch_flops(rows_per_epoch: float, per_row: int) -> float:
    """FLOPs of one training epoch: ``rows_per_epoch`` RHS row evaluations, forward and backward."""
    return BACKWARD_FACTOR * rows_per_epoch * per_row


@contextmanager
def count_network_rows(n_inputs: int, first_width: int) -> Iterator[Callable[[], int]]:
    """Count rows through the network's first layer while gradients are enabled (training only).

    Each hybrid RHS evaluation sends every batch row once through the first ``nn.Linear(n_inputs,
    first_width)``; evaluations under ``torch.no_grad`` (whole-trajectory validation) are skipped.
    Yields a function returning the count so far. Global hooks slow every module call: use this
    only in a separate, untimed counting pass.
    """
    import torch
    from torch import nn

    rows = [0]

    def hook(module: nn.Module, args: tuple[Any, ...], _out: Any) -> None:
        if isinstance(module, nn.Linear) and torch.is_grad_enabled() and module.in_features == n_inputs \
                and module.out_features == first_width and args:
            rows[0] += args[0].numel() // n_inputs

    handle = nn.modules.module.register_module_forward_hook(hook)
    try:
        yield lambda: rows[0]
    finally:
        handle.remove()

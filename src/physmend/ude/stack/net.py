"""The networks of a stack, padded to one shape: stacked weights ``(M, …)`` applied with batched
matmuls, padded units kept at zero; written back into each model's own network. Imports ``hybrid``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from torch import nn
import torch

from physmend.ude.hybrid import ACTIVATIONS, HybridModel, UDEConfigError


def linears(hybrid: HybridModel) -> list[nn.Linear]:
    return [m for m in hybrid.net if isinstance(m, nn.Linear)]


@dataclass
class StackedNet:
    """``M`` MLPs padded to one shape: layer ``l`` maps ``h (M, N, a)`` to ``baddbmm(b, h, W)``.

    Shapes: ``weights[l] (M, a_l, b_l)`` (transposed ``nn.Linear`` weights), ``biases[l] (M, 1, b_l)``;
    ``use[l] (M, 1, 1)`` False where a model has fewer hidden layers (the layer is skipped) or None;
    ``activations`` each model's activation name: models are ordered so that each activation's
    models are consecutive, and every activation runs on its own models only;
    ``scale (M, 1, k)`` the output scale times the output mask.
    """

    weights: list[torch.Tensor]
    biases: list[torch.Tensor]
    use: list[torch.Tensor | None]
    activations: list[str]
    scale: torch.Tensor
    runs: list[tuple[nn.Module, int, int]] = field(init=False)  # (activation, first model, end)

    def __post_init__(self) -> None:
        self.runs = []
        for i, name in enumerate(self.activations):
            if self.runs and self.activations[i - 1] == name:
                act, start, _ = self.runs[-1]
                self.runs[-1] = (act, start, i + 1)
            else:
                self.runs.append((ACTIVATIONS[name](), i, i + 1))

    def activation(self, a: torch.Tensor) -> torch.Tensor:
        if len(self.runs) == 1:
            return self.runs[0][0](a)
        if not torch.is_grad_enabled():  # evaluations: in place, no concatenation (``a`` is a fresh product)
            for act, start, end in self.runs:
                a[start:end] = act(a[start:end])
            return a
        return torch.cat([act(a[start:end]) for act, start, end in self.runs])

    def __call__(self, z: torch.Tensor | None, first: torch.Tensor | None = None) -> torch.Tensor:
        """Corrections ``(M, N, k)`` of normalised features ``z (M, N, n_in)``, or from the first
        layer's output ``first (M, N, b_0)`` (before its activation; ``z`` None, :mod:`physmend.ude.drive`)."""
        h = z
        last = len(self.weights) - 1
        for l, (w, b) in enumerate(zip(self.weights, self.biases)):
            a = first if l == 0 and first is not None else torch.baddbmm(b, h, w)
            if l == last:
                return a * self.scale
            a = self.activation(a)
            use = self.use[l]
            h = a if use is None else torch.where(use, a, h)
        raise AssertionError("a network has an output layer")

    def select(self, rows: torch.Tensor) -> StackedNet:
        """The networks of stack rows ``rows`` (no gradients)."""
        return StackedNet(
            weights=[w.detach()[rows] for w in self.weights],
            biases=[b.detach()[rows] for b in self.biases],
            use=[None if u is None else u[rows] for u in self.use],
            activations=[self.activations[i] for i in rows.tolist()],
            scale=self.scale[rows],
        )


def pad_networks(hybrids: Sequence[HybridModel], dtype: torch.dtype) -> tuple[StackedNet, list[torch.Tensor | None]]:
    """Padded stacked networks copied from ``hybrids``, and boolean masks of each layer's real entries."""
    m = len(hybrids)
    specs = [h.spec for h in hybrids]
    depths = [len(s.widths) for s in specs]
    if len({d == 0 for d in depths}) > 1:
        raise UDEConfigError(f"train_stack: ude.depth=0 (a linear correction) cannot share a stack with deeper networks, "
                             f"but got depths {depths}")
    depth = max(depths)
    n_in, n_out = specs[0].n_inputs, len(specs[0].corrected)
    width = max((w for s in specs for w in s.widths), default=0)
    dims = [(n_in if l == 0 else width, width) for l in range(depth)] + [(width if depth else n_in, n_out)]
    weights = [torch.zeros(m, a, b, dtype=dtype) for a, b in dims]
    biases = [torch.zeros(m, 1, b, dtype=dtype) for _, b in dims]
    w_mask = [torch.zeros(m, a, b, dtype=torch.bool) for a, b in dims]
    b_mask = [torch.zeros(m, 1, b, dtype=torch.bool) for _, b in dims]
    with torch.no_grad():
        for i, hybrid in enumerate(hybrids):
            lins = linears(hybrid)
            slots = list(range(len(lins) - 1)) + [depth]  # the output layer is always the last one
            for lin, l in zip(lins, slots):
                a, b = lin.in_features, lin.out_features
                weights[l][i, :a, :b] = lin.weight.T
                biases[l][i, 0, :b] = lin.bias
                w_mask[l][i, :a, :b] = True
                b_mask[l][i, 0, :b] = True
    use: list[torch.Tensor | None] = []
    for l in range(depth):
        rows = torch.tensor([d > l for d in depths]).reshape(m, 1, 1)
        use.append(None if bool(rows.all()) else rows)
    scale = torch.stack([h.out_scale * h.out_mask for h in hybrids])[:, None, :].to(dtype)
    net = StackedNet(weights, biases, use, [s.activation for s in specs], scale)
    masks: list[torch.Tensor | None] = []
    for mk in [x for pair in zip(w_mask, b_mask) for x in pair]:
        masks.append(None if bool(mk.all()) else mk)
    return net, masks


def write_back_row(net: StackedNet, row: int, hybrid: HybridModel, est_raw: torch.Tensor | None) -> None:
    """Copy stack row ``row`` into ``hybrid``'s own (unpadded) layers and estimates."""
    lins = linears(hybrid)
    depth = len(net.weights) - 1
    slots = list(range(len(lins) - 1)) + [depth]
    with torch.no_grad():
        for lin, l in zip(lins, slots):
            a, b = lin.in_features, lin.out_features
            lin.weight.copy_(net.weights[l].detach()[row, :a, :b].T)
            lin.bias.copy_(net.biases[l].detach()[row, 0, :b])
        if est_raw is not None:
            hybrid.est_raw.copy_(est_raw.detach()[row])

"""The training solve of :mod:`physmend.ude.adjoint` with its two time loops compiled
(:mod:`physmend.ude.rk4_loops`): the loops take numpy views of the tensors (no copies where the
inputs are contiguous), and every gradient that is a product over all stages (the matrices', the
weights') is one batched product here."""

from __future__ import annotations

import sys
import threading
from collections.abc import Sequence

import numpy as np
import torch

from physmend.ude import rk4_loops  # numba, imported with the trainer (not in the middle of a trial)
from physmend.ude.activation_loops import CODES


class CompiledSolve(torch.autograd.Function):
    """:class:`physmend.ude.adjoint._Solve` with its two time loops compiled (:mod:`physmend.ude.rk4_loops`): the same
    inputs, output and gradients (to rounding: the loops add in another order)."""

    @staticmethod
    def forward(ctx, meta, u0, A, d, pre, wu, gain, *layers):  # noqa: ANN001, ANN205
        h, steps, lo, hi, reads, index, activation = meta
        M, S, w0 = pre.shape[1:]
        R, n = u0.shape
        T, H = 4 * steps, 2 * steps + 1
        L = len(layers) // 2
        W, b, dims, fixed = pack(wu, gain, layers, reads, index, M, S, n)
        P, k, dt = W.shape[-1], dims[-1], u0.dtype
        boxed = lo is not None
        box = [torch.broadcast_to(x.detach(), (R, n)).to(dt).contiguous() for x in (lo, hi)] if boxed else [b[0]] * 2
        A = A.detach().expand(R, n, n).contiguous()
        take = SPARE.take  # every value of these the loops write (the layers' padding is never read)
        traj = u0.new_empty(steps + 1, R, n)
        Vs, Z, Y, OUT = take((R, T, n), dt), take((L, R, T, P), dt), take((L, R, T, P), dt), take((R, T, k), dt)
        MASK = take((R, T, n), dt) if boxed else OUT
        _loop(rk4_loops, "forward", R)(float(h), u0.detach().contiguous().numpy(), A.transpose(1, 2).contiguous().numpy(),
                          d.detach().expand(H, R, n).contiguous().numpy(),
                          pre.detach().expand(H, M, S, w0).contiguous().numpy(), *(x.numpy() for x in fixed),
                          codes(activation, M), S, boxed, box[0].numpy(), box[1].numpy(), traj.numpy(),
                          Vs.numpy(), Z.numpy(), Y.numpy(), OUT.numpy(), MASK.numpy())
        ctx.meta, ctx.shape, ctx.gain_shape, ctx.dims = meta, (M, S, R, n, L, P), gain.shape, dims
        ctx.loops = (A, fixed, Vs, Z, Y, OUT, MASK)
        return traj

    @staticmethod
    def backward(ctx, grad):  # noqa: ANN001, ANN205
        h, steps, lo, hi, reads, index, activation = ctx.meta
        M, S, R, n, L, P = ctx.shape
        dims = ctx.dims
        A, fixed, Vs, Z, Y, OUT, MASK = ctx.loops
        wu, W, _, dims_t, gain, reads_t, index_t = fixed
        T, H, w0, k, dt = 4 * steps, 2 * steps + 1, dims[0], dims[-1], A.dtype
        need = ctx.needs_input_grad
        # written by the loops (the layers' padding is never read)
        g_u0, G, GA = A.new_empty(R, n), SPARE.take((R, T, n), dt), SPARE.take((L + 1, R, T, P), dt)
        g_d, g_pre, g_gain = A.new_empty(H, R, n), A.new_empty(H, M, S, w0), A.new_empty(R, k)
        _loop(rk4_loops, "backward", R)(float(h), grad.detach().contiguous().numpy(), A.numpy(), wu.numpy(), W.numpy(),
                           dims_t.numpy(), gain.numpy(), reads_t.numpy(), index_t.numpy(), codes(activation, M),
                           S, lo is not None, Z.numpy(), Y.numpy(), OUT.numpy(), MASK.numpy(), g_u0.numpy(),
                           G.numpy(), GA.numpy(), g_d.numpy(), g_pre.numpy(), g_gain.numpy())

        def rows(x: torch.Tensor, width: int) -> torch.Tensor:  # (R, T, ≥width) -> (M, S·T, width)
            return x[..., :width].reshape(M, S * T, width)

        g_A = torch.bmm(G.transpose(1, 2), Vs) if need[2] else None
        g_wu = None
        if need[5]:
            vr = Vs if reads is None else Vs[..., reads]
            g_wu = tall_product(rows(vr, vr.shape[-1]), rows(GA[0], w0))
        g_gain = reduce_to(g_gain.view(M, S, k), ctx.gain_shape) if need[6] else None
        g_layers: list[torch.Tensor | None] = []
        for l in range(L):
            up = rows(GA[l + 1], dims[l + 1])
            g_layers.append(tall_product(rows(Y[l], dims[l]), up) if need[7 + 2 * l] else None)
            g_layers.append(up.sum(dim=1, keepdim=True) if need[8 + 2 * l] else None)
        return (None, g_u0, g_A, g_d if need[3] else None, g_pre if need[4] else None, g_wu, g_gain, *g_layers)


def tall_product(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``aᵀb (M, p, q)`` of ``a (M, K, p)`` and ``b (M, K, q)``, ``K`` long (every stage of every
    segment). With fewer models than torch threads, the sum over ``K`` is split into chunks, one
    product each, added after: BLAS shares a product of so few outputs between threads poorly
    (one model, 32 × 9,600 by 9,600 × 32, two threads: 1.04 ms as one product, 0.51 ms in 8 chunks;
    the same on one thread). One thread, or as many models as threads: one product, as before."""
    M, K, p = a.shape
    threads = torch.get_num_threads()
    chunks = next((c for c in (8, 4, 2) if K % c == 0), 1) if 1 < threads and M < threads else 1
    if chunks == 1:
        return torch.bmm(a.transpose(1, 2), b)
    q = b.shape[-1]
    return torch.bmm(a.reshape(M * chunks, K // chunks, p).transpose(1, 2),
                     b.reshape(M * chunks, K // chunks, q)).view(M, chunks, p, q).sum(1)


def codes(activation: str | Sequence[str], models: int) -> np.ndarray:
    """Each model's activation number ``(models,)`` (:data:`physmend.ude.activation_loops.CODES`), as the
    loops take them: ``activation`` one name for every model, or one per model."""
    names = [activation] * models if isinstance(activation, str) else list(activation)
    if len(names) != models:
        raise ValueError(f"compiled_solve.codes: one activation per model is needed ({models} models), "
                         f"but got {len(names)}: {names}")
    return np.array([CODES[a] for a in names], dtype=np.int64)


def pack(wu: torch.Tensor, gain: torch.Tensor, layers: Sequence[torch.Tensor], reads: torch.Tensor | None,
         index: torch.Tensor | None, M: int, S: int, n: int
         ) -> tuple[torch.Tensor, torch.Tensor, list[int], list[torch.Tensor]]:
    """The network in the loops' layout (:mod:`physmend.ude.rk4_loops`): the layers after the first
    zero-padded ``W (L, M, P, P)``, ``b (L, M, P)`` (the output layer transposed), the widths
    ``dims``, and ``[wu, W, b, dims, gain (R, k), reads, index]`` as the loops take them."""
    weights, biases = layers[0::2], layers[1::2]
    L = len(weights)
    dims = [wu.shape[-1], *(w.shape[-1] for w in weights)]
    P, k = max(dims), dims[-1]
    W, b = wu.new_zeros(L, M, P, P), wu.new_zeros(L, M, P)
    for l, (w, bias) in enumerate(zip(weights, biases)):
        if l == L - 1:  # the output layer transposed: its few outputs are then products of rows
            W[l, :, :w.shape[-1], :w.shape[-2]] = w.detach().transpose(-1, -2)
        else:
            W[l, :, :w.shape[-2], :w.shape[-1]] = w.detach()
        b[l, :, :w.shape[-1]] = bias.detach().reshape(M, -1)
    ints = {"device": "cpu", "dtype": torch.int64}
    fixed = [wu.detach().contiguous(), W, b, torch.tensor(dims, **ints),
             torch.broadcast_to(gain.detach(), (M, S, k)).reshape(M * S, k).contiguous(),
             torch.arange(n, **ints) if reads is None else reads.to(**ints).contiguous(),
             torch.arange(n, **ints) if index is None else index.to(**ints).contiguous()]
    return W, b, dims, fixed


def _loop(loops: object, name: str, rows: int):  # noqa: ANN202
    """``loops.<name>``, or its threaded twin on as many threads as torch has (``threads``) where
    there are rows to share."""
    threads = min(torch.get_num_threads(), rows)
    if threads <= 1:
        return getattr(loops, name)
    import numba

    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    return getattr(loops, f"{name}_threads")


class _Spare(threading.local):
    """Buffers of the compiled solve, reused by the next solve of the same shape once nothing holds
    them (the solve that used them was freed with its graph): a fresh buffer of a few MB is new
    memory that the loops fault in page by page, a fifth of an epoch's time (a sweep group of 32
    models: buffers of ~100 MB, 14 % of the process's time in the kernel when they were allocated
    every epoch). Holds the buffers of the shapes solved since the last shape that none fitted: a
    take that none fits frees the unused ones first (a stack that lost models solves smaller rows
    from then on), so what is held is what the latest solves needed, bounded as they are by the
    training plan's memory check (``train.memory_limit_gib``)."""

    def __init__(self) -> None:
        self.held: list[torch.Tensor] = []

    def take(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        for i in range(len(self.held)):
            if self.held[i].shape == shape and self.held[i].dtype == dtype and _unused(self.held, i):
                return self.held[i]
        free = [_unused(self.held, i) for i in range(len(self.held))]  # before any other reference is made
        self.held = [x for x, f in zip(self.held, free) if not f]
        t = torch.empty(shape, dtype=dtype)
        self.held.insert(0, t)
        return t


def _unused(held: list[torch.Tensor], i: int) -> bool:
    """Whether ``held[i]`` is referred to by ``held`` alone (no solve's context holds it)."""
    return sys.getrefcount(held[i]) <= _ALONE


_ALONE = sys.getrefcount(torch.empty(0)) + 1  # a list's element, as passed to getrefcount (the temporary's count + the list)
SPARE = _Spare()


def reduce_to(t: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """``t`` summed over the dimensions that ``shape`` broadcasts."""
    while t.dim() > len(shape):
        t = t.sum(0)
    dims = [i for i, s in enumerate(shape) if s == 1 and t.shape[i] != 1]
    return t.sum(dim=dims, keepdim=True) if dims else t


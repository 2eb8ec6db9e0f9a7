"""The multiple-shooting RK4 solve of a hybrid model with its backward pass written by hand.

Eager PyTorch pays per operation: autograd records every operation of the forward solve and
replays about twice as many backward, ~260 forward and ~520 backward operations per RK4 step of a
small hybrid model. Here the forward solve runs without recording (keeping the few tensors its
backward needs: each stage's state, hidden activations and clamp mask) and the backward pass is
the discrete adjoint of the RK4 recursion, written out: per stage a handful of batched products
(the network's layers transposed, the physics' ``Aᵀ``), and the gradients of every weight, bias,
physics matrix and drive summed over all stages, segments and models at the end in one product
each. The numbers are autograd's to rounding (tests/ude/test_adjoint.py, gradcheck in float64).
On the CPU both time loops run compiled (:mod:`physmend.ude.compiled_solve`, :mod:`physmend.ude.rk4_loops`):
the torch loops below (:class:`_Solve`) are the reference they are tested against and what runs on
other devices.

The right-hand side is the drive form of :mod:`physmend.ude.drive`, stacked over ``M`` models
(rows model-major, ``R = M·S``)::

    f(u, k) = A u + d_k + scatter_index( gain ⊙ net(act(pre_k + u[:, reads] · Wu)) )

with ``A (R, n, n)``, drives ``d (H, R, n)`` and ``pre (H, M, S, h₁)`` at the ``H = 2K+1`` half
steps, ``Wu (M, n_reads, h₁)``, hidden and output layers ``(W (M, a, b), b (M, 1, b))`` applied
as ``baddbmm(b, y, W)``, one activation per model (the same in every layer), ``gain`` broadcastable to
``(M, S, k)``. Each stage's state is held inside ``box = (lo, hi)`` (``clamp``) as
:func:`physmend.ude.shooting.rk4_segments` does.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import math

import torch
from torch import nn

from physmend.modeling.compile import BoundRhs
from physmend.ude.compiled_solve import CompiledSolve, reduce_to
from physmend.ude.drive import columns, drivable, split_first_layer
from physmend.ude.hybrid import HybridModel
from physmend.ude.shooting import Shooting

#: activations whose derivative is written here, as a function of the pre-activation ``a`` and the value ``y``
_DERIVATIVES = {
    "tanh": lambda a, y: 1.0 - y * y,
    "sigmoid": lambda a, y: y * (1.0 - y),
    "relu": lambda a, y: (a > 0).to(a.dtype),
    "softplus": lambda a, y: torch.sigmoid(a),
    "silu": lambda a, y: torch.sigmoid(a) * (1.0 + a * (1.0 - torch.sigmoid(a))),
    "elu": lambda a, y: torch.where(a > 0, torch.ones_like(a), y + 1.0),
    "gelu": lambda a, y: 0.5 * (1.0 + torch.erf(a * 0.5**0.5)) + a * torch.exp(-0.5 * a * a) * (2.0 * math.pi) ** -0.5,
}
_FUNCTIONS = {
    "tanh": torch.tanh,
    "sigmoid": torch.sigmoid,
    "relu": torch.relu,
    "softplus": torch.nn.functional.softplus,
    "silu": torch.nn.functional.silu,
    "elu": torch.nn.functional.elu,
    "gelu": torch.nn.functional.gelu,
}
ACTIVATIONS = tuple(_FUNCTIONS)


def _each_model(activation: str | tuple[str, ...], table: dict) -> Callable[..., torch.Tensor]:
    """``table[activation]``, or for one name per model a function that applies each model's own
    to its slice of the model dimension (``(…, M, S, w)``, dimension -3)."""
    if isinstance(activation, str):
        return table[activation]
    runs: list[tuple[str, int, int]] = []
    for i, name in enumerate(activation):
        if runs and runs[-1][0] == name:
            runs[-1] = (name, runs[-1][1], i + 1)
        else:
            runs.append((name, i, i + 1))

    def apply(*xs: torch.Tensor) -> torch.Tensor:
        out = torch.empty_like(xs[0])
        for name, start, end in runs:
            out[..., start:end, :, :] = table[name](*(x[..., start:end, :, :] for x in xs))
        return out

    return apply
#: solves run with the hand-written backward pass in this process (what tests check it was used)
STATS = {"solves": 0}
#: on the CPU, the time loops compiled (:class:`physmend.ude.compiled_solve.CompiledSolve`); False: written in torch (:class:`_Solve`)
LOOPS = {"compiled": True}


class _Solve(torch.autograd.Function):
    """Inputs: ``meta``, ``u0 (R, n)``, ``A (R, n, n)``, ``d (H, R, n)``, ``pre (H, M, S, h1)``,
    ``wu (M, r, h1)``, ``gain``, then ``W_1, b_1, …, W_L, b_L`` (hidden layers after the first, and
    the output layer). Output: the states at the grid points ``(K+1, R, n)``.

    The forward solve keeps, per stage, the state it evaluated, each hidden layer's pre-activation
    and the network's output, and per clamp the state before it; the backward pass derives the
    activations, their derivatives and the clamp masks of all stages at once from those. Both write
    each stage's values straight into one buffer per kind (``out=``), so nothing is stacked after."""

    @staticmethod
    def forward(ctx, meta, u0, A, d, pre, wu, gain, *layers):  # noqa: ANN001, ANN205
        h, steps, lo, hi, reads, index, activation = meta
        act = _each_model(activation, _FUNCTIONS)
        M, S, _ = pre.shape[1:]
        R, n = u0.shape
        T = 4 * steps
        weights, biases = layers[0::2], layers[1::2]
        boxed = lo is not None
        # one model: plain 2-D products (fewer operations than batched ones of one matrix)
        flat = M == 1
        rows = (S,) if flat else (M, S)
        new = u0.new_empty
        traj = new(steps + 1, R, n)  # the grid points; stage 1 of step k evaluates traj[k]
        V = new(steps, 3, R, n)  # the state stages 2-4 evaluate f at
        # per hidden layer the pre-activation, and the network's output before the gain, of every stage
        PRE = [new(T, *rows, w.shape[-1]) for w in (wu, *weights[:-1])]
        OUT = new(T, *rows, weights[-1].shape[-1])
        UNHELD = new(T, R, n) if boxed else None  # per step the states before its clamps: stages 2-4, its end

        lin = torch.addmm if flat else torch.baddbmm
        net_w = [w[0] for w in weights] if flat else list(weights)
        net_b = [b[0] for b in biases] if flat else list(biases)
        w_first = wu[0] if flat else wu
        g_net = gain.reshape(gain.shape[-2:]) if flat else gain
        pres = (pre[:, 0] if flat else pre).unbind(0)
        drives = d.unsqueeze(-1).unbind(0)
        # each buffer's rows as views made at once (one call, not one indexing per stage)
        pre_at, out_at = [b.unbind(0) for b in PRE], OUT.unbind(0)
        point, state_at = traj.unbind(0), V.view(3 * steps, R, n).unbind(0)
        unheld_at = UNHELD.unbind(0) if boxed else ()

        def f(v: torch.Tensor, j: int, i: int) -> torch.Tensor:
            vm = v if flat else v.view(M, S, n)
            a = lin(pres[i], vm if reads is None else vm[..., reads], w_first, out=pre_at[0][j])
            y = act(a)
            for l in range(1, len(net_w)):
                a = lin(net_b[l - 1], y, net_w[l - 1], out=pre_at[l][j])
                y = act(a)
            out = lin(net_b[-1], y, net_w[-1], out=out_at[j])
            corr = (out * g_net).view(R, -1)
            du = torch.baddbmm(drives[i], A, v.unsqueeze(-1)).squeeze(-1)
            return du.add_(corr) if index is None else du.index_add_(-1, index, corr)

        def held(u: torch.Tensor, du: torch.Tensor, alpha: float, into: torch.Tensor, i: int) -> torch.Tensor:
            """``u + alpha·du`` written into ``into``, held in the box (the value before it kept as clamp ``i``)."""
            if not boxed:
                return torch.add(u, du, alpha=alpha, out=into)
            return torch.clamp(torch.add(u, du, alpha=alpha, out=unheld_at[i]), lo, hi, out=into)

        with torch.no_grad():
            point[0].copy_(u0)
            for k in range(steps):
                u = point[k]
                k1 = f(u, 4 * k, 2 * k)
                k2 = f(held(u, k1, 0.5 * h, state_at[3 * k], 4 * k), 4 * k + 1, 2 * k + 1)
                k3 = f(held(u, k2, 0.5 * h, state_at[3 * k + 1], 4 * k + 1), 4 * k + 2, 2 * k + 1)
                k4 = f(held(u, k3, h, state_at[3 * k + 2], 4 * k + 2), 4 * k + 3, 2 * k + 2)
                held(u, torch.add(k1, torch.add(k2, k3), alpha=2.0).add_(k4), h / 6.0, point[k + 1], 4 * k + 3)
        ctx.meta, ctx.shape, ctx.gain_shape = meta, (M, S, R, n), gain.shape
        ctx.stages = (traj, V, PRE, OUT, UNHELD)
        ctx.save_for_backward(A, wu, gain, *layers)
        return traj.clone()

    @staticmethod
    def backward(ctx, grad):  # noqa: ANN001, ANN205, PLR0915
        A, wu, gain, *layers = ctx.saved_tensors
        weights = layers[0::2]
        h, steps, lo, hi, reads, index, activation = ctx.meta
        act, dact = _each_model(activation, _FUNCTIONS), _each_model(activation, _DERIVATIVES)
        M, S, R, n = ctx.shape
        traj, V, PRE, OUT, UNHELD = ctx.stages
        boxed = lo is not None
        T = 4 * steps
        need = ctx.needs_input_grad
        flat = M == 1  # plain 2-D products, as forward
        with torch.no_grad():
            ys = [act(a) for a in PRE]  # per hidden layer (T, …, w)
            dys = [dact(a, y).unbind(0) for a, y in zip(PRE, ys)]  # per layer, T × (…, w)
            if boxed:
                masks = ((UNHELD >= lo) & (UNHELD <= hi)).to(UNHELD.dtype).unbind(0)  # 4K × (R, n)
            mm = torch.mm if flat else torch.bmm
            wts = [w[0].T if flat else w.transpose(1, 2) for w in weights]  # (M, b, a)
            wut = wu[0].T if flat else wu.transpose(1, 2)
            g_net = gain.reshape(gain.shape[-2:]) if flat else gain

            At = A  # g·A is Aᵀg for row vectors
            G = grad.new_empty(T, R, n)  # what each stage's f received
            GA = [torch.empty_like(a) for a in PRE] + [torch.empty_like(OUT)]  # per layer ∂pre-activation, the output layer last
            g_at, ga_at = G.unbind(0), [b.unbind(0) for b in GA]  # their rows, as in forward

            def vjp(j: int, g: torch.Tensor) -> torch.Tensor:
                """``J_f(v_j)ᵀ g`` for ``g = G[j] (R, n)``; records what the weight gradients need."""
                gc = g if index is None else g[:, index]
                ga = torch.mul(gc if flat else gc.view(M, S, -1), g_net, out=ga_at[-1][j])
                for l in range(len(wts) - 1, -1, -1):
                    ga = mm(ga, wts[l], out=ga_at[l][j]).mul_(dys[l][j])
                gv = torch.bmm(g.unsqueeze(1), At).squeeze(1)
                gr = mm(ga, wut).view(R, -1)
                return gv.add_(gr) if reads is None else gv.index_add_(-1, reads, gr)

            lam = torch.zeros_like(grad[0])
            for k in range(steps - 1, -1, -1):
                lam = lam + grad[k + 1]
                if boxed:
                    lam = lam * masks[4 * k + 3]
                j = 4 * k
                g23 = lam * (h / 3.0)
                g14 = torch.mul(lam, h / 6.0, out=g_at[j + 3])
                l4 = vjp(j + 3, g14)
                if boxed:
                    l4 = l4.mul_(masks[4 * k + 2])
                l3 = vjp(j + 2, torch.add(g23, l4, alpha=h, out=g_at[j + 2]))
                if boxed:
                    l3 = l3.mul_(masks[4 * k + 1])
                l2 = vjp(j + 1, torch.add(g23, l3, alpha=0.5 * h, out=g_at[j + 1]))
                if boxed:
                    l2 = l2.mul_(masks[4 * k])
                l1 = vjp(j, torch.add(g14, l2, alpha=0.5 * h, out=g_at[j]))
                lam = lam + l4 + l3 + l2 + l1
            g_u0 = lam + grad[0]

            # every other gradient summed over the T stages at once
            Vs = torch.cat((traj[:-1].unsqueeze(1), V), dim=1).view(T, R, n)  # the state each stage evaluated
            g_A = torch.bmm(G.permute(1, 2, 0), Vs.transpose(0, 1)) if need[2] else None
            H = 2 * steps + 1

            def at_half_steps(x: torch.Tensor) -> torch.Tensor:  # (T, …) -> (H, …): stage 1 at 2k, 2-3 at 2k+1, 4 at 2k+2
                xs = x.view(steps, 4, *x.shape[1:])
                out = x.new_zeros(H, *x.shape[1:])
                out[0:2 * steps:2] += xs[:, 0]
                out[1:2 * steps:2] += xs[:, 1] + xs[:, 2]
                out[2::2] += xs[:, 3]
                return out

            GA = [t.view(T, M, S, -1) for t in GA]  # (T, M, S, w) per layer, the output layer last
            g_d = at_half_steps(G) if need[3] else None
            g_pre = at_half_steps(GA[0]) if need[4] else None

            def rows(t: torch.Tensor) -> torch.Tensor:  # (T, M, S, w) -> (M, T·S, w)
                return t.transpose(0, 1).reshape(M, -1, t.shape[-1])

            g_wu = None
            if need[5]:
                vm = Vs.view(T, M, S, n)
                g_wu = torch.bmm(rows(vm if reads is None else vm[..., reads]).transpose(1, 2), rows(GA[0]))
            g_gain = None
            if need[6]:
                gc = G if index is None else G[..., index]
                g_gain = reduce_to((gc.view(T, M, S, -1) * OUT.view(T, M, S, -1)).sum(0), ctx.gain_shape)
            g_layers: list[torch.Tensor | None] = []
            for l in range(len(weights)):
                y = ys[l].view(T, M, S, -1)
                g_layers.append(torch.bmm(rows(y).transpose(1, 2), rows(GA[l + 1])) if need[7 + 2 * l] else None)
                g_layers.append(GA[l + 1].sum(dim=(0, 2)).unsqueeze(1) if need[8 + 2 * l] else None)
        return (None, g_u0, g_A, g_d, g_pre, g_wu, g_gain, *g_layers)


def rk4_adjoint(u0: torch.Tensor, A: torch.Tensor, d: torch.Tensor, pre: torch.Tensor, wu: torch.Tensor,
                layers: Sequence[tuple[torch.Tensor, torch.Tensor]], gain: torch.Tensor, *, h: float, steps: int,
                activation: str | Sequence[str], box: tuple[torch.Tensor, torch.Tensor] | None = None,
                reads: torch.Tensor | None = None, index: torch.Tensor | None = None) -> torch.Tensor:
    """Fixed-step RK4 of the drive form (module docstring) over all rows at once: the states at
    the grid points ``(steps+1, R, n)``, with the hand-written backward pass.

    ``u0 (R, n)``; ``A (R, n, n)``; ``d (2·steps+1, R, n)``; ``pre (2·steps+1, M, S, h1)``;
    ``wu (M, r, h1)``; ``layers``: ``(W (M, a, b), b (M, 1, b))`` after the first layer, the output
    layer last; ``gain`` broadcastable to ``(M, S, k)``; ``reads (r,)`` the state columns the network
    reads and ``index (k,)`` the corrected ones (None: all, in order); ``h`` the step (s);
    ``activation`` one name for every model, or one per model (``M`` names)."""
    names = [activation] if isinstance(activation, str) else list(activation)
    if not set(names) <= set(_FUNCTIONS):
        raise ValueError(f"rk4_adjoint: activation must be one of {list(_FUNCTIONS)}, but got {activation!r}")
    if not isinstance(activation, str) and len(names) != pre.shape[1]:
        raise ValueError(f"rk4_adjoint: one activation per model is needed ({pre.shape[1]} models), but got {names}")
    activation = names[0] if len(set(names)) == 1 else tuple(names)  # one name: every model's
    lo, hi = box if box is not None else (None, None)
    flat = [t for pair in layers for t in pair]
    STATS["solves"] += 1
    solve = CompiledSolve if u0.device.type == "cpu" and LOOPS["compiled"] else _Solve
    return solve.apply((h, steps, lo, hi, reads, index, activation), u0, A, d, pre, wu, gain, *flat)


def adjoint_applies(hybrid: HybridModel) -> bool:
    """Where :func:`hybrid_solve` applies: the drive form (:func:`physmend.ude.drive.drivable`) with
    an activation whose derivative is written here."""
    return drivable(hybrid) and hybrid.spec.activation in _FUNCTIONS


def hybrid_solve(hybrid: HybridModel, p: torch.Tensor, u0: torch.Tensor, plan: Shooting,
                 box: tuple[torch.Tensor, torch.Tensor] | None = None, rows: torch.Tensor | None = None) -> torch.Tensor:
    """``rk4_segments(*hybrid_drive(hybrid, p, plan.x_half, rows), …)``'s trajectory ``(K+1, S, n)``
    with the hand-written backward pass: ``p (S, n_params)`` per segment, or per experiment with
    ``rows (S,)``; ``u0 (S, n)``. Gradients reach the network, ``p`` (and so the estimates) and ``u0``."""
    xs = plan.x_half
    bound = hybrid.compiled.bind(p, rows)
    assert isinstance(bound, BoundRhs)
    d = bound.c.expand(xs.shape[0], *bound.c.shape)
    if hybrid.compiled.input_names:
        d = d + torch.einsum("sij,hsj->hsi", bound.B, xs)
    if rows is not None:
        p = p[rows]
    layers = [m for m in hybrid.net if isinstance(m, nn.Linear)]
    wu, wx, wp, b1 = split_first_layer(layers[0].weight, layers[0].bias, hybrid.mean, hybrid.std,
                                       len(hybrid.state_idx), len(hybrid.input_idx))
    pre = b1.expand(*xs.shape[:-1], b1.shape[0])
    if hybrid.input_idx:
        pre = pre + xs[..., hybrid.input_idx] @ wx.T
    if hybrid.param_idx:
        pre = pre + (p[:, hybrid.param_idx] @ wp.T)[None]
    gain = hybrid.out_scale * hybrid.out_mask
    if hybrid.coefficients is not None:
        gain = gain / hybrid.equation_coefficients(p)  # (S, k)
    reads, index = columns(hybrid)
    rest = [(m.weight.T.unsqueeze(0), m.bias.view(1, 1, -1)) for m in layers[1:]]
    return rk4_adjoint(u0, bound.A.expand(u0.shape[0], -1, -1), d, pre.unsqueeze(1), wu.T.unsqueeze(0), rest,
                       gain.unsqueeze(0) if gain.dim() == 2 else gain.view(1, 1, -1), h=plan.dt, steps=plan.steps,
                       activation=hybrid.spec.activation, box=box, reads=reads, index=index)


def warm(dtype: torch.dtype = torch.float64) -> None:
    """Compile the loops (the training solve's and :mod:`physmend.ude.rk4_steps`') for ``dtype`` (or load them from numba's cache beside the module) with a
    solve of a few numbers: the first compilation takes seconds, so a process that will train
    later does it while it would otherwise wait. Where another process is compiling them (discover's
    standby worker), this one waits for it and then reads its cache (:mod:`physmend.ude.compile_lock`)."""
    from physmend.ude import rk4_loops
    from physmend.ude.compile_lock import compiling

    g = torch.Generator().manual_seed(0)
    u0, A, d, pre, wu, w, b, gain = (torch.randn(*s, dtype=dtype, generator=g).requires_grad_()
                                     for s in ((2, 2), (2, 2, 2), (3, 2, 2), (3, 1, 2, 3), (1, 2, 3), (1, 3, 2), (1, 1, 2), (1, 2, 2)))
    box = (torch.full((2,), -5.0, dtype=dtype), torch.full((2,), 5.0, dtype=dtype))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with compiling(rk4_loops.__file__):
            traj = rk4_adjoint(u0, A, d, pre, wu, [(w, b)], gain, h=0.1, steps=1, activation="tanh", box=box)
            traj.sum().backward()
            if LOOPS["compiled"]:  # and the whole-trajectory loop (physmend.ude.fixed_step)
                from physmend.ude.fixed_step import DriveForm, _solve

                with torch.no_grad():
                    form = DriveForm(A, lambda times: (d, pre), wu, [(w, b)], gain, None, None, "tanh", 1)
                    _solve(form, u0, torch.tensor([[0.0, 0.1], [0.0, 0.1]], dtype=dtype))
    finally:
        torch.set_num_threads(threads)

"""The drive form of a stack's right-hand side (:mod:`physmend.ude.drive`): what does not depend on
the state — the physics' ``B(p)·x + c(p)`` and the networks' first layer on inputs and parameters —
computed once per solve, for the training solve (with autograd or the hand-written adjoint,
:mod:`physmend.ude.adjoint`) and as a table on the input knots for whole-trajectory solves. A part
of :class:`~physmend.ude.stack.solve.Stack` (mixed in), which supplies the template hybrid, the
normalisation, the output scale and the state box.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from physmend.simulate import PiecewiseLinear
from physmend.ude.adjoint import ACTIVATIONS as ADJOINT_ACTIVATIONS, rk4_adjoint
from physmend.ude.drive import Drives, columns, drivable, physics_drive, split_first_layer, table_fits, with_physics
from physmend.ude.fixed_step import DriveForm
from physmend.ude.shooting import Shooting
from physmend.ude.stack.net import StackedNet


class StackDrives:
    """The drive-form solves of the stacked models (mixed into :class:`~physmend.ude.stack.solve.Stack`)."""

    def _first_layer(self, net: StackedNet, m: int, p: torch.Tensor, xs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The first layer split as :func:`split_first_layer`: its state weights ``(M, b, n_in_states)``
        and its input, parameter and bias part at every half step ``(H, M, r, b)``."""
        h = self.template
        r = p.shape[0] // m
        wu, wx, wp, b1 = split_first_layer(net.weights[0].transpose(1, 2), net.biases[0][:, 0, :], self.mean,
                                           self.std, len(h.state_idx), len(h.input_idx))  # (M, b, ·), (M, b)
        pre = b1[None, :, None, :].expand(xs.shape[0], m, r, b1.shape[-1])  # (H, M, r, b)
        if h.input_idx:
            pre = pre + xs[..., h.input_idx].reshape(xs.shape[0], m, r, -1) @ wx.transpose(1, 2)
        if h.param_idx:
            pre = pre + (p[:, h.param_idx].reshape(m, r, -1) @ wp.transpose(1, 2))[None]
        return wu, pre

    def _drives_apply(self, net: StackedNet) -> bool:
        """Whether the drive form applies to the stack (:func:`~physmend.ude.drive.drivable`, no observed
        features, a hidden layer in every model)."""
        return (drivable(self.template) and net.use[0] is None
                and all(mem.hybrid.spec.widths for mem in self.members))

    def _network_split(self, net: StackedNet, m: int, p: torch.Tensor, xs: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The first layer's state weights transposed ``(M, n_in_states, b)``, its input, parameter
        and bias part ``(H, M, r, b)`` (:meth:`_first_layer`) and the equations' inverse coefficients (or None)."""
        wu, pre = self._first_layer(net, m, p, xs)
        coef = self._coef(p)
        return wu.transpose(1, 2), pre, None if coef is None else coef.reciprocal()

    def _drive(self, net: StackedNet, m: int, p: torch.Tensor, xs: torch.Tensor,
               shared: tuple[torch.Tensor, torch.Tensor] | None = None
               ) -> tuple[Callable[[torch.Tensor, Any], torch.Tensor], Drives] | None:
        """:meth:`_rhs` with what does not depend on the state computed once for the half-step inputs
        ``xs (H, m·R, n_inputs)`` (:mod:`physmend.ude.drive`); None where that does not apply.
        ``shared = (p_small, rows)`` with ``p = p_small[rows]``: the physics keeps one matrix per
        row of ``p_small`` (:class:`~physmend.modeling.compile.BoundRhs`)."""
        h = self.template
        if not self._drives_apply(net):
            return None
        linear_plus, physics = physics_drive(h, p, xs) if shared is None else physics_drive(h, shared[0], xs, shared[1])
        rows = p.shape[0]
        r = rows // m
        wu_t, pre, inv = self._network_split(net, m, p, xs)
        state_idx, index = columns(h)

        def f(u: torch.Tensor, drive: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
            d, first = drive
            us = u if state_idx is None else u[:, state_idx]
            corr = net(None, torch.baddbmm(first, us.reshape(m, r, -1), wu_t)).reshape(rows, -1)
            return with_physics(u, d, linear_plus, corr if inv is None else corr * inv, index)

        return f, Drives(physics, pre.reshape(xs.shape[0], m, r, -1))

    def _drive_table(self, net: StackedNet, m: int, p: torch.Tensor, inputs: PiecewiseLinear
                     ) -> tuple[Callable[[torch.Tensor, torch.Tensor], torch.Tensor], PiecewiseLinear] | None:
        """:meth:`_rhs` for a whole-trajectory solve as ``f(u, d)`` and its drive ``d(t)`` on the knots
        of ``inputs`` (``m·R`` rows, model-major), as :func:`~physmend.ude.drive.drive_table` for one
        model; None where the drives do not apply (:meth:`_drive`). ``u (..., m·R, n)`` may have
        leading dimensions (finite-difference Jacobians)."""
        h = self.template
        if not self._drives_apply(net):
            return None
        if not table_fits(p.shape[0], inputs.knots.shape[0], len(h.compiled.state_names) + net.weights[0].shape[-1],
                          p.dtype):
            return None
        xs = inputs.values.transpose(0, 1)  # (K, m·R, n_inputs): the inputs at their knots
        linear_plus, physics = physics_drive(h, p, xs)
        rows = p.shape[0]
        r = rows // m
        wu_t, pre, inv = self._network_split(net, m, p, xs)
        state_idx, index = columns(h)
        n = physics.shape[-1]
        table = PiecewiseLinear(inputs.knots, torch.cat([physics, pre.reshape(xs.shape[0], rows, -1)], -1)
                                .transpose(0, 1).contiguous())

        def f(u: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
            d_phys, first = d[..., :n], d[..., n:]
            us = u if state_idx is None else u[..., state_idx]
            if us.dim() == 2:
                corr = net(None, torch.baddbmm(first.reshape(m, r, -1), us.reshape(m, r, -1), wu_t)).reshape(rows, -1)
            else:  # copies (..., m·R, n): each model's rows of every copy through its own network
                lead = us.shape[:-2]
                copies = us.numel() // (rows * us.shape[-1])
                uu = us.reshape(copies, m, r, -1).movedim(0, 1).reshape(m, copies * r, -1)
                ff = first.expand(*lead, rows, first.shape[-1]).reshape(copies, m, r, -1).movedim(0, 1)
                out = net(None, torch.baddbmm(ff.reshape(m, copies * r, -1), uu, wu_t))
                corr = out.reshape(m, copies, r, -1).movedim(0, 1).reshape(*lead, rows, -1)
            return with_physics(u, d_phys, linear_plus, corr if inv is None else corr * inv, index)

        return f, table

    def _form(self, net: StackedNet, m: int, p: torch.Tensor, inputs: PiecewiseLinear) -> DriveForm | None:
        """The drive form of the stacked models on the rows of ``inputs`` (``m·R`` rows, model-major)
        for a whole-trajectory solve by :func:`~physmend.ude.fixed_step.rk4_states`; None where
        the adjoint's form does not apply (:meth:`_adjoint`)."""
        h = self.template
        if (not drivable(h) or any(u is not None for u in net.use)
                or not all(mem.hybrid.spec.widths for mem in self.members)):
            return None
        bound = h.compiled.bind(p)
        rows = p.shape[0]
        r = rows // m
        coef = self._coef(p)
        reads, index = columns(h)

        def drive(times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            xs = inputs.at_each(times)  # (H, m·R, n_inputs)
            d = bound.c.expand(xs.shape[0], *bound.c.shape)
            if h.compiled.input_names:
                d = d + torch.einsum("sij,hsj->hsi", bound.B, xs)
            return d, self._first_layer(net, m, p, xs)[1]

        wu = self._first_layer(net, m, p, inputs.values[:, :1].transpose(0, 1))[0]
        return DriveForm(bound.A, drive, wu.transpose(1, 2), list(zip(net.weights[1:], net.biases[1:])),
                         net.scale if coef is None else net.scale * coef.reciprocal().view(m, r, -1), reads, index,
                         tuple(net.activations), m)

    def _adjoint(self, net: StackedNet, m: int, p: torch.Tensor, u0: torch.Tensor, plan: Shooting,
                 shared: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor | None:
        """The training solve's trajectory ``(K+1, m·R, n)`` with the hand-written backward pass
        (``train.backward: adjoint``, :mod:`physmend.ude.adjoint`): the drive form of :meth:`_drive`
        with one depth for the whole stack (each model its own activation); None where that does not apply."""
        h = self.template
        if (self.members[0].cfg.train.backward != "adjoint" or not drivable(h) or any(u is not None for u in net.use)
                or not set(net.activations) <= set(ADJOINT_ACTIVATIONS)
                or not all(mem.hybrid.spec.widths for mem in self.members)):
            return None
        xs = plan.x_half
        bound = h.compiled.bind(p) if shared is None else h.compiled.bind(shared[0], shared[1])
        d = bound.c.expand(xs.shape[0], *bound.c.shape)
        if h.compiled.input_names:
            d = d + torch.einsum("sij,hsj->hsi", bound.B, xs)
        rows = p.shape[0]
        r = rows // m
        wu, pre = self._first_layer(net, m, p, xs)
        coef = self._coef(p)
        gain = net.scale if coef is None else net.scale * coef.reciprocal().view(m, r, -1)
        reads, index = columns(h)
        return rk4_adjoint(u0, bound.A, d, pre, wu.transpose(1, 2), list(zip(net.weights[1:], net.biases[1:])), gain,
                           h=plan.dt, steps=plan.steps, activation=tuple(net.activations), box=self.box, reads=reads,
                           index=index)

"""One entry point for batched simulation: ``odeint`` over a registry of solvers."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import torch

from physmend.simulate.errors import SimulationError
from physmend.simulate.rodas import odeint_rodas
from physmend.simulate.rosenbrock import odeint_rosenbrock

Rhs = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

#: physmend's own solvers; every torchdiffeq method name is accepted as well.
#: All take ``first_step``, ``max_steps``, ``tstops`` and ``jacobian`` options.
OWN_METHODS: dict[str, Callable[..., torch.Tensor]] = {
    "rosenbrock23": odeint_rosenbrock,
    "rodas3": partial(odeint_rodas, tableau="rodas3"),
    "rodas4": odeint_rodas,
    "rodas4p2": partial(odeint_rodas, tableau="rodas4p2"),
}


#: methods that can give every batch element its own clock (``options["clocks"]``: per element, the
#: times its steps end on; ``f`` then gets ``t (B,)``, see :mod:`physmend.simulate.clocks`)
CLOCK_METHODS = ("rodas3", "rodas4", "rodas4p2")


def available_methods() -> list[str]:
    from torchdiffeq._impl.odeint import SOLVERS

    return sorted(set(OWN_METHODS) | set(SOLVERS))


def odeint(
    f: Rhs,
    u0: torch.Tensor,
    t: torch.Tensor,
    *,
    method: str = "rosenbrock23",
    rtol: float = 1e-6,
    atol: float = 1e-6,
    options: dict | None = None,
    names: list[str] | None = None,
) -> torch.Tensor:
    """Solve ``du/dt = f(t, u)`` for a batch ``u0 (B, n)``; returns ``u`` at ``t (T,)``: ``(T, B, n)``.

    Args:
        f: right-hand side, ``f(t scalar tensor, u (B, n)) -> (B, n)``.
        u0: initial states of every batch element (experiment or segment).
        t: increasing evaluation times in seconds; ``t[0]`` is the initial time.
        method: ``"rosenbrock23"`` (stiff, L-stable, order 2; default), the stiffly accurate,
            L-stable Rosenbrock methods ``"rodas3"`` (order 3, as cheap per step as
            rosenbrock23), ``"rodas4"`` (order 4, Hairer-Wanner) and ``"rodas4p2"`` (order 4,
            Steinebach: keeps its order where stiff states follow their inputs), or any
            torchdiffeq method (``"dopri5"``, ``"bosh3"``, ``"rk4"`` …).
        rtol, atol: tolerances of adaptive methods (atol in state units).
        options: extra solver options (torchdiffeq ``options``; for physmend's own methods:
            ``first_step``, ``max_steps``, ``tstops``, ``jacobian``; for :data:`CLOCK_METHODS`
            ``clocks`` as well, where ``f`` and ``jacobian`` accept ``t (B,)``; other methods
            ignore it).
        names: a name per batch element, used in error messages.

    Raises:
        SimulationError: the method is unknown, or integration failed (names the experiment and time).
    """
    names = names or [str(i) for i in range(u0.shape[0])]
    options = dict(options or {})
    clocks = options.pop("clocks", None)
    if clocks is not None and method in CLOCK_METHODS:
        from physmend.simulate.clocks import odeint_rodas_each

        options.pop("tstops", None)
        return odeint_rodas_each(f, u0, t, clocks, rtol=rtol, atol=atol, names=names, tableau=method, **options)
    if method in OWN_METHODS:
        return OWN_METHODS[method](f, u0, t, rtol=rtol, atol=atol, names=names, **options)
    from torchdiffeq import odeint as tde_odeint
    from torchdiffeq._impl.odeint import SOLVERS

    if method not in SOLVERS:
        raise SimulationError(
            f"simulate.method must be one of {available_methods()}, but got {method!r}"
        )
    last: dict = {"t": float(t[0]), "rate": None}

    def watched(tt: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        du = f(tt, u)
        last["t"] = float(tt)
        last["rate"] = (du.detach().abs() / (1.0 + u.detach().abs())).amax(-1)
        ok = torch.isfinite(du).all(-1)
        if not bool(ok.all()):
            bad = [names[i] for i in torch.nonzero(~ok).flatten().tolist()]
            raise SimulationError(
                f"integration failed for experiment(s) {bad} at t = {float(tt):.6g} s: "
                "the derivative became non-finite (NaN/inf)"
            )
        return du

    try:
        return tde_odeint(watched, u0, t, method=method, rtol=rtol, atol=atol, options=options or None)
    except AssertionError as exc:
        worst = names[int(last["rate"].argmax())] if last["rate"] is not None else names
        raise SimulationError(
            f"integration with {method!r} failed for experiment {worst!r} (fastest-changing) at "
            f"t = {last['t']:.6g} s: {exc}; if the model is stiff, use simulate.method=rosenbrock23"
        ) from exc

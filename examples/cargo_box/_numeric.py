"""Numpy/scipy evaluation of a simplified model, for the telemetry generator and its checks.

The pipeline simulates with torch (``physmend.modeling.compile_model``); the generator and the
library's checks need an independent, stiff-capable reference instead: the simplified model
lambdified to numpy (derivatives, Jacobian, outputs, start values) and integrated with
``scipy.integrate.solve_ivp`` (Radau/BDF).

Shapes: ``u`` states ``(n_states,)``, ``x`` inputs ``(n_inputs,)``, ``p`` parameters
``(n_params,)``; :meth:`NumpyModel.outputs` also takes stacked states ``(n_t, n_states)``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import sympy as sp
from scipy.integrate import solve_ivp

from physmend.modeling import Model, SimplifiedModel


def _lambdify(args: list[sp.Symbol], exprs: list[sp.Expr]) -> Callable[..., list]:
    safe = {s: sp.Symbol(f"a{i}", real=True) for i, s in enumerate(args)}
    renamed = [sp.sympify(e).xreplace(safe) for e in exprs]
    return sp.lambdify(list(safe.values()), renamed, modules="numpy", cse=True)


@dataclass
class NumpyModel:
    """Numpy functions of a :class:`SimplifiedModel` (derivatives in state units per second)."""

    model: SimplifiedModel
    _rhs: Callable[..., list]
    _jac: Callable[..., list]
    _outputs: Callable[..., list]
    _start: Callable[..., list]

    @classmethod
    def from_model(cls, model: Model | SimplifiedModel) -> NumpyModel:
        """Simplify ``model`` if needed and lambdify it (takes about a second for 28 states)."""
        sm = model.simplify() if isinstance(model, Model) else model
        u = [v.symbol for v in sm.states]
        x = [v.symbol for v in sm.inputs]
        p = [v.symbol for v in sm.parameters]
        f = sp.Matrix([sm.rhs[n] for n in sm.state_names])
        jac = f.jacobian(u)
        return cls(
            model=sm,
            _rhs=_lambdify(u + x + p, list(f)),
            _jac=_lambdify(u + x + p, list(jac)),
            _outputs=_lambdify(u + x + p, list(sm.outputs.values())),
            _start=_lambdify(p, [v.start if v.start is not None else sp.Integer(0) for v in sm.states]),
        )

    @property
    def n_states(self) -> int:
        return len(self.model.states)

    def parameters(self, values: Mapping[str, float] | None = None) -> np.ndarray:
        """Declared parameter values with ``values`` (name -> value) overriding them: ``(n_params,)``."""
        names = self.model.parameter_names
        unknown = sorted(set(values or {}) - set(names))
        if unknown:
            raise KeyError(f"model {self.model.name!r} has no parameter(s) {unknown}; parameters are {names}")
        merged = {v.name: float(v.value) for v in self.model.parameters} | {k: float(v) for k, v in (values or {}).items()}
        return np.array([merged[n] for n in names], dtype=float)

    def rhs(self, u: np.ndarray, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Derivatives ``du/dt``, shape ``(n_states,)``."""
        return np.array(self._rhs(*u, *x, *p), dtype=float)

    def jac(self, u: np.ndarray, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Jacobian ``d(du/dt)/du``, shape ``(n_states, n_states)``.

        Entries the symbolic form cannot evaluate (0/0 at a kink such as ``x·sqrt|x|`` at
        ``x = 0``) are replaced by central finite differences of their column.
        """
        n = self.n_states
        with np.errstate(divide="ignore", invalid="ignore"):
            J = np.array(self._jac(*u, *x, *p), dtype=float).reshape(n, n)
        bad_cols = np.flatnonzero(~np.isfinite(J).all(axis=0))
        for j in bad_cols:
            h = 1e-6 * max(1.0, abs(float(u[j])))
            up, um = np.array(u, dtype=float), np.array(u, dtype=float)
            up[j] += h
            um[j] -= h
            J[:, j] = (self.rhs(up, x, p) - self.rhs(um, x, p)) / (2 * h)
        return J

    def outputs(self, u: np.ndarray, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Measured outputs for states ``(n_t, n_states)`` and inputs ``(n_t, n_inputs)``: ``(n_t, n_outputs)``."""
        u, x = np.atleast_2d(u), np.atleast_2d(x)
        cols = self._outputs(*u.T, *x.T, *p)
        return np.stack(np.broadcast_arrays(*cols, u[:, 0]), axis=-1)[:, :-1]

    def start(self, p: np.ndarray) -> np.ndarray:
        """Default initial states for parameters ``p``: ``(n_states,)``."""
        return np.array(self._start(*p), dtype=float)


def piecewise_linear_inputs(
    channels: list[tuple[np.ndarray, np.ndarray]],
) -> Callable[[float], np.ndarray]:
    """Inputs as the linear interpolation of each channel's ``(times, values)`` samples (NaN-free).

    Returns ``x(t) -> (n_inputs,)``; outside a channel's samples its end value is held.
    """
    for k, (t, v) in enumerate(channels):
        if len(t) == 0 or len(t) != len(v) or not np.all(np.isfinite(v)):
            raise ValueError(f"input channel {k}: needs matching, non-empty, finite samples, got {len(t)} times, {len(v)} values")

    def x(t: float) -> np.ndarray:
        return np.array([np.interp(t, tc, vc) for tc, vc in channels])

    return x


def simulate(
    nm: NumpyModel,
    p: np.ndarray,
    inputs: Callable[[float], np.ndarray],
    t_eval: np.ndarray,
    *,
    u0: np.ndarray | None = None,
    breakpoints: np.ndarray | None = None,
    method: str = "BDF",
    rtol: float = 1e-6,
    atol: float = 1e-6,
) -> np.ndarray:
    """Integrate from ``t_eval[0]`` (start values unless ``u0``) and return states ``(n_t, n_states)``.

    ``breakpoints`` (sorted times, e.g. input sample times) split the integration so the solver
    never steps across a kink of the piecewise-linear inputs; without them one solve covers all.
    """
    t_eval = np.asarray(t_eval, dtype=float)
    u = nm.start(p) if u0 is None else np.asarray(u0, dtype=float)
    knots = np.unique(np.concatenate([t_eval[[0, -1]], [] if breakpoints is None else breakpoints]))
    knots = knots[(knots >= t_eval[0]) & (knots <= t_eval[-1])]
    out = np.empty((len(t_eval), nm.n_states))
    out[0] = u
    for a, b in zip(knots[:-1], knots[1:]):
        want = (t_eval > a) & (t_eval <= b)
        t_ev = t_eval[want]
        if not t_ev.size or t_ev[-1] != b:
            t_ev = np.append(t_ev, b)  # always return the state at the knot, to continue from
        sol = solve_ivp(
            lambda t, y: nm.rhs(y, inputs(t), p), (a, b), u, method=method,
            jac=lambda t, y: nm.jac(y, inputs(t), p), t_eval=t_ev, rtol=rtol, atol=atol,
        )
        if not sol.success:
            raise RuntimeError(f"model {nm.model.name!r}: integration failed on [{a}, {b}] s: {sol.message}")
        out[want] = sol.y.T[: int(want.sum())]
        u = sol.y[:, -1]
    return out

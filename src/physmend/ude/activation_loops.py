"""Each activation's loop over one layer of the compiled loops (:mod:`physmend.ude.rk4_loops`,
:mod:`physmend.ude.rk4_steps`), and the choice among them by number (:data:`CODES`).

Each loop writes the layer's values ``Y = act(Z)`` and, with ``keep`` (a training solve, whose
backward pass needs them), overwrites ``Z`` with the derivatives ``act'(Z)``: the forward pass has
in hand what they are made of (gelu's ``erf`` and ``e^{-x²}``, softplus' ``e^{|a|}``), which the
backward pass computed a second time (a third of its time with gelu). The same expressions as
before, so the same values.

Each loop is a compiled function of its own, written with :mod:`physmend.ude.vector_math` (no call
into the C library), and compiles to vector instructions. The loops index whole arrays ``(L, R, T,
P)`` at ``[l, r, t, :width]``: a slice would be a new array each time.

numba's cache keys each compiled function on the contents of its own file: after editing
:mod:`physmend.ude.vector_math`, whose functions these inline, delete the cache files
(``__pycache__/*.nbi``, ``*.nbc`` beside this module); touching a file does not recompile it.
"""

from __future__ import annotations

import math

import numba

from physmend.ude.vector_math import FAST, gelu, gelu_derivative, sigmoid, softplus, tanh

#: the activations written here, by the number the loops take
CODES = {"tanh": 0, "sigmoid": 1, "relu": 2, "softplus": 3, "silu": 4, "elu": 5, "gelu": 6}
_FAST = FAST

_LAYER = {"cache": True, "fastmath": _FAST, "error_model": "numpy"}


@numba.njit(**_LAYER)
def _tanh(Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        y = tanh(Z[l, r, t, c])
        Y[l, r, t, c] = y
        if keep:
            Z[l, r, t, c] = 1.0 - y * y


@numba.njit(**_LAYER)
def _sigmoid(Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        y = sigmoid(Z[l, r, t, c])
        Y[l, r, t, c] = y
        if keep:
            Z[l, r, t, c] = y * (1.0 - y)


@numba.njit(**_LAYER)
def _relu(Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        Y[l, r, t, c] = a if a > 0.0 or a != a else 0.0
        if keep:
            Z[l, r, t, c] = 1.0 if a > 0.0 else 0.0


@numba.njit(**_LAYER)
def _softplus(Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        Y[l, r, t, c] = softplus(a)
        if keep:  # e^{|a|} is softplus' own: computed once
            Z[l, r, t, c] = sigmoid(a)


@numba.njit(**_LAYER)
def _silu(Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        s = sigmoid(a)
        Y[l, r, t, c] = a * s
        if keep:
            Z[l, r, t, c] = s * (1.0 + a * (1.0 - s))


@numba.njit(**_LAYER)
def _elu(Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        y = a if a > 0.0 else math.expm1(a)
        Y[l, r, t, c] = y
        if keep:  # e^a = y + 1 below 0
            Z[l, r, t, c] = 1.0 if a > 0.0 else y + 1.0


@numba.njit(**_LAYER)
def _gelu(Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        Y[l, r, t, c] = gelu(a)
        if keep:  # erf and e^{-x²} are gelu's own: computed once
            Z[l, r, t, c] = gelu_derivative(a)


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")
def activate(code, Z, Y, l, r, t, width, keep):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    """``Y[l, r, t, :width] = act(Z[l, r, t, :width])`` for activation number ``code``, and with
    ``keep`` ``Z[l, r, t, :width] = act'(Z[l, r, t, :width])`` (module docstring). Each loop is
    called, not inlined: the seven loops inlined into one function compiled to code that ran softplus
    and gelu 2–4 times slower than alone."""
    if code == 0:
        _tanh(Z, Y, l, r, t, width, keep)
    elif code == 1:
        _sigmoid(Z, Y, l, r, t, width, keep)
    elif code == 2:
        _relu(Z, Y, l, r, t, width, keep)
    elif code == 3:
        _softplus(Z, Y, l, r, t, width, keep)
    elif code == 4:
        _silu(Z, Y, l, r, t, width, keep)
    elif code == 5:
        _elu(Z, Y, l, r, t, width, keep)
    else:
        _gelu(Z, Y, l, r, t, width, keep)

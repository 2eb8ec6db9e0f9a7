"""Each activation's loop over one layer of the compiled loops (:mod:`physmend.ude.rk4_loops`,
:mod:`physmend.ude.rk4_steps`), and the choice among them by number (:data:`CODES`).

Each loop is a compiled function of its own, written with :mod:`physmend.ude.vector_math` (no call
into the C library), and compiles to vector instructions. The loops index whole arrays ``(L, R, T,
P)`` at ``[l, r, t, :width]``: a slice would be a new array each time.

numba's cache keys each compiled function on its own file: after editing this module or
:mod:`physmend.ude.vector_math`, touch ``rk4_loops.py`` and ``rk4_steps.py`` so that they recompile
(an installation writes every file).
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
def _tanh(Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        Y[l, r, t, c] = tanh(Z[l, r, t, c])


@numba.njit(**_LAYER)
def _sigmoid(Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        Y[l, r, t, c] = sigmoid(Z[l, r, t, c])


@numba.njit(**_LAYER)
def _relu(Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        Y[l, r, t, c] = a if a > 0.0 or a != a else 0.0


@numba.njit(**_LAYER)
def _softplus(Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        Y[l, r, t, c] = softplus(Z[l, r, t, c])


@numba.njit(**_LAYER)
def _silu(Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        Y[l, r, t, c] = a * sigmoid(a)


@numba.njit(**_LAYER)
def _elu(Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        Y[l, r, t, c] = a if a > 0.0 else math.expm1(a)


@numba.njit(**_LAYER)
def _gelu(Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        Y[l, r, t, c] = gelu(Z[l, r, t, c])


@numba.njit(**_LAYER)
def _d_tanh(Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        y = Y[l, r, t, c]
        GA[l, r, t, c] *= 1.0 - y * y


@numba.njit(**_LAYER)
def _d_sigmoid(Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        y = Y[l, r, t, c]
        GA[l, r, t, c] *= y * (1.0 - y)


@numba.njit(**_LAYER)
def _d_relu(Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        GA[l, r, t, c] *= 1.0 if Z[l, r, t, c] > 0.0 else 0.0


@numba.njit(**_LAYER)
def _d_softplus(Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        GA[l, r, t, c] *= sigmoid(Z[l, r, t, c])


@numba.njit(**_LAYER)
def _d_silu(Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        a = Z[l, r, t, c]
        s = sigmoid(a)
        GA[l, r, t, c] *= s * (1.0 + a * (1.0 - s))


@numba.njit(**_LAYER)
def _d_elu(Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):  # e^a = y + 1 below 0
        GA[l, r, t, c] *= 1.0 if Z[l, r, t, c] > 0.0 else Y[l, r, t, c] + 1.0


@numba.njit(**_LAYER)
def _d_gelu(Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    for c in range(width):
        GA[l, r, t, c] *= gelu_derivative(Z[l, r, t, c])


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")
def activate(code, Z, Y, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    """``Y[l, r, t, :width] = act(Z[l, r, t, :width])`` for activation number ``code``. Each loop is
    called, not inlined: the seven loops inlined into one function compiled to code that ran softplus
    and gelu 2–4 times slower than alone."""
    if code == 0:
        _tanh(Z, Y, l, r, t, width)
    elif code == 1:
        _sigmoid(Z, Y, l, r, t, width)
    elif code == 2:
        _relu(Z, Y, l, r, t, width)
    elif code == 3:
        _softplus(Z, Y, l, r, t, width)
    elif code == 4:
        _silu(Z, Y, l, r, t, width)
    elif code == 5:
        _elu(Z, Y, l, r, t, width)
    else:
        _gelu(Z, Y, l, r, t, width)


@numba.njit(cache=True, fastmath=_FAST, error_model="numpy", inline="always")
def times_derivative(code, Z, Y, GA, l, r, t, width):  # noqa: ANN001, ANN202, PLR0913  # pragma: no cover - compiled
    """``GA[l, r, t, :width] *= act'(Z[l, r, t, :width])`` (``Y`` the activation's values)."""
    if code == 0:
        _d_tanh(Z, Y, GA, l, r, t, width)
    elif code == 1:
        _d_sigmoid(Z, Y, GA, l, r, t, width)
    elif code == 2:
        _d_relu(Z, Y, GA, l, r, t, width)
    elif code == 3:
        _d_softplus(Z, Y, GA, l, r, t, width)
    elif code == 4:
        _d_silu(Z, Y, GA, l, r, t, width)
    elif code == 5:
        _d_elu(Z, Y, GA, l, r, t, width)
    else:
        _d_gelu(Z, Y, GA, l, r, t, width)

"""The activations of the compiled loops, written without the C library
(:mod:`physmend.ude.vector_math`), are the exact values to a few units in the last place (mpmath at
30 digits), keep NaN, and give the limits at ±infinity."""

from __future__ import annotations

import math
from collections.abc import Callable

import mpmath
import numba
import numpy as np
import pytest

from physmend.ude import vector_math as vm


def _each(f: Callable[[float], float]) -> Callable[[np.ndarray], np.ndarray]:
    """``f`` (compiled) on each value of a float64 array, in a compiled loop as the training loops call it."""
    @numba.njit(fastmath=vm.FAST, error_model="numpy")
    def loop(x: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
        for i in range(x.shape[0]):
            out[i] = f(x[i])

    def run(x: np.ndarray) -> np.ndarray:
        out = np.empty_like(x)
        loop(x, out)
        return out
    return run


@numba.njit
def _erf(x: float) -> float:  # pragma: no cover - compiled
    return vm.erf_and_gauss(x)[0]


@numba.njit
def _gauss(x: float) -> float:  # pragma: no cover - compiled
    return vm.erf_and_gauss(x)[1]


def _mp(f: Callable) -> Callable[[float], float]:
    def exact(x: float) -> float:
        with mpmath.workdps(30):
            return float(f(mpmath.mpf(x)))
    return exact


_RNG = np.random.default_rng(0)
_X = np.concatenate([_RNG.normal(0, 1, 1500), _RNG.normal(0, 8, 1500), np.linspace(-30, 30, 1201),
                     -np.logspace(-300, 2.5, 200), np.logspace(-300, 2.5, 200), [0.625, 1.5, 6.0, 20.0, -1.5, -6.0]])
_S = mpmath.sqrt(2)
# name, function, exact value, where the units in the last place are counted, at most
CASES = [
    ("exp_pos", vm.exp_pos, _mp(mpmath.exp), lambda x: (x >= 0) & (x < 700), 1.0),
    ("sigmoid", vm.sigmoid, _mp(lambda a: 1 / (1 + mpmath.exp(-a))), lambda x: x > -700, 2.0),
    ("softplus", vm.softplus, _mp(lambda a: a if a > 20 else mpmath.log1p(mpmath.exp(a))), lambda x: x > -700, 4.0),
    ("erf", _erf, _mp(mpmath.erf), lambda x: x != 0, 3.0),
    ("gauss", _gauss, _mp(lambda x: mpmath.exp(-(x * x))), lambda x: np.abs(x) < 3, 12.0),
    ("gelu", vm.gelu, _mp(lambda a: a / 2 * (1 + mpmath.erf(a / _S))), lambda x: x > 0, 3.0),
    ("gelu_derivative", vm.gelu_derivative,
     _mp(lambda a: (1 + mpmath.erf(a / _S)) / 2 + a * mpmath.exp(-a * a / 2) / mpmath.sqrt(2 * mpmath.pi)),
     lambda x: x > -0.5, 3.0),  # 0 at -0.7518
]


@pytest.mark.parametrize(("name", "f", "exact", "counted", "most"), CASES, ids=[c[0] for c in CASES])
def test_each_function_is_the_exact_value_to_a_few_units_in_the_last_place(
        name: str, f: Callable, exact: Callable, counted: Callable, most: float) -> None:
    x = _X[counted(_X)]
    got = _each(f)(x)
    want = np.array([exact(v) for v in x])
    ulps = np.abs(got - want) / np.spacing(np.abs(want))
    assert float(ulps.max()) <= most, (name, float(ulps.max()), float(x[np.argmax(ulps)]))
    # elsewhere (below 1e-300, near a zero, or 1 + erf(x) for x < 0, which cancels as in torch's gelu):
    # off by no more than a few units of the argument's size
    rest = _X[~counted(_X)] if name != "exp_pos" else np.array([])
    err = np.abs(_each(f)(rest) - np.array([exact(v) for v in rest]))
    assert bool(np.all(err <= 4e-16 * np.maximum(1.0, np.abs(rest)))), name


def test_tanh_is_the_c_library_tanh() -> None:
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(0, 1, 200_000), rng.normal(0, 6, 200_000), rng.uniform(-1e-6, 1e-6, 10_000),
                        np.linspace(-25, 25, 100_001), [0.625, -0.625, 20.0, -20.0, 19.999, 5e-324, 1e-300]])
    out = _each(vm.tanh)(x)
    want = np.array([math.tanh(v) for v in x])
    ulps = np.abs(out - want) / np.spacing(np.abs(want))
    assert float(ulps.max()) <= 2.0


SPECIAL = np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 800.0, -800.0])
LIMITS = {  # at NaN, +inf, -inf, 0, -0, 800, -800
    "tanh": (np.nan, 1.0, -1.0, 0.0, 0.0, 1.0, -1.0),
    "sigmoid": (np.nan, 1.0, 0.0, 0.5, 0.5, 1.0, 0.0),
    "softplus": (np.nan, np.inf, 0.0, math.log(2), math.log(2), 800.0, 0.0),
    "erf": (np.nan, 1.0, -1.0, 0.0, 0.0, 1.0, -1.0),
    "gauss": (np.nan, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0),
    "gelu": (np.nan, np.inf, np.nan, 0.0, 0.0, 800.0, 0.0),  # -inf·0, as torch
}


@pytest.mark.parametrize("name", list(LIMITS))
def test_nan_and_the_limits(name: str) -> None:
    f = {"erf": _erf, "gauss": _gauss}.get(name) or getattr(vm, name)
    got = _each(f)(SPECIAL)
    np.testing.assert_allclose(got, np.array(LIMITS[name]), rtol=1e-15, atol=0)
    assert _each(vm.exp_pos)(np.array([0.0, 708.0, np.inf, np.nan])).tolist()[:3] == [1.0, np.inf, np.inf]

"""``fit``: one entry point over a string registry of symbolic-regression back ends."""

from __future__ import annotations

import importlib
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from physmend.cpus import usable_cpus
from physmend.symbolic._errors import BackendUnavailable, SymbolicError
from physmend.modeling.evaluate import display, evaluate, mse_r2
from physmend.modeling.units import mismatch
from physmend.symbolic._front import Candidate, ParetoFront, pareto_filter
from physmend.modeling.interval import interval_violation

#: back end name -> module implementing it (imported lazily; the modules import nothing heavy at import time).
BACKENDS: dict[str, str] = {
    "operon": "physmend.symbolic._operon",
    "sindy": "physmend.symbolic._sindy",
    "pysr": "physmend.symbolic._pysr",
}

#: fewest points ``fit`` accepts.
MIN_POINTS = 10


def _backend(name: str) -> Any:
    if name not in BACKENDS:
        raise SymbolicError(f"symbolic.backend must be one of {sorted(BACKENDS)}, but got {name!r}")
    return importlib.import_module(BACKENDS[name])


def prepare(name: str) -> None:
    """Import back end ``name``'s library now (seconds where no bytecode is written), for a process
    that waits anyway before it searches; nothing where the back end cannot run here or has nothing
    to import ahead (PySR: importing it may start Julia's set-up)."""
    module = _backend(name)
    if module.unavailable_reason() is None and hasattr(module, "prepare"):
        module.prepare()


def available_backends() -> list[str]:
    """Names of the back ends that can run on this machine (checked without importing them)."""
    return [name for name in sorted(BACKENDS) if _backend(name).unavailable_reason() is None]


def _check_data(X: Any, y: Any, names: Any, units: Any) -> tuple[np.ndarray, np.ndarray, list[str], dict[str, str]]:
    try:
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float)
    except (TypeError, ValueError) as exc:
        raise SymbolicError(f"X and y must be numeric arrays ({exc})") from exc
    if X.ndim == 1:
        X = X[:, None]
    if X.ndim != 2:
        raise SymbolicError(f"X must be 2-D with shape (n_points, n_inputs), but got shape {X.shape}")
    if y.ndim == 2 and y.shape[1] == 1:
        y = y[:, 0]
    if y.ndim != 1:
        raise SymbolicError(f"y must be 1-D with shape (n_points,), but got shape {y.shape}")
    if X.shape[0] != y.shape[0]:
        raise SymbolicError(f"X and y must have the same number of points, but got X {X.shape[0]} and y {y.shape[0]}")
    if isinstance(names, str) or not all(isinstance(s, str) and s for s in names):
        raise SymbolicError(f"names must be a list of non-empty strings, but got {names!r}")
    names = list(names)
    if len(names) != X.shape[1]:
        raise SymbolicError(f"names must name every column of X ({X.shape[1]}), but got {len(names)} names: {names}")
    dup = sorted({s for s in names if names.count(s) > 1})
    if dup:
        raise SymbolicError(f"names must be unique, but {dup} occur more than once")
    if X.shape[0] < MIN_POINTS:
        raise SymbolicError(f"symbolic regression needs at least {MIN_POINTS} points, but got {X.shape[0]}")
    bad = ~np.isfinite(X)
    if bad.any():
        j = int(np.argmax(bad.any(axis=0)))
        raise SymbolicError(
            f"X must hold only finite values, but column {names[j]!r} has {int(bad[:, j].sum())} non-finite "
            f"values (first at row {int(np.argmax(bad[:, j]))})"
        )
    if not np.isfinite(y).all():
        bad_y = ~np.isfinite(y)
        raise SymbolicError(
            f"y must hold only finite values, but it has {int(bad_y.sum())} non-finite values "
            f"(first at row {int(np.argmax(bad_y))})"
        )
    units = dict(units or {})
    wrong = {k: v for k, v in units.items() if not isinstance(k, str) or not isinstance(v, str)}
    if wrong:
        raise SymbolicError(f"units must map input names to unit strings, but got {wrong!r}")
    return X, y, names, {k: v.strip() for k, v in units.items()}


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, str):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.integer, np.floating)):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


def fit(
    X: np.ndarray,
    y: np.ndarray,
    names: list[str],
    *,
    backend: str = "operon",
    target: str = "y",
    units: dict[str, str] | None = None,
    options: dict | None = None,
    seed: int = 0,
    operators: Mapping[str, int] | None = None,
    target_unit: str | None = None,
    check_units: bool = True,
) -> ParetoFront:
    """Fit formulas ``y ≈ g(X)`` and return their Pareto front (accuracy vs complexity).

    Args:
        X: inputs, shape ``(n_points, n_inputs)``, finite, in physical units.
        y: target, shape ``(n_points,)`` (e.g. a network's correction of one state derivative).
        names: one name per column of ``X``; the formulas' sympy Symbols carry exactly these names.
        backend: ``"operon"`` (genetic programming, default), ``"sindy"`` (sparse regression over
            physically motivated terms built from ``units``) or ``"pysr"`` (needs PySR and Julia).
        target: name of the target, kept on the front for reports.
        units: input name -> unit string (e.g. ``"K"``); ``"sindy"`` pairs only same-unit inputs.
        options: back-end settings overriding the defaults (unknown keys are an error); every back
            end takes ``max_points``: larger inputs are subsampled deterministically (by ``seed``)
            for the search, while MSE and R² are always computed on all points.
        seed: random seed of the search and the subsampling.
        operators: operator name -> complexity price (:mod:`physmend.symbolic.operators`, the
            ``operators`` config group): the operators every back end searches with (where
            ``options`` do not name the back end's own setting) and the one rule that prices every
            candidate's complexity. None: each back end's own defaults and size measure.
        target_unit: the unit ``y`` is in (the corrected equation's, e.g. ``"W"``); empty or None:
            not checked against.
        check_units: drop every formula whose units cannot be consistent — within itself (``T + Q``
            with ``T`` in K and ``Q`` in W, ``exp(T)``) or with ``target_unit`` — by the declared
            ``units`` (:func:`physmend.modeling.units.mismatch`: a fitted constant may carry any
            unit, an unknown unit is never a reason). ``info["unit_rejected"]`` counts them. It also
            drops every formula that uses a quantity on an interval scale (a unit with an offset:
            ``degC``, ``degF``, a unit the model declares affine) other than linearly or as a
            difference (``sign(T)``, ``√|T|``, ``T1·T2``; :mod:`physmend.modeling.interval`):
            ``info["interval_rejected"]`` counts them.

    Returns:
        The non-dominated formulas, complexity ascending; choose one with :func:`choose`.

    Raises:
        SymbolicError: unknown back end or option; bad input (shapes, non-finite values, names,
            fewer than 10 points); no formula could be evaluated; every formula's units are wrong.
        BackendUnavailable: the back end cannot run here (raised at once, nothing is downloaded).
    """
    return _searched(_prepare(X, y, names, backend=backend, target=target, units=units, options=options, seed=seed,
                              operators=operators, target_unit=target_unit, check_units=check_units))


def fit_many(calls: Sequence[Mapping[str, Any]]) -> list[ParetoFront]:
    """:func:`fit` of each keyword set in ``calls`` (one per target), in order: the same fronts.

    Where the back end's search can run beside another (pyoperon's, one thread each, releases the
    interpreter lock while it evolves), the searches run side by side in threads, one per CPU this
    process may use; everything else — checks, parsing, units, scores — runs one call after another.
    Two kept equations of the cargo box: 5.1 s each, 10.1 s one after the other (2 cores).
    """
    jobs = [_prepare(**dict(c)) for c in calls]
    regress = [getattr(job.module, "regress", None) for job in jobs]
    cpus = usable_cpus()
    if len(jobs) < 2 or cpus < 2 or any(r is None for r in regress):
        return [_searched(job) for job in jobs]

    def run(job: _Job) -> tuple[Any, float]:
        start = time.perf_counter()
        fitted = job.module.regress(job.Xs, job.ys, job.names, units=job.units, options=job.settings, seed=job.seed)
        return fitted, time.perf_counter() - start

    with ThreadPoolExecutor(max_workers=min(len(jobs), cpus)) as pool:
        futures = [pool.submit(run, job) for job in jobs]
        fronts = []
        for job, future in zip(jobs, futures):
            fitted, seconds = future.result()
            start = time.perf_counter()
            raw, details = job.module.read_front(fitted, job.names)
            fronts.append(_front(job, raw, details, seconds + time.perf_counter() - start))
    return fronts


def _searched(job: _Job) -> ParetoFront:
    """The front of ``job``'s search, run here."""
    start = time.perf_counter()
    raw, details = job.module.search(job.Xs, job.ys, job.names, units=job.units, options=job.settings, seed=job.seed)
    return _front(job, raw, details, time.perf_counter() - start)


@dataclass
class _Job:
    """One :func:`fit` call checked and resolved: the back end, the data (``X (n, k)``, ``y (n,)``),
    the search's subsample ``Xs``, ``ys`` and settings, and what scoring the front needs."""

    module: Any
    backend: str
    target: str
    X: np.ndarray
    y: np.ndarray
    names: list[str]
    units: dict[str, str]
    settings: dict[str, Any]
    Xs: np.ndarray
    ys: np.ndarray
    seed: int
    ops: dict[str, int] | None
    target_unit: str | None
    check_units: bool


def _prepare(X: np.ndarray, y: np.ndarray, names: list[str], *, backend: str = "operon", target: str = "y",
             units: dict[str, str] | None = None, options: dict | None = None, seed: int = 0,
             operators: Mapping[str, int] | None = None, target_unit: str | None = None,
             check_units: bool = True) -> _Job:
    """:func:`fit`'s checks and settings, before the search (the same arguments)."""
    module = _backend(backend)
    reason = module.unavailable_reason()
    if reason is not None:
        raise BackendUnavailable(reason)
    X, y, names, units = _check_data(X, y, names, units)
    settings = module.resolve_options(dict(options or {}))
    if operators is not None:
        from physmend.config_check import check_operators

        ops = check_operators(dict(operators), "operators")
        settings = module.with_operators(settings, ops, set(options or {}))
    max_points = settings["max_points"]
    if isinstance(max_points, bool) or not isinstance(max_points, int) or max_points < MIN_POINTS:
        raise SymbolicError(f"symbolic option max_points must be an integer >= {MIN_POINTS}, but got {max_points!r}")

    n = X.shape[0]
    if n > max_points:
        rows = np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))
        Xs, ys = X[rows], y[rows]
    else:
        Xs, ys = X, y

    return _Job(module, backend, target, X, y, names, units, settings, Xs, ys, seed,
                ops if operators is not None else None, target_unit, check_units)


def _front(job: _Job, raw: list, details: dict[str, Any], seconds: float) -> ParetoFront:
    """The Pareto front of the search's formulas ``raw`` (:func:`fit`'s scoring and unit checks)."""
    X, y, names, units, n = job.X, job.y, job.names, job.units, job.X.shape[0]
    backend, target, target_unit, check_units, ops = job.backend, job.target, job.target_unit, job.check_units, job.ops
    columns = {name: X[:, j] for j, name in enumerate(names)}
    candidates: list[Candidate] = []
    rejected: list[str] = []
    interval_rejected: list[str] = []
    for expr, complexity, terms, text in raw:
        if isinstance(expr, str):  # a back end's text: the restricted parser, never sympify
            from physmend.modeling.safe_parse import parse_safe

            expr = parse_safe(expr, where=f"{backend} formula", new_symbols=True)
        if check_units:
            why = mismatch(expr, units, target_unit)
            if why is not None:
                rejected.append(f"{display(expr)}: {why}")
                continue
            why = interval_violation(expr, units)
            if why is not None:
                interval_rejected.append(f"{display(expr)}: {why}")
                continue
        y_hat = evaluate(expr, columns, n=n)
        if not np.isfinite(y_hat).all():
            continue
        mse, r2 = mse_r2(y, y_hat)
        if ops is not None:
            from physmend.symbolic.operators import priced_size

            complexity = priced_size(expr, ops)
        candidates.append(Candidate(expr, int(complexity), mse, r2, text or display(expr), dict(terms)))
    front = pareto_filter(candidates)
    if not raw:
        raise SymbolicError(f"back end {backend!r} returned no formula for {target!r}")
    if interval_rejected and not candidates:
        raise SymbolicError(
            f"every formula back end {backend!r} returned for {target!r} uses a quantity on an interval scale (a unit "
            f"with an offset such as degC) other than linearly or as a difference (first: {interval_rejected[0]}); "
            "give the model such quantities in an absolute unit (K), or set symbolic.units=false to skip this check")
    if rejected and not candidates:
        raise SymbolicError(
            f"every formula back end {backend!r} returned for {target!r} has units that cannot be "
            f"{target_unit or 'consistent'} with the declared units {units} (first: {rejected[0]}); check the units the "
            "model declares, or set symbolic.units=false to skip this check")
    if not front:
        raise SymbolicError(
            f"back end {backend!r} returned {len(raw)} formulas for {target!r}, but none gives finite values on all "
            f"{n} points"
        )
    info = {
        "settings": _jsonable(job.settings),
        "seconds": round(seconds, 3),
        "n_points_search": int(job.Xs.shape[0]),
        "seed": int(job.seed),
        "n_raw_candidates": len(raw),
        "unit_rejected": len(rejected),
        "unit_rejected_examples": rejected[:3],
        "interval_rejected": len(interval_rejected),
        "interval_rejected_examples": interval_rejected[:3],
        **_jsonable(details),
    }
    return ParetoFront(backend, target, names, front, units=units, n_points=n, info=info)


def resolve(options: dict, defaults: dict[str, Any], *, backend: str, extra: frozenset[str] = frozenset()) -> dict[str, Any]:
    """``defaults`` updated by ``options``; keys outside ``defaults`` and ``extra`` are an error."""
    unknown = sorted(set(options) - set(defaults) - set(extra))
    if unknown:
        valid = sorted(set(defaults) | set(extra))
        raise SymbolicError(f"options of back end {backend!r} must be among {valid}, but got unknown {unknown}")
    return {**defaults, **options}

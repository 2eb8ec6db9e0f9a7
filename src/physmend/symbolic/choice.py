"""Choosing one formula per kept equation: the catalogue's forms as candidates, the BIC against
the recorded mismatch of a measured equation (:func:`choose_by_recordings`), and the corrected
model's multiple-shooting fit of the training records for an equation whose state is not
measured (:func:`choose_by_simulation`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import sympy as sp

from physmend.settings import SymbolicSettings
from physmend.symbolic.corrected import corrected_problem, refit

def tree_size(expr: sp.Expr) -> int:
    """Nodes of the expression tree (comparable to a symbolic-regression back end's length)."""
    return sum(1 for _ in sp.preorder_traversal(expr))


#: a form that takes one value on at least this share of the samples is a constant there
CONSTANT_SHARE = 0.98


def nearly_constant(t: np.ndarray) -> bool:
    """Whether ``t (N,)`` takes its median value on :data:`CONSTANT_SHARE` of the samples or more
    (``sign`` of a quantity that never changes sign, a parameter equal in every experiment)."""
    return bool(np.mean(np.isclose(t, np.median(t), rtol=1e-9, atol=0.0)) >= CONSTANT_SHARE)


def catalogue_candidates(inputs: list[str], units: dict[str, str], columns: dict[str, np.ndarray],
                         y: np.ndarray, *, operators: dict[str, int] | None = None,
                         scale_only: frozenset[str] | set[str] = frozenset()) -> list[Any]:
    """The catalogue's forms over ``inputs`` (unit rules obeyed), each ``c`` fitted to ``y (N,)``,
    alone and plus a steady offset (``c·form + c0``: an offset the rest of the model leaves);
    complexity priced by ``operators`` (:func:`physmend.symbolic.operators.priced_size`; None: nodes).

    ``scale_only``: parameters seen at too few values to be tested as a variable
    (:func:`physmend.ude.spec.scale_parameters`): a form of those alone is offered with its one
    constant only — ``c·p + c0`` (or ``c·|p|^k``) would fit any two per-experiment sizes."""
    from physmend.symbolic.operators import priced_size
    import itertools

    from physmend.explain.catalogue import SECOND, load_catalogue, shape_function
    from physmend.explain.mechanisms import fit_with_k
    from physmend.symbolic import Candidate, display, evaluate, mse_r2

    out, seen = [], set()
    for m in load_catalogue():
        f = shape_function(m) if m.k else None  # once per form, not per assignment
        for combo in itertools.permutations(inputs, len(m.placeholders)):
            assignment = dict(zip(m.placeholders, combo))
            if not m.admissible(assignment, units):
                continue
            if m.k and set(combo) <= set(scale_only):
                continue  # a second fitted constant on two values: any two per-experiment sizes
            shape = m.shape.xreplace({sp.Symbol(ph): sp.Symbol(v) for ph, v in assignment.items()})
            if m.k:  # the second constant (threshold, scale, exponent): the best of its grid, then fixed
                fitted = fit_with_k(m, f, [np.asarray(columns[v], dtype=float) for v in combo], y)
                if fitted is None:
                    continue
                shape = shape.xreplace({sp.Symbol(SECOND): sp.Float(fitted[1])})
            t = evaluate(shape, columns, n=y.size)
            tt = float(t @ t) if np.isfinite(t).all() else 0.0
            if tt == 0.0 or (not shape.is_Number and nearly_constant(t)):
                continue  # a form that is one value along the samples is the steady source, said less simply
            variants = [(float(t @ y) / tt, 0.0)]
            if not shape.is_Number and not set(combo) <= set(scale_only):
                (c1, c0), *_ = np.linalg.lstsq(np.stack([t, np.ones_like(t)], 1), y, rcond=None)
                variants.append((float(c1), float(c0)))
            for c, c0 in variants:
                mse, r2 = mse_r2(y, c * t + c0)
                key = (m.id, frozenset(combo), c0 != 0.0, round(mse, 9))
                if key in seen:  # a - b and b - a: the same form up to the sign of c
                    continue
                seen.add(key)
                expr = sp.Float(c) * shape + (sp.Float(c0) if c0 != 0.0 else 0)
                out.append(Candidate(expr=expr, complexity=tree_size(expr) if operators is None else priced_size(expr, operators), mse=mse, r2=r2,
                                     text=f"{display(expr)}   [catalogue: {m.name}{' + offset' if c0 else ''}]"))
    return out


def choose_by_recordings(rates: Any, state: str, front: Any) -> tuple[int, str, list[tuple[float, float]]]:
    """The formula with the lowest BIC against the recorded mismatch of ``state``'s equation.

    ``BIC = n·ln(MSE) + k·ln(n)`` with ``k`` the formula's constants (plus its scale) and ``n`` the
    number of *independent* windows (the sliding windows overlap: one per ``window`` grid points),
    so a formula buys each extra constant only with a real gain on the recordings. Returns the
    index, the sentence why, and ``(α, R²)`` per candidate.
    """
    from physmend.modeling.evaluate import n_constants

    scores = [rates.score(c.expr, state) for c in front.candidates]
    n = max(2.0, independent_windows(rates))
    bic = [n * np.log(max(mse, 1e-300)) + n_constants(c.expr) * np.log(n) if np.isfinite(mse) else np.inf
           for c, (_, mse, _) in zip(front.candidates, scores)]
    pick = int(np.argmin(bic))
    c = front.candidates[pick]
    why = (f"Rule 'recorded': against the recorded mismatch of the {state} equation (windows of {rates.window} grid "
           f"steps, {n:.0f} independent), the lowest BIC = n·ln(MSE) + k·ln(n); chose index {pick} "
           f"({n_constants(c.expr)} constant(s), recorded R² {scores[pick][2]:.4f}): {c.text}")
    return pick, why, [(a, r2) for a, _, r2 in scores]


#: the simulated choice screens a long front: every candidate re-fitted with SCREEN_STEPS
#: Levenberg–Marquardt steps first, the SCREEN_KEEP best by that BIC (and the best of each smaller
#: count of constants, :func:`finalists_of`) then re-fitted in full — as the chosen formula will be
#: (``symbolic.refit_epochs``): a loss short of convergence favours the form with more constants
SCREEN_STEPS = 3
SCREEN_KEEP = 8


def finalists_of(screened: list[float], constants: list[int], bic_of: Any) -> list[int]:
    """The candidates a screening sends on to the full re-fit: the :data:`SCREEN_KEEP` best by the BIC
    of their ``screened`` losses, and the best of every smaller count of ``constants`` than theirs.

    A few steps from shared segment starts do not converge, and a form with more constants moves
    further in them: the screening's BIC is biased towards them. The simplest forms' best are re-fitted
    in full whatever that bias, so that the full re-fit's BIC judges whether a constant pays."""
    order = sorted(range(len(screened)), key=lambda i: bic_of(i, screened[i]))
    kept = order[:SCREEN_KEEP]
    most = max((constants[i] for i in kept), default=0)
    for k in sorted({constants[i] for i in order if constants[i] < most}):
        best = next(i for i in order if constants[i] == k)
        if best not in kept and np.isfinite(screened[best]):
            kept.append(best)
    return kept


def _bar(items: Any, desc: str) -> Any:
    """``items`` with a progress bar (each is a model simulated and re-fitted: seconds)."""
    from tqdm import tqdm

    return tqdm(list(items), desc=desc, unit="formula", dynamic_ncols=True)


def choose_by_simulation(work: Any, problem: Any, state: str, front: Any, build: Any,
                         refit_steps: int = 0, *, reason: str | None = None, guide: Any = None) -> tuple[int, str]:
    """The formula for ``state`` whose corrected *model* best reproduces the training records.

    Where a kept equation's state is not measured, no recorded mismatch exists for it and the
    network's output is the only per-sample target (which a network that leans on look-alike
    inputs, or an estimate that absorbed part of the term, distorts — in form and in size). Each
    candidate is judged instead by what the engineer would judge: the corrected model (``build(i)``
    gives its corrections, the other equations at their current choice) simulated over the
    training records by multiple shooting — segments of the records, hidden segment starts free —
    with its constants re-fitted (at most ``refit_steps`` Levenberg–Marquardt steps: a right form
    sized wrong by the regression would otherwise lose to a wrong one; :mod:`physmend.symbolic.refit`).
    ``BIC = n·ln(L) + k·ln(n)`` with ``L`` the re-fitted multiple-shooting loss (the mean squared
    normalised output error plus the continuity penalty), ``k`` the formula's constants and ``n``
    the independent windows (``symbolic.window`` long) of the training records (the residuals of a
    misfit are correlated over a window: the samples are not independent). A candidate whose segments cannot be solved is out. Validation and
    test records decide nothing here. ``reason`` says why the simulation decides (default: the state
    is not measured). ``guide``: the trained hybrid the formulas stand for; every re-fit starts its
    segments from its states (:func:`physmend.symbolic.refit.segment_guesses`); without it, the
    screening from the model as written's and each finalist from its own forced records.
    """
    import dataclasses

    from physmend.modeling.evaluate import n_constants
    from physmend.simulate import make_batch
    from physmend.symbolic.refit import segment_guesses
    from physmend.ude.metrics import checkpoint_problem
    from physmend.ude.reference import reference

    window = max(float(SymbolicSettings.build(work.symbolic).window), 1e-300)  # resolved: a number
    span = sum(float(e.split_time if e.split_time is not None else e.obs_time[-1]) - float(e.obs_time[0])
               for e in problem.experiments if e.role == "train")
    n = max(2.0, span / window)
    # the model as written, simulated once: the segments' plan, initial guesses and scales (a
    # candidate's own parameters — its constants — come with its own batch)
    base = reference(checkpoint_problem(problem), work, bounded=True)
    shared: list[Any] = []  # shared segment-start guesses (the guide's, else the model as written's), made once

    def starts() -> Any:
        if not shared:
            shared.append(segment_guesses(checkpoint_problem(problem), work, base, guide))
        return shared[0]

    def loss_of(i: int, steps: int, screening: bool = False) -> float:
        corrections = build(i)
        corrected = checkpoint_problem(corrected_problem(work, corrections))
        ref = dataclasses.replace(base, batch=make_batch(corrected.experiments, corrected.compiled, corrected.dtype))
        try:
            # without a guide a finalist starts from its own forced records (a solve each)
            _, result = refit(work, corrected, ref, corrections, steps, uncertainty=False,
                              starts=starts() if screening or guide is not None else None)
            loss = float(result.loss_after)
        except Exception:  # noqa: BLE001 - a candidate whose segments cannot be solved is out
            loss = float("inf")
        return loss if np.isfinite(loss) else float("inf")

    def bic_of(i: int, loss: float) -> float:
        return n * np.log(max(loss, 1e-300)) + n_constants(front.candidates[i].expr) * np.log(n) if np.isfinite(loss) else np.inf

    count = len(front.candidates)
    if count > SCREEN_KEEP and refit_steps > SCREEN_STEPS:
        # screening: every candidate with a few steps from shared segment starts; the best SCREEN_KEEP by
        # that BIC, and the best of each smaller count of constants, re-fitted in full (finalists_of)
        first = [loss_of(i, SCREEN_STEPS, screening=True) for i in _bar(range(count), f"symbolic: {state}, screening")]
        finalists = finalists_of(first, [n_constants(c.expr) for c in front.candidates], bic_of)
        losses = [float("inf")] * count
        for i in _bar(finalists, f"symbolic: {state}, finalists re-fitted"):
            losses[i] = loss_of(i, refit_steps)
    else:
        losses = [loss_of(i, refit_steps) for i in _bar(range(count), f"symbolic: {state}, each formula re-fitted")]
    bic = [bic_of(i, v) for i, v in enumerate(losses)]
    if not np.isfinite(bic).any():
        return 0, (f"Rule 'simulated': no formula for {state} gave a corrected model whose segments could be "
                   "solved; index 0 (the simplest) is kept for the fallback along the front")
    pick = int(np.argmin(bic))
    c = front.candidates[pick]
    screened = (f"; screened first with {SCREEN_STEPS} steps each, the best {SCREEN_KEEP} and the best of each "
                "smaller count of constants re-fitted in full"
                if count > SCREEN_KEEP and refit_steps > SCREEN_STEPS else "")
    reason = reason or f"{state} is not measured, so no recorded mismatch exists for it"
    unit_n = f"{n:.0f} independent windows of {window:.4g}"
    why = (f"Rule 'simulated' ({reason}): each formula put "
           f"into the model, its constants re-fitted through the simulator (multiple shooting over the training "
           f"records, at most {refit_steps} steps{screened}); the lowest BIC = n·ln(L) + k·ln(n) of that loss ({unit_n}); chose index {pick} ({n_constants(c.expr)} constant(s), "
           f"loss {losses[pick]:.4g}): {c.text}")
    return pick, why


#: the recorded mismatch ranks formulas only where the training records give at least this many
#: independent windows: BIC's ``n·ln(MSE) + k·ln(n)`` weighs a fit over ``n`` values against ``k``
#: constants, and with a handful of window means (a short record) a one-variable shape with two
#: constants matches them as well as the right product of two states. Below it the corrected model's
#: simulation over every training sample decides (:func:`choose_by_simulation`).
MIN_RECORDED_WINDOWS = 20


def independent_windows(rates: Any) -> float:
    """The independent windows of the recorded mismatch (its sliding windows overlap: one per window)."""
    return float(rates.valid.sum()) / max(int(rates.window), 1)

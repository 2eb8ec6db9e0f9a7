"""Keep only the corrections that matter, then retrain (the mask stage's work).

Ranks the trained network's outputs by ``mean_t |ΔNN_i| / max_t |du_i/dt|`` on the training
samples, simulates the hybrid with only the top k corrections for k = 1, 2, … and keeps the
smallest k whose *validation* RMSE (whole-trajectory simulation) is within a tolerance of the
full network's; then retrains a network that corrects only those equations — and, when the last
kept equation is a measured state's, for each of the next ``mask.rivals`` unmeasured states in the
ranking, one with the last kept equation swapped for it. The set whose retrained network validates
best is kept (a set equal to the source network's own is not retrained: that would reproduce it,
so the source network stands for it). (The ranking favours what a warm start could
fit — the equations of measured states; a correction needed on a hidden state's equation can hide
behind one on the measured state downstream, and only a network trained on it alone shows it.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import Any

from omegaconf import OmegaConf

from physmend.masking.choice import SourceNetwork, best_retrained, choose_k, rivals, val_rmse
from physmend.masking.retrain import close_figures, retrain_sets, with_held_out


def _quiet(what: str) -> AbstractContextManager[None]:
    return nullcontext()


@dataclass
class MaskOutcome:
    """What the mask found.

    ``ranking``: ``(state, score)`` best first; ``by_k``: ``(k, validation RMSE)`` of the source
    network masked to the top k; ``full``: the full network's validation RMSE; ``kept``: the kept
    states (ranking order) and ``kept_in_order`` (the model's order); ``tried``: each candidate set
    with its retraining (a :class:`~physmend.ude.TrainResult`, the exception it failed with, or a
    :class:`SourceNetwork`); ``winner``: the candidate kept; ``again``: the sets trained again,
    longer; ``trained``: the kept retraining (None: the source network goes on) and ``held_out``
    the same with the test experiments' metrics; ``metrics``/``artifacts``: where the source network
    goes on, its metrics with only the kept corrections and its model files; ``config``: the
    configuration the kept network was trained with; ``own``: whether the kept set is every
    equation the source network corrects; ``retrained``: whether retraining was asked for."""

    ranking: list[tuple[str, float]]
    by_k: list[tuple[int, float]]
    full: float
    k: int
    kept: list[str]
    kept_in_order: list[str]
    corrected: list[str]
    config: Any
    own: bool
    retrained: bool
    tried: list[tuple[list[str], Any]] = field(default_factory=list)
    winner: Any = None
    again: list[list[str]] = field(default_factory=list)
    trained: Any = None
    held_out: Any = None
    metrics: dict[str, float] = field(default_factory=dict)
    artifacts: dict[str, str | bytes] = field(default_factory=dict)

    def own_set(self, names: list[str]) -> bool:
        """Whether ``names`` is every equation the source network corrects."""
        return sorted(names) == sorted(self.corrected)

    def masked_rmse(self) -> float:
        """The source network's validation RMSE with only the kept corrections."""
        return self.full if self.own else dict(self.by_k).get(self.k, self.full)

    def summary_metrics(self) -> dict[str, float]:
        """``full.val.rmse``, ``val.rmse.k<k>`` and ``retrained.<i>.val.rmse`` (finite ones)."""
        return {"full.val.rmse": self.full, **{f"val.rmse.k{kk}": r for kk, r in self.by_k},
                **{f"retrained.{i}.val.rmse": val_rmse(r) for i, (_, r) in enumerate(self.tried)
                   if math.isfinite(val_rmse(r))}}

    def record(self) -> dict[str, Any]:
        """The ranking, the masked and retrained candidates' RMSEs and the kept set (JSON-ready)."""
        return {"ranking": self.ranking, "by_k": self.by_k, "full_val_rmse": self.full, "kept": self.kept_in_order,
                "retrained": [{"corrected": names, "val.rmse": val_rmse(r),
                               "error": None if not isinstance(r, Exception) else str(r)} for names, r in self.tried]}


def mask_corrections(hybrid: Any, problem: Any, work: Any, mc: Any, *,
                     progress: Callable[[str], AbstractContextManager[Any]] = _quiet) -> MaskOutcome:
    """Mask the corrections of ``hybrid`` (trained on ``problem`` with the configuration ``work``) as
    the module says, with the ``mask`` settings ``mc`` (``mask.keep``: the states to keep, checked
    by the caller to be corrected by ``hybrid``). ``progress(what)``: a context shown while a step
    with no count runs. ``work`` is not changed; ``hybrid`` is left correcting all it corrects."""
    from physmend.ude import TrainingDiverged, evaluate, train
    from physmend.ude.analysis import rank_corrections, training_trajectories
    from physmend.ude.artifacts import artifacts_of
    from physmend.ude.metrics import checkpoint_problem, evaluate_kept
    from physmend.ude.reference import solver_options
    from physmend.ude.warmstart import measured_states

    with progress("mask: ranking the corrections"):
        traj = training_trajectories(hybrid, problem, work)
        ranking = rank_corrections(hybrid, traj)
    checked = checkpoint_problem(problem)  # val.rmse needs the train and validation experiments only
    order = [n for n, _ in ranking]
    tries = range(0) if mc.keep else range(1, min(int(mc.max_k), len(order)) + 1)
    # the full network and every k in one solve where each experiment has its own clock (evaluate_kept)
    with progress("mask: simulating the full network" + (f" and the top k = 1…{len(tries)} of {len(order)} corrections"
                                                        if tries else "")):
        outcomes = evaluate_kept(hybrid, checked, solver_options(work),
                                 [list(hybrid.spec.corrected)] + [order[:k_try] for k_try in tries])
    if isinstance(outcomes[0], TrainingDiverged):
        raise outcomes[0]
    full = outcomes[0]["val.rmse"]
    by_k: list[tuple[int, float]] = []
    if mc.keep:
        kept = [str(n) for n in mc.keep]
        k = len(kept)
    else:
        # recorded up to the first k within the tolerance, as a search one k after another would
        for k_try, got in zip(tries, outcomes[1:]):
            # a TrainingDiverged: without the other corrections this network leaves every range
            by_k.append((k_try, math.inf if isinstance(got, TrainingDiverged) else got["val.rmse"]))
            if by_k[-1][1] <= (1.0 + float(mc.tolerance)) * full:
                break
        k = choose_k(full, by_k, float(mc.tolerance))
        kept = order[:k]
    result = None
    winner: Any = None  # the candidate kept (retrained or the source network), for the printout
    tried: list[tuple[list[str], Any]] = []
    again_sets: list[list[str]] = []  # sets trained again, longer (their first training stayed at its warm start)
    if bool(mc.retrain):
        work = OmegaConf.merge(work, OmegaConf.from_dotlist([str(o) for o in mc.train_overrides]))
        measured = {problem.model.state_names[i] for _, i in measured_states(problem)}
        sets = [kept] + ([] if mc.keep else rivals(kept, [n for n, _ in ranking], int(mc.rivals), measured))
        # retraining the source network's own set with the source's settings gives the source network
        # (same configuration, same seed): it stands for itself
        same = sorted(kept) == sorted(hybrid.spec.corrected) and not list(mc.train_overrides)
        todo = [names for names in sets if not (same and names is kept)]
        # retrained on training and validation experiments only (a choice); the kept one is then
        # simulated on the test experiments once, for the report (with_held_out)
        results, again = retrain_sets(work, checked, todo, mc, train)
        again_sets = [todo[i] for i in again]
        done = iter(results)
        tried = [(names, SourceNetwork(full) if same and names is kept else next(done)) for names in sets]
        masked = dict(by_k).get(len(kept))
        if not same and masked is not None and math.isfinite(masked):
            # the source network masked to the kept set is a candidate too: a retraining of that set that
            # validates worse than the masked network it stands for is not kept instead of it
            tried.append((kept, SourceNetwork(masked)))
        if any(not isinstance(r, Exception) for _, r in tried):
            kept, result = best_retrained(tried, float(mc.tolerance))
            winner = result
            for _, other in tried:  # the candidates not kept: their fit figures are never shown
                if other is not result:
                    close_figures(other)
            k = len(kept)
            if isinstance(result, SourceNetwork):
                result = None  # the source network goes on, its corrections masked to the kept set
        else:  # no retraining could be simulated: the source network, masked to the kept set, goes on
            print(f"Every retrained candidate set diverged ({tried[0][1]}); the source network goes on with "
                  f"its corrections masked to {', '.join(kept)}.")
    out = MaskOutcome(ranking=ranking, by_k=by_k, full=full, k=k, kept=kept,
                      kept_in_order=[n for n in problem.model.state_names if n in kept],
                      corrected=list(hybrid.spec.corrected), config=work, own=False, retrained=bool(mc.retrain),
                      tried=tried, winner=winner, again=again_sets, trained=result)
    out.own = out.own_set(kept)  # the kept set is all the source network corrects
    if result is not None:
        work.ude.corrected = out.kept_in_order  # the retrained network's configuration
        out.held_out = with_held_out(result, problem, work)
    else:  # the source network; the kept outputs are recorded in the tag physmend.kept
        # its whole-trajectory metrics with only the kept corrections, held-out experiments too (reported,
        # chosen by nothing)
        hybrid.keep_only(kept)
        try:
            out.metrics = {k_: v for k_, v in evaluate(hybrid, problem, work).items() if math.isfinite(v)}
        except TrainingDiverged:
            out.metrics = {"val.rmse": out.masked_rmse()}
        hybrid.keep_only(hybrid.spec.corrected)
        out.artifacts = artifacts_of(hybrid, out.metrics)
    return out

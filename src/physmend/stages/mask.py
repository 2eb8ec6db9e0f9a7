"""``physmend mask [RUN_ID]``: keep only the corrections that matter, then retrain.

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

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from omegaconf import OmegaConf

STAGE = "mask"


def choose_k(full: float, by_k: list[tuple[int, float]], tolerance: float) -> int:
    """The smallest k with ``rmse_k <= (1 + tolerance) * full``.

    When no k qualifies (the network spread small corrections over many equations, so every
    masked version loses some fit — the retraining restores it), the smallest k within the same
    tolerance of the best masked RMSE: more corrections that barely help are not kept.
    """
    for k, rmse in by_k:
        if rmse <= (1.0 + tolerance) * full:
            return k
    best = min(r for _, r in by_k)
    return next(k for k, r in by_k if r <= (1.0 + tolerance) * best)


def rivals(kept: list[str], order: list[str], n: int, measured: set[str] | None = None) -> list[list[str]]:
    """Other equation sets worth retraining: the last kept equation swapped for each of the next
    ``n`` in the ranking ``order``. With ``measured`` (states that are outputs), only when the last
    kept state is measured, and only unmeasured rivals: the ranking is biased exactly there (a
    warm start fits measured equations; a hidden state's correction hides behind them). And a kept
    set that mixes measured and unmeasured states has the unmeasured ones alone and the measured
    ones alone as rivals: one side's correction may be the shadow of the other's (the two-tank
    network put 96% of an upper tank's leak on the measured lower tank, the upper tank's equation
    retrained alone validated 2.5x better than both; a drug's elimination from the measured plasma
    can be spread onto the hidden tissue compartment)."""
    if n <= 0 or not kept:
        return []
    sets: list[list[str]] = []
    if measured is not None:
        hidden = [name for name in kept if name not in measured]
        if hidden and len(hidden) < len(kept):  # either side alone: one term may be split between them
            sets += [hidden, [name for name in kept if name in measured]]
    others = [o for o in order if o not in kept]
    if measured is not None:
        if kept[-1] not in measured:
            return sets
        others = [o for o in others if o not in measured]
    return sets + [kept[:-1] + [name] for name in others[:n] if kept[:-1] + [name] not in sets]


@dataclass
class SourceNetwork:
    """The mask's source network standing for a retraining of its own equation set (``val_rmse``:
    its validation RMSE): that retraining would reproduce it."""

    val_rmse: float


def _val(result: Any) -> float:
    return float("nan") if isinstance(result, Exception) else float(result.val_rmse)


def _val_text(result: Any) -> str:
    """A candidate's validation RMSE for the printout; where it has none, why (the error, one line)."""
    if isinstance(result, Exception):
        from physmend.sweep.restart import one_line

        return f"nan ({one_line(result)})"
    return f"{_val(result):.4g}"


def best_retrained(tried: list[tuple[list[str], Any]], tolerance: float = 0.0) -> tuple[list[str], Any]:
    """The equation set whose retrained network validates best (training and validation experiments
    only) — or a smaller set whose validation RMSE is within ``(1 + tolerance)`` of that best (fewest
    equations first, then the lowest RMSE): the same rule as the choice of k. The first set's error
    when every one diverged."""
    ok = [(names, r) for names, r in tried if not isinstance(r, Exception) and math.isfinite(r.val_rmse)]
    if not ok:
        raise tried[0][1]
    best = min(r.val_rmse for _, r in ok)
    near = [(names, r) for names, r in ok if r.val_rmse <= (1.0 + tolerance) * best]
    return min(near, key=lambda item: (len(item[0]), item[1].val_rmse))


def _plot(ranking: list[tuple[str, float]], by_k: list[tuple[int, float]], full: float, k: int) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4))
    names = [n for n, _ in ranking][:20]
    a1.barh(range(len(names))[::-1], [s for _, s in ranking][:20], color=["C0" if i < k else "0.7" for i in range(len(names))])
    a1.set_yticks(range(len(names))[::-1], names, fontsize=7)
    a1.set_xlabel("mean |correction| / max |du/dt|")
    a2.plot([kk for kk, _ in by_k], [r for _, r in by_k], "o-")
    a2.axhline(full, color="k", lw=0.8, ls="--", label="all corrections")
    a2.axvline(k, color="C3", lw=0.8, label=f"chosen k = {k}")
    a2.set_xlabel("k (top corrections kept)")
    a2.set_ylabel("validation RMSE")
    a2.legend()
    fig.tight_layout()
    return fig


def stuck_at_warm_start(result: Any) -> bool:
    """Whether a retraining's best checkpoint is its warm start (epoch 0): its training never
    validated better than the derivative-matching fit it started from."""
    if isinstance(result, BaseException) or not getattr(result, "history", None):
        return False
    history = result.history
    return len(history) > 1 and history[0]["epoch"] == 0 and min(history, key=lambda r: r["val.rmse"]) is history[0]


def longer_settings(work: Any, mc: Any) -> list[str]:
    """Overrides (dotlist) for training again a retraining stuck at its warm start
    (:func:`stuck_at_warm_start`): ``train.epochs`` × ``mask.retrain_epochs`` with as many L-BFGS
    polish iterations as before, and ``train.patience_fit_gain`` = ``mask.retrain_fit_gain``.

    A network that leaves a good warm start often fits the validation record worse for a while
    before it fits everything better; patience that counted validation alone stopped it there, and
    the cosine schedule had no time left. The retrained network is what every later stage reads
    and what must carry over to held-out conditions; a sweep's trials only need to be ranked."""
    factor, gain = int(mc.get("retrain_epochs", 1)), float(mc.get("retrain_fit_gain", 0.0))  # ranges: config_check
    polish = float(work.train.get("polish", 0.0)) / factor
    return [f"train.epochs={int(work.train.epochs) * factor}", f"train.patience_fit_gain={gain!r}",
            f"train.polish={polish!r}"]


def retrain_sets(work: Any, problem: Any, todo: list[list[str]], mc: Any, train: Any) -> tuple[list[Any], list[int]]:
    """Each set of ``todo`` retrained (side by side); those stuck at their warm start trained again
    with :func:`longer_settings`, the longer run kept where it validates better. Returns the results
    and the positions trained again."""
    from physmend.stages.mask_retrain import retrain_all, workers

    n = workers(mc.get("workers", "auto"))
    done = list(retrain_all(work, problem, todo, train, n))
    again = [i for i, r in enumerate(done) if stuck_at_warm_start(r)] if int(mc.get("retrain_epochs", 1)) > 1 else []
    if again:
        longer = OmegaConf.merge(work, OmegaConf.from_dotlist(longer_settings(work, mc)))
        for i, r in zip(again, retrain_all(longer, problem, [todo[i] for i in again], train, n)):
            if not isinstance(r, BaseException) and r.val_rmse < done[i].val_rmse:
                done[i], r = r, done[i]
            _close_figures(r)  # the run not kept: its fit figures are never shown
    return done, again


def _close_figures(result: Any) -> None:
    """Close the matplotlib figures of a training result that is not kept (pyplot holds them)."""
    import matplotlib.pyplot as plt

    for fig in (getattr(result, "figures", None) or {}).values():
        plt.close(fig)


def with_held_out(result: Any, problem: Any, work: Any) -> Any:
    """``result`` (a :class:`physmend.ude.TrainResult` trained without the test experiments of
    ``problem``) with the test experiments' metrics (``test.*``, ``rmse.<test experiment>.*``) added
    from one whole-trajectory simulation — report only; unchanged where ``problem`` has none or
    the simulation leaves the finite range."""
    from physmend.ude import TrainingDiverged, evaluate

    test = {str(e.id) for e in problem.experiments if e.role == "test"}
    if not test or result.hybrid is None:
        return result
    try:
        metrics = evaluate(result.hybrid, problem, work)
    except TrainingDiverged:
        return result
    held = {k: v for k, v in metrics.items()
            if k.startswith("test.") or any(k.startswith(f"rmse.{e}.") for e in test)}
    return dataclasses.replace(result, metrics={**result.metrics, **held})


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the mask stage on a trial (default: the current selection); returns the new run ID."""
    import matplotlib.pyplot as plt

    from physmend.stages.common import load_source, log_artifacts, log_training, merged, resolve
    from physmend.tracking import TrackingError, open_store, stage_run
    from physmend.ude import TrainingDiverged, evaluate, train
    from physmend.ude.analysis import rank_corrections, training_trajectories
    from physmend.ude.metrics import checkpoint_problem
    from physmend.ude.warmstart import measured_states

    store = open_store(cfg.tracking)
    src_run = resolve(store, source_run_id, stages=("trial",))
    src = load_source(store, src_run, cfg)
    work = merged(src.cfg, cfg, "mask")
    hybrid, problem = src.hybrid, src.problem
    mc = cfg.mask
    from physmend.stages.activity import activity

    with activity("mask: ranking the corrections and simulating the full network"):
        traj = training_trajectories(hybrid, problem, work)
        ranking = rank_corrections(hybrid, traj)
        checked = checkpoint_problem(problem)  # val.rmse needs the train and validation experiments only
        full = evaluate(hybrid, checked, work)["val.rmse"]
    if mc.keep:
        kept = [str(n) for n in mc.keep]
        unknown = [n for n in kept if n not in hybrid.spec.corrected]
        if unknown:
            raise TrackingError(f"mask.keep names {unknown}, which run {src_run.info.run_id!r} does not correct "
                                f"(it corrects {hybrid.spec.corrected})")
        by_k: list[tuple[int, float]] = []
        k = len(kept)
    else:
        by_k = []
        order = [n for n, _ in ranking]
        for k_try in range(1, min(int(mc.max_k), len(order)) + 1):
            hybrid.keep_only(order[:k_try])
            try:
                with activity(f"mask: simulating with the top {k_try} of {len(order)} corrections"):
                    by_k.append((k_try, evaluate(hybrid, checked, work)["val.rmse"]))
            except TrainingDiverged:  # without the other corrections this network leaves every range
                by_k.append((k_try, math.inf))
            if by_k[-1][1] <= (1.0 + float(mc.tolerance)) * full:
                break
        hybrid.keep_only(hybrid.spec.corrected)
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
                    _close_figures(other)
            k = len(kept)
            if isinstance(result, SourceNetwork):
                result = None  # the source network goes on, its corrections masked to the kept set
        else:  # no retraining could be simulated: the source network, masked to the kept set, goes on
            print(f"Every retrained candidate set diverged ({tried[0][1]}); the source network goes on with "
                  f"its corrections masked to {', '.join(kept)}.")
    def own_set(names: list[str]) -> bool:
        """Whether ``names`` is every equation the source network corrects."""
        return sorted(names) == sorted(hybrid.spec.corrected)

    kept_in_order = [n for n in problem.model.state_names if n in kept]
    own = own_set(kept)  # the kept set is all the source network corrects
    if result is not None:
        work.ude.corrected = kept_in_order  # the retrained network's configuration
    with stage_run(store, work, stage=STAGE, source_run_id=src_run.info.run_id, run_name="mask",
                   tags={"physmend.kept": ",".join(kept_in_order)}) as run_:
        run_.log_params({"k": k, "kept": ",".join(kept_in_order), "tolerance": mc.tolerance})
        run_.log_metrics({"full.val.rmse": full, **{f"val.rmse.k{kk}": r for kk, r in by_k},
                          **{f"retrained.{i}.val.rmse": _val(r) for i, (_, r) in enumerate(tried) if math.isfinite(_val(r))}})
        run_.log_json({"ranking": ranking, "by_k": by_k, "full_val_rmse": full, "kept": kept_in_order,
                       "retrained": [{"corrected": names, "val.rmse": _val(r),
                                      "error": None if not isinstance(r, Exception) else str(r)} for names, r in tried]},
                      "ranking.json")
        run_.describe(f"Kept corrections: {', '.join(kept_in_order)} (of {len(hybrid.spec.corrected)} the network corrects); "
                      + (f"retrained, validation RMSE {result.val_rmse:.4g}" if result is not None
                         else f"the source network masked, validation RMSE {full if own else dict(by_k).get(k, full):.4g}")
                      + f". Source trial: {src_run.info.run_id}. Next: physmend sensitivity <this run>.")
        fig = _plot(ranking, by_k or [(k, full)], full, k)
        run_.log_figure(fig, "plots/ranking.png")
        plt.close(fig)
        if result is not None:
            log_training(run_, with_held_out(result, problem, work))
        else:  # the source network; the kept outputs are recorded in the tag physmend.kept
            from physmend.ude.artifacts import artifacts_of

            # its whole-trajectory metrics with only the kept corrections, held-out experiments too (reported,
            # chosen by nothing)
            hybrid.keep_only(kept)
            try:
                metrics = {k_: v for k_, v in evaluate(hybrid, problem, work).items() if math.isfinite(v)}
            except TrainingDiverged:
                metrics = {"val.rmse": full if own else dict(by_k).get(k, full)}
            hybrid.keep_only(hybrid.spec.corrected)
            run_.log_metrics(metrics)
            log_artifacts(run_, artifacts_of(hybrid, metrics))
        run_id = run_.run_id
    lines = [f"# physmend mask — source trial {src_run.info.run_id}", "",
             "Corrections ranked by mean |ΔNN| / max |du/dt| on the training samples:", ""]
    lines += [f"{i + 1:3d}. {n}  {s:.3g}" for i, (n, s) in enumerate(ranking[:10])]
    lines += ["", f"Full network: validation RMSE {full:.4g}."]
    lines += [f"  top {kk}: {r:.4g}" for kk, r in by_k]
    if len(tried) > 1:
        lines += ["", "Each candidate set retrained alone (the ranking favours equations a warm start could fit; "
                      "a hidden state's equation may explain the data better):"]
        lines += [f"  {', '.join(names)}: validation RMSE {_val_text(r)}"
                  + (" (the source network masked to it, not retrained)" if isinstance(r, SourceNetwork) and not own_set(names) else "")
                  + (f" (its first training never validated better than its warm start: trained again with "
                     f"{int(mc.retrain_epochs)}× the epochs, the better of the two shown)"
                     if names in again_sets and not isinstance(r, SourceNetwork) else "")
                  + ("  <- kept" if r is winner else "") for names, r in tried]
    lines += [f"Kept k = {k}: {', '.join(kept_in_order)} (tolerance {float(mc.tolerance):.0%})."]
    if result is None and bool(mc.retrain) and own:
        lines.append("The kept set is the source network's own: it goes on as it is (a retraining would reproduce it).")
    if result is not None:
        lines.append(f"Retrained with {k} output(s): validation RMSE {result.val_rmse:.4g}, "
                     f"test RMSE {result.metrics.get('test.rmse', float('nan')):.4g}.")
    print("\n".join(lines))
    print(f"\nmask run: {run_id}\nnext: physmend sensitivity {run_id}")
    return run_id

"""``physmend mask [RUN_ID]``: keep only the corrections that matter, then retrain.

Ranks the trained network's outputs by ``mean_t |ΔNN_i| / max_t |du_i/dt|`` on the training
samples, simulates the hybrid with only the top k corrections for k = 1, 2, … and keeps the
smallest k whose *validation* RMSE (whole-trajectory simulation) is within a tolerance of the
full network's; then retrains a network that corrects only those equations.
"""

from __future__ import annotations

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


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the mask stage on a trial (default: the current selection); returns the new run ID."""
    import matplotlib.pyplot as plt

    from physmend.stages.common import load_source, log_artifacts, log_training, merged, resolve
    from physmend.tracking import TrackingError, open_store, stage_run
    from physmend.ude import evaluate, train
    from physmend.ude.analysis import rank_corrections, training_trajectories
    from physmend.ude.metrics import checkpoint_problem

    store = open_store(cfg.tracking)
    src_run = resolve(store, source_run_id, stages=("trial",))
    src = load_source(store, src_run, cfg)
    work = merged(src.cfg, cfg, "mask")
    hybrid, problem = src.hybrid, src.problem
    mc = cfg.mask
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
            by_k.append((k_try, evaluate(hybrid, checked, work)["val.rmse"]))
            if by_k[-1][1] <= (1.0 + float(mc.tolerance)) * full:
                break
        hybrid.keep_only(hybrid.spec.corrected)
        k = choose_k(full, by_k, float(mc.tolerance))
        kept = order[:k]
    kept_in_order = [n for n in problem.model.state_names if n in kept]
    result = None
    if bool(mc.retrain):
        work = OmegaConf.merge(work, OmegaConf.from_dotlist([str(o) for o in mc.train_overrides]))
        work.ude.corrected = kept_in_order
        result = train(work, problem)
    with stage_run(store, work, stage=STAGE, source_run_id=src_run.info.run_id, run_name="mask",
                   tags={"physmend.kept": ",".join(kept_in_order)}) as run_:
        run_.log_params({"k": k, "kept": ",".join(kept_in_order), "tolerance": mc.tolerance})
        run_.log_metrics({"full.val.rmse": full, **{f"val.rmse.k{kk}": r for kk, r in by_k}})
        run_.log_json({"ranking": ranking, "by_k": by_k, "full_val_rmse": full, "kept": kept_in_order}, "ranking.json")
        fig = _plot(ranking, by_k or [(k, full)], full, k)
        run_.log_figure(fig, "plots/ranking.png")
        plt.close(fig)
        if result is not None:
            log_training(run_, result)
        else:  # the source network; the kept outputs are recorded in the tag physmend.kept
            from physmend.ude.artifacts import artifacts_of

            log_artifacts(run_, artifacts_of(hybrid, {"val.rmse": full}))
        run_id = run_.run_id
    lines = [f"# physmend mask — source trial {src_run.info.run_id}", "",
             "Corrections ranked by mean |ΔNN| / max |du/dt| on the training samples:", ""]
    lines += [f"{i + 1:3d}. {n}  {s:.3g}" for i, (n, s) in enumerate(ranking[:10])]
    lines += ["", f"Full network: validation RMSE {full:.4g}."]
    lines += [f"  top {kk}: {r:.4g}" for kk, r in by_k]
    lines += [f"Kept k = {k}: {', '.join(kept_in_order)} (tolerance {float(mc.tolerance):.0%})."]
    if result is not None:
        lines.append(f"Retrained with {k} output(s): validation RMSE {result.val_rmse:.4g}, "
                     f"test RMSE {result.metrics.get('test.rmse', float('nan')):.4g}.")
    print("\n".join(lines))
    print(f"\nmask run: {run_id}\nnext: physmend sensitivity {run_id}")
    return run_id

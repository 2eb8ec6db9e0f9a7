"""``physmend mask [RUN_ID]``: keep only the corrections that matter, then retrain.

Finds the trial (default: the current selection), checks ``mask.keep`` against its network, and
hands the network to :func:`physmend.masking.mask_corrections` (ranking, the choice of k, rival
equation sets, the retrainings); then logs the ranking, the kept set and the network that goes on
(retrained, or the source network masked to the kept set), and prints the findings.
"""

from __future__ import annotations

from typing import Any

STAGE = "mask"


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the mask stage on a trial (default: the current selection); returns the new run ID."""
    import matplotlib.pyplot as plt

    from physmend.masking import mask_corrections, outcome_figure, report
    from physmend.settings import group_settings
    from physmend.stages.activity import activity
    from physmend.stages.common import load_source, log_artifacts, log_training, merged, resolve
    from physmend.tracking import TrackingError, open_store, stage_run

    store = open_store(cfg.tracking)
    src_run = resolve(store, source_run_id, stages=("trial",))
    src = load_source(store, src_run, cfg)
    hybrid, mc = src.hybrid, group_settings(cfg, "mask")
    unknown = [n for n in (str(n) for n in mc.keep or []) if n not in hybrid.spec.corrected]
    if unknown:
        raise TrackingError(f"mask.keep names {unknown}, which run {src_run.info.run_id!r} does not correct "
                            f"(it corrects {hybrid.spec.corrected})")
    out = mask_corrections(hybrid, src.problem, merged(src.cfg, cfg, "mask"), mc, progress=activity)
    result = out.trained
    with stage_run(store, out.config, stage=STAGE, source_run_id=src_run.info.run_id, run_name="mask",
                   tags={"physmend.kept": ",".join(out.kept_in_order)}) as run_:
        run_.log_params({"k": out.k, "kept": ",".join(out.kept_in_order), "tolerance": mc.tolerance})
        run_.log_metrics(out.summary_metrics())
        run_.log_json(out.record(), "ranking.json")
        run_.describe(f"Kept corrections: {', '.join(out.kept_in_order)} (of {len(hybrid.spec.corrected)} the network "
                      "corrects); " + (f"retrained, validation RMSE {result.val_rmse:.4g}" if result is not None
                                       else f"the source network masked, validation RMSE {out.masked_rmse():.4g}")
                      + f". Source trial: {src_run.info.run_id}. Next: physmend sensitivity <this run>.")
        fig = outcome_figure(out)
        run_.log_figure(fig, "plots/ranking.png")
        plt.close(fig)
        if result is not None:
            log_training(run_, out.held_out)
        else:  # the source network; the kept outputs are recorded in the tag physmend.kept
            run_.log_metrics(out.metrics)
            log_artifacts(run_, out.artifacts)
        run_id = run_.run_id
    print(report(out, src_run.info.run_id, mc))
    print(f"\nmask run: {run_id}\nnext: physmend sensitivity {run_id}")
    return run_id

"""``physmend sensitivity [RUN_ID]``: which inputs the kept corrections depend on.

Finds the mask run (default: the latest) or a trial, checks the ``sensitivity`` settings against
its network, and hands the network to :func:`physmend.symbolic.sensitivity.input_sensitivity`
(Jacobian along the training trajectories, inputs ranked singly or in groups that move together,
the top k or the named ones passed on to symbolic regression); then logs the ranking and the
heatmap and prints the findings.
"""

from __future__ import annotations

from typing import Any

STAGE = "sensitivity"


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the sensitivity stage on a mask run (default: the latest); returns the new run ID."""
    import matplotlib.pyplot as plt

    from physmend.settings import group_settings
    from physmend.stages.common import load_source, merged, resolve
    from physmend.symbolic.sensitivity import heatmap, input_sensitivity, report
    from physmend.tracking import TrackingError, open_store, stage_run

    store = open_store(cfg.tracking)
    src_run = resolve(store, source_run_id, stages=("mask", "trial"), latest=source_run_id is None)
    src = load_source(store, src_run, cfg)
    work = merged(src.cfg, cfg, "sensitivity")
    hybrid = src.hybrid
    names = hybrid.spec.input_names
    sc = group_settings(cfg, "sensitivity")  # group_r in (0, 1] or null, checked
    given = [str(n) for n in sc.inputs] if sc.inputs else None
    unknown = [n for n in given or [] if n not in names]
    if unknown:
        raise TrackingError(
            f"sensitivity.inputs names {unknown}, which are not inputs of the network of run "
            f"{src_run.info.run_id!r}; its inputs are {names}"
        )
    found = input_sensitivity(hybrid, src.problem, work, max_rows=sc.max_rows, top_k=sc.top_k, group_r=sc.group_r,
                              names=given)
    chosen, kept = found.chosen, found.kept
    with stage_run(store, work, stage=STAGE, source_run_id=src_run.info.run_id, run_name="sensitivity",
                   tags={"physmend.inputs": ",".join(chosen), "physmend.kept": ",".join(kept)}) as run_:
        run_.log_params({"inputs": ",".join(chosen), "kept": ",".join(kept), "how": found.how})
        run_.log_json(found.record(), "sensitivity.json")
        run_.describe(f"Inputs for symbolic regression: {', '.join(chosen)} (kept corrections: {', '.join(kept)}). "
                      f"Source mask run: {src_run.info.run_id}. Next: physmend symbolic <this run>.")
        fig = heatmap(found)
        run_.log_figure(fig, "plots/sensitivity.png")
        plt.close(fig)
        run_id = run_.run_id
    print(report(found, f"{src_run.data.tags.get('physmend.stage')} run {src_run.info.run_id}"))
    print(f"\nsensitivity run: {run_id}\nnext: physmend symbolic {run_id}")
    return run_id

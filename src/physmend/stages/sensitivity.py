"""``physmend sensitivity [RUN_ID]``: which inputs the kept corrections depend on.

Jacobian of the kept corrections with respect to every network input along the training
trajectories (``torch.func``), each column scaled by its input's spread; inputs ranked by mean
absolute sensitivity; a heatmap (inputs × outputs, top inputs marked); the top k (or the names
given in ``sensitivity.inputs``) are passed on to symbolic regression.

Along training trajectories some inputs move together (an air temperature and the wall surface
layers beside it correlate at r > 0.98), and one network may lean on any of them: the data cannot
tell them apart. Inputs correlated at ``|r| >= sensitivity.group_r`` with a representative are
therefore ranked as one group, by the sensitivity along their common direction; a measured
quantity represents its group (its values are known, a hidden state's are simulated), and the
representatives of the top k groups are passed on. ``group_r: null`` ranks single inputs.
"""

from __future__ import annotations

from typing import Any

STAGE = "sensitivity"


def _heatmap(jac_mean: Any, inputs: list[str], outputs: list[str], top: list[str]) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 0.32 * len(inputs)), 1.2 + 0.5 * len(outputs)))
    im = ax.imshow(jac_mean, aspect="auto", cmap="viridis")
    ax.set_xticks(range(len(inputs)), [("★ " if n in top else "") + n for n in inputs], rotation=90, fontsize=7)
    ax.set_yticks(range(len(outputs)), outputs, fontsize=8)
    fig.colorbar(im, ax=ax, label="mean |d correction / d input| · std(input), per output max = 1")
    ax.set_title("sensitivity of the kept corrections (★: passed to symbolic regression)")
    fig.tight_layout()
    return fig


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the sensitivity stage on a mask run (default: the latest); returns the new run ID."""
    import matplotlib.pyplot as plt

    from physmend.stages.common import load_source, merged, resolve
    from physmend.tracking import TrackingError, open_store, stage_run
    from physmend.ude.analysis import group_inputs, input_jacobian, rank_groups, rank_inputs, training_trajectories
    from physmend.ude.warmstart import measured_states

    store = open_store(cfg.tracking)
    src_run = resolve(store, source_run_id, stages=("mask", "trial"), latest=source_run_id is None)
    src = load_source(store, src_run, cfg)
    work = merged(src.cfg, cfg, "sensitivity")
    hybrid, problem = src.hybrid, src.problem
    kept = [n for n, m in zip(hybrid.spec.corrected, hybrid.out_mask.tolist()) if m > 0]
    traj = training_trajectories(hybrid, problem, work)
    jac = input_jacobian(hybrid, traj, max_rows=int(cfg.sensitivity.max_rows))
    ranking = rank_inputs(hybrid, jac, kept)
    names = hybrid.spec.input_names
    group_r = cfg.sensitivity.get("group_r")
    if group_r is not None and (isinstance(group_r, bool) or not isinstance(group_r, (int, float)) or not 0 < group_r <= 1):
        raise TrackingError(f"sensitivity.group_r must be a correlation in (0, 1] or null, but got {group_r!r}")
    measured = [problem.model.state_names[i] for _, i in measured_states(problem)]
    groups = group_inputs(hybrid, traj, measured, float(group_r) if group_r is not None else 1.1, [n for n, _ in ranking])
    grouped = rank_groups(hybrid, jac, groups, kept)
    top_k = int(cfg.sensitivity.top_k)
    if cfg.sensitivity.inputs:
        chosen = [str(n) for n in cfg.sensitivity.inputs]
        unknown = [n for n in chosen if n not in names]
        if unknown:
            raise TrackingError(
                f"sensitivity.inputs names {unknown}, which are not inputs of the network of run "
                f"{src_run.info.run_id!r}; its inputs are {names}"
            )
        how = "chosen by name (sensitivity.inputs)"
    elif group_r is not None:
        chosen = [g.representative for g, _ in grouped[:top_k]]
        how = f"representatives of the top {top_k} groups (|r| >= {float(group_r):g})"
    else:
        chosen = [n for n, _ in ranking[:top_k]]
        how = f"top {top_k} by sensitivity"
    rows = [hybrid.spec.corrected.index(k) for k in kept]
    mag = jac[:, rows].abs().mean(0)
    mag = (mag / mag.amax(-1, keepdim=True).clamp_min(1e-300)).numpy()
    with stage_run(store, work, stage=STAGE, source_run_id=src_run.info.run_id, run_name="sensitivity",
                   tags={"physmend.inputs": ",".join(chosen), "physmend.kept": ",".join(kept)}) as run_:
        run_.log_params({"inputs": ",".join(chosen), "kept": ",".join(kept), "how": how})
        run_.log_json({"ranking": ranking, "chosen": chosen, "kept": kept, "inputs": names,
                       "groups": [{"representative": g.representative, "members": g.members, "score": sc}
                                  for g, sc in grouped],
                       "matrix": mag.tolist()}, "sensitivity.json")
        run_.describe(f"Inputs for symbolic regression: {', '.join(chosen)} (kept corrections: {', '.join(kept)}). "
                      f"Source mask run: {src_run.info.run_id}. Next: physmend symbolic <this run>.")
        fig = _heatmap(mag, names, kept, chosen)
        run_.log_figure(fig, "plots/sensitivity.png")
        plt.close(fig)
        run_id = run_.run_id
    lines = [f"# physmend sensitivity — source {src_run.data.tags.get('physmend.stage')} run {src_run.info.run_id}", "",
             f"Kept corrections: {', '.join(kept)}. Inputs ranked by mean |∂correction/∂input|·std(input):", ""]
    lines += [f"{i + 1:3d}. {'★' if n in chosen else ' '} {n}  {s:.3f}" for i, (n, s) in enumerate(ranking[:12])]
    if group_r is not None and any(len(g.members) > 1 for g, _ in grouped[:8]):  # else the same list again
        lines += ["", f"Ranked as groups of inputs that move together (|r| >= {float(group_r):g} along the training "
                  "trajectories), by the sensitivity along their common direction:", ""]
        for i, (g, sc) in enumerate(grouped[:8]):
            others = f"  (with {', '.join(g.members[1:])})" if len(g.members) > 1 else ""
            lines.append(f"{i + 1:3d}. {'★' if g.representative in chosen else ' '} {g.representative}  {sc:.3f}{others}")
    lines += ["", f"Passed to symbolic regression ({how}): {', '.join(chosen)}"]
    print("\n".join(lines))
    print(f"\nsensitivity run: {run_id}\nnext: physmend symbolic {run_id}")
    return run_id

"""The mask's findings shown: the ranking figure and the printed summary."""

from __future__ import annotations

from typing import Any

from physmend.masking.choice import SourceNetwork, val_text
from physmend.masking.corrections import MaskOutcome


def ranking_figure(ranking: list[tuple[str, float]], by_k: list[tuple[int, float]], full: float, k: int) -> Any:
    """Left: the top 20 of ``ranking`` (``(state, score)``), the kept ``k`` coloured; right: the
    validation RMSE of the network masked to the top k (``by_k``) against the full network's ``full``."""
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


def outcome_figure(out: MaskOutcome) -> Any:
    """:func:`ranking_figure` of a mask's outcome (the chosen k alone where no k was tried)."""
    return ranking_figure(out.ranking, out.by_k or [(out.k, out.full)], out.full, out.k)


def report(out: MaskOutcome, source_run_id: str, mc: Any) -> str:
    """The Markdown the mask stage prints (``mc``: the ``mask`` settings)."""
    lines = [f"# physmend mask — source trial {source_run_id}", "",
             "Corrections ranked by mean |ΔNN| / max |du/dt| on the training samples:", ""]
    lines += [f"{i + 1:3d}. {n}  {s:.3g}" for i, (n, s) in enumerate(out.ranking[:10])]
    lines += ["", f"Full network: validation RMSE {out.full:.4g}."]
    lines += [f"  top {kk}: {r:.4g}" for kk, r in out.by_k]
    if len(out.tried) > 1:
        lines += ["", "Each candidate set retrained alone (the ranking favours equations a warm start could fit; "
                      "a hidden state's equation may explain the data better):"]
        lines += [f"  {', '.join(names)}: validation RMSE {val_text(r)}"
                  + (" (the source network masked to it, not retrained)"
                     if isinstance(r, SourceNetwork) and not out.own_set(names) else "")
                  + (f" (its first training never validated better than its warm start: trained again with "
                     f"{int(mc.retrain_epochs)}× the epochs, the better of the two shown)"
                     if names in out.again and not isinstance(r, SourceNetwork) else "")
                  + ("  <- kept" if r is out.winner else "") for names, r in out.tried]
    lines += [f"Kept k = {out.k}: {', '.join(out.kept_in_order)} (tolerance {float(mc.tolerance):.0%})."]
    if out.trained is None and out.retrained and out.own:
        lines.append("The kept set is the source network's own: it goes on as it is (a retraining would reproduce it).")
    if out.trained is not None:
        # the test experiments' figures are the held-out simulation's (training never saw them)
        metrics = (out.held_out if out.held_out is not None else out.trained).metrics
        test = f", test RMSE {metrics['test.rmse']:.4g}" if "test.rmse" in metrics else ""
        lines.append(f"Retrained with {out.k} output(s): validation RMSE {out.trained.val_rmse:.4g}{test}.")
    return "\n".join(lines)

"""The sweep's closing summary: what it found, its divergence rate, and the exact next commands."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from physmend.sweep.space import hydra_value
from physmend.sweep.storage import Tally

if TYPE_CHECKING:
    from physmend.sweep.loop import Sweep


def divergence(trials: Any, restarts: int) -> str:
    """The sweep's divergence rate, one line: of the trials that reached a verdict, how many diverged
    and were restarted (``sweep.restarts`` at most each), how many of those still failed, and how
    many failed in all (each failure's reason is on its own line above and in its run)."""
    from optuna.trial import TrialState

    from physmend.sweep.restart import RESTARTS_ATTR
    from physmend.sweep.storage import _uncounted

    counted = [t for t in trials if t.state.is_finished() and not _uncounted(t)]
    again = [t for t in counted if int(t.user_attrs.get(RESTARTS_ATTR, 0) or 0) > 0]
    lost = [t for t in again if t.state == TrialState.FAIL]
    failed = sum(t.state == TrialState.FAIL for t in counted)
    if not again:
        return (f"divergence: no trial of {len(counted)} diverged" if not failed
                else f"divergence: no trial of {len(counted)} was restarted; {failed} failed (reasons above)")
    return (f"divergence: {len(again)} of {len(counted)} trials diverged and were restarted (up to {restarts}×: "
            f"smaller steps, then no warm start): {len(again) - len(lost)} then trained to the end or were "
            f"pruned, {len(lost)} failed; {failed} of {len(counted)} failed in all")


def summary(sweep: Sweep, counts: Tally) -> str:
    """What the sweep found and the exact next commands."""
    from physmend.tracking import selection as sel

    parent = sweep.store.client.get_run(sweep.parent_run_id)
    tags = parent.data.tags
    lines = [
        f"sweep {sweep.study.study_name} (space {sweep.space.label}), run {sweep.parent_run_id}:",
        f"  {counts.counted} of {sweep.n_trials} trials: {counts.complete} complete, {counts.pruned} pruned, "
        f"{counts.failed} failed" + (f" ({counts.uncounted} interrupted, not counted)" if counts.uncounted else "")
        + (f"; {counts.running} still running in other workers" if counts.running else ""),
    ]
    if sweep.budget_line:
        lines.append(f"  {sweep.budget_line}")
    lines.append(f"  {divergence(sweep.study.get_trials(deepcopy=False), sweep.settings.restarts)}")
    best = tags.get(sel.BEST_TAG)
    if best is None or counts.best_value is None:
        lines += ["  no trial finished training, so nothing is selected.",
                  "next: look at the failures with `physmend runs`, then change the configuration or the search space"]
        return "\n".join(lines)
    frozen = next(t for t in sweep.study.get_trials(deepcopy=False) if t.number == counts.best_number)
    params = " ".join(f"{k}={hydra_value(v)}" for k, v in frozen.params.items())
    so_far = " so far" if counts.running else ""  # other workers still train: nothing here is final yet
    lines.append(f"  best{so_far}: trial {counts.best_number}, val.rmse {counts.best_value:.6g}, run {best}")
    lines.append(f"        {params}")
    selected, by = tags.get(sel.SELECTED_TAG), tags.get(sel.SELECTED_BY_TAG)
    if selected == best:
        lines.append(f"  selected{so_far}: {selected} (automatic: lowest val.rmse)")
    else:
        lines.append(f"  selected{so_far}: {selected} (chosen by {by}; kept — `physmend select {best}` takes the best)")
    if counts.running:
        lines.append(f"  not final: {counts.running} trial(s) still running in other workers; the last worker to "
                     "finish records the final choice (`physmend runs` shows it)")
    lines += [
        "next:",
        "  physmend runs                  # every trial, the selection marked",
        "  physmend select RUN_ID         # choose another trial",
        "  physmend mask                  # keep only the corrections that matter (on the selected trial)",
    ]
    return "\n".join(lines)

"""The corrected model validated: simulated with the model as written on every experiment, its
terms sized and matched to mechanisms, and the report written (the propose stage's work)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import Any

from physmend.proposal.fits import fit_rows, simulate
from physmend.proposal.report import markdown
from physmend.proposal.terms import describe_terms, training_samples


def _quiet(what: str) -> AbstractContextManager[None]:
    return nullcontext()


@dataclass
class Validation:
    """What the proposal found.

    ``written``/``corrected``: the problems of the model as written and of the corrected one;
    ``batch`` and ``traj_before``/``traj_after``: their whole-trajectory simulations on every
    experiment, ``diverged_before``/``diverged_after`` where they diverge; ``rows``: the fit per
    experiment and output before and after; ``terms``: the terms, sized and matched to mechanisms
    (JSON-ready); ``recalibrated``: declared-uncertain parameters re-fitted with the terms;
    ``title``, ``report`` (Markdown) and ``math`` (code-span text -> MathML) of the report."""

    written: Any
    corrected: Any
    batch: Any
    traj_before: Any
    traj_after: Any
    diverged_before: list[Any]
    diverged_after: list[Any]
    rows: list[dict[str, Any]]
    terms: list[dict[str, Any]]
    recalibrated: dict[str, float]
    title: str
    report: str
    math: dict[str, str]

    def held_out(self) -> list[dict[str, Any]]:
        """The rows of the test experiments (never used for any choice)."""
        return [r for r in self.rows if r["role"] == "test"]

    def figures(self) -> Iterator[tuple[str, Any]]:
        """``(artifact path, figure)`` per experiment: measured outputs, the model as written and the
        corrected model; the caller closes each."""
        from physmend.explain.plots import fit_figure

        t = self.batch.t.numpy()
        for b, e in enumerate(self.written.experiments):
            curves = [("model as written", self.traj_before.outputs[:, b].numpy(), {"ls": "--", "color": "C3", "lw": 1}),
                      ("corrected model", self.traj_after.outputs[:, b].numpy(), {"color": "C2", "lw": 1.2})]
            yield f"plots/fit_{e.id}.png", fit_figure(t, self.batch.obs[:, b].numpy(), curves,
                                                      self.written.model.output_names, self.written.model.units,
                                                      f"experiment {e.id} ({e.role})", time_unit=self.written.time_unit)


def validate(written: Any, corrected: Any, cfg: Any, corrections: list[Any], recalibrated: dict[str, float],
             source_run_id: str, *, progress: Callable[[str], AbstractContextManager[Any]] = _quiet) -> Validation:
    """Simulate ``written`` (the problem of the model as written) and ``corrected`` (the same with
    ``corrections`` attached) on every experiment with the settings ``cfg.simulate``, compare their
    fits, size the terms along the corrected training trajectories and write the report
    (``source_run_id``: the symbolic run the corrections come from). ``progress(what)``: a context
    shown while the simulations run."""
    with progress(f"propose: simulating the model as written and corrected on {len(written.experiments)} experiments"):
        batch, traj0, diverged0 = simulate(written, cfg)
        batch1, traj1, diverged1 = simulate(corrected, cfg)
    rows = fit_rows(written, batch, traj0, traj1)
    # the formulas along the corrected trajectories (training experiments) and their mechanisms
    samples = training_samples(corrected.model, corrected.experiments, batch1, traj1)
    terms = describe_terms(corrections, written.model, corrected.model, samples)
    title = f"physmend proposal — model {written.model.name}"
    report, math = markdown(title, source_run_id, written.model, written.time_unit, terms, recalibrated, rows,
                            diverged0, diverged1, written.experiments)
    return Validation(written, corrected, batch, traj0, traj1, diverged0, diverged1, rows, terms, recalibrated,
                      title, report, math)

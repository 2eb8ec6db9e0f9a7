"""What each stage found, as typed frozen results read back from its MLflow run.

Every result has its ``run_id`` (the same run ``physmend runs`` lists and later commands accept),
``printed`` (what the stage printed, as the command line shows it), tables as pandas DataFrames,
formulas as sympy expressions and ``figures`` (matplotlib, loaded from the run's PNG artifacts on
first use). In Jupyter a result shows itself (``_repr_html_``): formulas, its table, its plots.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from physmend.api import display
from physmend.api.artifacts import RunFiles, figure_of_png
from physmend.api.inputs import Inputs


@dataclass(frozen=True, eq=False)
class StageResult:
    """Base of every result: the run, what it printed, its plots (artifact paths of PNG files).

    Results compare by identity (their tables are DataFrames); compare ``run_id`` to compare runs."""

    run_id: str
    plots: tuple[str, ...] = field(default=(), repr=False)
    printed: str = field(default="", repr=False, compare=False)
    files: RunFiles | None = field(default=None, repr=False, compare=False)
    call: Inputs = field(default_factory=Inputs, repr=False, compare=False)

    title: ClassVar[str] = "physmend"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> StageResult:
        """The result of run ``files.run_id`` read from its artifacts (``common``: printed, call)."""
        return cls(files.run_id, files=files, **common)

    @functools.cached_property
    def figures(self) -> dict[str, Any]:
        """Artifact path -> matplotlib Figure of each plot of the run (read from the store on first use)."""
        return {p: figure_of_png(png, p) for p, png in self._pngs()}

    def _pngs(self, limit: int | None = None) -> list[tuple[str, bytes]]:
        if self.files is None:
            return []
        return [(p, self.files.read_bytes(p)) for p in self.plots[:limit]]

    def _summary(self) -> str:
        return ""

    def _body(self) -> str:
        return ""

    def __repr__(self) -> str:
        found = self._summary()
        return f"{type(self).__name__}(run_id={self.run_id!r}{', ' + found if found else ''})"

    def _repr_html_(self) -> str:
        return (display.heading(self.title, self.run_id, self._summary()) + self._body()
                + display.images(self._pngs(limit=4)))


def _frame(rows: Any, columns: list[str] | None = None) -> Any:
    import pandas as pd

    return pd.DataFrame(rows, columns=columns)


@dataclass(frozen=True, repr=False, eq=False)
class Diagnosis(StageResult):
    """The model as written against the telemetry.

    ``fits``: one row per experiment and output (``rmse``, ``bias``, ``noise`` in the output's unit;
    ``ratio_to_noise`` = rmse / noise). ``summary``: the stage's Markdown report.
    """

    fits: Any = None
    summary: str = field(default="", repr=False)
    metrics: Mapping[str, float] = field(default_factory=dict, repr=False)

    title: ClassVar[str] = "physmend diagnose"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> Diagnosis:
        analysis = files.read_json("diagnosis.json")
        keep = ["experiment", "role", "output", "unit", "n", "rmse", "bias", "noise", "ratio_to_noise"]
        fits = _frame([{k: f.get(k) for k in keep} for f in analysis.get("fits", [])], keep)
        return cls(files.run_id, plots=files.listing("plots"), files=files, fits=fits,
                   summary=files.read_text("summary.md"), metrics=files.metrics(), **common)

    def _summary(self) -> str:
        worst = self.fits["ratio_to_noise"].max() if self.fits is not None and len(self.fits) else float("nan")
        return f"worst misfit {display.short(worst)}× the noise"

    def _body(self) -> str:
        return display.table(self.fits, caption="Fit of the model as written")


@dataclass(frozen=True, repr=False, eq=False)
class SweepResult(StageResult):
    """The architecture sweep (the parent run): ``trials`` (one row per trial: ``run_id``, ``number``,
    ``state``, ``val_rmse`` in output units, ``selected``, ``best``, ``params``), the automatic
    ``best_run_id`` and the current ``selected_run_id`` (the trial later stages start from)."""

    trials: Any = None
    best_run_id: str | None = None
    selected_run_id: str | None = None

    title: ClassVar[str] = "physmend sweep"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> SweepResult:
        from physmend.stages.select import collect

        sweep = collect(files.store, files.run_id)["sweeps"][0]
        columns = ["run_id", "number", "state", "val_rmse", "selected", "best", "params"]
        trials = _frame([{k: t.get(k) for k in columns} for t in sweep["trials"]], columns)
        chosen = sweep.get("selected_run_id")
        plots = RunFiles(files.store, chosen).listing("plots") if chosen else ()
        return cls(files.run_id, plots=plots, files=RunFiles(files.store, chosen) if chosen else files,
                   trials=trials, best_run_id=sweep.get("best_run_id"), selected_run_id=chosen, **common)

    def _summary(self) -> str:
        n = 0 if self.trials is None else len(self.trials)
        return f"{n} trial(s), selected {self.selected_run_id}"

    def _body(self) -> str:
        shown = None if self.trials is None else self.trials.drop(columns=["params"])
        return display.table(shown, caption="Trials")


@dataclass(frozen=True, repr=False, eq=False)
class MaskResult(StageResult):
    """Which corrections matter: ``kept`` (state names), ``ranking`` (``state``, ``score`` = mean |ΔNN| /
    max |du/dt|), ``by_k`` (``k``, ``val_rmse`` with the top k unmasked) and the full network's
    ``full_val_rmse`` (output units)."""

    kept: tuple[str, ...] = ()
    ranking: Any = None
    by_k: Any = field(default=None, repr=False)
    full_val_rmse: float = float("nan")

    title: ClassVar[str] = "physmend mask"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> MaskResult:
        data = files.read_json("ranking.json")
        return cls(files.run_id, plots=files.listing("plots"), files=files, kept=tuple(data.get("kept", [])),
                   ranking=_frame(data.get("ranking", []), ["state", "score"]),
                   by_k=_frame(data.get("by_k", []), ["k", "val_rmse"]),
                   full_val_rmse=float(data.get("full_val_rmse", float("nan"))), **common)

    def _summary(self) -> str:
        return f"kept {', '.join(self.kept) or '(none)'}"

    def _body(self) -> str:
        return display.table(self.ranking, caption="Corrections ranked")


@dataclass(frozen=True, repr=False, eq=False)
class SensitivityResult(StageResult):
    """Which inputs the kept corrections depend on: ``inputs`` (those passed to symbolic regression),
    ``ranking`` (``input``, ``score`` = mean |∂correction/∂input|·std(input), normalised) and
    ``matrix`` (kept corrections × inputs, each row scaled to its largest entry)."""

    inputs: tuple[str, ...] = ()
    kept: tuple[str, ...] = ()
    ranking: Any = None
    matrix: Any = field(default=None, repr=False)

    title: ClassVar[str] = "physmend sensitivity"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> SensitivityResult:
        import pandas as pd

        data = files.read_json("sensitivity.json")
        matrix = pd.DataFrame(data.get("matrix", []), index=data.get("kept", []), columns=data.get("inputs", []))
        return cls(files.run_id, plots=files.listing("plots"), files=files, inputs=tuple(data.get("chosen", [])),
                   kept=tuple(data.get("kept", [])), ranking=_frame(data.get("ranking", []), ["input", "score"]),
                   matrix=matrix, **common)

    def _summary(self) -> str:
        return f"inputs {', '.join(self.inputs)}"

    def _body(self) -> str:
        return display.table(self.ranking, caption="Inputs ranked")


@dataclass(frozen=True, repr=False, eq=False)
class SymbolicResult(StageResult):
    """The network's corrections as formulas.

    ``formulas``: state -> sympy expression added to its equation (constants at their fitted values,
    in the equation's units per time unit); ``terms``: one row per correction (``state``, ``term`` with
    named constants, ``constants``, ``unit``); ``pareto``: every candidate of each state's Pareto front
    (``state``, ``index``, ``complexity``, ``r2``, ``formula``, ``chosen``); ``metrics``: RMSEs of the
    corrected model (no network).
    """

    formulas: Mapping[str, Any] = field(default_factory=dict)
    terms: Any = field(default=None, repr=False)
    pareto: Any = field(default=None, repr=False)
    metrics: Mapping[str, float] = field(default_factory=dict, repr=False)

    title: ClassVar[str] = "physmend symbolic"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> SymbolicResult:
        import yaml

        from physmend.api.artifacts import formula

        corrections = (yaml.safe_load(files.read_text("corrections.yaml")) or {}).get("corrections", [])
        chosen = files.read_json("chosen.json")
        formulas = {c["state"]: formula(c["term"], c.get("constants"), where=f"corrections.yaml, {c['state']}")
                    for c in corrections}
        terms = _frame([{"state": c["state"], "term": c["term"], "constants": dict(c.get("constants", {})),
                         "unit": c.get("unit", "")} for c in corrections], ["state", "term", "constants", "unit"])
        rows = []
        for state, front in files.read_json("pareto.json").items():
            for i, cand in enumerate(front.get("candidates", [])):
                rows.append({"state": state, "index": i, "complexity": cand.get("complexity"), "r2": cand.get("r2"),
                             "formula": cand.get("str"), "chosen": i == chosen.get(state, {}).get("index")})
        pareto = _frame(rows, ["state", "index", "complexity", "r2", "formula", "chosen"])
        return cls(files.run_id, files=files, formulas=formulas, terms=terms, pareto=pareto,
                   metrics=files.metrics(), **common)

    def _summary(self) -> str:
        return display.terms(self.formulas)

    def _body(self) -> str:
        return display.equations(self.formulas) + display.table(self.terms, caption="Terms")


@dataclass(frozen=True, repr=False, eq=False)
class Proposal(StageResult):
    """The corrected model checked on every experiment, held-out ones included.

    ``formulas``: state -> sympy term added to its equation (constants at their re-fitted values);
    ``fit``: one row per experiment and output (``role``, RMSE ``before``/``after`` in the output's unit,
    ``improvement`` = before/after, estimated ``noise``); ``parameters``: re-calibrated uncertain
    parameters; ``report``: the Markdown report (``report.html`` in the run).
    """

    formulas: Mapping[str, Any] = field(default_factory=dict)
    fit: Any = field(default=None, repr=False)
    parameters: Mapping[str, float] = field(default_factory=dict, repr=False)
    report: str = field(default="", repr=False)

    title: ClassVar[str] = "physmend propose"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> Proposal:
        from physmend.api.artifacts import formula

        data = files.read_json("proposal.json")
        formulas = {t["state"]: formula(t["expr"], where=f"proposal.json, {t['state']}") for t in data.get("terms", [])}
        columns = ["experiment", "role", "output", "before", "after", "improvement", "noise"]
        fit = _frame([{k: r.get(k) for k in columns} for r in data.get("rows", [])], columns)
        return cls(files.run_id, plots=files.listing("plots"), files=files, formulas=formulas, fit=fit,
                   parameters=dict(data.get("parameters") or {}), report=files.read_text("report.md"), **common)

    def _summary(self) -> str:
        held = self.fit[self.fit["role"] == "test"] if self.fit is not None and len(self.fit) else None
        gain = (f"held-out RMSE improved {held['improvement'].min():.1f}× to {held['improvement'].max():.1f}×"
                if held is not None and len(held) else "")
        terms = display.terms(self.formulas)
        return ", ".join(x for x in (terms, gain) if x)

    def _body(self) -> str:
        return display.equations(self.formulas) + display.table(self.fit, caption="Fit before and after (RMSE)")


@dataclass(frozen=True, repr=False, eq=False)
class Decision(StageResult):
    """The engineer's decision on a proposal: ``decision`` (``accepted``/``rejected``), the written
    ``corrections_file`` (accepted; load it with ``model.corrections=<file>``) or the ``reason``."""

    decision: str = ""
    corrections_file: str | None = None
    reason: str = ""

    title: ClassVar[str] = "physmend decision"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> Decision:
        tags = files.tags()
        return cls(files.run_id, files=files, decision=tags.get("physmend.decision", ""),
                   corrections_file=tags.get("physmend.corrections_file"),
                   reason=tags.get("physmend.reject_reason", ""), **common)

    def _summary(self) -> str:
        where = f", file {self.corrections_file}" if self.corrections_file else ""
        return f"{self.decision}{where}" + (f", reason {self.reason!r}" if self.reason else "")


@dataclass(frozen=True, repr=False, eq=False)
class ExportResult(StageResult):
    """The files ``export`` wrote: ``paths``, format (``latex``, ``sympy``, ``python``, ``petab`` …) -> its
    file or folder; ``written``, every file and folder it wrote (absolute paths)."""

    paths: Mapping[str, str] = field(default_factory=dict)
    written: tuple[str, ...] = field(default=(), repr=False)

    title: ClassVar[str] = "physmend export"

    def _summary(self) -> str:
        return ", ".join(f"{k} {v}" for k, v in self.paths.items())

    def _body(self) -> str:
        import html

        return "<ul>" + "".join(f"<li>{html.escape(k)}: <code>{html.escape(v)}</code></li>"
                                for k, v in self.paths.items()) + "</ul>"

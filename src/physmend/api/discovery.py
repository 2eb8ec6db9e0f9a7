"""The result of :func:`physmend.discover`: every stage's result, the formulas and the fit."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from physmend.api import display
from physmend.api.artifacts import RunFiles, lineage
from physmend.api.results import (
    Diagnosis,
    MaskResult,
    Proposal,
    SensitivityResult,
    StageResult,
    SweepResult,
    SymbolicResult,
)


@dataclass(frozen=True, repr=False, eq=False)
class Discovery(StageResult):
    """Diagnose → sweep → mask → sensitivity → symbolic → propose, end to end.

    ``run_id`` is the proposal's (pass the result to :func:`physmend.accept`, :func:`physmend.reject`
    or :func:`physmend.export`); each stage's own result is an attribute; ``formulas`` and ``fit`` are
    the proposal's (state -> sympy term added to its equation; RMSE before/after per experiment and
    output, in output units).
    """

    diagnosis: Diagnosis | None = field(default=None, repr=False)
    sweep: SweepResult | None = field(default=None, repr=False)
    mask: MaskResult | None = field(default=None, repr=False)
    sensitivity: SensitivityResult | None = field(default=None, repr=False)
    symbolic: SymbolicResult | None = field(default=None, repr=False)
    proposal: Proposal | None = field(default=None, repr=False)

    title: ClassVar[str] = "physmend discover"

    @classmethod
    def read(cls, files: RunFiles, **common: Any) -> Discovery:
        """Every stage's result, found from the proposal back through the runs' source tags."""
        ids = lineage(files)
        parts: dict[str, Any] = {}
        shared = {"call": common["call"]} if "call" in common else {}
        for name, stage, kind in (("diagnosis", "diagnose", Diagnosis), ("sweep", "sweep", SweepResult),
                                  ("mask", "mask", MaskResult), ("sensitivity", "sensitivity", SensitivityResult),
                                  ("symbolic", "symbolic", SymbolicResult), ("proposal", "propose", Proposal)):
            if stage in ids:
                parts[name] = kind.read(RunFiles(files.store, ids[stage]), **shared)
        proposal = parts.get("proposal")
        return cls(files.run_id, plots=proposal.plots if proposal else (), files=files, **common, **parts)

    @property
    def formulas(self) -> Mapping[str, Any]:
        return self.proposal.formulas if self.proposal else {}

    @property
    def fit(self) -> Any:
        return self.proposal.fit if self.proposal else None

    @property
    def run_ids(self) -> dict[str, str]:
        """Stage -> run ID of every stage of this discovery."""
        return {name: part.run_id for name in ("diagnosis", "sweep", "mask", "sensitivity", "symbolic", "proposal")
                if (part := getattr(self, name)) is not None}

    def _summary(self) -> str:
        return self.proposal._summary() if self.proposal else ""

    def _body(self) -> str:
        kept = f"<p>kept corrections: {', '.join(self.mask.kept)}; inputs: {', '.join(self.sensitivity.inputs)}</p>" \
            if self.mask and self.sensitivity else ""
        return (display.equations(self.formulas) + kept
                + display.table(self.fit, caption="Fit before and after (RMSE, held-out experiments: role test)"))

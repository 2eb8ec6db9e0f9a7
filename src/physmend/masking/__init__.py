"""Output masking: keep only the corrections that matter, then retrain.

One entry point, :func:`mask_corrections` (ranking, the choice of k, rival equation sets, the
retrainings side by side), returning a :class:`MaskOutcome`; :func:`report` and
:func:`outcome_figure` show it. The rules on their own: :func:`choose_k`, :func:`rivals`,
:func:`best_retrained`. It trains networks, so it sits above :mod:`physmend.ude`.
"""

from __future__ import annotations

from physmend.masking.choice import SourceNetwork, best_retrained, choose_k, rivals
from physmend.masking.corrections import MaskOutcome, mask_corrections
from physmend.masking.report import outcome_figure, report

__all__ = ["MaskOutcome", "SourceNetwork", "best_retrained", "choose_k", "mask_corrections", "outcome_figure",
           "report", "rivals"]

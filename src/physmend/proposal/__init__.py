"""The proposal: the corrected model validated against the model as written, with a report.

One entry point, :func:`validate`, returning a :class:`Validation`: both models simulated whole on
every experiment (:mod:`physmend.proposal.fits`), the terms sized along the corrected training
trajectories and matched to the mechanism catalogue (:mod:`physmend.proposal.terms`), and the
Markdown report (:mod:`physmend.proposal.report`). It simulates as the diagnosis does, so it sits
above :mod:`physmend.diagnosis`.
"""

from __future__ import annotations

from physmend.proposal.findings import Validation, validate
from physmend.proposal.report import MIN_MECHANISM_R2

__all__ = ["MIN_MECHANISM_R2", "Validation", "validate"]

"""Diagnosis: the model as written simulated against every experiment; where does it miss?

One entry point, :func:`diagnose`, returning a :class:`Diagnosis`: per experiment and output the
RMSE and bias against an estimate of the sensor noise, the time windows with the largest
residuals, the model variables and inputs that the residual (and its drift rate) correlate with
(:mod:`physmend.diagnosis.analysis`), where the model diverges (:mod:`physmend.diagnosis.simulation`),
and a Markdown summary (:mod:`physmend.diagnosis.summary`); :func:`plot_experiment` draws one
experiment's fit. It simulates with the bounded reference of :mod:`physmend.ude.reference`, so it
sits beside :mod:`physmend.ude`.
"""

from __future__ import annotations

from physmend.diagnosis.findings import Diagnosis, diagnose
from physmend.diagnosis.plots import plot_experiment
from physmend.diagnosis.simulation import simulate_as_written

__all__ = ["Diagnosis", "diagnose", "plot_experiment", "simulate_as_written"]

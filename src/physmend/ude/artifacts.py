"""What a trained hybrid model leaves in its run: the plain files ``model/weights.pt`` and
``model/hybrid.json`` (read back by :func:`physmend.ude.io.load_hybrid`) and the fit figures, one
per experiment. Imports ``hybrid``, ``reference`` (and ``explain.plots`` when figures are drawn).
"""

from __future__ import annotations

from typing import Any
import io
import json

import torch

from physmend.problem import Problem
from physmend.simulate import Batch
from physmend.ude.hybrid import HybridModel
from physmend.ude.reference import Reference


def artifacts_of(hybrid: HybridModel, metrics: dict[str, float]) -> dict[str, str | bytes]:
    """Plain files: ``model/weights.pt`` (a state_dict of tensors) and ``model/hybrid.json``."""
    buf = io.BytesIO()
    torch.save({k: v.detach().cpu() for k, v in hybrid.state_dict().items()}, buf)
    meta = {"spec": hybrid.spec.to_dict(), "estimates": hybrid.estimates(), "metrics": metrics, "format": 1}
    return {"model/weights.pt": buf.getvalue(), "model/hybrid.json": json.dumps(meta, indent=2)}


def fit_figures(problem: Problem, batch: Batch, y: torch.Tensor, ref: Reference) -> dict[str, Any]:
    """Measured vs model-as-written vs hybrid outputs, one figure per experiment."""
    from physmend.explain.plots import fit_figure

    t = batch.t.cpu().numpy()
    y_ref = problem.compiled.outputs(ref.states, ref.inputs, ref.batch.params[None]).cpu().numpy()
    figs: dict[str, Any] = {}
    for b, e in enumerate(problem.experiments):
        curves = [("model as written", y_ref[:, b], {"ls": "--", "color": "C3", "lw": 1}),
                  ("hybrid (UDE)", y[:, b].cpu().numpy(), {"color": "C0", "lw": 1.2})]
        split = float(e.split_time) if e.split_time is not None else None
        figs[f"plots/fit_{e.id}.png"] = fit_figure(t, batch.obs[:, b].cpu().numpy(), curves, problem.model.output_names,
                                                   problem.model.units, f"experiment {e.id} ({e.role})", split,
                                                   problem.time_unit)
    return figs

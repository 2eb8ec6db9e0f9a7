"""``physmend propose [RUN_ID]``: the corrected model, validated on held-out experiments, with a report.

Finds the symbolic run (default: the latest), builds the model as written and the corrected model
(the user's equations plus the chosen formulas, attached to the equations they correct) from the
user's configuration, and hands both to :func:`physmend.proposal.validate` (every experiment
simulated, fits before/after against the sensor noise, each term's size in physical units and the
mechanism its form suggests); then logs the Markdown and HTML report. Nothing changes the user's
model until ``accept``.
"""

from __future__ import annotations

import io
import tempfile
from pathlib import Path
from typing import Any

STAGE = "propose"


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the propose stage on a symbolic run (default: the latest); returns the new run ID."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from physmend.explain.report import to_html
    from physmend.modeling import read_corrections
    from physmend.problem import load_problem
    from physmend.proposal import validate
    from physmend.redact import redact
    from physmend.settings import group_settings
    from physmend.stages.activity import activity
    from physmend.stages.common import merged, resolve
    from physmend.tracking import download_artifact, open_store, stage_run
    from physmend.tracking.fingerprint import check_same_model
    from physmend.tracking.stored_config import read_stored_config

    store = open_store(cfg.tracking)
    src_run = resolve(store, source_run_id, stages=("symbolic",), latest=source_run_id is None)
    cfg_path = download_artifact(store, src_run.info.run_id, "config.yaml")
    corr_path = download_artifact(store, src_run.info.run_id, "corrections.yaml")
    base_cfg = merged(read_stored_config(cfg_path, src_run.info.run_id, cfg), cfg, "propose")
    base_cfg.model.corrections = None
    corrections, meta = read_corrections(corr_path)
    before = load_problem(base_cfg)
    check_same_model(store, src_run, base_cfg)
    fixed_cfg = base_cfg.copy()
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / "corrections.yaml"
        local.write_text(Path(corr_path).read_text())
        fixed_cfg.model.corrections = str(local)
        after = load_problem(fixed_cfg)
    found = validate(before, after, base_cfg, corrections, meta["parameters"], src_run.info.run_id, progress=activity)
    rows, terms, held = found.rows, found.terms, found.held_out()
    with stage_run(store, base_cfg, stage=STAGE, source_run_id=src_run.info.run_id, run_name="propose") as run_:
        run_.log_metrics({f"rmse_before.{r['experiment']}.{r['output']}": r["before"] for r in rows})
        run_.log_metrics({f"rmse_after.{r['experiment']}.{r['output']}": r["after"] for r in rows})
        run_.log_json({"rows": rows, "terms": terms, "parameters": found.recalibrated}, "proposal.json")
        run_.log_text(found.report, "report.md")
        run_.describe("Corrections: " + "; ".join(f"{t['state']} + {t['term']}" for t in terms)
                      + (f". Held-out RMSE improved {min(r['improvement'] for r in held):.1f}× to "
                         f"{max(r['improvement'] for r in held):.1f}×" if held else "")
                      + f". Report: report.html. Source symbolic run: {src_run.info.run_id}. "
                      "Next: physmend accept <this run> (or reject, or export).")
        run_.log_text(Path(corr_path).read_text(), "corrections.yaml")
        images: dict[str, bytes] = {}  # embedded in report.html, which then shows them wherever it is opened
        if group_settings(cfg, "propose").plots:
            for rel, fig in found.figures():
                run_.log_figure(fig, rel)
                png = io.BytesIO()
                fig.savefig(png, format="png")
                images[rel] = png.getvalue()
                plt.close(fig)
        run_.log_text(to_html(found.report, found.title, images, found.math), "report.html")
        run_id = run_.run_id
    print(found.report)
    where = redact(str(store.client.get_run(run_id).info.artifact_uri))
    print(f"propose run: {run_id}\nreport: {where}/report.html  (and report.md; in the MLflow UI: physmend ui, this run, "
          f"Artifacts)\nnext: physmend accept {run_id}   (or: physmend reject {run_id} decide.reason='…'; "
          f"physmend export {run_id} for LaTeX, sympy, Python, the network, PEtab)")
    return run_id

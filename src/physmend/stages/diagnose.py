"""``physmend diagnose``: simulate the model as written against every experiment; where does it miss?

Builds the problem from the configuration, hands it to :func:`physmend.diagnosis.diagnose` (the
model as written simulated on every experiment, residual statistics against the sensor noise, the
worst windows, the correlates, where it diverges), then logs the findings (``diagnosis.json``,
``summary.md``, one fit figure per experiment) and prints the summary. A model as written that
diverges is a finding, not a failure. Nothing is written if the inputs are bad.
"""

from __future__ import annotations

from typing import Any

STAGE = "diagnose"


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the diagnose stage; returns the MLflow run ID. Nothing is written if the inputs are bad."""
    from physmend.diagnosis import diagnose, plot_experiment
    from physmend.problem import load_problem
    from physmend.settings import group_settings
    from physmend.stages.activity import activity
    from physmend.tracking import open_store, stage_run

    problem = load_problem(cfg)
    found = diagnose(problem, cfg, progress=activity)
    store = open_store(cfg.tracking)
    with stage_run(store, cfg, stage=STAGE, source_run_id=source_run_id, run_name="diagnose") as run_:
        run_.log_params(
            {
                "model": problem.model.name,
                "data": cfg.data.name,
                "n_states": len(problem.model.states),
                "n_experiments": len(problem.experiments),
                "simulate.method": group_settings(cfg, "simulate").method,
            }
        )
        description = found.description()
        if description is not None:
            run_.describe(description)
        run_.log_metrics(found.metrics())
        run_.log_json(found.analysis, "diagnosis.json")
        run_.log_text(found.summary, "summary.md")
        if group_settings(cfg, "diagnose").plots:
            import matplotlib.pyplot as plt

            for b, exp in enumerate(problem.experiments):
                fig = plot_experiment(problem, found.t, found.traj, b)
                run_.log_figure(fig, f"plots/fit_{exp.id}.png")
                plt.close(fig)
        run_id = run_.run_id
    print(found.summary)
    print(f"diagnose run: {run_id}  (browse: physmend ui)")
    print("next: physmend sweep      # train corrections for what is missing (or: physmend discover, every stage)")
    return run_id

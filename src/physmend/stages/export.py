"""``physmend export RUN_ID``: a proposal's corrected model as files the engineer can use elsewhere.

Builds the model the current configuration names (never one from the store), applies the
proposal's corrections (constants at their re-fitted values) and writes, into
``export.output_dir``, one file per ``export.format``: LaTeX (``.tex``), sympy expressions
(``.sympy.json``, ``srepr`` text) and a plain Python module (``.py``, a right-hand side for
``scipy.integrate.solve_ivp``). An existing file is never overwritten; the run is not changed.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

STAGE = "export"


def _formats(value: Any) -> list[str]:
    from physmend.modeling.export import FORMATS

    return list(FORMATS) if str(value) == "all" else [str(value)]


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Write the corrected model of proposal ``source_run_id``; returns that run ID."""
    import numpy as np
    import torch

    from physmend.modeling import read_corrections
    from physmend.modeling.errors import ModelError
    from physmend.modeling.export import FORMATS, latex_text, module_name, python_module, sympy_json
    from physmend.problem import load_problem
    from physmend.stages.common import merged
    from physmend.tracking import TrackingError, download_artifact, get_run, open_store
    from physmend.tracking.stored_config import read_stored_config

    if not source_run_id:
        raise TrackingError("export needs the run ID of a proposal: physmend export RUN_ID")
    store = open_store(cfg.tracking)
    run_ = get_run(store, source_run_id, stage="propose")
    run_id = run_.info.run_id
    if run_.info.status != "FINISHED":
        raise TrackingError(f"proposal {run_id!r} did not finish (status {run_.info.status})")
    out_dir = Path(str(cfg.export.output_dir)).expanduser()
    formats = _formats(cfg.export.format)
    stored = read_stored_config(download_artifact(store, run_id, "config.yaml"), run_id, cfg)
    work = merged(stored, cfg, "export")
    corr_path = download_artifact(store, run_id, "corrections.yaml")
    corrections, meta = read_corrections(corr_path)
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / "corrections.yaml"
        local.write_text(Path(corr_path).read_text())
        work.model.corrections = str(local)
        problem = load_problem(work)
    sm = problem.model
    name = str(meta.get("model", sm.name))
    base = module_name(name, run_id)
    targets = {f: out_dir / f"{base}{FORMATS[f]}" for f in formats}
    there = [str(p) for p in targets.values() if p.exists()]
    if there:
        raise ModelError(f"export.output_dir: {there[0]} exists; physmend never overwrites a file (move it or "
                         f"choose another export.output_dir)")
    corrected = [c.state for c in corrections]
    constants = {p.name: float(p.value) for p in sm.parameters
                 if any(p.name.startswith(f"{c.state}_") and p.name[len(c.state) + 1:] in c.constants for c in corrections)}
    info = {"model": name, "source_run_id": run_id, "time_unit": problem.time_unit}
    declared = np.array([float(v.value) for v in sm.parameters])
    experiments = {}
    for e in problem.experiments:  # initial states as the simulations take them: the start expressions, then the data's
        start = problem.compiled.start(torch.as_tensor(np.asarray(e.parameters, dtype=np.float64))).tolist()
        initial = {**dict(zip(sm.state_names, start)), **{n: float(v) for n, v in (e.initial or {}).items()}}
        experiments[e.id] = {"role": e.role, "initial": initial,
                             "parameters": {n: float(v) for n, v, d in zip(sm.parameter_names, e.parameters, declared) if v != d}}
    texts = {"latex": lambda: latex_text(sm, corrected, constants, info),
             "sympy": lambda: sympy_json(sm, corrected, info),
             "python": lambda: python_module(sm, experiments, info)}
    written = {f: texts[f]() for f in formats}  # every text first: a failing writer leaves no file behind
    made: list[Path] = []
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for f, text in written.items():
            with open(targets[f], "x", encoding="utf-8") as fh:  # "x": never overwrite, even in a race
                made.append(targets[f])
                fh.write(text)
    except OSError as exc:  # a folder that cannot be made or written: one line, none of this call's files left
        for path in made:
            path.unlink(missing_ok=True)
        raise ModelError(f"export.output_dir: cannot write {exc.filename or out_dir}: {exc.strerror or exc}") from None
    print(f"# physmend export — proposal {run_id}, model {name}: {', '.join(corrected)} corrected")
    for f in formats:
        print(f"  {f:7s} {targets[f]}")
    if "python" in formats:
        print(f"use: import {base}; scipy.integrate.solve_ivp(lambda t, x: {base}.rhs(t, x, inputs(t)), "
              f"(t0, t1), {base}.initial_state())")
    return run_id

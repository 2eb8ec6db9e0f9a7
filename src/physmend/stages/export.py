"""``physmend export RUN_ID``: a proposal's corrected model as files the engineer can use elsewhere.

Builds the model the current configuration names (never one from the store), applies the
proposal's corrections (constants at their re-fitted values) and writes, into
``export.output_dir``, one file per ``export.format``: a standalone LaTeX document (``.tex``, the
found terms marked, constants with units and standard errors), sympy expressions
(``.sympy.json``, ``srepr`` text, constants with units), a plain Python module (``.py``, a
right-hand side for ``scipy.integrate.solve_ivp``), the correcting network the formulas came from
(``.network.json`` architecture + ``.network.safetensors`` weights, :mod:`physmend.ude.network_file`)
and a PEtab problem (``.petab/``: SBML model and tables, see :mod:`physmend.modeling.petab`). An
existing file is never overwritten; the run is not changed. The stage reads the proposal and
its store, and :mod:`physmend.proposal.files` makes and writes the texts.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

STAGE = "export"


def _stderr(store: Any, run_: Any) -> dict[str, Any]:
    """The standard errors of the re-fitted constants (``uncertainty.json`` of the proposal's source
    run), or ``{}`` where no re-fit improved the fit."""
    from physmend.tracking import SOURCE_TAG, TrackingError, download_artifact

    source = run_.data.tags.get(SOURCE_TAG)
    if not source:
        return {}
    try:
        return json.loads(download_artifact(store, source, "uncertainty.json").read_text())
    except (TrackingError, ValueError, OSError):  # no re-fit improved the fit: no standard errors
        return {}


def _network_of(store: Any, run_: Any, cfg: Any) -> Any:
    """The trained network the proposal's formulas were fitted to: the model run (trial or mask)
    its symbolic run names, loaded as the stages load it (kept corrections only)."""
    from physmend.stages.common import load_source
    from physmend.tracking import SOURCE_TAG, TrackingError, get_run

    symbolic = get_run(store, run_.data.tags.get(SOURCE_TAG, ""), stage="symbolic")
    model_run_id = symbolic.data.tags.get("physmend.model_run_id")
    if not model_run_id:
        raise TrackingError(f"symbolic run {symbolic.info.run_id!r} names no network run (tag physmend.model_run_id); "
                            "export.format=network needs one")
    return load_source(store, get_run(store, model_run_id), cfg).hybrid


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Write the corrected model of proposal ``source_run_id``; returns that run ID."""
    from physmend.modeling import read_corrections
    from physmend.modeling.errors import ModelError
    from physmend.modeling.export import FORMATS, module_name
    from physmend.problem import load_problem
    from physmend.proposal.files import corrected_model_texts, formats as named_formats, report, write_new
    from physmend.settings import group_settings
    from physmend.stages.common import merged
    from physmend.tracking import TrackingError, download_artifact, get_run, open_store
    from physmend.tracking.fingerprint import check_same_model
    from physmend.tracking.stored_config import read_stored_config

    if not source_run_id:
        raise TrackingError("export needs the run ID of a proposal: physmend export RUN_ID")
    store = open_store(cfg.tracking)
    run_ = get_run(store, source_run_id, stage="propose")
    run_id = run_.info.run_id
    if run_.info.status != "FINISHED":
        raise TrackingError(f"proposal {run_id!r} did not finish (status {run_.info.status})")
    ec = group_settings(cfg, "export")
    out_dir = Path(ec.output_dir).expanduser()
    formats = named_formats(ec.format)
    if "petab" in formats:
        from physmend.modeling.petab import unavailable_reason

        if unavailable_reason():
            raise ModelError(str(unavailable_reason()))
    stored = read_stored_config(download_artifact(store, run_id, "config.yaml"), run_id, cfg)
    work = merged(stored, cfg, "export")
    corr_path = download_artifact(store, run_id, "corrections.yaml")
    corrections, meta = read_corrections(corr_path)
    with tempfile.TemporaryDirectory() as tmp:
        local = Path(tmp) / "corrections.yaml"
        local.write_text(Path(corr_path).read_text())
        work.model.corrections = str(local)
        try:
            problem = load_problem(work)
        except ModelError as exc:  # name the proposal's file, not the copy that is gone when the line is read
            raise ModelError(str(exc).replace(str(local), f"proposal {run_id!r}: corrections.yaml")) from None
    check_same_model(store, run_, work)
    sm = problem.model
    name = str(meta.get("model", sm.name))
    base = module_name(name, run_id)
    targets = {f: out_dir / f"{base}{FORMATS.get(f, '.petab')}" for f in formats}  # petab: a folder of files
    there = [str(p) for p in [*targets.values(), out_dir / f"{base}.network.safetensors"] if p.exists()]
    if there:
        raise ModelError(f"export.output_dir: {there[0]} exists; physmend never overwrites a file (move it or "
                         f"choose another export.output_dir)")
    info = {"model": name, "source_run_id": run_id, "time_unit": problem.time_unit}

    def network() -> dict[str, str | bytes]:
        from physmend.ude.network_file import network_files

        hybrid = _network_of(store, run_, cfg)
        units = {v.name: v.unit for v in sm.states + sm.inputs + sm.parameters} | dict(sm.units or {})
        return network_files(hybrid, units, stem=base, meta=info)

    written = corrected_model_texts(problem, corrections, formats, info, _stderr(store, run_), network,
                                    every=ec.format == "all")
    write_new(written, targets, out_dir)
    print(report(run_id, name, [c.state for c in corrections], list(written), targets, base))
    return run_id

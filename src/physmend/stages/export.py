"""``physmend export RUN_ID``: a proposal's corrected model as files the engineer can use elsewhere.

Builds the model the current configuration names (never one from the store), applies the
proposal's corrections (constants at their re-fitted values) and writes, into
``export.output_dir``, one file per ``export.format``: a standalone LaTeX document (``.tex``, the
found terms marked, constants with units and standard errors), sympy expressions
(``.sympy.json``, ``srepr`` text, constants with units), a plain Python module (``.py``, a
right-hand side for ``scipy.integrate.solve_ivp``), the correcting network the formulas came from
(``.network.json`` architecture + ``.network.safetensors`` weights, :mod:`physmend.ude.network_file`)
and a PEtab problem (``.petab/``: SBML model and tables, see :mod:`physmend.modeling.petab`). An
existing file is never overwritten; the run is not changed.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

STAGE = "export"


def _formats(value: Any) -> list[str]:
    """The formats ``export.format`` names: ``all`` is every one this machine can write (PEtab
    needs python-libsbml: left out with one line where it is missing)."""
    from physmend.modeling.export import FORMATS
    from physmend.modeling.petab import unavailable_reason

    if str(value) != "all":
        return [str(value)]
    reason = unavailable_reason()
    if reason is not None:
        print(f"petab left out: {reason}")
    return [*FORMATS, *([] if reason else ["petab"])]


def _constants(store: Any, run_: Any, sm: Any, corrections: list[Any], terms: dict[str, Any],
               values: dict[str, float]) -> dict[str, dict[str, Any]]:
    """Each correction constant (parameter name ->) ``state``, ``name``, ``value``, ``unit`` (from
    the term's unit where the constant enters linearly, else ``""``) and, where the symbolic run's
    re-fit computed one, ``stderr`` (``uncertainty.json`` of the proposal's source run)."""
    import json

    from physmend.modeling.constant_units import constant_unit
    from physmend.tracking import SOURCE_TAG, TrackingError, download_artifact

    stderr: dict[str, Any] = {}
    source = run_.data.tags.get(SOURCE_TAG)
    if source:
        try:
            stderr = json.loads(download_artifact(store, source, "uncertainty.json").read_text())
        except (TrackingError, ValueError, OSError):  # no re-fit improved the fit: no standard errors
            stderr = {}
    units = {v.name: v.unit for v in sm.states + sm.inputs + sm.parameters if v.unit} | dict(sm.units or {})
    symbols = {v.name: v.symbol for v in sm.parameters}
    out: dict[str, dict[str, Any]] = {}
    for c in corrections:
        for k in c.constants:
            pname = f"{c.state}_{k}"
            if pname not in values:
                continue
            info: dict[str, Any] = {"state": c.state, "name": k, "value": values[pname],
                                    "unit": constant_unit(terms[c.state], symbols[pname], c.unit, units)}
            se = stderr.get(pname, {}).get("stderr") if isinstance(stderr.get(pname), dict) else None
            if isinstance(se, (int, float)):
                info["stderr"] = float(se)
            out[pname] = info
    return out


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
    import numpy as np
    import torch

    from physmend.modeling import read_corrections
    from physmend.modeling.errors import ModelError
    from physmend.modeling.export import FORMATS, module_name, python_module, sympy_json
    from physmend.modeling.latex import found_terms, latex_document
    from physmend.problem import load_problem
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
    out_dir = Path(str(cfg.export.output_dir)).expanduser()
    formats = _formats(cfg.export.format)
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
    corrected = [c.state for c in corrections]
    constants = {p.name: float(p.value) for p in sm.parameters
                 if any(p.name.startswith(f"{c.state}_") and p.name[len(c.state) + 1:] in c.constants for c in corrections)}
    info = {"model": name, "source_run_id": run_id, "time_unit": problem.time_unit}
    terms = found_terms(sm, corrections)
    const_info = _constants(store, run_, sm, corrections, terms, constants)
    declared = np.array([float(v.value) for v in sm.parameters])
    experiments = {}
    for e in problem.experiments:  # initial states as the simulations take them: the start expressions, then the data's
        start = problem.compiled.start(torch.as_tensor(np.asarray(e.parameters, dtype=np.float64))).tolist()
        initial = {**dict(zip(sm.state_names, start)), **{n: float(v) for n, v in (e.initial or {}).items()}}
        experiments[e.id] = {"role": e.role, "initial": initial,
                             "parameters": {n: float(v) for n, v, d in zip(sm.parameter_names, e.parameters, declared) if v != d}}
    def petab() -> dict[str, str]:
        from physmend.modeling.petab import petab_files

        records = [{**experiments[e.id], "id": e.id, "obs_time": e.obs_time, "obs": e.obs,
                    "inputs": {n: (c.time, c.values) for n, c in e.inputs.items()}} for e in problem.experiments]
        estimated = {v.name: tuple(map(float, v.bounds)) for v in sm.parameters if v.uncertain and v.bounds}
        estimated |= {n: (-10 * abs(v) or -1.0, 10 * abs(v) or 1.0) for n, v in constants.items()}
        from physmend.explain.residuals import noise_floor

        sigmas = {}
        for j, out in enumerate(sm.outputs):  # each output's noise: the median over the records' estimates
            found = [noise_floor(np.asarray(e.obs_time), np.asarray(e.obs)[:, j]) for e in problem.experiments]
            found = [v for v in found if np.isfinite(v) and v > 0]
            sigmas[out] = float(np.median(found)) if found else 1.0
        return petab_files(sm, records, estimated, sigmas)

    def network() -> dict[str, str | bytes]:
        from physmend.ude.network_file import network_files

        hybrid = _network_of(store, run_, cfg)
        units = {v.name: v.unit for v in sm.states + sm.inputs + sm.parameters} | dict(sm.units or {})
        return network_files(hybrid, units, stem=base, meta=info)

    texts = {"latex": lambda: latex_document(sm, terms, const_info, info),
             "sympy": lambda: sympy_json(sm, corrected, info, const_info),
             "python": lambda: python_module(sm, experiments, info),
             "network": network,
             "petab": petab}
    if str(cfg.export.format) == "all":  # every format this proposal allows: a network that cannot be loaded is left out
        try:
            network_files = network()
        except ValueError as exc:  # TrackingError, ModelError, DataError, ConfigError: one line naming the run
            print(f"network left out: {exc}")
            formats = [f for f in formats if f != "network"]
        else:
            texts["network"] = lambda: network_files
    written = {f: texts[f]() for f in formats}  # every text first: a failing writer leaves no file behind
    made: list[Path] = []
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for f, text in written.items():
            if isinstance(text, str):
                files = {targets[f]: text}
            elif f == "network":  # two files beside the others
                files = {out_dir / n: t for n, t in text.items()}
            else:
                files = {targets[f] / n: t for n, t in text.items()}
                targets[f].mkdir()  # fails if it exists: never overwrite
                made.append(targets[f])
            for path, body in files.items():
                binary = isinstance(body, bytes)
                with open(path, "xb" if binary else "x", **({} if binary else {"encoding": "utf-8"})) as fh:
                    made.append(path)  # "x": never overwrite, even in a race
                    fh.write(body)
    except OSError as exc:  # a folder that cannot be made or written: one line, none of this call's files left
        for path in reversed(made):
            path.rmdir() if path.is_dir() else path.unlink(missing_ok=True)
        raise ModelError(f"export.output_dir: cannot write {exc.filename or out_dir}: {exc.strerror or exc}") from None
    print(f"# physmend export — proposal {run_id}, model {name}: {', '.join(corrected)} corrected")
    for f in formats:
        print(f"  {f:7s} {targets[f]}" + (f" + {targets[f].name.replace('.json', '.safetensors')}" if f == "network" else ""))
    if "petab" in formats:
        print(f"PEtab: {targets['petab'] / 'problem.yaml'} (e.g. amici.petab or PEtab.jl; a recorded input is a "
              "piecewise-linear SBML rule per experiment, picked by its condition)")
    if "python" in formats:
        print(f"use: import {base}; scipy.integrate.solve_ivp(lambda t, x: {base}.rhs(t, x, inputs(t)), "
              f"(t0, t1), {base}.initial_state())")
    return run_id

"""A proposal's corrected model as files the engineer can use elsewhere (the export stage's work).

One text per format: a standalone LaTeX document, sympy expressions, a plain Python module, the
correcting network and a PEtab problem (:mod:`physmend.modeling.export`,
:mod:`physmend.modeling.latex`, :mod:`physmend.modeling.petab`, :mod:`physmend.ude.network_file`);
every text is made before any file is written, and a file is never overwritten.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch


def formats(value: Any) -> list[str]:
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


def constant_info(sm: Any, corrections: list[Any], terms: dict[str, Any], values: dict[str, float],
                  stderr: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each correction constant of the model ``sm`` (parameter name ->) ``state``, ``name``,
    ``value`` (``values``), ``unit`` (from the term's unit where the constant enters linearly, else
    ``""``) and, where ``stderr`` (the symbolic run's ``uncertainty.json``) has one, ``stderr``."""
    from physmend.modeling.constant_units import constant_unit

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


def correction_constants(sm: Any, corrections: list[Any]) -> dict[str, float]:
    """The value of each correction constant of the model ``sm`` (a parameter ``<state>_<name>``)."""
    return {p.name: float(p.value) for p in sm.parameters
            if any(p.name.startswith(f"{c.state}_") and p.name[len(c.state) + 1:] in c.constants for c in corrections)}


def experiment_settings(problem: Any) -> dict[str, dict[str, Any]]:
    """Per experiment: its role, its initial states as the simulations take them (the start
    expressions, then the data's) and the parameters it sets other than the declared values."""
    sm = problem.model
    declared = np.array([float(v.value) for v in sm.parameters])
    experiments = {}
    for e in problem.experiments:  # initial states as the simulations take them: the start expressions, then the data's
        start = problem.compiled.start(torch.as_tensor(np.asarray(e.parameters, dtype=np.float64))).tolist()
        initial = {**dict(zip(sm.state_names, start)), **{n: float(v) for n, v in (e.initial or {}).items()}}
        experiments[e.id] = {"role": e.role, "initial": initial,
                             "parameters": {n: float(v) for n, v, d in zip(sm.parameter_names, e.parameters, declared) if v != d}}
    return experiments


def petab_texts(problem: Any, experiments: dict[str, dict[str, Any]], constants: dict[str, float]) -> dict[str, str]:
    """The PEtab problem's files (name -> text): the records, the declared-uncertain parameters and
    the correction constants estimated, each output's noise the median of the records' estimates."""
    from physmend.explain.residuals import noise_floor
    from physmend.modeling.petab import petab_files

    sm = problem.model
    records = [{**experiments[e.id], "id": e.id, "obs_time": e.obs_time, "obs": e.obs,
                "inputs": {n: (c.time, c.values) for n, c in e.inputs.items()}} for e in problem.experiments]
    estimated = {v.name: tuple(map(float, v.bounds)) for v in sm.parameters if v.uncertain and v.bounds}
    estimated |= {n: (-10 * abs(v) or -1.0, 10 * abs(v) or 1.0) for n, v in constants.items()}
    sigmas = {}
    for j, out in enumerate(sm.outputs):  # each output's noise: the median over the records' estimates
        found = [noise_floor(np.asarray(e.obs_time), np.asarray(e.obs)[:, j]) for e in problem.experiments]
        found = [v for v in found if np.isfinite(v) and v > 0]
        sigmas[out] = float(np.median(found)) if found else 1.0
    return petab_files(sm, records, estimated, sigmas)


def corrected_model_texts(problem: Any, corrections: list[Any], chosen: list[str], info: dict[str, Any],
                          stderr: dict[str, Any], network: Callable[[], Any], *, every: bool) -> dict[str, Any]:
    """The text of each format of ``chosen`` (``network()``: the correcting network's files, loaded
    only where needed); with ``every`` (``export.format=all``) a network that cannot be loaded is
    left out with one line. Format -> a text, or file name -> text for the network and PEtab."""
    from physmend.modeling.export import python_module, sympy_json
    from physmend.modeling.latex import found_terms, latex_document

    sm = problem.model
    corrected = [c.state for c in corrections]
    constants = correction_constants(sm, corrections)
    terms = found_terms(sm, corrections)
    const_info = constant_info(sm, corrections, terms, constants, stderr)
    experiments = experiment_settings(problem)
    texts = {"latex": lambda: latex_document(sm, terms, const_info, info),
             "sympy": lambda: sympy_json(sm, corrected, info, const_info),
             "python": lambda: python_module(sm, experiments, info),
             "network": network,
             "petab": lambda: petab_texts(problem, experiments, constants)}
    if every:  # every format this proposal allows: a network that cannot be loaded is left out
        try:
            network_files = network()
        except ValueError as exc:  # TrackingError, ModelError, DataError, ConfigError: one line naming the run
            print(f"network left out: {exc}")
            chosen = [f for f in chosen if f != "network"]
        else:
            texts["network"] = lambda: network_files
    return {f: texts[f]() for f in chosen}  # every text first: a failing writer leaves no file behind


def write_new(written: dict[str, Any], targets: dict[str, Path], out_dir: Path) -> None:
    """Write each format's text of ``written`` to its target (the network's two files and PEtab's
    folder of files beside the others), never over an existing file; where the folder cannot be
    made or written, none of this call's files is left and one line says why (:class:`ModelError`)."""
    from physmend.modeling.errors import ModelError

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


def report(run_id: str, name: str, corrected: list[str], written: list[str], targets: dict[str, Path], base: str) -> str:
    """What the export stage prints: the files written per format and how to use them."""
    lines = [f"# physmend export — proposal {run_id}, model {name}: {', '.join(corrected)} corrected"]
    for f in written:
        lines.append(f"  {f:7s} {targets[f]}" + (f" + {targets[f].name.replace('.json', '.safetensors')}" if f == "network" else ""))
    if "petab" in written:
        lines.append(f"PEtab: {targets['petab'] / 'problem.yaml'} (e.g. amici.petab or PEtab.jl; a recorded input is a "
                     "piecewise-linear SBML rule per experiment, picked by its condition)")
    if "python" in written:
        lines.append(f"use: import {base}; scipy.integrate.solve_ivp(lambda t, x: {base}.rhs(t, x, inputs(t)), "
                     f"(t0, t1), {base}.initial_state())")
    return "\n".join(lines)

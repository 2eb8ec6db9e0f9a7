"""Corrections: discovered terms added to the equations of the components where they act.

A corrections file (YAML, written by ``physmend accept``) lists terms; each is added to the
right-hand side of the equation that defines one state's derivative, so a corrected model reads
like the original (``C·der(T) = port.Q_flow + Δ``). The term's constants become model parameters
named ``<state>_<name>`` so they can be estimated and reported with units.

Example file::

    physmend_corrections: 1
    model: cargo_box
    source_run_id: 3f2c…
    corrections:
      - state: zone1.air.T
        term: "c1*(zone2.air.T - zone1.air.T)*sqrt(Abs(zone2.air.T - zone1.air.T))"
        unit: W
        constants: {c1: 1.02}
    parameters: {walls.UA: 41.3}   # optional: declared-uncertain parameters re-calibrated with the terms

``parameters`` holds new values of parameters the model declares uncertain (within their declared
bounds): the symbolic stage re-fits them together with the terms' constants, because a model
calibrated without the missing term (a stiffness fitted by a linear model, a conductance that
carried a radiation loss) keeps values that only fit without it. Any other parameter is refused.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import sympy as sp
import yaml

from physmend.modeling.errors import ModelError
from physmend.modeling.safe_parse import MAX_LENGTH, quoted
from physmend.modeling.expressions import parse_expression
from physmend.modeling.model import Equation, Model, der_name

FORMAT = 1


@dataclass
class Correction:
    """One term ``term`` (in model variable names and constant names) added to ``state``'s equation."""

    state: str
    term: str
    constants: dict[str, float] = field(default_factory=dict)
    unit: str = ""
    mechanism: str = ""

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"state": self.state, "term": self.term, "constants": dict(self.constants)}
        if self.unit:
            out["unit"] = self.unit
        if self.mechanism:
            out["mechanism"] = self.mechanism
        return out


def constant_parameter_name(owner: str, state: str, constant: str) -> str:
    """The model parameter holding ``constant`` of the correction of ``state`` (unique per state)."""
    return f"{state}_{constant}"


def apply_corrections(
    model: Model, corrections: list[Correction], *, where: str = "corrections", estimate: bool = False,
    parameters: Mapping[str, float] | None = None,
) -> Model:
    """A copy of ``model`` with each correction added to its state's defining equation.

    ``estimate=True`` declares the constants uncertain (bounds: same sign, a factor 20 either
    way) so that training can re-fit them through the simulator. ``parameters``: new values of
    parameters ``model`` declares uncertain (each within its declared bounds; see the module).
    """
    out = copy.deepcopy(model)
    for name, value in (parameters or {}).items():
        var = out.variables.get(name)
        if var is None or var.kind != "parameter" or not var.uncertain:
            raise ModelError(f"{where}: parameters.{quoted(str(name), 60)} must name a parameter that model "
                             f"{out.name!r} declares uncertain (its re-calibrated value), but it does not")
        lo, hi = var.bounds or (-math.inf, math.inf)
        if not (math.isfinite(value) and lo <= value <= hi):
            raise ModelError(f"{where}: parameters.{name} must be a finite number within its declared bounds "
                             f"[{lo:g}, {hi:g}], but is {value!r}")
        out.variables[name] = dataclasses.replace(var, value=float(value))
    by_name = {v.name: v.symbol for v in out.variables.values()}
    for k, corr in enumerate(corrections):
        label = f"{where}: correction {k + 1} ({corr.state})"
        var = out.variables.get(corr.state)
        if var is None or var.kind != "state":
            raise ModelError(f"{label}: {corr.state!r} is not a state of model {out.name!r}")
        der = out.der(var.symbol)
        idx = [i for i, eq in enumerate(out.equations) if der in eq.residual.free_symbols]
        if len(idx) != 1:
            raise ModelError(
                f"{label}: der({corr.state}) must appear in exactly one equation of model {out.name!r}, "
                f"but appears in {len(idx)}"
            )
        eq = out.equations[idx[0]]
        owner = eq.owner or corr.state.rsplit(".", 1)[0]
        consts: dict[str, sp.Symbol] = {}
        for cname, value in corr.constants.items():
            pname = constant_parameter_name(owner, corr.state, cname)
            if pname in out.variables:
                consts[cname] = out.variables[pname].symbol
                continue
            value = float(value)
            bounds = None
            if estimate:
                lo, hi = (value / 20, value * 20) if value > 0 else (value * 20, value / 20) if value < 0 else (-1.0, 1.0)
                bounds = (lo, hi)
            consts[cname] = out.parameter(
                pname, value, description=f"constant of the correction of {corr.state}", uncertain=estimate, bounds=bounds
            )
        term = parse_expression(corr.term, {**by_name, **consts}, where=f"{label}: term")
        if any(s.name.startswith("der(") or s.name == der_name(corr.state) for s in term.free_symbols):
            raise ModelError(f"{label}: a correction may not contain derivatives")
        out.equations[idx[0]] = Equation(eq.lhs, eq.rhs + term, owner=eq.owner, label=(eq.label or owner) + " + correction")
    return out


def read_corrections(path: str | Path) -> tuple[list[Correction], dict[str, Any]]:
    """Read a corrections file; returns the corrections and the file's other keys (model, run ID …)."""
    from physmend.modeling.safe_yaml import load_bounded

    path = Path(path).expanduser()
    if not path.is_file():
        raise ModelError(f"model.corrections: file {str(path)!r} does not exist")
    data = load_bounded(path, ModelError, where=f"model.corrections: {path}")
    if not isinstance(data, Mapping) or data.get("physmend_corrections") != FORMAT:
        raise ModelError(f"model.corrections: {path} must be a physmend corrections file (physmend_corrections: {FORMAT})")
    items = data.get("corrections")
    if not isinstance(items, list) or not items:
        raise ModelError(f"model.corrections: {path} needs a non-empty list under 'corrections'")
    out = []
    for k, item in enumerate(items):
        if not isinstance(item, Mapping) or "state" not in item or "term" not in item:
            raise ModelError(f"model.corrections: {path}: corrections[{k}] needs keys 'state' and 'term'")
        for key in ("state", "term"):
            if not isinstance(item[key], (str, int, float)) or isinstance(item[key], bool):
                raise ModelError(f"model.corrections: {path}: corrections[{k}].{key} must be text, but is a "
                                 f"{type(item[key]).__name__}")
            if len(str(item[key])) > MAX_LENGTH:
                raise ModelError(f"model.corrections: {path}: corrections[{k}].{key} may have at most {MAX_LENGTH} "
                                 f"characters, but has {len(str(item[key]))}")
        constants = item.get("constants") or {}
        if not isinstance(constants, Mapping):
            raise ModelError(f"model.corrections: {path}: corrections[{k}].constants must be a mapping name: number")
        values: dict[str, float] = {}
        for c, v in constants.items():
            try:
                values[str(c)[:200]] = float(v)
            except (TypeError, ValueError):
                raise ModelError(f"model.corrections: {path}: corrections[{k}].constants.{quoted(str(c), 40)} must be "
                                 f"a number, but is {quoted(str(v), 40)}") from None
        out.append(
            Correction(
                state=str(item["state"]),
                term=str(item["term"]),
                constants=values,
                unit=str(item.get("unit", "")),
                mechanism=str(item.get("mechanism", "")),
            )
        )
    meta = {k: v for k, v in data.items() if k != "corrections"}
    meta["parameters"] = _parameters(data.get("parameters"), path)
    return out, meta


def _parameters(raw: Any, path: Path) -> dict[str, float]:
    """The file's ``parameters`` (name -> number; checked against the model by :func:`apply_corrections`)."""
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise ModelError(f"model.corrections: {path}: parameters must be a mapping name: number, but is a "
                         f"{type(raw).__name__}")
    out: dict[str, float] = {}
    for name, value in raw.items():
        try:
            if isinstance(value, bool):
                raise TypeError
            out[str(name)[:200]] = float(value)
        except (TypeError, ValueError):
            raise ModelError(f"model.corrections: {path}: parameters.{quoted(str(name), 40)} must be a number, "
                             f"but is {quoted(str(value), 40)}") from None
    return out


def write_corrections(path: str | Path, corrections: list[Correction], *, parameters: Mapping[str, float] | None = None,
                      **meta: Any) -> Path:
    """Write a corrections file (never overwrites an existing file); ``parameters``: re-calibrated
    values of declared-uncertain parameters (written only where there are any)."""
    path = Path(path).expanduser()
    if path.exists():
        raise ModelError(f"corrections file {str(path)!r} exists already; physmend never overwrites it")
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"physmend_corrections": FORMAT, **meta, "corrections": [c.to_dict() for c in corrections]}
    if parameters:
        data["parameters"] = {str(k): float(v) for k, v in parameters.items()}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path

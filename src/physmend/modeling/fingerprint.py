"""A model's fingerprint: what a run was made with, compared when a later stage loads that run.

Two hashes (SHA-256, hex): ``structure`` — the model as built (every variable with its kind, unit,
start, value, bounds; every equation as written with its owner; outputs; connections), written
canonically so that the same model built twice hashes alike; ``source`` — the bytes of the file
that defines the builder. A stage records both on its run (tags, plus the structure as text); a
stage that loads a run compares them with the model the *user's own* configuration builds now
(see :mod:`physmend.tracking.fingerprint`). Nothing here imports or evaluates anything a store holds.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import sympy as sp

if TYPE_CHECKING:
    from physmend.modeling.model import Model


@dataclass(frozen=True)
class Fingerprint:
    """``structure``: SHA-256 of :attr:`text`; ``source``: SHA-256 of the builder's file ("" when unknown)."""

    structure: str
    source: str
    text: str


def _expr(e: Any) -> str:
    return "" if e is None else sp.srepr(e)


def structure_text(model: Model) -> str:
    """The model as canonical text, one line per declaration (sorted where order carries no meaning)."""
    lines = [f"model {model.name}"]
    for name in sorted(model.variables):
        v = model.variables[name]
        lines.append(json.dumps(["var", v.name, v.kind, v.unit, _expr(v.start), v.value, v.uncertain,
                                 list(v.bounds) if v.bounds else None]))
    for eq in model.equations:  # as written, in order: the order names the equations
        lines.append(json.dumps(["eq", eq.owner, _expr(eq.lhs), _expr(eq.rhs)]))
    for name in sorted(model.outputs):
        lines.append(json.dumps(["out", name, _expr(model.outputs[name].expr), model.outputs[name].unit]))
    for group in sorted(tuple(sorted(c)) for c in model.connections):
        lines.append(json.dumps(["connect", list(group)]))
    return "\n".join(lines) + "\n"


def source_file(builder: str) -> Path | None:
    """The file that defines ``builder`` (``path/file.py:fn`` or an imported ``package.module:fn``)."""
    where = builder.rsplit(":", 1)[0]
    if where.endswith(".py") or "/" in where or "\\" in where:
        path = Path(where).expanduser().resolve()
        return path if path.is_file() else None
    module = sys.modules.get(where)
    file = getattr(module, "__file__", None)
    return Path(file) if file and Path(file).is_file() else None


def fingerprint(model: Model, builder: str) -> Fingerprint:
    """The fingerprint of ``model`` as built by ``builder`` (before any corrections file)."""
    text = structure_text(model)
    path = source_file(builder)
    source = hashlib.sha256(path.read_bytes()).hexdigest() if path is not None else ""
    return Fingerprint(hashlib.sha256(text.encode()).hexdigest(), source, text)


#: fingerprints of the models built in this process, by builder and options (see :func:`known`)
_BUILT: dict[str, Fingerprint] = {}


def _plain(obj: Any) -> Any:
    from omegaconf import OmegaConf

    if OmegaConf.is_config(obj):
        return OmegaConf.to_container(obj, resolve=True)
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def _key(builder: str, options: Any) -> str:
    return json.dumps([str(builder), _plain(options or {})], sort_keys=True, default=str)


def remember(builder: str, options: Any, model: Model) -> Fingerprint:
    """Fingerprint ``model`` (just built by ``builder`` with ``options``) and keep it for :func:`known`."""
    found = fingerprint(model, builder)
    _BUILT[_key(builder, options)] = found
    return found


def known(builder: str, options: Any) -> Fingerprint | None:
    """The fingerprint of the model ``builder`` built with ``options`` in this process, if it did."""
    return _BUILT.get(_key(builder, options))


def difference(theirs: str, mine: str) -> str:
    """The first difference between two :func:`structure_text` texts, in words ("" when equal)."""

    def parse(text: str) -> tuple[dict[str, list[Any]], list[list[Any]], dict[str, list[Any]]]:
        variables: dict[str, list[Any]] = {}
        equations: list[list[Any]] = []
        outputs: dict[str, list[Any]] = {}
        for line in text.splitlines()[1:]:
            try:
                row = json.loads(line)  # data: JSON only, never evaluated
            except ValueError:
                continue
            if not isinstance(row, list) or not row:
                continue
            if row[0] == "var" and len(row) > 1:
                variables[str(row[1])] = row
            elif row[0] == "eq":
                equations.append(row)
            elif row[0] == "out" and len(row) > 1:
                outputs[str(row[1])] = row
        return variables, equations, outputs

    tv, te, to = parse(theirs)
    mv, me, mo = parse(mine)
    for name in sorted(set(tv) | set(mv)):
        if name not in mv:
            return f"the run's model has a variable {name!r} that yours lacks"
        if name not in tv:
            return f"your model has a variable {name!r} that the run's lacks"
        if tv[name] != mv[name]:
            return f"variable {name!r} is declared differently (kind, unit, start, value or bounds)"
    if len(te) != len(me):
        return f"the run's model has {len(te)} equations, yours {len(me)}"
    for i, (a, b) in enumerate(zip(te, me)):
        if a != b:
            owner = b[1] if len(b) > 1 and b[1] else "the model"
            return f"equation {i + 1} (of {owner}) is written differently"
    for name in sorted(set(to) | set(mo)):
        if to.get(name) != mo.get(name):
            return f"output {name!r} differs"
    return "" if theirs == mine else "the connections differ"

"""A run's ``model/hybrid.json`` and ``model/weights.pt`` read as data, checked before use.

A shared store holds what anyone with write access put there, so the files of a trained hybrid model
are checked against the user's own model *before* anything is built from them:

* ``hybrid.json`` at most :data:`MAX_JSON_BYTES`, valid JSON (nesting included), a ``spec`` object
  with exactly the keys of :class:`~physmend.ude.hybrid.HybridSpec`;
* every name list (``corrected``, ``in_states``, ``in_observed``, ``in_inputs``, ``in_parameters``,
  ``estimated``) names, once each, things of the model of the right kind;
* ``widths`` whole numbers within the configuration's bounds (``ude.width`` ≤
  :data:`~physmend.settings.MAX_UNITS`, ``ude.depth`` ≤ :data:`~physmend.settings.MAX_LAYERS`),
  so no network is allocated that would not fit in memory; ``activation`` and ``units`` known words;
* the normalisation and scales finite numbers, one per network input, output or state;
* ``weights.pt`` no larger than its network needs, read with ``weights_only`` (a pickle is never
  run), holding exactly the network's tensors in their shapes.

Each failure is one :class:`ArtifactError` line naming the file and key, what was expected and (at
most :data:`~physmend.modeling.safe_parse.QUOTE` characters of) what was found.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import torch

from physmend.settings import MAX_LAYERS, MAX_UNITS
from physmend.exceptions import PhysmendError
from physmend.modeling.safe_parse import QUOTE, quoted
from physmend.ude.hybrid import ACTIVATIONS, HybridSpec

SPEC_FILE = "model/hybrid.json"
WEIGHTS_FILE = "model/weights.pt"
#: the largest ``hybrid.json`` read (a spec holds a few numbers per state and network input)
MAX_JSON_BYTES = 4 * 2**20
#: ``weights.pt`` may exceed its tensors' bytes by this factor plus :data:`WEIGHTS_SLACK` (zip headers)
WEIGHTS_FACTOR = 2
WEIGHTS_SLACK = 2**20
UNITS = ("equation", "state")


class ArtifactError(PhysmendError, ValueError):
    """A run's model artifacts are missing or do not fit the model; the message names the file."""


def _shown(value: Any) -> str:
    """``repr(value)``, cut to about ``QUOTE`` characters (an error never echoes a whole file)."""
    text = repr(value)
    return text if len(text) <= QUOTE else f"{text[:QUOTE]}… ({len(text)} characters)"


def _fail(key: str, rule: str, value: Any) -> ArtifactError:
    return ArtifactError(f"{SPEC_FILE}: spec.{key} must be {rule}, but is {_shown(value)}")


def _names(spec: dict[str, Any], key: str, allowed: list[str], kind: str) -> None:
    """``spec[key]`` is a list of distinct names out of ``allowed`` (the model's ``kind``)."""
    value = spec[key]
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise _fail(key, f"a list of names of the model's {kind}", value)
    for name in value:
        if name not in allowed:
            some = ", ".join(n if len(n) <= 24 else n[:24] + "…" for n in allowed[:3])
            some += "…" if len(allowed) > 3 else ""
            raise ArtifactError(
                f"{SPEC_FILE}: spec.{key} names {quoted(name)}, none of the model's {kind} "
                f"({some or 'it has none'}): a run of another model")
        if value.count(name) > 1:
            raise ArtifactError(f"{SPEC_FILE}: spec.{key} names {quoted(name)} twice; each name must appear once")


def _numbers(spec: dict[str, Any], key: str, n: int, what: str, *, positive: bool = False,
             optional: bool = False, nulls: bool = False) -> None:
    """``spec[key]`` is a list of ``n`` finite numbers (> 0 with ``positive``; None allowed with
    ``nulls``; the empty list allowed with ``optional``)."""
    value = spec[key]
    rule = f"a list of {n} numbers{' > 0' if positive else ''}{' or nulls' if nulls else ''} ({what})"
    if optional:
        rule = f"empty or {rule}"
    if not isinstance(value, list) or (optional and not value):
        if isinstance(value, list):
            return
        raise _fail(key, rule, value)
    ok = len(value) == n and all(
        (v is None and nulls) or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                  and (v > 0 or not positive))
        for v in value)
    if not ok:
        raise _fail(key, rule, value)


def _widths(value: Any) -> None:
    """Hidden-layer widths within the configuration's bounds (checked before anything is allocated)."""
    rule = f"a list of at most {MAX_LAYERS} whole numbers from 1 to {MAX_UNITS} (ude.depth, ude.width)"
    if not isinstance(value, list) or len(value) > MAX_LAYERS or not all(
            isinstance(w, int) and not isinstance(w, bool) and 1 <= w <= MAX_UNITS for w in value):
        raise _fail("widths", rule, value)


def read_spec(path: str | Path, problem: Any) -> HybridSpec:
    """The :class:`HybridSpec` stored in ``path`` (a run's ``hybrid.json``), checked against
    ``problem``'s model (see the module docstring). Raises :class:`ArtifactError`."""
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_JSON_BYTES:
        raise ArtifactError(f"{SPEC_FILE} has {size} bytes; a hybrid model's description has at most "
                            f"{MAX_JSON_BYTES} (the file was not read)")
    try:
        meta = json.loads(path.read_bytes())
    except (ValueError, RecursionError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ArtifactError(f"{SPEC_FILE} is not valid JSON ({quoted(why)})") from None
    spec = meta.get("spec") if isinstance(meta, dict) else None
    if not isinstance(spec, dict):
        raise ArtifactError(f"{SPEC_FILE} must hold an object with a 'spec' object, but holds {_shown(meta)}")
    known = {f.name: f for f in fields(HybridSpec)}
    unknown = [k for k in spec if k not in known]
    if unknown:
        raise ArtifactError(f"{SPEC_FILE}: spec has the unknown key {quoted(str(unknown[0]))} "
                            f"(the keys are {', '.join(known)})")
    for name, f in known.items():
        if name not in spec and f.default is MISSING and f.default_factory is MISSING:
            raise ArtifactError(f"{SPEC_FILE}: spec.{name} is missing; a physmend trial writes it")
    spec = {name: spec[name] for name in known if name in spec}
    model, compiled = problem.model, problem.compiled
    states = list(compiled.state_names)
    uncertain = [v.name for v in model.parameters if v.uncertain and v.bounds is not None]
    for key, allowed, kind in (("corrected", states, "states"), ("in_states", states, "states"),
                               ("in_observed", list(compiled.observed_names), "observed variables"),
                               ("in_inputs", list(compiled.input_names), "inputs"),
                               ("in_parameters", list(compiled.parameter_names), "parameters"),
                               ("estimated", uncertain, "uncertain parameters")):
        if key in spec:
            _names(spec, key, allowed, kind)
    _widths(spec["widths"])
    if not isinstance(spec["activation"], str) or spec["activation"] not in ACTIVATIONS:
        raise _fail("activation", f"one of {', '.join(sorted(ACTIVATIONS))}", spec["activation"])
    if not isinstance(spec.get("units", "state"), str) or spec.get("units", "state") not in UNITS:
        raise _fail("units", "'equation' or 'state'", spec["units"])
    n_in = sum(len(spec[k]) for k in ("in_states", "in_observed", "in_inputs", "in_parameters"))
    n_out = len(spec["corrected"])
    _numbers(spec, "mean", n_in, "one per network input")
    _numbers(spec, "std", n_in, "one per network input", positive=True)
    _numbers(spec, "out_scale", n_out, "one per corrected state")
    for key in ("rate_scale", "state_low", "state_high"):
        if key in spec:
            n, what = (n_out, "one per corrected state") if key == "rate_scale" else (len(states), "one per state")
            _numbers(spec, key, n, what, optional=True, nulls=key != "rate_scale")
    low, high = spec.get("state_low") or [], spec.get("state_high") or []
    if len(low) != len(high) or any(a is not None and b is not None and a > b for a, b in zip(low, high)):
        raise ArtifactError(f"{SPEC_FILE}: spec.state_low and spec.state_high must be ranges of the same states "
                            f"(low ≤ high), but are {_shown(low)} and {_shown(high)}")
    return HybridSpec(**spec)


def read_weights(path: str | Path, expected: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The tensors stored in ``path`` (a run's ``weights.pt``), checked to be exactly ``expected``'s
    names and shapes (a network's ``state_dict()``). The file is read only when it is no larger than
    those tensors need, and with ``weights_only`` (a pickled object is refused, never run)."""
    path = Path(path)
    need = sum(t.numel() * t.element_size() for t in expected.values())
    size = path.stat().st_size
    if size > WEIGHTS_FACTOR * need + WEIGHTS_SLACK:
        raise ArtifactError(f"{WEIGHTS_FILE} has {size} bytes, but the network {SPEC_FILE} describes needs {need}; "
                            "the file was not read")
    try:
        with warnings.catch_warnings():  # torch warns about a pickle protocol before it refuses the file
            warnings.simplefilter("ignore")
            state = torch.load(path, weights_only=True, map_location="cpu")
    except Exception as exc:  # noqa: BLE001 - whatever the file is, it is not tensors only: one line
        raise ArtifactError(f"{WEIGHTS_FILE} is not a file of tensors only ({type(exc).__name__}): a pickled "
                            "object or a damaged file is refused, never run") from None
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise ArtifactError(f"{WEIGHTS_FILE} must map names to tensors, but holds {quoted(type(state).__name__)}")
    for name, tensor in expected.items():
        if name not in state:
            raise ArtifactError(f"{WEIGHTS_FILE}: the tensor {quoted(name)} of the network {SPEC_FILE} describes is missing")
        got = state[name]
        if tuple(got.shape) != tuple(tensor.shape) or got.is_floating_point() != tensor.is_floating_point():
            raise ArtifactError(f"{WEIGHTS_FILE}: the tensor {quoted(name)} has shape {tuple(got.shape)} "
                                f"({got.dtype}), but the network {SPEC_FILE} describes needs {tuple(tensor.shape)} "
                                f"({tensor.dtype})")
    extra = [k for k in state if k not in expected]
    if extra:
        raise ArtifactError(f"{WEIGHTS_FILE} holds the tensor {quoted(extra[0])}, which the network {SPEC_FILE} "
                            "describes does not have")
    return state

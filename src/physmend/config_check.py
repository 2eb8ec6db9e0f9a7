"""Settings checked when the configuration is composed, before any run or file is written.

Every group physmend ships (``train``, ``ude``, ``simulate``, ``sweep``, ``symbolic`` …) and the
top-level ``seed``, ``threads`` and ``device`` are typed (:data:`physmend.settings.TYPED`): each key
is checked by the rule of its field, and a number given as text (``"1e-5"``) becomes that number in
the configuration; a key a group does not know (in a user's own option file of a shipped group, or
added with ``+group.key=…``) is an error naming the keys it knows. The same rules hold where a stage
builds a group's settings (:func:`physmend.settings.group_settings`). Model, data and search-space
groups are the user's own and are checked where they are read.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from omegaconf import DictConfig, OmegaConf

from physmend.settings import TYPED, rule_of


def check_settings(cfg: DictConfig) -> None:
    """Check (and normalise: numbers given as text) every setting of a shipped group in ``cfg`` by
    the rules of its settings class, and the top-level ``seed``, ``threads`` and ``device``."""
    for group, cls in TYPED.items():
        if not group:
            _walk_typed(cfg, cls, "")
        elif group in cfg and isinstance(cfg[group], DictConfig):
            _walk_typed(cfg[group], cls, group)


def _raw(node: DictConfig, key: str) -> Any:
    return node._get_node(key)._value()  # noqa: SLF001 - the raw value, interpolations unresolved


def _walk_typed(node: DictConfig, cls: type, prefix: str) -> None:
    """``node``'s keys checked by the rules of settings class ``cls`` (nested groups by theirs), a key
    it does not know named with the keys it knows (the top level: only ``cls``'s keys are checked)."""
    if prefix:
        cls.check_keys(node.keys(), prefix)  # type: ignore[attr-defined]
    for f in dataclasses.fields(cls):
        key = f.name
        if key not in node:
            continue
        value = _raw(node, key)
        if isinstance(value, str) and "${" in value:
            continue  # an interpolation: checked where it is used
        name = f"{prefix}.{key}" if prefix else key
        rule = rule_of(cls, key)
        if rule is not None and rule.kind == "group":
            if isinstance(node[key], DictConfig):
                _walk_typed(node[key], cls.__pydantic_fields__[key].annotation, name)  # type: ignore[attr-defined]
            continue
        given = node[key]
        is_config = OmegaConf.is_config(given)
        checked = cls.check(key, OmegaConf.to_container(given, resolve=True) if is_config else given, name)  # type: ignore[attr-defined]
        if not is_config and not isinstance(checked, tuple) and checked is not given:
            node[key] = checked


# -- the operators config group (physmend.symbolic.operators prices and maps them) ----------------------
#: operator name -> (arity, what it is); the names every back end maps from
KNOWN: dict[str, tuple[int, str]] = {
    "add": (2, "a + b"),
    "sub": (2, "a - b"),
    "mul": (2, "a·b (products of states, inputs and parameters)"),
    "div": (2, "a / b (quotients)"),
    "square": (1, "a²"),
    "abs": (1, "|a|"),
    "sqrt": (1, "sqrt(|a|) (with mul: the signed power a·|a|^½)"),
    "sign": (1, "sign(a) (Coulomb friction, switching loads)"),
    "min": (2, "min(a, b) (saturation, clipping, thresholds)"),
    "max": (2, "max(a, b) (overflow, one-way flow)"),
    "exp": (1, "exp(a)"),
    "log": (1, "log(|a|)"),
    "tanh": (1, "tanh(a) (smooth saturation)"),
    "sin": (1, "sin(a) of a phase a (an angle: pendulums, cranks, rotating frames)"),
    "cos": (1, "cos(a) of a phase a (an angle)"),
    "pow": (2, "|a|^c, c a fitted exponent (power laws: turbulent drag, creep, flow curves)"),
}


class OperatorError(ValueError):
    """An operators file or setting is wrong; the message names the file and the entry."""


def check_operators(ops: Any, where: str) -> dict[str, int]:
    """``ops`` (a mapping name -> price) checked; ``where`` names the file or key for the message."""
    if ops is None:
        raise OperatorError(f"{where}: no operators given; list at least one, e.g. 'add: 1'")
    if not isinstance(ops, Mapping):
        raise OperatorError(f"{where} must map operator names to prices (e.g. 'mul: 1'), but got {type(ops).__name__}")
    out: dict[str, int] = {}
    for name, price in ops.items():
        name = str(name)
        if name not in KNOWN:
            raise OperatorError(f"{where}: unknown operator {name!r} (known: {', '.join(KNOWN)})")
        if price is None:
            continue  # listed and switched off ('sign: null')
        if isinstance(price, bool) or not isinstance(price, int) or price < 1:
            raise OperatorError(f"{where}: the price of {name!r} must be a whole number ≥ 1, but got {price!r}")
        out[name] = int(price)
    if not out:
        raise OperatorError(f"{where}: every operator is switched off; keep at least one (e.g. 'add: 1')")
    return out

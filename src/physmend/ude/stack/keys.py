"""What the models of one stack must share (:data:`SHARED_KEYS`): the settings that shape the common
solve, as :func:`stack_key` gives them, and the check that a stack's configurations agree.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any
import json

from omegaconf import DictConfig, OmegaConf

from physmend.ude.hybrid import UDEConfigError

#: Settings every model of one stack must share: they shape the common solve (or the problem).
SHARED_KEYS: tuple[str, ...] = (
    "model",
    "data",
    "simulate",
    "train.step",
    "train.segment_length",
    "train.segment_samples",
    "train.epochs",
    "train.restarts",
    "train.schedule",
    "train.eval_every",
    "train.patience",
    "train.patience_fit_gain",
    "train.continuity_weight",
    "train.estimate_parameters",
    "train.backward",
    "ude.corrected",
    "ude.inputs",
)

_LINEAR_KEY = "ude.depth == 0"  # a linear correction (no hidden layer) cannot be padded into an MLP

def _plain(value: Any) -> Any:
    """A hashable, comparable form of a config value (containers as canonical JSON)."""
    if isinstance(value, DictConfig) or OmegaConf.is_list(value):
        return json.dumps(OmegaConf.to_container(value, resolve=True), sort_keys=True)
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(value, sort_keys=True)
    return value


def stack_key(cfg: DictConfig, *, architecture: bool = False) -> tuple[tuple[str, Any], ...]:
    """The settings that must agree for configurations to train in one stack, as ``(key, value)`` pairs.

    Trials whose keys are equal can be passed together to :func:`train_stack`; they may differ in
    ``seed``, ``ude.width``, ``ude.depth`` (all ≥ 1, or all 0), ``ude.activation``,
    ``ude.output_scale``, ``train.lr``, ``train.weight_decay``, ``train.sparsity`` and the
    warm-start settings. ``architecture=True`` adds width, depth and activation to the key: stacks
    of one architecture need no padding, which pays where arithmetic, not dispatch, dominates.
    """
    pairs = [(key, _plain(OmegaConf.select(cfg, key, default=None))) for key in SHARED_KEYS]
    pairs.append((_LINEAR_KEY, int(cfg.ude.depth) == 0))
    if architecture:
        pairs += [(key, _plain(OmegaConf.select(cfg, key, default=None))) for key in ("ude.width", "ude.depth", "ude.activation")]
    return tuple(pairs)


def check_shared(cfgs: Sequence[DictConfig]) -> None:
    first = dict(stack_key(cfgs[0]))
    for i, cfg in enumerate(cfgs[1:], 1):
        for key, value in stack_key(cfg):
            if value != first[key]:
                raise UDEConfigError(
                    f"train_stack: every model of a stack must have the same `{key}` (it shapes the shared solve), "
                    f"but model 0 has {first[key]!r} and model {i} has {value!r}; group trials by stack_key()"
                )

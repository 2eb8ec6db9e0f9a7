"""``physmend sweep``: an Optuna study over UDE architectures and training settings, one MLflow child
run per trial under the sweep's parent run (see :mod:`physmend.sweep` for how it works and where).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from physmend.sweep import run_sweep

STAGE = "sweep"


def run(
    cfg: DictConfig,
    source_run_id: str | None = None,
    *,
    overrides: Sequence[str] | None = None,
    config_dir: str | Path | None = None,
    given_wins: bool = False,
    standby: Sequence[Any] = (),
    meanwhile: Callable[[], None] | None = None,
) -> str:
    """Run (or resume, or join as a worker) the sweep configured by ``cfg.sweep``; returns the parent run ID.

    :func:`physmend.sweep.run_sweep` does it all: what ``overrides``, ``config_dir``, ``given_wins``,
    ``standby`` and ``meanwhile`` mean, what is checked before any run is written, restarts, and Ctrl-C.
    """
    return run_sweep(cfg, source_run_id, overrides=overrides, config_dir=config_dir, given_wins=given_wins, standby=standby,
                     meanwhile=meanwhile)

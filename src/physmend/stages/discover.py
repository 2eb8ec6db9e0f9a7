"""``physmend discover``: every stage with default choices, end to end.

diagnose → sweep → mask → sensitivity → symbolic → propose; each stage's run ID feeds the next,
and each prints its finding. The proposal is left for the engineer to accept or reject.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf


SWEEP_KEYS = ("n_trials", "space", "group", "group_shapes", "budget", "max_trials", "workers")
"""``discover.<key>`` sets ``sweep.<key>`` unless the command line gives ``sweep.<key>`` itself."""


def _key(override: str) -> str:
    return override.split("=", 1)[0].lstrip("+~")


def _workers(setting: str | int, n_trials: int) -> int:
    """``discover.workers``: a count as given, or ``auto``: the CPUs this process may use, at most
    ``n_trials`` (the first trials; more processes would find nothing to run before the budget's decision)."""
    from physmend.cpus import usable_cpus

    return int(setting) if setting != "auto" else max(1, min(usable_cpus(), n_trials))


def sweep_settings(cfg: Any, overrides: Sequence[str] | None) -> Any:
    """A copy of ``cfg`` whose ``sweep.*`` keys are discover's (:data:`SWEEP_KEYS`) where the command
    line (``overrides``) does not give them; ``sweep.workers`` resolved to a count (:func:`run`).

    Raises:
        ConfigError: a ``discover.*`` setting breaks its rule (checked before any stage writes a run).
    """
    from physmend.config import ConfigError
    from physmend.settings import SettingError, group_settings

    try:
        dc = group_settings(cfg, "discover")
    except SettingError as exc:
        raise ConfigError(str(exc)) from None
    given = {_key(o) for o in overrides or ()}
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    chosen = {"n_trials": dc.n_trials, "space": dc.space, "group": dc.group, "group_shapes": dc.group_shapes,
              "budget": dc.budget, "max_trials": dc.max_trials}
    if "sweep.n_trials" in given and "sweep.budget" not in given:
        chosen["budget"] = None  # the user's count of trials is the count, not a minimum under discover's budget
    for key, value in chosen.items():
        if f"sweep.{key}" not in given:
            cfg.sweep[key] = value
    if "sweep.workers" not in given:
        cfg.sweep.workers = 1 if overrides is None else _workers(dc.workers, int(cfg.sweep.n_trials))
    return cfg


def _for_later_stages(cfg: Any) -> Callable[[], None]:
    """What the later stages will need that the sweep's idle time can prepare: the loop that
    simulates the kept network on all this process's threads compiled for the mask stage
    (:func:`physmend.ude.fixed_step.warm_shared`; 8 s on a fresh install), the symbolic back end's
    library imported (1.5 s without bytecode). Settings resolved now, while this process is not one
    of the sweep's workers."""
    from physmend.cpus import threads as thread_count
    from physmend.device import resolve_device
    from physmend.problem import dtype_of
    from physmend.settings import group_settings

    top = group_settings(cfg, "")
    count, dtype = thread_count(top.threads), dtype_of(cfg)
    on_cpu = resolve_device(top.device).type == "cpu"
    backend = str(group_settings(cfg, "symbolic").backend)

    def work() -> None:
        if on_cpu:
            from physmend.ude.fixed_step import warm_shared

            warm_shared(dtype, threads=count)
        from physmend.symbolic import prepare

        prepare(backend)

    return work


def run(cfg: Any, source_run_id: str | None = None, *, overrides: Sequence[str] | None = None,
        config_dir: str | Path | None = None) -> str:
    """Run the whole pipeline; returns the proposal's run ID.

    ``overrides``/``config_dir``: what ``cfg`` was composed from (the CLI passes them). The user's
    settings win: a ``sweep.*`` key on the command line is kept (``discover.*`` fills the rest; a
    ``sweep.n_trials`` given without ``sweep.budget`` is the number of trials, not a minimum), and
    a key the search space would search is left out of the search, said in one line.

    ``discover.workers: auto`` runs the sweep's first trials side by side, one process per CPU this
    process may use, at most ``sweep.n_trials`` of them. Without ``overrides`` (a direct call, not
    the command line nor :func:`physmend.discover`) the worker processes could not compose the
    configuration, so one process runs the trials in turn; with ``sweep.group: 1`` each trial
    trains alone either way, so the trials are the same.
    """
    from physmend.cpus import side_by_side
    from physmend.stages import diagnose, mask, propose, sensitivity, sweep, symbolic
    from physmend.sweep import hydra_value, standby
    from physmend.sweep.workers import worker_overrides

    cfg = sweep_settings(cfg, overrides)
    ids: list[tuple[str, str]] = []
    seconds: list[tuple[str, float]] = []
    banner = "\n" + "=" * 78 + "\n== physmend discover: {} \n" + "=" * 78
    clock = time.perf_counter()

    def stage(number: int, name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        if number > 1:
            seconds.append((ids[-1][0], now - clock))
        clock = now
        print(banner.format(f"{number}/6 {name}"))

    sweep_overrides = None
    given = {_key(o) for o in overrides or ()}
    if overrides is not None:
        sweep_overrides = [*overrides, *(f"sweep.{k}={hydra_value(cfg.sweep[k])}"
                                         for k in SWEEP_KEYS if f"sweep.{k}" not in given)]
    # the sweep's extra workers import, and prepare their first trial, while diagnose runs
    # (physmend.sweep.standby): this process works beside them from now on (threads: auto, its share)
    early = standby.start(int(cfg.sweep.workers) - 1) if sweep_overrides is not None else []
    if sweep_overrides is not None:
        standby.brief(early, worker_overrides(sweep_overrides), None if config_dir is None else str(config_dir))
    try:
        stage(1, "diagnose")
        with side_by_side(len(early) + 1):
            ids.append(("diagnose", diagnose.run(cfg, source_run_id)))
        stage(2, "sweep")
        sweep_id = sweep.run(cfg, ids[-1][1], overrides=sweep_overrides, config_dir=config_dir, given_wins=True,
                             standby=early, meanwhile=_for_later_stages(cfg))
    finally:
        standby.release(early)
    ids.append(("sweep", sweep_id))
    stage(3, "mask")
    ids.append(("mask", mask.run(cfg, None)))  # the sweep's selection
    stage(4, "sensitivity")
    ids.append(("sensitivity", sensitivity.run(cfg, ids[-1][1])))
    stage(5, "symbolic")
    ids.append(("symbolic", symbolic.run(cfg, ids[-1][1])))
    stage(6, "propose")
    ids.append(("propose", propose.run(cfg, ids[-1][1])))
    seconds.append(("propose", time.perf_counter() - clock))
    print("\nwall time per stage: " + ", ".join(f"{name} {s:.0f} s" for name, s in seconds)
          + f" (total {sum(s for _, s in seconds):.0f} s)")
    print("\nrun IDs: " + ", ".join(f"{s} {r}" for s, r in ids))
    print(f"accept the proposal: physmend accept {ids[-1][1]}   reject it: physmend reject {ids[-1][1]}")
    return ids[-1][1]

"""``physmend discover``: every stage with default choices, end to end.

diagnose → sweep → mask → sensitivity → symbolic → propose; each stage's run ID feeds the next,
and each prints its finding. The proposal is left for the engineer to accept or reject.
"""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """Run the whole pipeline; returns the proposal's run ID."""
    from physmend.config import ConfigError
    from physmend.stages import diagnose, mask, propose, sensitivity, sweep, symbolic

    shapes = cfg.discover.get("group_shapes", False)
    if not isinstance(shapes, bool):  # checked before any stage writes a run
        raise ConfigError(f"discover.group_shapes must be true or false, but got {shapes!r}")
    cfg = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    cfg.sweep.n_trials = int(cfg.discover.n_trials)
    cfg.sweep.space = str(cfg.discover.space)
    cfg.sweep.group = int(cfg.discover.get("group", 1))
    cfg.sweep.group_shapes = shapes
    ids: list[tuple[str, str]] = []
    banner = "\n" + "=" * 78 + "\n== physmend discover: {} \n" + "=" * 78
    print(banner.format("1/6 diagnose"))
    ids.append(("diagnose", diagnose.run(cfg, source_run_id)))
    print(banner.format("2/6 sweep"))
    sweep_id = sweep.run(cfg, ids[-1][1])
    ids.append(("sweep", sweep_id))
    print(banner.format("3/6 mask"))
    ids.append(("mask", mask.run(cfg, None)))  # the sweep's selection
    print(banner.format("4/6 sensitivity"))
    ids.append(("sensitivity", sensitivity.run(cfg, ids[-1][1])))
    print(banner.format("5/6 symbolic"))
    ids.append(("symbolic", symbolic.run(cfg, ids[-1][1])))
    print(banner.format("6/6 propose"))
    ids.append(("propose", propose.run(cfg, ids[-1][1])))
    print("\nrun IDs: " + ", ".join(f"{s} {r}" for s, r in ids))
    print(f"accept the proposal: physmend accept {ids[-1][1]}   reject it: physmend reject {ids[-1][1]}")
    return ids[-1][1]

"""``physmend accept RUN_ID`` / ``physmend reject RUN_ID``: the engineer's decision on a proposal.

Accept writes the proposal's corrections file (readable YAML with the source run ID) into
``decide.output_dir`` — never overwriting a file — and tags the run; the corrected model is then
loaded with ``model.corrections=<file>``. Reject only tags the run (with an optional reason).
Nothing else is changed: not the user's model files, not earlier runs.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

DECISION_TAG = "physmend.decision"
#: characters of a model name that do not go into a file name (a space, a quote, a separator …)
_NAME_UNSAFE = re.compile(r"[^\w.-]")


def _validate(cfg: Any, run_id: str, model_name: str, corrections: list[Any], parameters: dict[str, float]) -> None:
    """Parse the proposal's terms before anything is written or tagged: on your own model exactly as
    ``diagnose ++model.corrections=…`` will where your configuration builds the proposal's model;
    otherwise each term by the restricted parser alone (bounded: a term that cannot be read is refused)."""
    from omegaconf import OmegaConf

    from physmend.modeling import apply_corrections
    from physmend.modeling.loader import load_model
    from physmend.modeling.safe_parse import parse_safe

    builder = OmegaConf.select(cfg, "model.builder")
    mine = None
    if builder:
        try:
            mine = load_model(str(builder), dict(OmegaConf.select(cfg, "model.options") or {}))
        except Exception:  # noqa: BLE001 - not the proposal's model (or not buildable here): parse the terms alone
            mine = None
    if mine is not None and mine.name == model_name:
        apply_corrections(mine, corrections, where=f"proposal {run_id!r}: corrections.yaml", parameters=parameters)
        return
    for k, c in enumerate(corrections):
        parse_safe(c.term, where=f"proposal {run_id!r}: corrections.yaml, corrections[{k}].term", new_symbols=True)


def _proposal(cfg: Any, run_id: str | None) -> tuple[Any, Any]:
    from physmend.tracking import TrackingError, get_run, open_store

    if not run_id:
        raise TrackingError("accept/reject need the run ID of a proposal: physmend accept RUN_ID")
    store = open_store(cfg.tracking)
    run = get_run(store, run_id, stage="propose")
    if run.info.status != "FINISHED":
        raise TrackingError(f"proposal {run_id!r} did not finish (status {run.info.status})")
    done = run.data.tags.get(DECISION_TAG)
    if done:
        raise TrackingError(f"proposal {run_id!r} was already {done} by {run.data.tags.get('physmend.decided_by', '?')}")
    return store, run


def accept(cfg: Any, source_run_id: str | None = None) -> str:
    """Write the accepted corrections file and tag the proposal; returns the proposal's run ID."""
    from physmend.modeling import read_corrections, write_corrections
    from physmend.settings import group_settings
    from physmend.tracking import TrackingError, download_artifact
    from physmend.tracking.selection import os_user, utc_now

    store, run = _proposal(cfg, source_run_id)
    run_id = run.info.run_id
    corrections, meta = read_corrections(download_artifact(store, run_id, "corrections.yaml"))
    model_name = meta.get("model", "model")
    if not isinstance(model_name, str) or not model_name or any(c in model_name for c in "/\\\0") \
            or model_name.startswith(".") or len(model_name) > 100:
        from physmend.modeling.safe_parse import quoted

        raise TrackingError(f"proposal {run_id!r}: its corrections.yaml names the model {quoted(str(model_name), 60)}, "
                            "but a model name is a name of at most 100 characters, never a path; nothing written")
    _validate(cfg, run_id, model_name, corrections, meta["parameters"])
    out_dir = Path(group_settings(cfg, "decide").output_dir).expanduser()
    target = out_dir / f"{_NAME_UNSAFE.sub('_', model_name)}-{run_id[:8]}.yaml"
    if target.resolve().parent != out_dir.resolve():
        raise TrackingError(f"proposal {run_id!r}: the corrections file would leave decide.output_dir; nothing written")
    path = write_corrections(target, corrections, parameters=meta["parameters"], model=model_name, source_run_id=run_id,
                             accepted_by=os_user(), accepted_at=utc_now())
    store.client.set_tag(run_id, DECISION_TAG, "accepted")
    store.client.set_tag(run_id, "physmend.decided_by", os_user())
    store.client.set_tag(run_id, "physmend.decided_at", utc_now())
    store.client.set_tag(run_id, "physmend.corrections_file", str(path.resolve()))
    print(f"accepted proposal {run_id}: corrections written to {path}")
    print(f"use the corrected model: physmend diagnose ++model.corrections={path}")
    return run_id


def reject(cfg: Any, source_run_id: str | None = None) -> str:
    """Tag the proposal as rejected (with ``decide.reason``); returns its run ID."""
    from physmend.settings import group_settings
    from physmend.tracking.selection import os_user, utc_now

    store, run = _proposal(cfg, source_run_id)
    run_id = run.info.run_id
    store.client.set_tag(run_id, DECISION_TAG, "rejected")
    store.client.set_tag(run_id, "physmend.decided_by", os_user())
    store.client.set_tag(run_id, "physmend.decided_at", utc_now())
    reason = group_settings(cfg, "decide").reason
    if reason:
        store.client.set_tag(run_id, "physmend.reject_reason", reason)
    print(f"rejected proposal {run_id}; your model is unchanged")
    return run_id

"""``physmend runs`` and ``physmend select``: list sweeps, trials and stage runs; choose a trial.

``runs`` marks the current selection of each sweep with ``*`` and its automatic best with ``+``;
``select RUN_ID`` records a person's choice on the trial's sweep run (tags only: see
:mod:`physmend.tracking.selection`).
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

from physmend.redact import redact
from physmend.tracking import STAGE_TAG, SOURCE_TAG, TrackingError, get_run, open_store
from physmend.tracking import selection as sel

if TYPE_CHECKING:
    from physmend.tracking import Store

_PARAM_WIDTH = 10


def _iso(ms: int | None) -> str | None:
    import datetime as dt

    if not ms:
        return None
    return dt.datetime.fromtimestamp(ms / 1000, dt.timezone.utc).isoformat(timespec="seconds")


def _trial_row(run: Any, selected: str | None, best: str | None) -> dict[str, Any]:
    metrics = run.data.metrics
    return {
        "run_id": run.info.run_id,
        "number": int(run.data.tags.get(sel.TRIAL_NUMBER_TAG, "-1")),
        "state": sel.trial_state(run),
        "status": run.info.status,
        "val_rmse": metrics.get("val.rmse"),
        "params": dict(sorted(run.data.params.items())),
        "error": run.data.tags.get("physmend.error"),
        "selected": run.info.run_id == selected,
        "best": run.info.run_id == best,
    }


def _sweep_row(store: "Store", run: Any, current: str | None) -> dict[str, Any]:
    tags = run.data.tags
    selected, best = tags.get(sel.SELECTED_TAG), tags.get(sel.BEST_TAG)
    trials = [_trial_row(r, selected, best) for r in sel.trial_runs(store, run.info.run_id)]
    return {
        "run_id": run.info.run_id,
        "study": tags.get(sel.STUDY_TAG),
        "space": tags.get(sel.SPACE_TAG),
        "status": run.info.status,
        "started": _iso(run.info.start_time),
        "source_run_id": tags.get(SOURCE_TAG) or None,
        "n_trials": int(tags["physmend.n_trials"]) if tags.get("physmend.n_trials", "").isdigit() else None,
        "best_run_id": best,
        "selected_run_id": selected,
        "selected_by": tags.get(sel.SELECTED_BY_TAG),
        "selected_at": tags.get(sel.SELECTED_AT_TAG),
        "current": selected is not None and selected == current,
        "trials": trials,
    }


def _stage_row(run: Any) -> dict[str, Any]:
    return {
        "run_id": run.info.run_id,
        "stage": run.data.tags.get(STAGE_TAG),
        "name": run.info.run_name,
        "status": run.info.status,
        "started": _iso(run.info.start_time),
        "source_run_id": run.data.tags.get(SOURCE_TAG) or None,
    }


def collect(store: "Store", sweep_run_id: str | None = None) -> dict[str, Any]:
    """Sweeps (with their trials), other stage runs and the current selection, as plain data."""
    try:
        current: str | None = sel.current_selection(store)
    except TrackingError:
        current = None
    if sweep_run_id is not None:
        sweeps = [get_run(store, sweep_run_id, stage=sel.SWEEP_STAGE)]
        stages: list[Any] = []
    else:
        sweeps = sel.sweep_runs(store)
        others = sel.search_all(store, f"tags.`{STAGE_TAG}` != '{sel.TRIAL_STAGE}'", ["attributes.start_time ASC"])
        stages = [r for r in others if r.data.tags.get(STAGE_TAG) not in (None, sel.SWEEP_STAGE)]
    return {
        "store": redact(store.uri),
        "experiment": store.experiment_name,
        "current_selection": current,
        "sweeps": [_sweep_row(store, r, current) for r in sweeps],
        "stage_runs": [_stage_row(r) for r in stages],
    }


def _fmt_value(value: float | None) -> str:
    return "-" if value is None else f"{value:.4g}"


def _short(text: str, width: int = _PARAM_WIDTH) -> str:
    return text if len(text) <= width else text[: width - 1] + "…"


def _value_text(text: str) -> str:
    """A logged parameter value for a listing: numbers to 4 significant digits, text shortened."""
    try:
        number = float(text)
    except ValueError:
        return _short(text)
    return text if text.lstrip("-").isdigit() else f"{number:.4g}"


def _params_text(params: dict[str, str], keys: list[str]) -> str:
    """``name=value`` for ``keys``; a key is shown by its last part unless that is ambiguous."""
    last = [k.rsplit(".", 1)[-1] for k in keys]
    names = {k: (n if last.count(n) == 1 else k) for k, n in zip(keys, last)}
    return "  ".join(f"{names[k]}={_value_text(params[k])}" for k in keys if k in params)


def format_listing(data: dict[str, Any]) -> str:
    """The human-readable listing of :func:`collect`'s data."""
    lines = [f"experiment {data['experiment']!r} in {data['store']}", ""]
    if not data["sweeps"]:
        lines += ["no sweeps yet: run `physmend sweep`", ""]
    for sw in data["sweeps"]:
        lines += _format_sweep(sw)
    if data["stage_runs"]:
        lines.append("stage runs:")
        for r in data["stage_runs"]:
            src = f"  source {r['source_run_id']}" if r["source_run_id"] else ""
            lines.append(f"  {r['stage']:<12} {r['run_id']}  {r['status']:<8}  {r['started']}{src}")
        lines.append("")
    current = data["current_selection"]
    if current:
        lines.append(f"current selection: {current}   (later stages use it unless given a run ID)")
    lines.append("next: physmend select RUN_ID   # choose another trial (a COMPLETE one)")
    return "\n".join(lines)


def _format_sweep(sw: dict[str, Any]) -> list[str]:
    trials = sw["trials"]
    states = [t["state"] for t in trials]
    counts = ", ".join(f"{states.count(s)} {s.lower()}" for s in ("COMPLETE", "PRUNED", "FAIL", "RUNNING") if s in states)
    head = f"sweep {sw['study']}  run {sw['run_id']}  {sw['status']}  started {sw['started']}"
    lines = [head, f"  space {sw['space']}; {len(trials)} trials ({counts or 'none'})"
             + (f"; source {sw['source_run_id']}" if sw["source_run_id"] else "")]
    if sw["selected_run_id"]:
        lines.append(f"  selected by {sw['selected_by']} at {sw['selected_at']}"
                     + ("  <- current selection" if sw["current"] else ""))
    keys = sorted({k for t in trials for k in t["params"]})
    lines.append(f"      {'trial':>5}  {'state':<8}  {'val.rmse':>9}  {'run ID':<32}  params")
    for t in trials:
        mark = ("*" if t["selected"] else " ") + ("+" if t["best"] else " ")
        lines.append(
            f"  {mark}  {t['number']:>5}  {t['state']:<8}  {_fmt_value(t['val_rmse']):>9}  {t['run_id']:<32}  "
            f"{_params_text(t['params'], keys)}"
        )
        if t.get("error") and t["state"] == "FAIL":  # why it failed, one line (the full text: physmend runs --json)
            lines.append(f"         {' ' * 5}  failed: {' '.join(str(t['error']).split())[:160]}")
    lines += ["  (* selected, + automatic best: lowest val.rmse)", ""]
    return lines


def runs(cfg: Any, *, as_json: bool = False, sweep_run_id: str | None = None) -> dict[str, Any]:
    """``physmend runs``: print the listing (or JSON); returns the data."""
    store = open_store(cfg.tracking)
    data = collect(store, sweep_run_id)
    from physmend.redact import printable

    print(json.dumps(data, indent=2) if as_json else printable(format_listing(data)))
    return data


def run(cfg: Any, source_run_id: str | None = None) -> str:
    """``physmend select RUN_ID``: make the trial ``source_run_id`` the selection of its sweep; returns it."""
    if not source_run_id:
        raise TrackingError("select needs the run ID of a trial (`physmend runs` lists them)")
    store = open_store(cfg.tracking)
    choice = sel.select(store, source_run_id)
    trial = store.client.get_run(choice.run_id)
    number = trial.data.tags.get(sel.TRIAL_NUMBER_TAG, "?")
    val = trial.data.metrics.get("val.rmse")
    before = f" (was {choice.previous_run_id})" if choice.previous_run_id and choice.previous_run_id != choice.run_id else ""
    print(
        f"selected trial {number} (run {choice.run_id}, val.rmse {_fmt_value(val)}) of sweep run "
        f"{choice.sweep_run_id}{before}, by {choice.by} at {choice.at}\n"
        "next: physmend runs   # the listing marks it with *; later stages use it unless given a run ID"
    )
    return choice.run_id

"""Summaries of repeated runs and the plain-text table (times in s, memory in MiB, FLOPs in GFLOP)."""

from __future__ import annotations

import math
import statistics
from typing import Any


def _median(values: list[float]) -> float:
    vals = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return float(statistics.median(vals)) if vals else float("nan")


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median figures over repeats; a run that did not reach the target counts as ``inf`` time.

    ``time_lower_s``: median of each run's time to target, a run that did not reach it counting
    with its wall time (a lower bound of its time to target).
    """
    reached = [r for r in runs if r.get("status") == "reached"]
    times = [r["wall_s"] if r.get("status") == "reached" else math.inf for r in runs]
    flops = next((r for r in runs if "flops_per_epoch" in r and "rows_source" in r), {})
    return {
        "runs": len(runs),
        "reached": len(reached),
        "statuses": [r.get("status", "?") for r in runs],
        "time_s": float(statistics.median(times)) if times else float("nan"),
        "time_excl_eval_s": float(statistics.median(
            [r["wall_s"] - r.get("eval_total_s", math.nan) if r.get("status") == "reached" else math.inf for r in runs]))
        if runs else float("nan"),
        "time_lower_s": _median([r.get("wall_s", float("nan")) for r in runs]),
        "epochs": _median([float(r.get("epochs", float("nan"))) for r in runs]),
        "s_per_epoch": _median([r.get("s_per_epoch", float("nan")) for r in runs]),
        "train_s_per_epoch": _median([r.get("train_s_per_epoch", float("nan")) for r in runs]),
        "eval_s": _median([r.get("eval_s", float("nan")) for r in runs]),
        "compile_s": _median([r.get("compile_s", float("nan")) for r in runs]),
        "val_rmse_at_stop": _median([r.get("final_val_rmse", float("nan")) for r in runs]),
        "best_val_rmse": _median([min((h["val.rmse"] for h in r.get("history", [])), default=float("nan")) for r in runs]),
        "peak_rss_mib": _median([r.get("peak_rss_mib", float("nan")) for r in runs]),
        "rss_after_load_mib": _median([r.get("rss_after_load_mib", float("nan")) for r in runs]),
        "rows_per_epoch": flops.get("rows_per_epoch", float("nan")),
        "rows_source": flops.get("rows_source", ""),
        "rhs_flops": flops.get("rhs_flops", {}),
        "flops_per_epoch": flops.get("flops_per_epoch", float("nan")),
        "setup_flops": flops.get("setup_flops", float("nan")),
    }


def ratio(b: dict[str, Any], a: dict[str, Any]) -> dict[str, Any]:
    """``b/a`` of the median times to target; a bound (``<`` or ``>``) when one side did not reach it."""
    tb, ta = b["time_s"], a["time_s"]
    if math.isfinite(tb) and math.isfinite(ta):
        return {"kind": "=", "value": tb / ta}
    if math.isfinite(tb) and ta > 0 and math.isfinite(a["time_lower_s"]):
        return {"kind": "<", "value": tb / a["time_lower_s"]}
    if math.isfinite(ta) and math.isfinite(b["time_lower_s"]):
        return {"kind": ">", "value": b["time_lower_s"] / ta}
    return {"kind": "n/a", "value": float("nan")}


def _num(v: Any, fmt: str = "{:.3g}") -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return fmt.format(v)


def _time(s: dict[str, Any]) -> str:
    if not s:
        return "-"
    if math.isfinite(s["time_s"]):
        return f"{s['time_s']:.1f}"
    if all(st == "capped" for st in s["statuses"]):
        return f"> {s['time_lower_s']:.0f} (cap)"
    return f"not reached (>{s['time_lower_s']:.0f})"


def _excl(s: dict[str, Any]) -> str:
    if not s:
        return "-"
    v = s["time_excl_eval_s"]
    return f"{v:.1f}" if math.isfinite(v) else ("-" if math.isnan(v) else "n/r")


def _ratio_text(r: dict[str, Any] | None) -> str:
    if not r or r["kind"] == "n/a":
        return "n/a (neither reached the target)" if r else "n/a"
    sign = "" if r["kind"] == "=" else r["kind"] + " "
    speed = {"=": "", "<": "> ", ">": "< "}[r["kind"]]
    return f"{sign}{r['value']:.3g}  (speed-up {speed}{1 / r['value']:.3g}x)" if r["value"] > 0 else "n/a"


def _rows(rows: list[tuple[str, ...]], first: int = 38, width: int = 22) -> list[str]:
    """Aligned rows: a label ``first`` characters wide, then columns ``width`` wide."""
    return [(f"  {r[0]:<{first}}" + "".join(f"{c:<{width - 1}} " for c in r[1:])).rstrip() for r in rows]


def table(res: dict[str, Any]) -> str:
    """The whole report as aligned plain text."""
    m = res["machine"]
    lines = [f"physmend benchmark  {m['date']}  git {m['git']}",
             f"machine: {m['cpu']}, {m['cores']} cores ({m['cores_usable']} usable), torch {m['torch']}, "
             f"python {m['python']}, load avg {m['loadavg_1m']:.2f} at start"]
    if "ttacc" in res:
        lines += _ttacc_lines(res)
    if "sweep" in res:
        lines += _sweep_lines(res["sweep"])
    if "cli" in res:
        c = res["cli"]
        lines += ["", "command line", *_rows([(f"physmend -h, median of {len(c['runs_s'])} [s]", f"{c['median_s']:.3f}",
                                             f"(min {c['min_s']:.3f}, max {c['max_s']:.3f})")])]
    return "\n".join(lines)


def _ttacc_lines(res: dict[str, Any]) -> list[str]:
    t, p = res["ttacc"], res["problem"]
    a, b = t.get("baseline", {}).get("summary", {}), t.get("physmend", {}).get("summary", {})
    c = t.get("jax", {}).get("summary", {})
    n = res["noise"]
    lines = [
        "",
        f"time to accuracy: {p['name']} ({p['states']} states, {p['inputs']} inputs, {p['outputs']} outputs; "
        f"{p['train_experiments']} training experiments)",
        f"  noise floor (RMS of {len(n['per_series'])} series, training samples): {n['pooled']:.4g} {p['unit']}"
        f"  -> target val.rmse <= {res['target_rmse']:.4g} {p['unit']}  (val.rmse^2 <= 2 noise^2)",
        f"  evaluation every {t['eval_every']} epochs for both (physmend default {t['default_eval_every']}; patience "
        f"{t.get('physmend_patience', '-')} evals = same epochs); cap {t['cap_s']:.0f} s; median of {t['repeats']} repeat(s), "
        f"alternating a, b; {t.get('threads', 1)} thread(s) per method",
        "",
        f"  {'':<38}{'(a) torchdiffeq':<22}{'(b) physmend':<22}{'(c) JAX + diffrax' if c else ''}".rstrip(),
    ]

    def g(s: dict[str, Any], key: str, fmt: str = "{:.3g}", scale: float = 1.0) -> str:
        v = s.get(key, float("nan")) if s else float("nan")
        return _num(v * scale if isinstance(v, (int, float)) else v, fmt)

    def reached(s: dict[str, Any]) -> str:
        return f"{s.get('reached', 0)}/{s.get('runs', 0)}" if s else "-"

    def flops_row(s: dict[str, Any]) -> str:
        return _num((s.get("rhs_flops") or {}).get("total"), "{:d}") if s else "-"

    rows = [
        ("time to target [s]", _time(a), _time(b), _time(c)),
        ("  excl. evaluations [s]", _excl(a), _excl(b) + (" (est.)" if b and math.isfinite(b["time_excl_eval_s"]) else ""), _excl(c)),
        ("reached / runs", reached(a), reached(b), reached(c)),
        ("epochs (at stop)", g(a, "epochs", "{:.0f}"), g(b, "epochs", "{:.0f}"), g(c, "epochs", "{:.0f}")),
        ("wall per epoch, incl. eval [s]", g(a, "s_per_epoch"), g(b, "s_per_epoch"), g(c, "s_per_epoch")),
        ("train step per epoch [s]", g(a, "train_s_per_epoch"), g(b, "train_s_per_epoch"), g(c, "train_s_per_epoch")),
        ("one evaluation [s]", g(a, "eval_s"), g(b, "eval_s"), g(c, "eval_s")),
        ("RHS rows per epoch", g(a, "rows_per_epoch", "{:.4g}"), g(b, "rows_per_epoch", "{:.4g}"), g(c, "rows_per_epoch", "{:.4g}")),
        ("FLOPs per RHS row", flops_row(a), flops_row(b), flops_row(c)),
        ("GFLOP per epoch (est.)", g(a, "flops_per_epoch", "{:.3g}", 1e-9), g(b, "flops_per_epoch", "{:.3g}", 1e-9),
         g(c, "flops_per_epoch", "{:.3g}", 1e-9)),
        ("GFLOP/s achieved in the train step", _rate(a), _rate(b), _rate(c)),
        ("GFLOP one-off, before epoch 1 (est.)", "-" if not a else "0", g(b, "setup_flops", "{:.3g}", 1e-9), "-" if not c else "0"),
        ("one-off compilation [s]", "-", "-", g(c, "compile_s")),
        ("val.rmse at stop", g(a, "val_rmse_at_stop", "{:.4g}"), g(b, "val_rmse_at_stop", "{:.4g}"), g(c, "val_rmse_at_stop", "{:.4g}")),
        ("best val.rmse of the run", g(a, "best_val_rmse", "{:.4g}"), g(b, "best_val_rmse", "{:.4g}"), g(c, "best_val_rmse", "{:.4g}")),
        ("peak RSS [MiB]", g(a, "peak_rss_mib", "{:.0f}"), g(b, "peak_rss_mib", "{:.0f}"), g(c, "peak_rss_mib", "{:.0f}")),
        ("peak RSS after loading only [MiB]", g(a, "rss_after_load_mib", "{:.0f}"), g(b, "rss_after_load_mib", "{:.0f}"),
         g(c, "rss_after_load_mib", "{:.0f}")),
        ("run statuses", ",".join(a.get("statuses", [])) or "-", ",".join(b.get("statuses", [])) or "-",
         ",".join(c.get("statuses", [])) or "-"),
    ]
    if not c:
        rows = [r[:3] for r in rows]
    lines += _rows(rows)
    lines.append(f"  {'ratio b/a (time to target)':<38}{_ratio_text(t.get('ratio'))}")
    if c:
        lines.append(f"  {'ratio b/c (time to target)':<38}{_ratio_text(t.get('ratio_peer'))}")
        per = b.get("train_s_per_epoch", math.nan) / c.get("train_s_per_epoch", math.nan)
        lines.append(f"  {'ratio b/c (train step per epoch)':<38}{_num(per, '{:.3g}')}")
    return lines


def _rate(s: dict[str, Any]) -> str:
    """The FLOP estimate of one epoch over its measured train step (GFLOP/s): how close the step is
    to arithmetic-bound (one core of this machine does tens of GFLOP/s in float64 matmuls)."""
    if not s:
        return "-"
    step, flops = s.get("train_s_per_epoch", math.nan), s.get("flops_per_epoch", math.nan)
    return _num(flops * 1e-9 / step if step and step > 0 else math.nan, "{:.3g}")

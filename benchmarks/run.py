"""physmend benchmark harness: time to accuracy, sweep throughput, CLI start-up.

    .venv/bin/python benchmarks/run.py [--repeats 3] [--quick] [--out benchmarks/results.json]

Prints one plain-text table and writes every figure (and each run's evaluation history) as JSON.
See benchmarks/README.md for what each figure means. Each time-to-accuracy run is a fresh
subprocess (``--one baseline|physmend``) so that its peak memory is its own.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import DEFAULT_EVAL_EVERY, ROOT, Target, load, machine, peak_rss_mib  # noqa: E402
from _table import summarise, ratio, table  # noqa: E402

METHODS = ("baseline", "physmend", "jax")
PEER_PACKAGES = ("jax", "diffrax", "optax")
PARTS = ("ttacc", "sweep", "cli")
QUICK = {"repeats": 1, "cap": 60.0, "sweep_trials": 2, "sweep_epochs": 20}


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=3, help="time-to-accuracy repeats per method (median reported)")
    p.add_argument("--quick", action="store_true",
                   help=f"smoke test: {QUICK['repeats']} repeat, cap {QUICK['cap']:.0f} s, sweep of "
                        f"{QUICK['sweep_trials']} trials with train.epochs={QUICK['sweep_epochs']}")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results.json", help="JSON output file")
    p.add_argument("--cap", type=float, default=900.0, help="wall-clock cap per time-to-accuracy run (s)")
    p.add_argument("--eval-every", type=int, default=DEFAULT_EVAL_EVERY, help="epochs between evaluations (both methods)")
    p.add_argument("--seed", type=int, default=0, help="seed of repeat 0; repeat r uses seed + r (both methods)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help="comma-separated subset of baseline,physmend,jax (jax: pip install '.[bench]')")
    p.add_argument("--only", default=",".join(PARTS), help="comma-separated subset of ttacc,sweep,cli")
    p.add_argument("--override", action="append", default=[], metavar="KEY=VALUE",
                   help="physmend config override for both time-to-accuracy methods (repeatable)")
    p.add_argument("--sweep-trials", type=int, default=20, help="trials of the sweep")
    p.add_argument("--sweep-workers", type=int, default=1, help="sweep workers (sweep.workers if the config has it, else processes)")
    p.add_argument("--sweep-override", action="append", default=[], metavar="KEY=VALUE", help="extra sweep override (repeatable)")
    p.add_argument("--sweep-timeout", type=float, default=6 * 3600.0, help="kill the sweep after this long (s)")
    p.add_argument("--keep-sweep-dir", action="store_true", help="keep the sweep's temporary folder (path in the JSON)")
    p.add_argument("--cli-repeats", type=int, default=5, help="fresh `physmend -h` processes")
    p.add_argument("--render", type=Path, metavar="JSON", help="only print the table of an earlier results file")
    # internal: one time-to-accuracy run in this process
    p.add_argument("--one", choices=METHODS, help=argparse.SUPPRESS)
    p.add_argument("--noise", type=float, help=argparse.SUPPRESS)
    p.add_argument("--count-flops", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.quick:
        args.repeats, args.cap = QUICK["repeats"], min(args.cap, QUICK["cap"])
        args.sweep_trials = QUICK["sweep_trials"]
        args.sweep_override = [f"train.epochs={QUICK['sweep_epochs']}", *args.sweep_override]
    return args


# -- one run (child process) ---------------------------------------------------------------------
def one(args: argparse.Namespace) -> None:
    """Run one method once and write its result JSON to ``args.result``."""
    import _baseline
    import _jax
    import _trainer

    cfg, problem = load(args.override)
    target = Target(args.noise)
    rss_loaded = peak_rss_mib()
    module = {"baseline": _baseline, "physmend": _trainer, "jax": _jax}[args.one]
    res = module.run(cfg, problem, target, cap_s=args.cap, eval_every=args.eval_every, seed=args.seed)
    res["peak_rss_mib"], res["rss_after_load_mib"], res["seed"] = peak_rss_mib(), rss_loaded, args.seed
    if args.one == "physmend":
        res["eval_s"] = _trainer.eval_seconds(cfg, problem)
        res["eval_total_s"] = res["evaluations"] * res["eval_s"]  # estimate: a fresh hybrid's evaluation time
        # measured between optimiser steps (the estimate from callback times and a fresh hybrid's evaluation
        # counted the warm start and the slower evaluations of a trained hybrid in)
        res["train_s_per_epoch"] = res["step_s"]
        res["train_s_per_epoch_from_callbacks"] = _trainer.train_step_seconds(res["history"], res["eval_s"])
        if args.count_flops:
            res.update(_trainer.count_flops(cfg, problem))
    args.result.write_text(json.dumps(res, indent=1))


def spawn(method: str, args: argparse.Namespace, noise: float, seed: int, count_flops: bool, threads: int = 1) -> dict[str, Any]:
    """Run ``--one method`` in a fresh interpreter on ``threads`` threads (torch, BLAS and XLA alike: the
    configuration's ``threads``, resolved); its result, or why it has none."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "result.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--one", method, "--noise", repr(noise), "--seed", str(seed),
               "--cap", repr(args.cap), "--eval-every", str(args.eval_every), "--result", str(out)]
        cmd += [f"--override={o}" for o in args.override] + (["--count-flops"] if count_flops else [])
        from _jax import xla_flags

        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads), "XLA_FLAGS": xla_flags(threads)}
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.cap + 600)
        except subprocess.TimeoutExpired:
            return {"status": "killed", "wall_s": time.perf_counter() - t0}
        if proc.returncode != 0 or not out.exists():
            return {"status": f"crashed (exit {proc.returncode})", "wall_s": time.perf_counter() - t0, "stderr": proc.stderr[-3000:]}
        return json.loads(out.read_text())


# -- the harness (parent process) ----------------------------------------------------------------
def problem_facts(problem: Any) -> dict[str, Any]:
    """Sizes of the benchmark problem for the table."""
    m = problem.model
    units = {m.units.get(o, "") for o in m.output_names}
    return {"name": m.name, "states": len(m.state_names), "inputs": len(m.input_names), "outputs": len(m.output_names),
            "train_experiments": len(problem.by_role("train")), "unit": units.pop() if len(units) == 1 else "(scaled)"}


def time_to_accuracy(args: argparse.Namespace, res: dict[str, Any]) -> None:
    """Alternate the methods per repeat, each in a fresh process; summaries and the ratio into ``res``."""
    from _common import noise_floor
    from _trainer import with_eval_every

    cfg, problem = load(args.override)
    from physmend.cpus import threads as thread_count

    noise = noise_floor(problem)
    threads = thread_count(cfg.threads)  # every method on as many (the configuration's threads, resolved)
    target = Target(noise["pooled"])
    res.update(problem=problem_facts(problem), noise=noise, target_rmse=target.rmse)
    methods = [m for m in METHODS if m in args.methods.split(",")]
    missing = [name for name in PEER_PACKAGES if importlib.util.find_spec(name) is None]
    if "jax" in methods and missing:
        print(f"[ttacc] (c) JAX + diffrax left out: {', '.join(missing)} not installed (pip install '.[bench]')",
              file=sys.stderr, flush=True)
        methods.remove("jax")
    t = res["ttacc"] = {"repeats": args.repeats, "cap_s": args.cap, "eval_every": args.eval_every,
                        "default_eval_every": int(cfg.train.eval_every),
                        "physmend_patience": int(with_eval_every(cfg, args.eval_every).train.patience),
                        "overrides": args.override, "threads": threads, **{m: {"runs": []} for m in methods}}
    for r in range(args.repeats):
        for m in methods:
            print(f"[ttacc] repeat {r + 1}/{args.repeats}: {m} ...", file=sys.stderr, flush=True)
            run = spawn(m, args, noise["pooled"], args.seed + r, count_flops=r == 0, threads=threads)
            t[m]["runs"].append(run)
            print(f"[ttacc]   {run.get('status')} after {run.get('wall_s', float('nan')):.1f} s, "
                  f"epoch {run.get('epochs', '-')}, val.rmse {run.get('final_val_rmse', float('nan')):.4g}", file=sys.stderr, flush=True)
    summarise_ttacc(t)


def summarise_ttacc(t: dict[str, Any]) -> None:
    """Medians per method and the ratio b/a into the time-to-accuracy record ``t`` (from its runs)."""
    for m in METHODS:
        if m in t:
            t[m]["summary"] = summarise(t[m]["runs"])
    if "physmend" in t and "baseline" in t:
        t["ratio"] = ratio(t["physmend"]["summary"], t["baseline"]["summary"])
    if "physmend" in t and "jax" in t:
        t["ratio_peer"] = ratio(t["physmend"]["summary"], t["jax"]["summary"])


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    if args.one:
        one(args)
        return 0
    if args.render:
        res = _floats(json.loads(args.render.read_text()))
        if "ttacc" in res:
            summarise_ttacc(res["ttacc"])
        print(table(res))
        return 0
    parts = set(args.only.split(","))
    res: dict[str, Any] = {"machine": machine(), "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                                                          if k not in ("one", "noise", "count_flops", "result")}}
    if "ttacc" in parts:
        time_to_accuracy(args, res)
    if "sweep" in parts:
        import _sweep

        print(f"[sweep] {args.sweep_trials} trials ...", file=sys.stderr, flush=True)
        res["sweep"] = _sweep.run(args.sweep_trials, workers=args.sweep_workers, extra=args.sweep_override,
                                  keep=args.keep_sweep_dir, timeout_s=args.sweep_timeout)
        res["sweep"]["extra"] = args.sweep_override
    if "cli" in parts:
        import _cli

        res["cli"] = _cli.help_seconds(args.cli_repeats)
    res["machine"]["loadavg_1m_end"] = os.getloadavg()[0]
    text = table(res)
    res["table"] = text
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(_plain(res), indent=1, allow_nan=False))
    print(f"\nwrote {args.out}")
    return 0


def _floats(v: Any) -> Any:
    """Inverse of :func:`_plain` for rendering: null -> NaN, "inf"/"-inf" -> infinities."""
    if v is None:
        return float("nan")
    if v in ("inf", "-inf"):
        return float(v)
    if isinstance(v, dict):
        return {k: _floats(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_floats(x) for x in v]
    return v


def _plain(v: Any) -> Any:
    """``v`` as strict JSON: NaN becomes null, infinities the strings "inf"/"-inf", others str()."""
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    return str(v)


if __name__ == "__main__":
    sys.exit(main())

"""The proving suite: ``physmend discover`` with defaults on every example, scored against its truth.

For each ``examples/<name>/`` that has a ``truth.yaml``, this runs::

    physmend discover --config-dir examples/<name>/conf model=<name> data=<name>

in a fresh folder (its own ``mlflow.db`` and ``optuna.db``), with no other setting, and then scores
what the tool *did* — not what its report says — against the example's truth:

* **equations**: the equations the masked network corrects and those the formulas correct,
  against the truth's ``corrections`` keys;
* **formula R²**: each true term against the found formula for that equation, both evaluated along
  the noise-free truth trajectory of every held-out (test) experiment (``truth/<id>.csv``, the
  experiment's parameters from the data config). R² is centred (1 − SSE/SST) unless the true term
  is nearly constant (its spread below 5 % of its RMS), where it is 1 − SSE/Σ term²;
* **held-out RMSE** per measured output of the test experiments, simulated here from the model as
  written and the model plus the corrections the tool proposes (``corrections.yaml`` of the
  proposal), and the masked network's (the mask run's whole-trajectory metric); each against the
  example's stated sensor noise σ. An output passes when it improves ≥ 5× or ends ≤ 1.5 σ;
* **mechanism**: whether the proposal's report names one of the truth's ``mechanism`` keywords;
* **wall time** and **peak memory** (maximum resident set of the discover process).

Usage::

    python benchmarks/discovery.py                      # every example, one after the other
    python benchmarks/discovery.py --only oscillator    # some
    python benchmarks/discovery.py --rescore DIR        # score the folders of an earlier run again

Writes a table to stdout and JSON (``--json``, default ``benchmarks/discovery.json``).
Units: seconds, MiB; RMSE in each output's own unit.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
IMPROVEMENT = 5.0  # held-out RMSE must improve at least this much ...
NEAR_NOISE = 1.5  # ... or end within this factor of the sensor noise
FORMULA_R2 = 0.95
WALL_LIMIT_S = 600.0
MEMORY_LIMIT_MIB = 2048.0


@dataclass
class Score:
    """One example's result; RMSE values are per output, in the output's unit."""

    example: str
    ok_run: bool = False
    wall_s: float = float("nan")
    peak_mib: float = float("nan")
    error: str = ""
    true_equations: list[str] = field(default_factory=list)
    network_equations: list[str] = field(default_factory=list)
    formula_equations: list[str] = field(default_factory=list)
    formulas: dict[str, str] = field(default_factory=dict)
    formula_r2: dict[str, float] = field(default_factory=dict)
    noise: dict[str, float] = field(default_factory=dict)
    rmse_before: dict[str, float] = field(default_factory=dict)
    rmse_network: dict[str, float] = field(default_factory=dict)
    rmse_formula: dict[str, float] = field(default_factory=dict)
    mechanism_named: bool = False
    mechanism_text: str = ""

    def _outputs_pass(self, after: dict[str, float]) -> bool:
        if not self.rmse_before or set(after) != set(self.rmse_before):
            return False
        for key, before in self.rmse_before.items():
            out = key.split("/", 1)[1]
            a = after[key]
            if not math.isfinite(a) or not (before / a >= IMPROVEMENT or a <= NEAR_NOISE * self.noise.get(out, 0.0)):
                return False
        return True

    @property
    def network_ok(self) -> bool:
        """Issue "discovery on any model": right equations and the masked network good enough."""
        return (self.ok_run and set(self.network_equations) == set(self.true_equations)
                and self._outputs_pass(self.rmse_network) and self.wall_s <= WALL_LIMIT_S
                and self.peak_mib <= MEMORY_LIMIT_MIB)

    @property
    def formula_ok(self) -> bool:
        """Issue "symbolic regression on any model": right equations, formula, fit and mechanism."""
        return (self.ok_run and set(self.formula_equations) == set(self.true_equations)
                and all(self.formula_r2.get(s, -math.inf) >= FORMULA_R2 for s in self.true_equations)
                and self._outputs_pass(self.rmse_formula) and self.mechanism_named)


# -- running -------------------------------------------------------------------------------------
def examples(only: list[str] | None) -> list[Path]:
    found = sorted(p.parent for p in EXAMPLES.glob("*/truth.yaml"))
    if only:
        missing = sorted(set(only) - {p.name for p in found})
        if missing:
            raise SystemExit(f"--only names {missing}, but the examples with a truth.yaml are {[p.name for p in found]}")
        found = [p for p in found if p.name in only]
    return found


def physmend_exe() -> str:
    exe = Path(sys.executable).with_name("physmend")
    return str(exe) if exe.exists() else (shutil.which("physmend") or "physmend")


def run_discover(example: Path, folder: Path, timeout: float, extra: list[str]) -> tuple[int, float, float]:
    """Run discover in ``folder``; returns (exit status, wall s, peak RSS MiB of the process tree's main process)."""
    folder.mkdir(parents=True, exist_ok=True)
    cmd = [physmend_exe(), "discover", "--config-dir", str(example / "conf"), f"model={example.name}",
           f"data={example.name}", *extra]
    (folder / "command.txt").write_text(" ".join(cmd) + "\n")
    start = time.perf_counter()
    with open(folder / "discover.log", "w") as log:
        proc = subprocess.Popen(cmd, cwd=folder, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = start + timeout
        status, usage = None, None
        while status is None:
            pid, st, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                status, usage = os.waitstatus_to_exitcode(st), ru
                break
            if time.perf_counter() > deadline:
                os.killpg(proc.pid, 9)
                _, st, ru = os.wait4(proc.pid, 0)
                status, usage = 124, ru
                break
            time.sleep(0.5)
        proc.returncode = status
    wall = time.perf_counter() - start
    return int(status), wall, usage.ru_maxrss / 1024.0 if usage else float("nan")


# -- scoring -------------------------------------------------------------------------------------
def _run_ids(log: str) -> dict[str, str]:
    m = re.search(r"^run IDs: (.*)$", log, re.M)
    if not m:
        return {}
    return dict(part.strip().split(" ", 1) for part in m.group(1).split(","))


def _r2(found: np.ndarray, truth: np.ndarray) -> float:
    ok = np.isfinite(found) & np.isfinite(truth)
    f, t = found[ok], truth[ok]
    if t.size == 0:
        return float("nan")
    sse = float(np.sum((f - t) ** 2))
    rms = float(np.sqrt(np.mean(t**2)))
    spread = float(np.std(t))
    denom = float(np.sum((t - t.mean()) ** 2)) if spread > 0.05 * rms else float(np.sum(t**2))
    return 1.0 - sse / denom if denom > 0 else (1.0 if sse == 0 else -math.inf)


def _config(example: Path, corrections: Path | None = None) -> Any:
    from physmend.config import compose

    overrides = [f"model={example.name}", f"data={example.name}"]
    if corrections is not None:
        overrides.append(f"++model.corrections={corrections}")
    return compose(overrides, user_config_dir=example / "conf")


def _held_out_rmse(cfg: Any) -> dict[str, float]:
    """RMSE per test experiment and output (``"<id>/<output>"``) of ``cfg``'s model, simulated."""
    import torch

    from physmend.problem import load_problem
    from physmend.simulate import make_batch, simulate_batch

    problem = load_problem(cfg)
    test = [e for e in problem.experiments if e.role == "test"]
    batch = make_batch(test, problem.compiled, problem.dtype)
    with torch.no_grad():
        traj = simulate_batch(problem.compiled, batch, method=str(cfg.simulate.method), rtol=1e-6, atol=1e-8)
    out: dict[str, float] = {}
    for b, e in enumerate(test):
        for j, name in enumerate(problem.model.output_names):
            err = (traj.outputs[:, b, j] - batch.obs[:, b, j]).numpy()
            err = err[np.isfinite(err)]
            out[f"{e.id}/{name}"] = float(np.sqrt(np.mean(err**2))) if err.size else float("nan")
    return out


def _formula_values(term: str, constants: dict[str, float], frame: pd.DataFrame, params: dict[str, float]) -> np.ndarray:
    from physmend.modeling.evaluate import evaluate
    from physmend.modeling.expressions import parse_expression
    import sympy as sp

    names = [c for c in frame.columns if c != "time" and not c.startswith("term:")] + list(params)
    symbols = {n: sp.Symbol(n) for n in [*names, *constants]}
    expr = parse_expression(term, symbols, where="formula").subs({symbols[k]: v for k, v in constants.items()})
    columns = {c: frame[c].to_numpy(float) for c in frame.columns if c != "time" and not c.startswith("term:")}
    columns.update({k: np.full(len(frame), float(v)) for k, v in params.items()})
    return np.broadcast_to(np.asarray(evaluate(expr, columns, n=len(frame)), float), (len(frame),))


def _parameters(cfg: Any, exp_id: str) -> dict[str, float]:
    from physmend.modeling import load_model

    model = load_model(str(cfg.model.builder), cfg.model.get("options") or {})
    values = {v.name: float(v.value) for v in model.of_kind("parameter") if v.value is not None}
    for e in cfg.data.experiments:
        if str(e.id) == exp_id:
            values.update({str(k): float(v) for k, v in (e.get("parameters") or {}).items()})
    return values


def score(example: Path, folder: Path, score_: Score) -> Score:
    import mlflow
    from mlflow.tracking import MlflowClient

    truth = yaml.safe_load((example / "truth.yaml").read_text())
    score_.true_equations = sorted(truth["corrections"])
    score_.noise = {str(k): float(v) for k, v in truth.get("noise", {}).items()}
    ids = _run_ids((folder / "discover.log").read_text(errors="replace"))
    if not ids.get("propose"):
        score_.error = score_.error or "no proposal (see discover.log)"
        return score_
    mlflow.set_tracking_uri(f"sqlite:///{folder / 'mlflow.db'}")
    client = MlflowClient()
    mask = client.get_run(ids["mask"])
    score_.network_equations = sorted(s for s in mask.data.tags.get("physmend.kept", "").split(",") if s)
    work = Path(tempfile.mkdtemp(prefix="score-", dir=folder))
    corr_path = Path(client.download_artifacts(ids["propose"], "corrections.yaml", str(work)))
    report = Path(client.download_artifacts(ids["propose"], "report.md", str(work))).read_text()
    corrections = yaml.safe_load(corr_path.read_text())["corrections"]
    score_.formula_equations = sorted({c["state"] for c in corrections})
    cfg = _config(example)
    test_ids = [str(e.id) for e in cfg.data.experiments if e.role == "test"]
    for state in score_.true_equations:
        mine = [c for c in corrections if c["state"] == state]
        if not mine:
            continue
        score_.formulas[state] = " + ".join(c["term"] for c in mine)
        found, true = [], []
        for exp_id in test_ids:
            frame = pd.read_csv(example / "truth" / f"{exp_id}.csv")
            params = _parameters(cfg, exp_id)
            total = sum(_formula_values(c["term"], c.get("constants") or {}, frame, params) for c in mine)
            found.append(total)
            true.append(frame[f"term:{state}"].to_numpy(float))
        score_.formula_r2[state] = _r2(np.concatenate(found), np.concatenate(true))
    score_.rmse_before = _held_out_rmse(cfg)
    score_.rmse_formula = _held_out_rmse(_config(example, corr_path))
    metrics = mask.data.metrics
    score_.rmse_network = {k: float(metrics.get(f"rmse.{k.replace('/', '.', 1)}", float("nan"))) for k in score_.rmse_before}
    lines = [ln for ln in report.splitlines() if "mechanism" in ln.lower()]
    score_.mechanism_text = " | ".join(lines)[:500]
    words = [str(w).lower() for w in truth.get("mechanism", [])]
    named = " ".join(ln for ln in lines if "suggested mechanism" in ln.lower()).lower()
    score_.mechanism_named = any(w in named for w in words)
    return score_


# -- the table -----------------------------------------------------------------------------------
def _fmt_rmse(s: Score, after: dict[str, float]) -> str:
    parts = []
    for key, before in s.rmse_before.items():
        out = key.split("/", 1)[1]
        a = after.get(key, float("nan"))
        parts.append(f"{out}: {before:.3g}→{a:.3g} ({before / a if a else float('inf'):.1f}×, σ {s.noise.get(out, float('nan')):.2g})")
    return "; ".join(parts) or "-"


def table(scores: list[Score]) -> str:
    head = ("| example | wall [s] | peak [MiB] | true eq. | network eq. | formula eq. | formula R² | "
            "held-out RMSE network (before→after) | held-out RMSE formula | mechanism | network pass | formula pass |")
    rows = [head, "|" + "---|" * 12]
    for s in scores:
        r2 = ", ".join(f"{v:.3f}" for v in s.formula_r2.values()) or "-"
        rows.append(
            f"| {s.example} | {s.wall_s:.0f} | {s.peak_mib:.0f} | {', '.join(s.true_equations)} | "
            f"{', '.join(s.network_equations) or '-'} | {', '.join(s.formula_equations) or '-'} | {r2} | "
            f"{_fmt_rmse(s, s.rmse_network)} | {_fmt_rmse(s, s.rmse_formula)} | {'yes' if s.mechanism_named else 'no'} | "
            f"{'PASS' if s.network_ok else 'fail'} | {'PASS' if s.formula_ok else 'fail'} |"
            + (f" {s.error}" if s.error else "")
        )
    n = len(scores)
    rows.append(f"\nnetwork pass: {sum(s.network_ok for s in scores)}/{n}   formula pass: {sum(s.formula_ok for s in scores)}/{n}")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="example names (default: every example with a truth.yaml)")
    ap.add_argument("--workdir", type=Path, help="where each example's folder goes (default: a new temp dir)")
    ap.add_argument("--rescore", type=Path, help="score the folders of an earlier run in this workdir; run nothing")
    ap.add_argument("--timeout", type=float, default=1800.0, help="s per example before the run is stopped")
    ap.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "discovery.json")
    ap.add_argument("overrides", nargs="*", help="extra overrides for every discover (the suite's figures use none)")
    args = ap.parse_args(argv)
    workdir = args.rescore or args.workdir or Path(tempfile.mkdtemp(prefix="physmend-discovery-"))
    scores = []
    for example in examples(args.only):
        folder = workdir / example.name
        s = Score(example.name)
        if args.rescore:
            meta = json.loads((folder / "run.json").read_text()) if (folder / "run.json").exists() else {}
            s.wall_s, s.peak_mib, status = meta.get("wall_s", math.nan), meta.get("peak_mib", math.nan), meta.get("status", 0)
        else:
            if folder.exists():
                shutil.rmtree(folder)
            print(f"== {example.name}: physmend discover in {folder}", flush=True)
            status, s.wall_s, s.peak_mib = run_discover(example, folder, args.timeout, args.overrides)
            (folder / "run.json").write_text(json.dumps({"status": status, "wall_s": s.wall_s, "peak_mib": s.peak_mib}))
        s.ok_run = status == 0
        if not s.ok_run:
            tail = (folder / "discover.log").read_text(errors="replace").strip().splitlines()[-1:] if (folder / "discover.log").exists() else []
            s.error = f"exit {status}: {tail[0][:200] if tail else ''}"
        try:
            score(example, folder, s)
        except Exception as exc:  # a scoring failure is a result, not a crash of the suite
            s.error = (s.error + f"; scoring failed: {exc!r}")[:400]
        scores.append(s)
        print(table([s]).splitlines()[2], flush=True)
    print()
    print(table(scores))
    args.json.write_text(json.dumps({"workdir": str(workdir), "scores": [
        {**asdict(s), "network_ok": s.network_ok, "formula_ok": s.formula_ok} for s in scores]}, indent=1))
    print(f"\nJSON: {args.json}   folders: {workdir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

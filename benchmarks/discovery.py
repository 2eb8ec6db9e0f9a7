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
  example's stated sensor noise σ. An output passes when it improves ≥ 5× or ends ≤ 1.5 σ; where
  the model as written is more than 10× worse than the records' own mean (it diverges: being better
  than it says nothing), the improvement counts from that mean;
* **mechanism**: whether the proposal's report names one of the truth's ``mechanism`` keywords;
* **stray terms** (issue 32): every formula the proposal puts on an equation that is *not* in the
  truth's ``corrections``, evaluated along the same trajectories as the formula R², its RMS over
  the RMS of the concealed term (the smallest, where several are concealed). It passes when every
  ratio is ≤ 20 % (nothing stray: passes; a concealed term with free constants and no formula on
  its equation has no known RMS: fails). Reported beside the formula pass, which already demands
  exactly the true equations;
* **wall time** and **peak memory** (maximum resident set of the discover process).

Real recordings. An example whose recordings are real has no noise-free truth trajectory and no
known constant for its missing term. Its ``truth.yaml`` then names

* ``free: [c, …]``: constants of the ``corrections`` whose values are not known. They must enter
  linearly; the scorer fits them by least squares to the found formula of that equation, so the
  formula R² scores the *form* of the formula, not its value. Without ``truth/<id>.csv`` the
  trajectories are the proposed corrected model's own simulation of each test experiment;
* ``published: {experiment, output, rmse, skip_samples, method, source}``: a published figure for
  that test experiment (RMSE of the simulated output, in the output's unit, over the samples after
  the first ``skip_samples``). The held-out criterion of such an example is that figure instead of
  the 5× / noise rule: the corrected model passes when its RMSE (the same samples) is ≤ the figure;
  the masked network when its whole-record RMSE (the mask run's metric) is. The table shows the
  model as written, the network and the corrected model against the figure.

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
DIVERGED = 10.0  # a model as written this many times worse than the records' own mean left the data: the
#   improvement then counts from that mean (5x better than a diverging model says nothing)
FORMULA_R2 = 0.95
STEPS_PER_SAMPLE = 20  # the scorer's simulations may take this many solver steps per sample of a record
STRAY_LIMIT = 0.2  # a formula on an equation the truth does not correct: RMS ≤ this × the concealed term's RMS
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
    # added for issue 32 (absent from older JSON files; defaults keep them readable)
    stray: dict[str, float] = field(default_factory=dict)  # other equation -> RMS(formula) / RMS(concealed term)
    truth_constants: dict[str, float] = field(default_factory=dict)  # free constants of the truth, as fitted
    r2_trajectory: str = "truth"  # along which trajectories R² and stray ratios were evaluated
    published: dict[str, Any] = field(default_factory=dict)  # the truth's published figure and ours beside it
    # the records' RMS deviation from their mean per "<id>/<output>": the constant prediction. Where the model as
    # written diverges (DIVERGED), "5x better than it" says nothing; the improvement counts from this
    rmse_mean: dict[str, float] = field(default_factory=dict)

    def _published_pass(self, which: str) -> bool:
        fig, ours = self.published.get("rmse", math.nan), self.published.get(which, math.nan)
        return math.isfinite(ours) and ours <= fig

    def _outputs_pass(self, after: dict[str, float], which: str = "") -> bool:
        if self.published:
            return self._published_pass(which)
        if not self.rmse_before or set(after) != set(self.rmse_before):
            return False
        for key, before in self.rmse_before.items():
            out = key.split("/", 1)[1]
            a = after[key]
            spread = self.rmse_mean.get(key, math.inf)
            if before > DIVERGED * spread:  # the model as written left the data: count from the records' mean
                before = spread
            if not math.isfinite(a) or not (before / a >= IMPROVEMENT or a <= NEAR_NOISE * self.noise.get(out, 0.0)):
                return False
        return True

    @property
    def network_ok(self) -> bool:
        """Issue "discovery on any model": right equations and the masked network good enough."""
        return (self.ok_run and set(self.network_equations) == set(self.true_equations)
                and self._outputs_pass(self.rmse_network, "network") and self.wall_s <= WALL_LIMIT_S
                and self.peak_mib <= MEMORY_LIMIT_MIB)

    @property
    def formula_ok(self) -> bool:
        """Issue "symbolic regression on any model": right equations, formula, fit and mechanism."""
        return (self.ok_run and set(self.formula_equations) == set(self.true_equations)
                and all(self.formula_r2.get(s, -math.inf) >= FORMULA_R2 for s in self.true_equations)
                and self._outputs_pass(self.rmse_formula, "formula") and self.mechanism_named)

    @property
    def stray_ok(self) -> bool:
        """Issue 32: no equation outside the truth gets a term above ``STRAY_LIMIT`` × the concealed term's RMS."""
        return self.ok_run and bool(self.formula_equations) and all(
            math.isfinite(v) and v <= STRAY_LIMIT for v in self.stray.values())


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


def _simulate_test(cfg: Any) -> tuple[Any, list[Any], Any, Any]:
    """Simulate ``cfg``'s model on its test experiments: (problem, test experiments, batch, trajectories)."""
    import torch

    from physmend.problem import load_problem
    from physmend.simulate import make_batch, simulate_batch
    from physmend.simulate.core import OWN_METHODS

    problem = load_problem(cfg)
    test = [e for e in problem.experiments if e.role == "test"]
    batch = make_batch(test, problem.compiled, problem.dtype)
    # a long record needs more steps than the solvers' default cap: allow STEPS_PER_SAMPLE per sample
    options = {"max_steps": max(100_000, STEPS_PER_SAMPLE * int(batch.t.numel()))} if str(cfg.simulate.method) in OWN_METHODS else {}
    with torch.no_grad():
        traj = simulate_batch(problem.compiled, batch, method=str(cfg.simulate.method), rtol=1e-6, atol=1e-8, options=options)
    return problem, test, batch, traj


def _rmse_of(problem: Any, test: list[Any], batch: Any, traj: Any, skip: int = 0) -> dict[str, float]:
    """RMSE per test experiment and output (``"<id>/<output>"``) of a simulation from :func:`_simulate_test`,
    leaving out each record's first ``skip`` samples."""
    out: dict[str, float] = {}
    for b, e in enumerate(test):
        for j, name in enumerate(problem.model.output_names):
            err = (traj.outputs[:, b, j] - batch.obs[:, b, j]).numpy()
            err = err[np.isfinite(err)][skip:]
            out[f"{e.id}/{name}"] = float(np.sqrt(np.mean(err**2))) if err.size else float("nan")
    return out


def _spread_of(problem: Any, test: list[Any], batch: Any, traj: Any, skip: int = 0) -> dict[str, float]:
    """The RMS deviation of each test record from its own mean (``"<id>/<output>"``): the error of the
    constant prediction, the baseline where the model as written diverges."""
    out: dict[str, float] = {}
    for b, e in enumerate(test):
        for j, name in enumerate(problem.model.output_names):
            y = batch.obs[:, b, j].numpy()
            y = y[np.isfinite(y)][skip:]
            out[f"{e.id}/{name}"] = float(np.sqrt(np.mean((y - y.mean()) ** 2))) if y.size else float("nan")
    return out


def _simulated_frames(sim: tuple[Any, list[Any], Any, Any]) -> dict[str, pd.DataFrame]:
    """A model's own trajectories on the test experiments (``sim`` from :func:`_simulate_test`): states,
    inputs and observed variables per experiment id, on its measurement times (for truths without
    ``truth/<id>.csv``)."""
    problem, test, batch, traj = sim
    sm = problem.model
    frames = {}
    for b, e in enumerate(test):
        columns: dict[str, np.ndarray] = {"time": batch.t.numpy()}
        for names, values in ((sm.state_names, traj.states), (sm.input_names, traj.inputs),
                              (list(sm.observed), traj.observed)):
            for i, n in enumerate(names):
                columns.setdefault(n, values[:, b, i].numpy())
        frame = pd.DataFrame(columns)
        measured = np.isfinite(batch.obs[:, b].numpy()).any(-1)
        frames[e.id] = frame[measured].reset_index(drop=True)
    return frames


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


def _fit_free(term: str, free: list[str], found: np.ndarray, frames: list[pd.DataFrame],
              params: list[dict[str, float]]) -> tuple[np.ndarray, dict[str, float]]:
    """The truth ``term`` with its ``free`` constants fitted (least squares) to the ``found`` formula's
    values along ``frames``: (its values on all frames, concatenated; the fitted constants).

    The constants must enter linearly (``term = t0 + Σ c_i·b_i``), checked at ``c_i = 2``.
    """
    def values(consts: dict[str, float]) -> np.ndarray:
        return np.concatenate([_formula_values(term, consts, f, p) for f, p in zip(frames, params)])

    zero = {c: 0.0 for c in free}
    t0 = values(zero)
    basis = []
    for c in free:
        one, two = values({**zero, c: 1.0}) - t0, values({**zero, c: 2.0}) - t0
        if not np.allclose(two, 2.0 * one, rtol=1e-9, atol=1e-12 * (1.0 + float(np.max(np.abs(one))))):
            raise ValueError(f"free constant {c!r} of the truth term {term!r} must enter linearly, but it does not")
        basis.append(one)
    ok = np.isfinite(found) & np.isfinite(t0) & np.all(np.isfinite(basis), axis=0)
    a = np.stack(basis, 1)[ok]
    coef = np.linalg.lstsq(a, (found - t0)[ok], rcond=None)[0] if ok.any() else np.full(len(free), np.nan)
    fitted = {c: float(v) for c, v in zip(free, coef)}
    return values(fitted), fitted


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
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # the scoring's downloads: no bars in the log
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
    corrected_cfg = _config(example, corr_path)
    sims: dict[str, tuple[Any, list[Any], Any, Any]] = {}

    def sim(which: str) -> tuple[Any, list[Any], Any, Any]:  # each model simulated once, when first needed
        if which not in sims:
            sims[which] = _simulate_test(cfg if which == "before" else corrected_cfg)
        return sims[which]

    test_ids = [str(e.id) for e in cfg.data.experiments if e.role == "test"]
    free = [str(c) for c in truth.get("free") or []]
    if all((example / "truth" / f"{i}.csv").exists() for i in test_ids):
        frames = {i: pd.read_csv(example / "truth" / f"{i}.csv") for i in test_ids}
    else:  # real recordings: no truth trajectory; the proposed model's own
        frames = _simulated_frames(sim("after"))
        score_.r2_trajectory = "corrected model (simulated)"
    params = {i: _parameters(cfg, i) for i in test_ids}
    f_list, p_list = [frames[i] for i in test_ids], [params[i] for i in test_ids]

    def found_values(cs: list[dict[str, Any]]) -> np.ndarray:
        return np.concatenate([sum(_formula_values(c["term"], c.get("constants") or {}, frames[i], params[i]) for c in cs)
                               for i in test_ids])

    concealed: dict[str, np.ndarray] = {}
    for state in score_.true_equations:
        mine = [c for c in corrections if c["state"] == state]
        term = str(truth["corrections"][state])
        if not mine:
            if not free:
                concealed[state] = np.concatenate([frames[i][f"term:{state}"].to_numpy(float) for i in test_ids])
            continue
        score_.formulas[state] = " + ".join(c["term"] for c in mine)
        found = found_values(mine)
        if free:
            true, fitted = _fit_free(term, free, found, f_list, p_list)
            score_.truth_constants.update({f"{state}:{k}": v for k, v in fitted.items()})
        else:
            true = np.concatenate([frames[i][f"term:{state}"].to_numpy(float) for i in test_ids])
        concealed[state] = true
        score_.formula_r2[state] = _r2(found, true)
    rms = [float(np.sqrt(np.nanmean(v**2))) for v in concealed.values() if np.isfinite(v).any()]
    concealed_rms = min(rms) if rms and len(rms) == len(score_.true_equations) else math.nan
    for state in sorted({c["state"] for c in corrections} - set(score_.true_equations)):
        try:
            vals = found_values([c for c in corrections if c["state"] == state])
            stray_rms = float(np.sqrt(np.nanmean(vals**2)))
        except Exception as exc:  # a formula in a quantity the truth trajectory lacks
            stray_rms = math.nan
            score_.error = (score_.error + f"; stray formula of {state} not evaluated: {exc!r}")[:400]
        score_.stray[state] = stray_rms / concealed_rms if concealed_rms > 0 else math.inf
    score_.rmse_before = _rmse_of(*sim("before"))
    score_.rmse_mean = _spread_of(*sim("before"))
    score_.rmse_formula = _rmse_of(*sim("after"))
    metrics = mask.data.metrics
    score_.rmse_network = {k: float(metrics.get(f"rmse.{k.replace('/', '.', 1)}", float("nan"))) for k in score_.rmse_before}
    if truth.get("published"):
        pub = dict(truth["published"])
        key = f"{pub['experiment']}/{pub['output']}"
        skip = int(pub.get("skip_samples", 0))
        score_.published = {**pub, "rmse": float(pub["rmse"]),
                            "before": _rmse_of(*sim("before"), skip).get(key, math.nan),
                            "network": score_.rmse_network.get(key, math.nan),
                            "formula": _rmse_of(*sim("after"), skip).get(key, math.nan)}
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


def _fmt_stray(s: Score) -> str:
    return ", ".join(f"{k}: {v:.0%}" for k, v in s.stray.items()) or "none"


def _fmt_published(s: Score) -> str:
    p = s.published
    if not p:
        return "-"
    return (f"{p['output']} on {p['experiment']}: as written {p['before']:.3g}, network {p['network']:.3g}, "
            f"formula {p['formula']:.3g} vs published {p['rmse']:.3g} (samples after {p.get('skip_samples', 0)})")


def table(scores: list[Score]) -> str:
    head = ("| example | wall [s] | peak [MiB] | true eq. | network eq. | formula eq. | formula R² | "
            "held-out RMSE network (before→after) | held-out RMSE formula | mechanism | network pass | formula pass | "
            "stray terms (RMS / concealed) | stray pass | published figure |")
    rows = [head, "|" + "---|" * 15]
    for s in scores:
        r2 = ", ".join(f"{v:.3f}" for v in s.formula_r2.values()) or "-"
        if s.r2_trajectory != "truth" and s.formula_r2:
            r2 += f" (form; along the {s.r2_trajectory})"
        rows.append(
            f"| {s.example} | {s.wall_s:.0f} | {s.peak_mib:.0f} | {', '.join(s.true_equations)} | "
            f"{', '.join(s.network_equations) or '-'} | {', '.join(s.formula_equations) or '-'} | {r2} | "
            f"{_fmt_rmse(s, s.rmse_network)} | {_fmt_rmse(s, s.rmse_formula)} | {'yes' if s.mechanism_named else 'no'} | "
            f"{'PASS' if s.network_ok else 'fail'} | {'PASS' if s.formula_ok else 'fail'} | {_fmt_stray(s)} | "
            f"{'PASS' if s.stray_ok else 'fail'} | {_fmt_published(s)} |"
            + (f" {s.error}" if s.error else "")
        )
    n = len(scores)
    rows.append(f"\nnetwork pass: {sum(s.network_ok for s in scores)}/{n}   formula pass: {sum(s.formula_ok for s in scores)}/{n}"
                f"   stray pass: {sum(s.stray_ok for s in scores)}/{n}")
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
        {**asdict(s), "network_ok": s.network_ok, "formula_ok": s.formula_ok, "stray_ok": s.stray_ok}
        for s in scores]}, indent=1))
    print(f"\nJSON: {args.json}   folders: {workdir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Replay of every attack listed under "Why" in issue 33, through the installed command line.

Not a test of the suite (its name does not start with ``test_``): a measurement, run by hand on a
quiet machine::

    REPLAY_OUT=/tmp/replay.md .venv/bin/python -m pytest -n 0 -s tests/security/replay.py

Each attack is a real file or a real store tampered as a hostile user of a shared store could, and
one ``physmend`` process under ``/usr/bin/time -v``: wall seconds, exit status, characters and lines
of output (stdout and stderr), peak resident memory. The bar (issue 33, "Done when"): within 10 s,
one line of at most 300 characters, exit 2 (exit 0 where the input is legitimate: a model that
diverges is diagnose's finding; ``physmend runs`` prints the table, escaped), under 1 GiB, no secret
in the output, nothing written outside the working folder. The table is printed and, with
``REPLAY_OUT`` set, written there (docs/security-replay.md holds one).
"""

from __future__ import annotations

import json
import os
import pickle
import re
import shutil
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .conftest import StoredTrial, physmend_command
from .test_bounded_files import BOMB, TERMS
from .test_stored_model import _Payload

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SECRET = "se'cretQ"
MAX_S, MAX_CHARS, MAX_MIB = 10.0, 300, 1024.0


@dataclass
class Attack:
    """One replayed attack: the command's words after ``physmend``, run in ``cwd``."""

    name: str
    argv: list[str]
    cwd: Path
    expect: int = 2
    prepare: Callable[[], None] = lambda: None
    check: Callable[[str], str | None] = lambda out: None  # a failure's description, or None
    note: str = ""
    max_s: float = MAX_S


@dataclass
class Row:
    attack: Attack
    seconds: float
    status: int
    chars: int
    lines: int
    mib: float
    output: str
    problems: list[str] = field(default_factory=list)


def measure(attack: Attack, scratch: Path) -> Row:
    """Run ``attack`` under ``/usr/bin/time -v``; the row, with what missed the bar."""
    attack.prepare()
    timing = scratch / "time.txt"
    start = time.perf_counter()
    done = subprocess.run(["/usr/bin/time", "-v", "-o", str(timing), *physmend_command(), *attack.argv],
                          cwd=attack.cwd, capture_output=True, text=True, errors="replace", timeout=600)
    seconds = time.perf_counter() - start
    report = timing.read_text()
    rss_kb = float(re.search(r"Maximum resident set size \(kbytes\): (\d+)", report)[1])
    out = (done.stdout + done.stderr).strip()
    row = Row(attack, seconds, done.returncode, len(out), len(out.splitlines()), rss_kb / 1024, out)
    if seconds > attack.max_s:
        row.problems.append(f"{seconds:.1f} s")
    if done.returncode != attack.expect:
        row.problems.append(f"exit {done.returncode}")
    if attack.expect == 2 and (row.lines != 1 or row.chars > MAX_CHARS):
        row.problems.append(f"{row.lines} lines, {row.chars} characters")
    if row.mib > MAX_MIB:
        row.problems.append(f"{row.mib:.0f} MiB")
    if SECRET in out or "Traceback" in out:
        row.problems.append("secret or traceback in the output")
    if (why := attack.check(out)) is not None:
        row.problems.append(why)
    return row


def table(rows: list[Row]) -> str:
    lines = ["| attack | s | exit | chars | MiB | |", "|---|---:|---:|---:|---:|---|"]
    for r in rows:
        verdict = "; ".join(r.problems) if r.problems else "ok"
        note = f" ({r.attack.note})" if r.attack.note else ""
        lines.append(f"| {r.attack.name}{note} | {r.seconds:.1f} | {r.status} | {r.chars} | {r.mib:.0f} | {verdict} |")
    return "\n".join(lines)


# ---- the files and stores attacked ----------------------------------------------------------------------


def _corrections(folder: Path, name: str, term_yaml: str, constants: str = "{}", extra: str = "") -> Path:
    path = folder / f"{name}.yaml"
    path.write_text(f"physmend_corrections: 1\nmodel: oscillator\n{extra}corrections:\n"
                    f"  - state: cart.v\n    term: {term_yaml}\n    unit: N\n    constants: {constants}\n")
    return path


def _absent(path: Path) -> Callable[[str], str | None]:
    return lambda out: f"{path} was written" if path.exists() else None


def _pristine(trial: StoredTrial) -> Callable[[Callable[[], None]], Callable[[], None]]:
    """``prepare`` functions that start from the trial's untampered artifacts."""
    folder = trial.artifact("config.yaml").parent
    keep = folder.parent / "pristine"
    shutil.copytree(folder, keep)

    def wrap(tamper: Callable[[], None]) -> Callable[[], None]:
        def prepare() -> None:
            shutil.rmtree(folder)
            shutil.copytree(keep, folder)
            tamper()
        return prepare

    return wrap


def _edit_spec(trial: StoredTrial, key: str, value: Any) -> Callable[[], None]:
    def tamper() -> None:
        path = trial.artifact("model/hybrid.json")
        meta = json.loads(path.read_text())
        meta["spec"][key] = value
        path.write_text(json.dumps(meta))
    return tamper


def _append(path: Callable[[], Path], text: str) -> Callable[[], None]:
    return lambda: path().write_text(path().read_text() + text)


def _predator_prey(folder: Path, change: Callable[[Path], None]) -> Path:
    project = folder / "predator_prey"
    shutil.copytree(EXAMPLES / "predator_prey", project, ignore=shutil.ignore_patterns("__pycache__"))
    change(project)
    return project


def _huge_value(project: Path) -> None:
    path = project / "telemetry" / "h2.csv"
    df = pd.read_csv(path)
    df.loc[5, "prey.x"] = 1e300
    df.to_csv(path, index=False)


def _fine_record(project: Path) -> None:
    original = pd.read_csv(project / "telemetry" / "h1.csv")
    t = np.linspace(float(original.time.iloc[0]), float(original.time.iloc[-1]), 2_000_001)
    fine = pd.DataFrame({c: np.interp(t, original.time, original[c]) for c in original.columns})
    fine.to_csv(project / "telemetry" / "h1.csv", index=False)


def attacks(trial: StoredTrial, scratch: Path, silent_port: int) -> list[Attack]:
    project, args = trial.project, trial.args()
    here = project
    files = scratch / "files"
    files.mkdir()
    pristine = _pristine(trial)

    def diagnose_with(path: Path) -> list[str]:
        return ["diagnose", *args, f"++model.corrections={path}", "diagnose.plots=false"]

    out: list[Attack] = []
    for name, words in [("tower", "tower"), ("symbolic exponent", "symbolic exponent"),
                        ("unary minus", "unary minus"), ("long chain", "long chain"),
                        ("parentheses", "parentheses"), ("one megabyte", "one megabyte")]:
        term = TERMS[words].replace("zone1.air.T", "cart.v")
        out.append(Attack(f"term: {name}", diagnose_with(_corrections(files, name.replace(" ", "_"), repr(term))), here))
    bomb = files / "bomb.yaml"
    bomb.write_text("physmend_corrections: 1\nmodel: oscillator\n" + BOMB
                    + "corrections:\n  - state: cart.v\n    term: *i\n")
    out.append(Attack("term: YAML alias bomb", diagnose_with(bomb), here))
    out.append(Attack("constants {c1: abc}", diagnose_with(_corrections(files, "abc", "'c1*cart.v'", "{c1: abc}")), here))

    out.append(Attack("stored config.yaml: alias bomb", ["mask", trial.run_id, *args], here,
                      prepare=pristine(_append(lambda: trial.artifact("config.yaml"), "bomb:\n" + "".join(
                          "  " + line + "\n" for line in BOMB.splitlines())))))
    marker = project / "pwned"
    out.append(Attack("stored config.yaml: !!python/object/apply", ["mask", trial.run_id, *args], here,
                      prepare=pristine(_append(lambda: trial.artifact("config.yaml"),
                                               f"evil: !!python/object/apply:os.system ['touch {marker}']\n")),
                      check=_absent(marker)))
    out.append(Attack("hybrid.json widths [200000, 200000]", ["mask", trial.run_id, *args], here,
                      prepare=pristine(_edit_spec(trial, "widths", [200000, 200000]))))
    out.append(Attack('hybrid.json in_observed ["nope"]', ["mask", trial.run_id, *args], here,
                      prepare=pristine(_edit_spec(trial, "in_observed", ["nope"]))))
    out.append(Attack("pickled weights.pt", ["mask", trial.run_id, *args], here,
                      prepare=pristine(lambda: trial.artifact("model/weights.pt").write_bytes(
                          pickle.dumps(_Payload(marker)))), check=_absent(marker)))

    elsewhere = scratch / "elsewhere"
    for label, model in [("model: /elsewhere/evil", str(elsewhere / "evil")), ("model: ../../x", "../../x")]:
        run_id = trial.proposal({"physmend_corrections": 1, "model": model,
                                   "corrections": [{"state": "cart.v", "term": "1.0"}]})
        out.append(Attack(f"accept, {label}", ["accept", run_id, *args], here,
                          check=lambda out: "a folder was written outside" if elsewhere.exists()
                          or (project.parent.parent / "x").exists() else None))
    tower = {"physmend_corrections": 1, "model": "oscillator",
             "corrections": [{"state": "cart.v", "term": TERMS["tower"], "unit": "N", "constants": {}}]}
    run_id = trial.proposal(tower)
    out.append(Attack("accept, tower term", ["accept", run_id, *args], here,
                      check=_absent(project / "corrections")))
    out.append(Attack("export, tower term", ["export", run_id, *args, f"export.output_dir={scratch / 'export'}"], here,
                      check=_absent(scratch / "export")))

    uri = f'tracking.uri="postgresql+psycopg2://bob:{SECRET}@127.0.0.1:9/physmend"'
    out.append(Attack("password with a quote, store refused", ["runs", *args, uri], here))
    out.append(Attack("ui, store refused", ["ui", uri], scratch, note="password kept off the command line: test"))
    silent = f'tracking.uri="postgresql+psycopg2://bob:{SECRET}@127.0.0.1:{silent_port}/physmend"'
    out.append(Attack("ui, store never answers", ["ui", silent], scratch, note="new"))
    out.append(Attack("runs, store never answers", ["runs", *args, silent], here, note="new"))

    def escape_tag() -> None:
        trial.store.client.set_tag(trial.run_id, "physmend.trial_state", "COMPLETE\x1b]0;owned\x07\x1b[2J")
    out.append(Attack("ESC sequences in a store tag", ["runs", *args], here, expect=0, prepare=escape_tag,
                      check=lambda out: "raw ESC in the output" if "\x1b" in out or "\x07" in out else None,
                      note="prints the table, escaped"))

    for label, change, name in [("a column of 1e300", _huge_value, "huge"),
                                ("2,000,001 rows at Δt 1.5e-5 tu", _fine_record, "fine")]:
        folder = scratch / name
        folder.mkdir()
        pp = _predator_prey(folder, change)
        out.append(Attack(label, ["diagnose", "--config-dir", str(pp / "conf"), "model=predator_prey",
                                  "data=predator_prey", "diagnose.plots=false"], folder))
    shunt = scratch / "shunt"
    shunt.mkdir()
    out.append(Attack("model as written diverges (shunt_generator)",
                      ["diagnose", "--config-dir", str(EXAMPLES / "shunt_generator" / "conf"), "model=shunt_generator",
                       "data=shunt_generator", "diagnose.plots=false"], shunt, expect=0,
                      note="a finding, exit 0"))
    sweep = scratch / "shunt_sweep"
    sweep.mkdir()
    out.append(Attack("a sweep trial on it (was 34 GB per trial)",
                      ["sweep", "--config-dir", str(EXAMPLES / "shunt_generator" / "conf"), "model=shunt_generator",
                       "data=shunt_generator", "sweep.n_trials=1", "train.epochs=10", "train.eval_every=5"], sweep,
                      expect=0, max_s=120, note="training, exit 0"))
    return out


def test_replay(stored_trial: StoredTrial, tmp_path: Path, silent_server: int) -> None:
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    rows = [measure(a, scratch) for a in attacks(stored_trial, scratch, silent_server)]
    load = Path("/proc/loadavg").read_text().split()[:3] if Path("/proc/loadavg").exists() else ["?"]
    text = table(rows) + f"\n\nload average before the last attack: {' '.join(load)}\n"
    print("\n" + text)
    for r in rows:  # what each printed (the last line where there are more)
        print(f"{r.attack.name}: {r.output.splitlines()[-1] if r.output else ''}"[:400])
    if os.environ.get("REPLAY_OUT"):
        Path(os.environ["REPLAY_OUT"]).write_text(text)
    missed = [f"{r.attack.name}: {'; '.join(r.problems)}" for r in rows if r.problems]
    assert not missed, missed

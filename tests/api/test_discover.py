"""``physmend.discover(...)`` from a plain Python script finds the formula ``physmend discover`` prints for
the same settings and seed (both run at once, each in its own folder and store; real training); each
side then continues from the other's runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

#: the bundled reactor with a cheap sweep, as the notebook runs it
SETTINGS = {"seed": 0, "discover.n_trials": 1, "discover.budget": None, "train.epochs": 60, "train.eval_every": 20,
            "ude.depth": 1, "symbolic.refit_epochs": 10}
CLI = ["model=cstr", "data=cstr", "seed=0", "discover.n_trials=1", "discover.budget=null", "train.epochs=60",
       "train.eval_every=20", "ude.depth=1", "symbolic.refit_epochs=10"]

SCRIPT = textwrap.dedent(
    """
    import json, sys
    import physmend

    d = physmend.discover("cstr", "cstr", **json.loads(sys.argv[1]))
    terms = d.symbolic.terms.to_dict("records")
    print("RESULT " + json.dumps({"terms": terms, "formulas": {k: str(v) for k, v in d.formulas.items()},
                                  "run_ids": d.run_ids}))
    """
)


@pytest.mark.slow
def test_discover_from_a_script_finds_the_formula_the_command_line_prints(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], reset_mlflow: None) -> None:
    (tmp_path / "py").mkdir()
    (tmp_path / "cli").mkdir()
    (tmp_path / "py" / "script.py").write_text(SCRIPT)
    bin_dir = Path(sys.executable).parent
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    script = subprocess.Popen([sys.executable, "script.py", json.dumps(SETTINGS)], cwd=tmp_path / "py", env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    cli = subprocess.Popen([str(bin_dir / "physmend"), "discover", *CLI], cwd=tmp_path / "cli", env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    py_out, py_err = script.communicate(timeout=900)
    cli_out, cli_err = cli.communicate(timeout=900)
    assert script.returncode == 0, py_err[-3000:]
    assert cli.returncode == 0, cli_err[-3000:]
    found = json.loads(next(line for line in py_out.splitlines() if line.startswith("RESULT "))[7:])
    symbolic = cli_out[cli_out.index("# physmend symbolic"):]
    for term in found["terms"]:  # the line the command line prints for each formula, character for character
        consts = ", ".join(f"{k} = {v:.4g}" for k, v in term["constants"].items())
        assert f"{term['state']}: + {term['term']}   ({consts})" in symbolic, (term, symbolic)
    assert len(found["terms"]) == sum(1 for line in symbolic.splitlines() if ": + " in line) >= 1

    # and exactly: the command line's own runs read back through the API give the same formulas
    from physmend.api import Discovery
    from physmend.api.artifacts import RunFiles
    from physmend.tracking import open_store
    from omegaconf import OmegaConf

    proposal = cli_out.split("propose run: ")[1].split()[0]
    store = open_store(OmegaConf.create({"uri": f"sqlite:///{tmp_path / 'cli' / 'mlflow.db'}",
                                         "experiment": "physmend"}))
    theirs = Discovery.read(RunFiles(store, proposal))
    assert {k: str(v) for k, v in theirs.formulas.items()} == found["formulas"]
    assert theirs.symbolic.terms.to_dict("records") == found["terms"]
    assert set(theirs.run_ids) == set(found["run_ids"]) == {"diagnosis", "sweep", "mask", "sensitivity", "symbolic",
                                                              "proposal"}

    # the runs are the same kind either way: each side continues from the other's run IDs
    import physmend
    from physmend.cli import main

    monkeypatch.chdir(tmp_path / "py")
    capsys.readouterr()
    assert main(["runs", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert {r["run_id"] for r in listed["stage_runs"]} >= {v for k, v in found["run_ids"].items() if k != "sweep"}
    assert found["run_ids"]["sweep"] in {s["run_id"] for s in listed["sweeps"]}
    assert main(["accept", found["run_ids"]["proposal"], "model=cstr", "data=cstr"]) == 0
    assert list((tmp_path / "py" / "corrections").glob("cstr-*.yaml"))
    # from Python on the command line's store: its runs continue from Python as from the command line
    on_cli = {**SETTINGS, "tracking.uri": f"sqlite:///{tmp_path / 'cli' / 'mlflow.db'}"}
    masked = physmend.mask(theirs.sweep.selected_run_id, model="cstr", data="cstr", **on_cli)
    assert masked.kept == theirs.mask.kept and masked.ranking.equals(theirs.mask.ranking)
    assert physmend.sensitivity(masked).inputs == theirs.sensitivity.inputs  # a result hands on its inputs
    proposal = physmend.propose(theirs.symbolic.run_id, model="cstr", data="cstr", **on_cli)
    assert {k: str(v) for k, v in proposal.formulas.items()} == found["formulas"]
    assert proposal.fit.equals(theirs.fit) and "propose run: " + proposal.run_id in proposal.printed
    exported = physmend.export(proposal, export={"output_dir": str(tmp_path / "exported")})
    assert {"latex", "sympy", "python"} <= set(exported.paths) and all(Path(p).exists() for p in exported.written)

"""``physmend.discover(...)`` from a plain Python script finds the formula ``physmend discover`` prints for
the same settings and seed (both run at once, each in its own folder and store; real training)."""

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
def test_discover_from_a_script_finds_the_formula_the_command_line_prints(tmp_path: Path) -> None:
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

"""The whole pipeline on a user's own non-thermal model, through the CLI, with real stores:
sweep → mask → sensitivity → symbolic → propose → accept / reject, and clear errors for bad IDs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from physmend.cli import main

TINY = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=40",
        "train.eval_every=20", "simulate.rtol=1e-6", "simulate.atol=1e-7", "ude.depth=1"]


def _run(project: Path, capsys, *args: str) -> tuple[int, str, str]:  # noqa: ANN001
    rc = main([args[0], "--config-dir", str(project / "my_conf"), *args[1:], *TINY])
    out = capsys.readouterr()
    return rc, out.out, out.err


def _last_run_id(text: str, stage: str) -> str:
    line = next(l for l in reversed(text.splitlines()) if l.startswith(f"{stage} run: "))
    return line.split()[2]


@pytest.mark.slow
def test_pipeline_end_to_end_on_a_user_model(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    from mlflow.tracking import MlflowClient

    monkeypatch.chdir(user_project)
    rc, out, err = _run(user_project, capsys, "sweep", "sweep.space=small", "sweep.n_trials=1")
    assert rc == 0, err
    rc, out, err = _run(user_project, capsys, "mask", "mask.max_k=2")
    assert rc == 0, err
    # the network corrects cart.v only (der(x) = v is a definition): the kept set is its own, not retrained
    assert "goes on as it is" in out and "Retrained with" not in out, out
    mask_id = _last_run_id(out, "mask")
    rc, out, err = _run(user_project, capsys, "sensitivity", mask_id)
    assert rc == 0, err
    sens_id = _last_run_id(out, "sensitivity")
    rc, _, err = _run(user_project, capsys, "sensitivity", mask_id, "sensitivity.group_r=2")
    assert rc == 2 and "sensitivity.group_r must be a number in (0, 1], but got 2" in err  # checked at compose
    rc, _, err = _run(user_project, capsys, "symbolic", sens_id, "symbolic.window=-5")
    assert rc == 2 and "symbolic.window must be 'auto' or a number > 0, but got -5" in err
    # a Pareto index out of range is a clear error naming the rule
    rc, _, err = _run(user_project, capsys, "symbolic", sens_id, "+symbolic.choice={cart.v: 999}", "symbolic.refit_epochs=0")
    assert rc == 2 and "Pareto index must be in [0," in err and "but got 999" in err
    # a choice for an equation that was not kept is a clear error, not silently ignored
    rc, _, err = _run(user_project, capsys, "symbolic", sens_id, "+symbolic.choice={cart.a: 0}", "symbolic.refit_epochs=0")
    assert rc == 2 and "symbolic.choice names ['cart.a'], but the formulas are for the kept corrections [" in err
    rc, out, err = _run(user_project, capsys, "symbolic", sens_id, "symbolic.refit_epochs=20")
    assert rc == 0, err
    sym_id = _last_run_id(out, "symbolic")
    rc, out, err = _run(user_project, capsys, "propose", sym_id)
    assert rc == 0, err
    prop_id = _last_run_id(out, "propose")
    assert "## Equations corrected" in out and "| run3 | test | cart.x |" in out
    client = MlflowClient(tracking_uri=f"sqlite:///{user_project / 'mlflow.db'}")
    proposal = json.loads(Path(client.download_artifacts(prop_id, "proposal.json", str(user_project))).read_text())
    after = {r["experiment"]: r["after"] for r in proposal["rows"]}
    # held-out experiment improves over the model as written
    test_row = next(r for r in proposal["rows"] if r["role"] == "test")
    assert test_row["after"] < test_row["before"]
    assert {"report.md", "report.html", "corrections.yaml"} <= {a.path for a in client.list_artifacts(prop_id)}
    # each stage's run says what it found, in the MLflow UI's description, and names its source
    # held-out means held out: a trial never simulates the test experiment (run3); the kept network
    # (mask) and the proposal report it
    trial = client.get_run(client.get_run(mask_id).data.tags["physmend.source_run_id"])
    assert trial.data.tags["physmend.stage"] == "trial" and "val.rmse" in trial.data.metrics
    assert not [k for k in trial.data.metrics if k.startswith("test.") or k.startswith("rmse.run3.")], trial.data.metrics
    assert "test.rmse" in client.get_run(mask_id).data.metrics and "rmse.run3.cart.x" in client.get_run(mask_id).data.metrics
    notes = {name: client.get_run(rid).data.tags.get("mlflow.note.content", "")
             for name, rid in (("mask", mask_id), ("symbolic", sym_id), ("propose", prop_id))}
    assert notes["mask"].startswith("Kept corrections: cart.v") and "Source trial:" in notes["mask"], notes
    assert notes["symbolic"].startswith("Formulas: cart.v: + ") and sens_id in notes["symbolic"], notes
    assert "Held-out RMSE improved" in notes["propose"] and sym_id in notes["propose"], notes
    page = Path(client.download_artifacts(prop_id, "report.html", str(user_project)))
    _report_reads_well(page.read_text(), [e for e in after])
    _report_in_chromium(page, len(after), user_project / "report.png")

    # reject changes nothing but tags
    before_files = sorted(p.name for p in user_project.iterdir())
    rc, out, err = _run(user_project, capsys, "reject", prop_id, "decide.reason=not convinced")
    assert rc == 0, err
    assert sorted(p.name for p in user_project.iterdir()) == before_files
    tags = client.get_run(prop_id).data.tags
    assert tags["physmend.decision"] == "rejected" and tags["physmend.reject_reason"] == "not convinced"
    rc, _, err = _run(user_project, capsys, "accept", prop_id)
    assert rc == 2 and "already rejected" in err

    # a fresh proposal from the same symbolic run, accepted: the written model reproduces the fit
    rc, out, err = _run(user_project, capsys, "propose", sym_id)
    prop2 = _last_run_id(out, "propose")
    rc, out, err = _run(user_project, capsys, "accept", prop2)
    assert rc == 0, err
    written = next((user_project / "corrections").glob("oscillator-*.yaml"))
    assert prop2 in written.read_text()
    rc, out, err = _run(user_project, capsys, "diagnose", f"++model.corrections={written}")
    assert rc == 0, err
    diag_id = _last_run_id(out, "diagnose")
    metrics = client.get_run(diag_id).data.metrics
    for exp, rmse in after.items():
        assert metrics[f"rmse.{exp}.cart.x"] == pytest.approx(rmse, rel=1e-6)
    _exports_round_trip(user_project, capsys, prop2, after)


def _report_reads_well(page: str, experiments: list[str]) -> None:
    """report.html: one self-contained page — every plot embedded as a PNG that decodes, formulas as
    MathML, tables as tables, and no Markdown marker left in the text a reader sees."""
    import base64
    from html.parser import HTMLParser

    class Page(HTMLParser):
        def __init__(self) -> None:
            super().__init__()
            self.images: list[str] = []
            self.tags: set[str] = set()
            self.text: list[str] = []

        def handle_starttag(self, tag: str, attrs: list) -> None:  # noqa: ANN001
            self.tags.add(tag)
            if tag == "img":
                self.images.append(dict(attrs)["src"])

        def handle_data(self, data: str) -> None:
            self.text.append(data)

    parsed = Page()
    parsed.feed(page)
    assert len(parsed.images) == len(experiments), parsed.images
    for src in parsed.images:
        assert src.startswith("data:image/png;base64,"), src[:60]
        assert base64.b64decode(src.split(",", 1)[1]).startswith(b"\x89PNG\r\n\x1a\n")
    assert {"math", "table", "th", "td", "h1", "h2", "ul", "code"} <= parsed.tags, parsed.tags
    text = "".join(parsed.text)
    for marker in ("**", "`", "![", "|---"):
        assert marker not in text, (marker, text[:500])


def _chromium() -> str | None:
    """A headless Chromium: the one installed, or the Debian package installed now (as root with apt)."""
    import os
    import shutil
    import subprocess

    found = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if found or os.geteuid() != 0 or not shutil.which("apt-get"):
        return found
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for cmd in (["apt-get", "update", "-q"], ["apt-get", "install", "-y", "-q", "--no-install-recommends", "chromium"]):
        if subprocess.run(cmd, env=env, capture_output=True, timeout=600).returncode != 0:
            return None
    return shutil.which("chromium")


def _report_in_chromium(page: Path, n_images: int, shot: Path) -> None:
    """report.html in a real browser: every image loaded (decoded, non-zero width), the MathML there,
    and a screenshot that is not blank."""
    import re
    import subprocess

    from PIL import Image

    browser = _chromium()
    if browser is None:
        pytest.skip("no Chromium here, and it could not be installed (needs root and apt-get)")
    probe = page.with_name("probe.html")  # a copy with a script that counts what loaded: the report has none
    probe.write_text(page.read_text().replace("</body>", (
        "<script>window.addEventListener('load', () => { const im = Array.from(document.images);"
        "document.body.dataset.images = im.length;"
        "document.body.dataset.loaded = im.filter(i => i.complete && i.naturalWidth > 0).length;"
        "document.body.dataset.math = document.querySelectorAll('math').length; });</script></body>")))
    flags = ["--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars"]
    dom = subprocess.run([browser, *flags, "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    body = re.search(r"<body[^>]*>", dom)
    assert body, dom[:500]
    attrs = dict(re.findall(r'data-(\w+)="(\d+)"', body.group(0)))
    assert attrs.get("images") == attrs.get("loaded") == str(n_images) and int(attrs.get("math", 0)) >= 2, attrs
    subprocess.run([browser, *flags, "--window-size=1280,2000", f"--screenshot={shot}", page.as_uri()],
                   capture_output=True, timeout=120, check=True)
    with Image.open(shot) as img:
        colours = img.convert("RGB").resize((128, 200)).getcolors(maxcolors=1 << 16)
    assert colours is not None and len(colours) > 20, "the screenshot is blank"


def _exports_round_trip(project: Path, capsys, prop_id: str, after: dict[str, float]) -> None:  # noqa: ANN001
    """``physmend export``: the Python module, simulated with scipy on the recorded inputs, and the
    sympy expressions, lambdified, reproduce the proposal's held-out fit; LaTeX shows the term;
    nothing is overwritten."""
    import importlib.util

    import numpy as np
    import pandas as pd
    import scipy.integrate
    import sympy as sp

    rc, out, err = _run(project, capsys, "export", prop_id, "export.output_dir=exported")
    assert rc == 0, err
    files = {"".join(p.suffixes[-2:]) if p.suffix == ".json" else p.suffixes[-1]: p for p in (project / "exported").iterdir()}
    assert set(files) == {".tex", ".py", ".sympy.json", ".petab", ".network.json", ".safetensors"}, files
    spec = importlib.util.spec_from_file_location("exported_model", files[".py"])
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.STATES == ["cart.x", "cart.v"] and mod.INPUTS == ["motor.F"] and mod.OUTPUTS == ["cart.x"]
    assert any(k.startswith("cart.v_") for k in mod.PARAMETERS)  # the correction's re-fitted constant
    data = pd.read_csv(project / "recordings" / "run3.csv")
    t, force, x_meas = data["t_s"].to_numpy() - 1000.0, data["motor.F"].to_numpy(), data["position"].to_numpy()
    p = {**mod.PARAMETERS, **mod.EXPERIMENTS["run3"]["parameters"]}
    x0 = [mod.EXPERIMENTS["run3"]["initial"][s] for s in mod.STATES]
    assert x0 == pytest.approx(mod.initial_state(p))  # the start expression cart.x = cart.x0

    def simulate(rhs):  # noqa: ANN001, ANN202
        sol = scipy.integrate.solve_ivp(lambda tt, x: rhs(tt, x, [float(np.interp(tt, t, force))], p), (t[0], t[-1]),
                                        x0, t_eval=t, rtol=1e-9, atol=1e-10, max_step=0.05)
        assert sol.success
        return sol.y[0]

    ok = np.isfinite(x_meas)
    x_module = simulate(mod.rhs)
    rmse = float(np.sqrt(np.mean((x_module[ok] - x_meas[ok]) ** 2)))
    assert rmse == pytest.approx(after["run3"], rel=0.02)  # the held-out fit the proposal reports
    doc = json.loads(files[".sympy.json"].read_text())
    symbols = {s.name: s for s in sp.sympify(doc["rhs"]["cart.v"]).free_symbols | sp.sympify(doc["rhs"]["cart.x"]).free_symbols}
    order = [symbols[n] for n in ("cart.x", "cart.v", "motor.F") if n in symbols]
    rest = sorted(set(symbols.values()) - set(order), key=str)
    f = sp.lambdify(order + rest, [sp.sympify(doc["rhs"][n]) for n in ("cart.x", "cart.v")])

    def rhs_sympy(tt, x, u, pp):  # noqa: ANN001, ANN202
        env = {"cart.x": x[0], "cart.v": x[1], "motor.F": u[0], **pp}
        return f(*[env[s.name] for s in order + rest])

    # the same model: the two simulations agree to the integration's tolerance (relative to the state's
    # size, not to the fit's RMSE, which is a thousandth of it)
    x_sympy = simulate(rhs_sympy)
    assert float(np.max(np.abs(x_sympy - x_module))) <= 1e-6 * float(np.max(np.abs(x_module)))
    rmse_sympy = float(np.sqrt(np.mean((x_sympy[ok] - x_meas[ok]) ** 2)))
    assert rmse_sympy == pytest.approx(rmse, rel=1e-6, abs=1e-6 * float(np.max(np.abs(x_module))))
    tex = files[".tex"].read_text()
    assert r"\documentclass" in tex and r"\frac{d\,v_{\mathrm{cart}}}{dt}" in tex and r"\texttt{cart.v\_c" in tex
    assert r"}}_{\text{found term}}" in tex  # the found term marked (tests/modeling/test_export_documents.py)
    # a second export of the same proposal overwrites nothing: one clear line, the files unchanged
    before = {p: p.read_bytes() for p in files.values() if p.is_file()}
    rc, _, err = _run(project, capsys, "export", prop_id, "export.output_dir=exported")
    assert rc == 2 and "never overwrites" in err and {p: p.read_bytes() for p in files.values() if p.is_file()} == before
    rc, _, err = _run(project, capsys, "export", prop_id, "export.format=pdf")
    assert rc == 2 and "export.format must be one of ['all', 'latex', 'sympy', 'python', 'network', 'petab'], but got 'pdf'" in err
    _petab_round_trip(next((project / "exported").glob("*.petab")), after)


def _petab_round_trip(folder: Path, after: dict[str, float]) -> None:
    """The PEtab problem: its tables name what the model holds, and its SBML model, simulated by
    libRoadRunner (a simulator physmend does not use) under each experiment's condition, gives the
    proposal's RMSE on every experiment, the held-out one included."""
    import numpy as np
    import pandas as pd
    import roadrunner

    assert sorted(p.name for p in folder.iterdir()) == sorted(
        ["problem.yaml", "model.xml", "conditions.tsv", "measurements.tsv", "observables.tsv", "parameters.tsv"])
    assert "format_version: 1" in (folder / "problem.yaml").read_text()
    cond = pd.read_csv(folder / "conditions.tsv", sep="\t")
    meas = pd.read_csv(folder / "measurements.tsv", sep="\t")
    obs = pd.read_csv(folder / "observables.tsv", sep="\t")
    pars = pd.read_csv(folder / "parameters.tsv", sep="\t")
    assert list(cond.conditionName) == ["run1", "run2", "run3"] and "cart_x0" in cond.columns  # differs per run
    assert "cart_x0" not in set(pars.parameterId)  # a condition column is never in the parameter table
    constant = pars[pars.parameterId.str.startswith("cart_v_")]
    assert len(constant) >= 1 and (constant.estimate == 1).all()  # the correction's constants, free to re-fit
    assert set(meas.datasetId) == {"train", "test"} and list(obs.observableFormula) == ["cart_x"]
    rr = roadrunner.RoadRunner(str(folder / "model.xml"))
    rr.integrator.relative_tolerance, rr.integrator.absolute_tolerance = 1e-9, 1e-10
    rr.integrator.maximum_time_step = 0.05
    for _, c in cond.iterrows():
        rr.resetAll()
        species = [k for k in cond.columns[2:] if k in rr.model.getFloatingSpeciesIds()]
        for k in species:  # initial amounts first: setting one resets the parameters to the model's
            rr.setValue(f"init({k})", float(c[k]))
        for k in cond.columns[2:]:
            if k not in species:
                rr.setValue(k, float(c[k]))
        m = meas[meas.simulationConditionId == c.conditionId]
        times = np.unique(np.concatenate([[0.0], m.time.to_numpy()]))
        sim = rr.simulate(times=times, selections=["time", "cart_x"])
        rmse = float(np.sqrt(np.mean((np.interp(m.time, sim[:, 0], sim[:, 1]) - m.measurement) ** 2)))
        assert rmse == pytest.approx(after[c.conditionName], rel=0.02), (c.conditionName, rmse, after)


def test_bad_run_ids_are_clear_errors(user_project: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    rc, out, err = _run(user_project, capsys, "diagnose")
    diag_id = _last_run_id(out, "diagnose")
    rc, _, err = _run(user_project, capsys, "mask", diag_id)
    assert rc == 2 and f"run {diag_id!r} must be a 'trial' run, but is a 'diagnose' run" in err
    rc, _, err = _run(user_project, capsys, "sensitivity", "0" * 32)
    assert rc == 2 and "does not exist" in err
    rc, _, err = _run(user_project, capsys, "propose")
    assert rc == 2 and "no finished 'symbolic' run" in err
    rc, _, err = _run(user_project, capsys, "accept", diag_id)
    assert rc == 2 and "must be a 'propose' run" in err
    rc, _, err = _run(user_project, capsys, "mask")
    assert rc == 2 and "no trial is selected" in err


def test_discover_rejects_a_bad_group_shapes_before_writing_anything(user_project: Path, monkeypatch: pytest.MonkeyPatch,
                                                                    capsys) -> None:  # noqa: ANN001
    monkeypatch.chdir(user_project)
    before = sorted(p.name for p in user_project.iterdir())
    rc, _, err = _run(user_project, capsys, "discover", "discover.group_shapes=no")
    assert rc == 2
    assert "discover.group_shapes must be true or false, but got 'no'" in err
    assert sorted(p.name for p in user_project.iterdir()) == before  # no MLflow store, no runs

"""The bundled two-zone cargo box (``examples/cargo_box``): model structure, concealed physics,
generator, telemetry, configs."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import sympy as sp
import torch
from omegaconf import OmegaConf

from physmend.config import compose
from physmend.modeling import compile_model, load_model

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "cargo_box"


def _example_modules() -> dict[str, object]:
    """The example's scripts, imported as its own scripts import each other (plain sibling names)."""
    names = ("model", "_numeric", "truth", "generate", "check")
    sys.path.insert(0, str(EXAMPLE))
    try:
        return {n: importlib.import_module(n) for n in names}
    finally:
        sys.path.remove(str(EXAMPLE))
        for n in names:
            sys.modules.pop(n, None)


_mods = _example_modules()
model_module = _mods["model"]
gen = _mods["generate"]
INPUTS, N_STATES, OUTPUTS, build_model = (getattr(model_module, n) for n in ("INPUTS", "N_STATES", "OUTPUTS", "build_model"))
NumpyModel = _mods["_numeric"].NumpyModel
compare, engineer_rmse, read_telemetry = (getattr(_mods["check"], n) for n in ("compare", "engineer_rmse", "read_telemetry"))
LEAK_COEFFICIENT, build_truth_model, true_leakage = (
    getattr(_mods["truth"], n) for n in ("LEAK_COEFFICIENT", "build_truth_model", "true_leakage")
)
SHIPPED = gen.TELEMETRY_DIR
NOISE = gen.NOISE_SIGMA


@pytest.fixture(scope="module")
def simplified():
    return build_model().simplify()


@pytest.fixture(scope="module")
def truth_numpy() -> NumpyModel:
    return NumpyModel.from_model(build_truth_model())


@pytest.fixture(scope="module")
def regenerated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("regenerated")
    gen.generate(out)
    return out


@pytest.fixture(scope="module")
def shipped() -> dict[str, pd.DataFrame]:
    return {exp.id: read_telemetry(SHIPPED / exp.file) for exp in gen.EXPERIMENTS}


# -- the engineer's model -------------------------------------------------------------------------
def test_model_simplifies_to_28_states_each_owned_by_its_component(simplified) -> None:
    assert len(simplified.states) == N_STATES == 28
    assert len(simplified.observed) > 200  # acausal model: many algebraic variables before simplification
    for name in simplified.state_names:
        owner = simplified.owner.get(name, "")
        assert owner and name == f"{owner}.T", f"state {name!r} must be owned by its component, got {owner!r}"
        assert simplified.units[name] == "degC"


def test_model_names_inputs_outputs_and_parameters(simplified) -> None:
    assert simplified.input_names == list(INPUTS) == ["ambient.T", "zone1.cooling.Q", "zone2.cooling.Q"]
    assert simplified.output_names == list(OUTPUTS) == ["zone1.air.T", "zone2.air.T"]
    assert {str(e) for e in simplified.outputs.values()} == set(OUTPUTS)
    params = {v.name: v for v in simplified.parameters}
    for name in ("zone1.length", "zone2.length", "box.width", "box.height", "box.T_initial", "wall.thickness",
                 "wall.conductivity", "bulkhead.thickness", "cargo.mass_per_length", "cargo.cp"):
        assert name in params and params[name].unit, name
    uncertain = [v for v in params.values() if v.uncertain]
    assert 1 <= len(uncertain) <= 3
    assert all(v.bounds and v.bounds[0] <= v.value <= v.bounds[1] for v in uncertain)
    T0 = params["box.T_initial"].symbol
    assert all(v.start == T0 for v in simplified.states), "every state starts at box.T_initial"


def test_geometry_depends_on_zone_lengths(simplified) -> None:
    L1 = next(v.symbol for v in simplified.parameters if v.name == "zone1.length")
    assert L1 in simplified.rhs["zone1.air.T"].free_symbols
    assert L1 in simplified.rhs["zone1.envelope.layer1.T"].free_symbols


def test_compiled_derivatives_are_sane(simplified) -> None:
    cm = compile_model(simplified)
    p = cm.default_parameters()
    u0 = cm.start(p)
    assert torch.allclose(u0, torch.full_like(u0, float(p[cm.parameter_names.index("box.T_initial")])))
    T0 = float(u0[0])
    # soaked box, ambient equal to it, no cooling: equilibrium
    assert torch.allclose(cm.rhs(u0, torch.tensor([T0, 0.0, 0.0], dtype=p.dtype), p), torch.zeros(28, dtype=p.dtype), atol=1e-12)
    # cooling zone 1 only: its coil starts cooling at Q/C, nothing else moves yet
    du = cm.rhs(u0, torch.tensor([T0, 3000.0, 0.0], dtype=p.dtype), p)
    C = float(p[cm.parameter_names.index("zone1.coil.capacity")])
    i = cm.state_names.index("zone1.coil.T")
    assert du[i].item() == pytest.approx(-3000.0 / C)
    assert torch.count_nonzero(du.abs() > 1e-12) == 1
    # warmer ambient heats the outer wall layers only
    du = cm.rhs(u0, torch.tensor([T0 + 10.0, 0.0, 0.0], dtype=p.dtype), p)
    moving = {n for n, d in zip(cm.state_names, du) if abs(float(d)) > 1e-12}
    assert moving == {"zone1.envelope.layer5.T", "zone2.envelope.layer5.T",
                      "zone1.front_wall.layer4.T", "zone2.rear_doors.layer4.T"}
    assert all(float(d) > 0 for d in du if abs(float(d)) > 1e-12)


# -- the concealed physics ------------------------------------------------------------------------
def test_truth_is_the_model_plus_the_leak_only(simplified, truth_numpy) -> None:
    eng = NumpyModel.from_model(simplified)
    ts = truth_numpy.model
    assert ts.state_names == simplified.state_names
    assert ts.input_names == simplified.input_names and ts.output_names == simplified.output_names
    assert ts.parameter_names == simplified.parameter_names
    rng = np.random.default_rng(0)
    p = eng.parameters({"zone1.length": 4.5, "zone2.length": 9.0})
    names = ts.state_names
    L1 = 4.5
    C_air1 = 1.2 * 1005.0 * 2.5 * 2.5 * L1
    for _ in range(5):
        u = rng.uniform(-25.0, 30.0, size=28)
        x = np.array([25.0, 2000.0, 800.0])
        diff = truth_numpy.rhs(u, x, p) - eng.rhs(u, x, p)
        T1, T2 = u[names.index("zone1.air.T")], u[names.index("zone2.air.T")]
        leak = true_leakage(T1, T2)
        assert diff[names.index("zone1.air.T")] * C_air1 == pytest.approx(-leak, rel=1e-9)
        others = [j for j, n in enumerate(names) if n not in ("zone1.air.T", "zone2.air.T")]
        assert np.abs(diff[others]).max() < 1e-12


def test_leak_size_and_sign() -> None:
    assert true_leakage(np.array(-20.0), np.array(0.0)) == pytest.approx(-LEAK_COEFFICIENT * 20**1.5)
    bulkhead_conduction_20K = 20.0 / (1 / 6.0 + 0.05 / 0.025 + 1 / 6.0) * 2.5 * 2.5
    assert 80.0 <= abs(true_leakage(np.array(20.0), np.array(0.0))) <= 250.0
    assert abs(true_leakage(np.array(20.0), np.array(0.0))) > bulkhead_conduction_20K


# -- generator ------------------------------------------------------------------------------------
def test_generator_is_reproducible(regenerated: Path, tmp_path: Path) -> None:
    exp2 = next(e for e in gen.EXPERIMENTS if e.id == "2")
    gen.generate(tmp_path, [exp2])
    assert (tmp_path / "exp2.csv").read_bytes() == (regenerated / "exp2.csv").read_bytes()


def test_shipped_files_are_what_the_generator_writes(regenerated: Path, shipped) -> None:
    """Identical up to rare one-step rounding flips (a platform's last float bits at a rounding edge)."""
    for exp in gen.EXPERIMENTS:
        new, old = read_telemetry(regenerated / exp.file), shipped[exp.id]
        assert list(new.columns) == list(old.columns)
        assert new.shape == old.shape
        np.testing.assert_array_equal(new["time"], old["time"])
        np.testing.assert_array_equal(new.isna().to_numpy(), old.isna().to_numpy())
        diff = (new - old).abs().to_numpy()
        ok = ~np.isnan(diff)
        assert (diff[ok] == 0).mean() >= 0.995, f"{exp.file}: regenerated file differs in >0.5% of cells"
        temps = new[list(OUTPUTS) + ["ambient.T"]].sub(old[list(OUTPUTS) + ["ambient.T"]]).abs()
        assert np.nanmax(temps.to_numpy()) <= 0.1 + 1e-9


def test_generator_cli_writes_to_out(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    monkeypatch.setattr(gen, "generate", lambda out: calls.append(out) or [])
    assert gen.main(["--out", str(tmp_path)]) == 0
    assert calls == [tmp_path]


# -- telemetry ------------------------------------------------------------------------------------
def test_telemetry_looks_like_real_telemetry(shipped) -> None:
    for exp in gen.EXPERIMENTS:
        path = SHIPPED / exp.file
        assert path.stat().st_size < 100_000
        df = shipped[exp.id]
        assert list(df.columns) == ["time", *OUTPUTS, *INPUTS]
        t = df["time"].to_numpy()
        dt = np.diff(t)
        assert t[0] == 0.0 and t[-1] == pytest.approx(12 * 3600.0)
        assert np.all(dt > 0), "time must be strictly increasing"
        assert np.std(dt[dt < 90]) > 0.5, "timestamps must be irregular (jitter)"
        assert (dt > 100).sum() >= 3, "a few rows are missing"
        # ambient: a slower channel, NaN on the rows between its samples
        amb = df["ambient.T"].notna().to_numpy()
        assert 0.15 < amb.mean() < 0.25
        assert np.median(np.diff(t[amb])) == pytest.approx(300.0, abs=10.0)
        # inputs cover the whole span
        assert df.iloc[[0, -1]][list(INPUTS)].notna().all().all()
        assert df[["zone1.cooling.Q", "zone2.cooling.Q"]].notna().mean().min() == 1.0
        q = df[["zone1.cooling.Q", "zone2.cooling.Q"]].to_numpy()
        assert q.min() >= 0 and q[:, 0].max() <= 5000 and q[:, 1].max() <= 3000
        # zone temperatures: quantised, with dropout windows
        for col in OUTPUTS:
            v = df[col].to_numpy()
            ok = ~np.isnan(v)
            assert np.allclose(v[ok] * 10, np.round(v[ok] * 10), atol=1e-9), f"{col} must be quantised to 0.1"
            runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], (~ok).astype(int), [0]]))))[::2]
            assert (runs >= 10).sum() >= 2, f"{exp.file}: {col} needs at least two dropout windows of >= 10 min"


def test_telemetry_tells_a_pulldown_then_regulation(shipped) -> None:
    for exp in gen.EXPERIMENTS:
        df = shipped[exp.id]
        first = df.iloc[0]
        assert first["ambient.T"] == pytest.approx(exp.T_initial)
        assert first["zone1.air.T"] == pytest.approx(exp.T_initial, abs=0.5)
        last_hour = df[df["time"] > 11 * 3600]
        for z, sp_ in (("zone1", exp.setpoint1), ("zone2", exp.setpoint2)):
            assert last_hour[f"{z}.air.T"].mean() == pytest.approx(sp_, abs=0.5)


def test_truth_model_on_recorded_inputs_reproduces_the_recordings(shipped, truth_numpy) -> None:
    """Honesty: the truth was driven by the interpolated recorded inputs, so it fits to sensor noise."""
    for exp in gen.EXPERIMENTS:
        rmse = compare(exp, shipped[exp.id], truth_numpy).rmse
        assert all(v < 1.3 * NOISE for v in rmse.values()), f"experiment {exp.id}: {rmse}"


def test_engineer_model_misses_by_clearly_more_than_noise() -> None:
    rmse = engineer_rmse(SHIPPED)
    assert set(rmse) == {"1", "2", "3"}
    for exp_id, per_zone in rmse.items():
        assert min(per_zone.values()) > 4 * NOISE, f"experiment {exp_id}: {per_zone}"
        assert max(per_zone.values()) < 10.0, f"experiment {exp_id}: {per_zone}"


# -- configs --------------------------------------------------------------------------------------
def test_model_config_loads_the_builder() -> None:
    cfg = compose([]).model  # the default project is the bundled example; ${project:} is its folder
    assert cfg.builder == f"{EXAMPLE}/model.py:build_model"
    model = load_model(cfg.builder, cfg.options)
    assert model.name == "cargo_box"


def test_data_config_matches_the_generator() -> None:
    cfg = OmegaConf.load(EXAMPLE / "conf" / "data" / "cargo_box.yaml")
    assert cfg.name == "cargo_box" and cfg.time_column == "time"
    assert OmegaConf.to_container(cfg)["root"] == "${project:}/telemetry"
    assert compose([]).data.root == f"{EXAMPLE}/telemetry"
    assert [e.id for e in cfg.experiments] == [e.id for e in gen.EXPERIMENTS]
    params = {v.name for v in build_model().of_kind("parameter")}
    for entry, exp in zip(cfg.experiments, gen.EXPERIMENTS):
        assert entry.file == exp.file and (SHIPPED / entry.file).is_file()
        assert entry.role == exp.role
        given = OmegaConf.to_container(entry.parameters)
        assert given == exp.parameters  # dotted names stay plain keys
        assert set(given) <= params
    assert sorted(e.role for e in cfg.experiments) == ["test", "train", "train"]


def test_truth_is_not_imported_by_the_engineer_side(simplified) -> None:
    src = Path(model_module.__file__).read_text()
    assert "truth" not in src and "LEAK" not in src
    assert not simplified.rhs["zone1.air.T"].has(sp.Abs)

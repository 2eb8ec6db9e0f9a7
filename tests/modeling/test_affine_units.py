"""Units with an offset (interval scales): built-in degC/degF, a model's own declaration, bad declarations."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from physmend.modeling import Model, ModelError
from physmend.modeling import units as units_module
from physmend.modeling.units import AffineUnitError, affine_offset, declare_affine, dimension, is_affine, same


@pytest.fixture(autouse=True)
def fresh_registry(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Each test starts from the built-in affine units only (declarations are process-wide)."""
    monkeypatch.setattr(units_module, "_USER_AFFINE", {})
    monkeypatch.setattr(units_module, "_USER_BASE", {})
    yield


@pytest.mark.parametrize("unit, offset", [("degC", 273.15), ("°C", 273.15), ("degF", 459.67), ("°F", 459.67),
                                          (" degC ", 273.15)])
def test_celsius_and_fahrenheit_are_affine_and_temperatures(unit: str, offset: float) -> None:
    assert is_affine(unit) and affine_offset(unit) == offset
    d = dimension(unit)
    assert d is not None and same(d, dimension("K"))  # type: ignore[arg-type]


@pytest.mark.parametrize("unit", ["K", "mK", "W", "degC/s", "K/s", "", None, "kanimals", "m3/s"])
def test_absolute_units_compounds_and_no_unit_are_not_affine(unit: str | None) -> None:
    assert not is_affine(unit) and affine_offset(unit) is None


def test_a_model_declares_its_own_affine_unit_with_offset_and_base() -> None:
    m = Model("m")
    assert not is_affine("degRe")
    m.affine_unit("degRe", offset=218.52, base="K")
    m.affine_unit("degRe", offset=218.52, base="K")  # the same declaration again: nothing changes
    m.state("x.T", start=10.0, unit="degRe")
    assert is_affine("degRe") and affine_offset("degRe") == 218.52
    assert same(dimension("degRe"), dimension("K"))  # type: ignore[arg-type]
    assert same(dimension("W/degRe"), dimension("W/K"))  # type: ignore[arg-type]


def test_without_a_base_the_affine_unit_is_a_dimension_of_its_own() -> None:
    declare_affine("barg", 1.01325)
    assert is_affine("barg") and dimension("barg") == {"barg": 1.0}


def test_an_affine_unit_without_offset_is_one_line_naming_it() -> None:
    with pytest.raises(ModelError) as err:
        Model("plant").affine_unit("degRe")
    text = str(err.value)
    assert "\n" not in text and "'degRe'" in text and "offset" in text and "'plant'" in text
    assert not is_affine("degRe")  # nothing was recorded


@pytest.mark.parametrize("unit, offset, base, message", [
    ("degX", float("nan"), None, r"affine unit 'degX' needs a finite number as offset, but got nan"),
    ("degX", True, None, r"needs a finite number as offset, but got True"),
    ("degX", "273", None, r"needs a finite number as offset, but got '273'"),
    ("K", 0.0, None, r"unit 'K' is an absolute \(ratio-scale\) unit and cannot be declared affine"),
    ("kW", 0.0, None, r"unit 'kW' is an absolute"),
    ("degC/s", 1.0, None, r"one unit word .* but got 'degC/s'"),
    ("degC", 0.0, None, r"affine unit 'degC' is already declared with offset 273.15, but got offset 0"),
    ("degX", 1.0, "m/(s", r"base must be a readable unit such as 'K', but got 'm/\(s'"),
])
def test_bad_declarations_state_the_rule_and_the_value(unit: str, offset: object, base: str | None,
                                                       message: str) -> None:
    with pytest.raises(AffineUnitError, match=message):
        declare_affine(unit, offset, base=base)  # type: ignore[arg-type]
    assert not is_affine("degX")


def test_redeclaring_with_another_offset_is_refused() -> None:
    declare_affine("degRe", 218.52)
    with pytest.raises(AffineUnitError, match=r"'degRe' is already declared with offset 218.52, but got offset 200"):
        declare_affine("degRe", 200.0)
    assert affine_offset("degRe") == 218.52


def test_a_model_file_declaring_without_offset_fails_to_load_in_one_line(tmp_path) -> None:
    from physmend.modeling.loader import load_model

    path = tmp_path / "plant.py"
    path.write_text(
        "from physmend.modeling import Model\n"
        "def build():\n"
        "    m = Model('plant')\n"
        "    m.affine_unit('degRe')\n"
        "    return m\n", encoding="utf-8")
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(ModelError) as err:
        load_model(f"{path}:build")
    text = str(err.value)
    assert "\n" not in text and "'degRe'" in text and "offset" in text, text
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "__pycache__") == before  # nothing written

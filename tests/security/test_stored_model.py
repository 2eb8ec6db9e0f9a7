"""A trained model read back from a shared store is data written by someone else: a ``hybrid.json``
whose network would not fit in memory, names nothing of the model or does not match its weights, a
``weights.pt`` that is a pickle, a ``config.yaml`` with a Python tag — each is refused by the stage
that loads the run (``physmend mask RUN_ID``) in one line naming the run, the file and the key,
exit 2, within seconds, before anything is allocated or run; nothing the user owns changes."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

Cli = Callable[..., tuple[int, str]]


def _tree(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _edit_spec(trial: Any, change: Callable[[dict[str, Any]], None]) -> None:
    path = trial.artifact("model/hybrid.json")
    meta = json.loads(path.read_text())
    change(meta["spec"])
    path.write_text(json.dumps(meta))


def _refused(trial: Any, run_cli: Cli, *words: str) -> str:
    """``physmend mask RUN_ID`` on the tampered trial: one short line naming ``words``, exit 2, fast."""
    before = _tree(trial.project / "recordings"), _tree(trial.project / "my_conf")
    start = time.perf_counter()
    rc, err = run_cli("mask", trial.run_id, *trial.args())
    assert time.perf_counter() - start < 10
    assert rc == 2, err
    line = err.strip()
    assert "\n" not in line and "Traceback" not in line and len(line) <= 300, err
    assert f"run {trial.run_id!r}" in line, line
    for word in words:
        assert word in line, (word, line)
    assert (_tree(trial.project / "recordings"), _tree(trial.project / "my_conf")) == before
    return line


def test_the_untampered_trial_loads(stored_trial: Any) -> None:
    from physmend.config import compose
    from physmend.stages.common import load_source
    from physmend.tracking.runs import get_run

    cfg = compose(["model=oscillator", "data=oscillator"], user_config_dir=stored_trial.project / "my_conf")
    src = load_source(stored_trial.store, get_run(stored_trial.store, stored_trial.run_id), cfg)
    assert src.hybrid.spec.widths == [4, 4] and src.hybrid.spec.in_inputs == ["motor.F"]


def test_widths_that_would_not_fit_in_memory_are_refused_before_allocating(stored_trial: Any, run_cli: Cli) -> None:
    _edit_spec(stored_trial, lambda s: s.__setitem__("widths", [200000, 200000]))
    _refused(stored_trial, run_cli, "model/hybrid.json", "spec.widths", "200000")


#: (key, tampered value, words the line must hold): one per name list and number of the spec
SPEC_CASES: list[tuple[str, Any, list[str]]] = [
    ("in_observed", ["nope"], ["spec.in_observed", "'nope'", "observed variables"]),
    ("in_inputs", ["cart.x"], ["spec.in_inputs", "'cart.x'", "inputs"]),
    ("in_parameters", ["nope"], ["spec.in_parameters", "'nope'"]),
    ("corrected", ["cart.v", "cart.v"], ["spec.corrected", "twice"]),
    ("in_states", ["cart.x", "cart.v", "cart.F_net"], ["spec.in_states", "'cart.F_net'"]),
    ("estimated", ["spring.k"], ["spec.estimated", "'spring.k'", "uncertain parameters"]),
    ("activation", "__import__", ["spec.activation", "'__import__'"]),
    ("units", "furlongs", ["spec.units", "'furlongs'"]),
    ("widths", [4, -3], ["spec.widths", "-3"]),
    ("widths", "44", ["spec.widths", "'44'"]),
    ("widths", [4] * 40, ["spec.widths", "at most 16"]),
    ("mean", [0.0], ["spec.mean", "3 numbers"]),
    ("std", [1.0, 0.0, 1.0], ["spec.std", "0.0"]),
    ("out_scale", [1e400], ["spec.out_scale", "inf"]),
    ("state_low", [None], ["spec.state_low", "2"]),
    ("in_observed", ["x" * 5000], ["spec.in_observed", "5000 characters"]),
    ("format", 1, ["spec", "'format'"]),
]


def test_every_name_list_and_number_is_checked_against_the_model(stored_trial: Any, run_cli: Cli) -> None:
    path = stored_trial.artifact("model/hybrid.json")
    original = path.read_text()
    for key, value, words in SPEC_CASES:
        _edit_spec(stored_trial, lambda s: s.__setitem__(key, value))
        _refused(stored_trial, run_cli, "model/hybrid.json", *words)
        path.write_text(original)


def test_a_missing_spec_key_and_broken_json_are_one_line(stored_trial: Any, run_cli: Cli) -> None:
    _edit_spec(stored_trial, lambda s: s.pop("in_inputs"))
    _refused(stored_trial, run_cli, "model/hybrid.json", "spec.in_inputs", "missing")
    stored_trial.artifact("model/hybrid.json").write_text("[" * 100_000)
    _refused(stored_trial, run_cli, "model/hybrid.json", "JSON")


class _Payload:
    """Unpickling this runs ``touch pwned``: what a pickled ``weights.pt`` could carry."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return os.system, (f"touch {self.marker}",)


def test_a_pickled_weights_file_is_refused_unopened(stored_trial: Any, run_cli: Cli) -> None:
    import torch

    marker = stored_trial.project / "pwned"
    torch.save({"net.0.weight": _Payload(marker)}, stored_trial.artifact("model/weights.pt"))
    _refused(stored_trial, run_cli, "model/weights.pt", "tensors only")
    assert not marker.exists()
    stored_trial.artifact("model/weights.pt").write_bytes(pickle.dumps(_Payload(marker)))
    _refused(stored_trial, run_cli, "model/weights.pt")
    assert not marker.exists()


def test_weights_that_do_not_fit_the_network_are_one_line(stored_trial: Any, run_cli: Cli) -> None:
    import torch

    path = stored_trial.artifact("model/weights.pt")
    state = torch.load(path, weights_only=True)
    state["net.0.weight"] = torch.zeros(7, 3, dtype=torch.float64)
    torch.save(state, path)
    _refused(stored_trial, run_cli, "model/weights.pt", "net.0.weight", "(7, 3)", "(4, 3)")
    state.pop("net.0.weight")
    torch.save(state, path)
    _refused(stored_trial, run_cli, "model/weights.pt", "net.0.weight", "missing")


def test_a_weights_file_far_larger_than_its_network_is_never_read(stored_trial: Any, run_cli: Cli) -> None:
    import torch

    torch.save({"big": torch.zeros(2_000_000, dtype=torch.float64)}, stored_trial.artifact("model/weights.pt"))
    _refused(stored_trial, run_cli, "model/weights.pt", "bytes")


def test_a_python_tag_in_the_stored_config_is_one_line_and_never_runs(stored_trial: Any, run_cli: Cli) -> None:
    marker = stored_trial.project / "pwned"
    path = stored_trial.artifact("config.yaml")
    path.write_text(path.read_text() + f"evil: !!python/object/apply:os.system ['touch {marker}']\n")
    _refused(stored_trial, run_cli, "config.yaml")
    assert not marker.exists()


def test_a_kept_tag_naming_no_corrected_state_is_one_line(stored_trial: Any, run_cli: Cli) -> None:
    stored_trial.store.client.set_tag(stored_trial.run_id, "physmend.kept", "cart.v,nope")
    _refused(stored_trial, run_cli, "physmend.kept", "'nope'")


def test_a_deeply_nested_stored_config_is_one_line(stored_trial: Any, run_cli: Cli) -> None:
    path = stored_trial.artifact("config.yaml")
    path.write_text(path.read_text() + "deep: " + "[" * 5000 + "]" * 5000 + "\n")
    _refused(stored_trial, run_cli, "config.yaml", "nests", "100 levels")

"""The correcting network written as open files (:mod:`physmend.ude.network_file`): the architecture
JSON in PEtab-SciML's layout and the safetensors weights, read back by plain numpy (no physmend, no
torch), give the network's own corrections."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch


def test_the_network_files_reproduce_the_corrections(user_project: Path) -> None:
    from physmend.config import compose
    from physmend.problem import load_problem
    from physmend.ude.hybrid import HybridModel, HybridSpec
    from physmend.ude.network_file import network_files, read_safetensors

    problem = load_problem(compose(["model=oscillator", "data=oscillator"], user_config_dir=user_project / "my_conf"))
    spec = HybridSpec(corrected=["cart.x", "cart.v"], in_states=["cart.x", "cart.v"], in_observed=[], in_inputs=["motor.F"],
                      in_parameters=[], widths=[5, 3], activation="tanh", mean=[0.1, -0.2, 0.3], std=[2.0, 0.5, 1.5],
                      out_scale=[0.5, 2.0], units="state")
    torch.manual_seed(3)
    hybrid = HybridModel(problem.compiled, spec, problem.dtype)
    with torch.no_grad():
        for p in hybrid.net.parameters():
            p.normal_()
    hybrid.keep_only(["cart.v"])
    files = network_files(hybrid, {"cart.x": "m", "cart.v": "m/s", "motor.F": "N"}, stem="m1", meta={"model": "osc"})
    assert sorted(files) == ["m1.network.json", "m1.network.safetensors"]
    doc = json.loads(files["m1.network.json"])
    (model,) = doc["models"]
    assert [layer["args"] for layer in model["layers"]] == [
        {"in_features": 3, "out_features": 5, "bias": True}, {"in_features": 5, "out_features": 3, "bias": True},
        {"in_features": 3, "out_features": 2, "bias": True}]
    assert [step["op"] for step in model["forward"]] == ["placeholder", "call_module", "call_function", "call_module",
                                                         "call_function", "call_module", "output"]
    info = doc["physmend"]
    assert [f["name"] for f in info["features"]] == ["cart.x", "cart.v", "motor.F"] and info["features"][2]["unit"] == "N"
    assert [(o["state"], o["kept"]) for o in info["outputs"]] == [("cart.x", False), ("cart.v", True)]
    weights = read_safetensors(files["m1.network.safetensors"])
    assert weights["layer1.weight"].shape == (5, 3) and weights["layer3.bias"].shape == (2,)

    # the JSON's forward graph, evaluated with numpy alone, is the network's correction
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(7, 3))
    values: dict[str, np.ndarray] = {}
    for step in model["forward"]:
        if step["op"] == "placeholder":
            mean = np.array([f["mean"] for f in info["features"]])
            std = np.array([f["std"] for f in info["features"]])
            values[step["name"]] = (feats - mean) / std
        elif step["op"] == "call_module":
            x = values[step["args"][0]]
            values[step["name"]] = x @ weights[f"{step['target']}.weight"].T + weights[f"{step['target']}.bias"]
        elif step["op"] == "call_function":
            values[step["name"]] = getattr(np, step["target"])(values[step["args"][0]])
        else:
            out = values[step["args"][0]]
    scale = np.array([o["scale"] * o["kept"] for o in info["outputs"]])
    with torch.no_grad():
        want = hybrid.net((torch.as_tensor(feats) - hybrid.mean) / hybrid.std) * hybrid.out_scale * hybrid.out_mask
    assert out * scale == pytest.approx(want.numpy(), rel=1e-12, abs=1e-12)

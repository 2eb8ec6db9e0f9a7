"""``device=auto|cpu|cuda|cuda:N``: the rule that resolves it on this machine, and a network that is
initialised on the CPU (the same weights for a seed on every device) and then follows the device its
training is placed on. (Bad values on the command line: tests/security/test_bad_input.py.)"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from physmend.config import ConfigError, compose
from physmend.device import CPU, placed, resolve_device
from physmend.problem import load_problem
from physmend.ude.hybrid import HybridModel
from physmend.ude.spec import build_spec
from physmend.ude.timescale import resolve_times
from physmend.ude.reference import reference


def test_auto_is_the_gpu_when_torch_sees_one_else_the_cpu() -> None:
    expected = torch.device("cuda") if torch.cuda.is_available() else CPU
    assert resolve_device("auto") == expected
    assert resolve_device(None) == expected
    assert resolve_device("CPU") == CPU and resolve_device(" cpu ") == CPU


@pytest.mark.parametrize("word", ["gpu", "cuda:x", "cuda:-1", "tpu", ""])
def test_an_unknown_device_names_the_choices(word: str) -> None:
    with pytest.raises(ConfigError, match=r"device must be auto, cpu, cuda or cuda:N"):
        resolve_device(word)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
@pytest.mark.parametrize("word", ["cuda", "cuda:0", "cuda:3"])
def test_cuda_without_a_gpu_says_so_and_what_to_use(word: str) -> None:
    with pytest.raises(ConfigError, match=rf"device={word}: this torch .* sees no CUDA device; use device=auto .* or device=cpu"):
        resolve_device(word)


def test_a_network_starts_from_the_cpu_weights_and_moves_to_the_training_device(user_project: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Under a non-CPU device (``meta`` stands in for a GPU here) the network is drawn from the CPU's
    random numbers exactly as on the CPU — the same draws, nothing more — and then every parameter
    and buffer of the model is on that device."""
    monkeypatch.chdir(user_project)
    cfg = compose(["model=oscillator", "data=oscillator", "simulate=explicit"], user_config_dir=user_project / "my_conf")
    problem = load_problem(cfg)
    assert problem.device == resolve_device("auto")
    ref = reference(problem, cfg)
    spec = build_spec(resolve_times(cfg, problem, ref), problem, ref)

    torch.manual_seed(3)
    on_cpu = HybridModel(problem.compiled, spec, problem.dtype)
    after_cpu = torch.rand(4)
    torch.manual_seed(3)
    with placed(torch.device("meta")):
        moved = HybridModel(problem.compiled, spec, problem.dtype)
    after_meta = torch.rand(4)
    assert torch.equal(after_cpu, after_meta)  # the same random draws made the weights
    tensors = dict(moved.named_parameters()) | dict(moved.named_buffers())
    assert tensors and {t.device.type for t in tensors.values()} == {"meta"}, {k: t.device for k, t in tensors.items()}
    assert {t.device.type for t in on_cpu.state_dict().values()} == {"cpu"}
    moved.keep_only(spec.corrected[:1])  # a mask made later stays on the model's device
    assert moved.out_mask.device.type == "meta"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (the GPU check of benchmarks/README.md)")
def test_training_on_the_gpu_gives_the_cpu_result_back_on_the_cpu(user_project: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """One small training and one stack of two on each device: the same checkpoints' metrics (to the
    solver's tolerance: kernels round differently), and models returned on the CPU."""
    from physmend.ude.stack import train_stack
    from physmend.ude.train import train

    monkeypatch.chdir(user_project)
    tiny = ["model=oscillator", "data=oscillator", "train.step=0.05", "train.segment_length=3.0", "train.epochs=20",
            "train.eval_every=5", "ude.width=8", "ude.depth=1"]
    results = {}
    for device in ("cpu", "cuda"):
        cfg = compose([*tiny, f"device={device}"], user_config_dir=user_project / "my_conf")
        problem = load_problem(cfg)
        assert problem.device.type == device
        other = compose([*tiny, f"device={device}", "train.lr=0.003", "seed=1"], user_config_dir=user_project / "my_conf")
        results[device] = [train(cfg, problem), *train_stack([cfg, other], problem)]
    for cpu, gpu in zip(results["cpu"], results["cuda"]):
        assert {t.device.type for t in gpu.hybrid.state_dict().values()} == {"cpu"}
        assert gpu.val_rmse == pytest.approx(cpu.val_rmse, rel=1e-4)
        assert [r["epoch"] for r in gpu.history] == [r["epoch"] for r in cpu.history]

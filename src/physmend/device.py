"""Where training runs: the ``device`` setting (``auto | cpu | cuda | cuda:N``) resolved against this
machine, and the context that places a training's tensors there.

Training (the sweep's trials, the mask's retrainings) and the simulations inside it — the
reference, the multiple-shooting epochs, the checkpoint evaluations — run on the resolved device;
what a training returns (:class:`physmend.ude.TrainResult`) is moved back to the CPU, so every other
stage, every artifact and every figure is the same whichever device trained. Networks are
initialised on the CPU and then moved: a seed gives the same initial weights on every device.

Imports ``config`` only (its error).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from physmend.config import ConfigError

CPU = torch.device("cpu")

_CUDA = re.compile(r"cuda(?::(\d+))?")


def resolve_device(setting: object) -> torch.device:
    """The torch device ``setting`` names on this machine.

    ``auto`` (or unset): the first CUDA device when torch sees one, else the CPU; ``cpu``;
    ``cuda`` / ``cuda:N``: that CUDA device, which must exist.

    Raises:
        ConfigError: an unknown word, or a CUDA device this machine (or this build of torch) lacks.
    """
    text = "auto" if setting is None else str(setting).strip().lower()
    if text == "auto":
        return torch.device("cuda") if torch.cuda.is_available() else CPU
    if text == "cpu":
        return CPU
    match = _CUDA.fullmatch(text)
    if match is None:
        raise ConfigError(f"device must be auto, cpu, cuda or cuda:N (N a device number), but got {setting!r}")
    if not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
        raise ConfigError(f"device={text}: this torch {torch.__version__} ({build}) sees no CUDA device; "
                          "use device=auto (the GPU when there is one) or device=cpu")
    index = int(match.group(1) or 0)
    count = torch.cuda.device_count()
    if index >= count:
        raise ConfigError(f"device={text}: this machine has {count} CUDA device(s), numbered 0 to {count - 1}")
    return torch.device("cuda", index)


@contextmanager
def placed(device: torch.device) -> Iterator[None]:
    """Tensors created inside (factory functions, ``torch.as_tensor`` of data, new modules) land on
    ``device``. On the CPU nothing is entered: the code runs exactly as without a device."""
    if device.type == "cpu":
        yield
        return
    with torch.device(device):
        yield


@contextmanager
def on_cpu() -> Iterator[None]:
    """Inside :func:`placed`: create on the CPU after all (networks are initialised there, then
    moved, so a seed gives the same weights on every device). Outside it: nothing entered."""
    if torch.get_default_device().type == "cpu":
        yield
        return
    with torch.device(CPU):
        yield


"""The correcting network in open files, beside the formula: its architecture as JSON laid out as
PEtab-SciML's neural-network model format (``models[].layers`` and a ``forward`` graph in
``torch.fx`` terms: ``placeholder``, ``call_module``, ``call_function``, ``output``) and its weights
as safetensors (the format of Hugging Face's ``safetensors``: an 8-byte little-endian header length,
a JSON header naming each tensor's dtype, shape and byte range, then the raw little-endian data).

PEtab-SciML's own library needs Python ≥ 3.12 and its parameter files HDF5 (``h5py``), neither
available here; safetensors needs no library to write or read (``safetensors.safe_open``,
``numpy.frombuffer``). Tensor names are PEtab-SciML's ``<layer_id>.weight`` (``(out, in)``) and
``<layer_id>.bias`` (``(out,)``), as in a PyTorch ``state_dict``.

What the network's numbers mean in the model (its ``physmend`` section): the features are the
listed variables in their units, normalised ``z = (feature - mean) / std``; the correction of state
``i`` is ``scale_i · kept_i · network(z)_i`` — in the units of that state's equation and then
divided by the equation's coefficient of ``der(x_i)`` when ``units`` is ``equation``, a rate of the
state per time unit when it is ``state``.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

FORMAT = "physmend-network 1"
_DTYPES = {np.dtype("float64"): "F64", np.dtype("float32"): "F32"}


def safetensors_bytes(tensors: dict[str, np.ndarray], metadata: dict[str, str] | None = None) -> bytes:
    """``tensors`` (name -> array, float32/64) as one safetensors file."""
    header: dict[str, Any] = {}
    blobs = []
    offset = 0
    for name, array in tensors.items():
        a = np.ascontiguousarray(array)
        dtype = _DTYPES.get(a.dtype)
        if dtype is None:
            raise ValueError(f"tensor {name!r}: dtype {a.dtype} is not float32 or float64")
        data = a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
        header[name] = {"dtype": dtype, "shape": list(a.shape), "data_offsets": [offset, offset + len(data)]}
        blobs.append(data)
        offset += len(data)
    if metadata:
        header["__metadata__"] = {str(k): str(v) for k, v in metadata.items()}
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the data starts 8-byte aligned
    return struct.pack("<Q", len(text)) + text + b"".join(blobs)


def read_safetensors(data: bytes) -> dict[str, np.ndarray]:
    """The tensors of a safetensors file (the inverse of :func:`safetensors_bytes`)."""
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + n])
    body = data[8 + n:]
    kinds = {"F64": "<f8", "F32": "<f4"}
    out = {}
    for name, info in header.items():
        if name == "__metadata__":
            continue
        lo, hi = info["data_offsets"]
        out[name] = np.frombuffer(body[lo:hi], dtype=kinds[info["dtype"]]).reshape(info["shape"])
    return out


def network_files(hybrid: Any, units: dict[str, str], *, stem: str, meta: dict[str, Any]) -> dict[str, bytes | str]:
    """``{stem}.network.json`` (architecture and meaning) and ``{stem}.network.safetensors`` (weights)
    of ``hybrid`` (:class:`physmend.ude.hybrid.HybridModel`); ``units``: variable name -> unit."""
    import torch

    spec = hybrid.spec
    layers, forward, tensors = [], [{"name": "input0", "op": "placeholder", "target": "input0", "args": [], "kwargs": {}}], {}
    last, k = "input0", 0
    for module in hybrid.net:
        if isinstance(module, torch.nn.Linear):
            k += 1
            lid = f"layer{k}"
            layers.append({"layer_id": lid, "layer_type": "Linear",
                           "args": {"in_features": module.in_features, "out_features": module.out_features,
                                    "bias": module.bias is not None}})
            forward.append({"name": lid, "op": "call_module", "target": lid, "args": [last], "kwargs": {}})
            tensors[f"{lid}.weight"] = module.weight.detach().cpu().numpy()
            if module.bias is not None:
                tensors[f"{lid}.bias"] = module.bias.detach().cpu().numpy()
            last = lid
        else:
            name = f"{spec.activation}_{k}"
            forward.append({"name": name, "op": "call_function", "target": spec.activation, "args": [last], "kwargs": {}})
            last = name
    forward.append({"name": "output", "op": "output", "target": "output", "args": [last], "kwargs": {}})
    mask = hybrid.out_mask.detach().cpu().tolist()
    doc = {
        "format": FORMAT,
        "layout": "PEtab-SciML neural-network model (models: mlmodel_id, inputs, layers, forward), as JSON",
        **{k2: v for k2, v in meta.items() if isinstance(v, (str, int, float))},
        "weights": f"{stem}.network.safetensors",
        "models": [{"mlmodel_id": "correction", "inputs": [{"input_id": "input0", "shape": [spec.n_inputs]}],
                    "layers": layers, "forward": forward}],
        "physmend": {
            "features": [{"name": n, "unit": units.get(n, ""), "mean": float(m), "std": float(s)}
                         for n, m, s in zip(spec.input_names, spec.mean, spec.std)],
            "outputs": [{"state": n, "unit": units.get(n, ""), "scale": float(sc), "kept": bool(on)}
                        for n, sc, on in zip(spec.corrected, spec.out_scale, mask)],
            "units": spec.units,
            "correction": ("correction_i = scale_i * kept_i * network((features - mean) / std)_i"
                           + (", in the units of state i's equation; divided by that equation's coefficient of "
                              "der(x_i) it is a rate" if spec.units == "equation" else ", a rate of state i per time unit")),
            "jointly_estimated": hybrid.estimates(),
        },
    }
    weights = safetensors_bytes({k2: np.asarray(v, dtype=np.float64) for k2, v in tensors.items()},
                                {"format": FORMAT, "architecture": f"{stem}.network.json"})
    return {f"{stem}.network.json": json.dumps(doc, indent=1) + "\n", f"{stem}.network.safetensors": weights}

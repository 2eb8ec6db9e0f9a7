"""Rebuild ``telemetry/`` from the Silverbox benchmark's raw recording — deterministic.

THE DATA ARE REAL: the Silverbox (Wigren & Schoukens, ECC 2013), an electronic circuit built to
behave as a Duffing oscillator, ``m·y'' + d·y' + k·y + k3·y³ = u``. ``V1`` is the input voltage u,
``V2`` the measured output y, both sampled at fs = 10^7/2^14 = 610.3515625 Hz. Nothing here is
synthetic and nothing is added: this script only cuts the one raw file into experiments, puts a
``time`` column in front and writes the initial values it derives from each record's first three
samples into the data config's table below (they are already in ``conf/data/silverbox.yaml``).

Raw file: ``SNLS80mV.csv`` of ``SilverboxFiles.zip`` (nonlinearbenchmark.org), SHA-256
``ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1``; a byte-identical copy is
committed in github.com/forgi86/pytorch-ident at f00d79ff8c6cb96d094d9ea1c079d4dcbf9a67e0,
``examples/statespace/silverbox/SilverboxFiles/SNLS80mV.csv``.

    python prepare.py PATH/TO/SNLS80mV.csv     # writes telemetry/ beside this file

Experiments (0-based sample indices of the raw file, end exclusive):

* ``arrow`` (test) = samples 100–32100: the benchmark's standard ``test_arrow_no_extrapolation``
  split (the official loader ``nonlinear_benchmarks.Silverbox()``: the first 32,000 samples of
  ``test_arrow_full`` = samples 100–40575), a filtered noise of linearly growing amplitude (the
  "arrow head") that stays within the amplitudes of the estimation data. The benchmark scores
  samples 50 onwards of a test set; the first 50 may be used to set the state.
* ``ms2``, ``ms3`` (train) and ``ms4`` (validation): the first 1,500 samples (2.46 s, about 170
  periods of the resonance) of the 2nd, 3rd and 4th of the ten odd random-phase multisine blocks
  that follow the arrow head, each from the sample where its input leaves the quiet gap before
  it. All three lie inside the standard estimation split ``train_val`` = samples 40650–105712; the
  rest of it is not used, so that ``physmend discover`` stays within minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent
SHA256 = "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1"
FS = 1e7 / 2**14  # Hz, the benchmark's sampling frequency
EXPERIMENTS = [  # id, role, first sample, end sample (exclusive)
    ("ms2", "train", 49229, 50729),
    ("ms3", "train", 57924, 59424),
    ("ms4", "validation", 66616, 68116),
    ("arrow", "test", 100, 32100),
]
INPUT, OUTPUT = "source.u", "mass.x"  # model names of V1 and V2


def initial_velocity(y: np.ndarray) -> float:
    """``der(y)`` at a record's first sample from its first three (V/s): ``(−3y0 + 4y1 − y2)/(2Δ)``.

    Uses only samples inside the benchmark's 50-sample state-initialisation window.
    """
    return float((-3.0 * y[0] + 4.0 * y[1] - y[2]) * FS / 2.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("raw", type=Path, help="the benchmark's SNLS80mV.csv (columns V1, V2)")
    args = ap.parse_args(argv)
    digest = hashlib.sha256(args.raw.read_bytes()).hexdigest()
    if digest != SHA256:
        raise SystemExit(f"{args.raw}: SHA-256 must be {SHA256} (SilverboxFiles.zip's SNLS80mV.csv), but got {digest}")
    raw = pd.read_csv(args.raw, usecols=["V1", "V2"], dtype=str)
    out = HERE / "telemetry"
    out.mkdir(exist_ok=True)
    print("| id | role | samples | start mass.x [V] | start mass.v [V/s] |")
    for exp_id, role, start, end in EXPERIMENTS:
        part = raw.iloc[start:end]
        n = end - start
        # time from the record's first sample, exact in decimal (Δ = 1.6384 ms)
        time = [f"{i * 16384 / 1e7:.7f}".rstrip("0").rstrip(".") for i in range(n)]
        frame = pd.DataFrame({"time": time, INPUT: part["V1"].to_numpy(), OUTPUT: part["V2"].to_numpy()})
        frame.to_csv(out / f"{exp_id}.csv", index=False)
        y = part["V2"].astype(float).to_numpy()
        print(f"| {exp_id} | {role} | {n} | {y[0]:.6g} | {initial_velocity(y):.6g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

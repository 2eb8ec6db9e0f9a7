"""The model a run was made with, recorded on the run and compared when a later stage loads it.

A stage run records the fingerprint of the model it built (:mod:`physmend.modeling.fingerprint`):
tags ``physmend.model.structure`` and ``physmend.model.source`` (SHA-256) and the structure as text
(``model_structure.txt``). A stage that loads a run builds the model from the user's *own*
configuration and compares: equations, variables or outputs that differ are one clear error naming
the first difference (the run's network, formulas and constants belong to another model); a model
file whose bytes changed but which builds the same equations is a one-line note, not an error (an
edited comment changes nothing physmend computes). A run recorded without a fingerprint (an older
physmend) is compared by configuration only.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from physmend.tracking.store import Store, TrackingError

STRUCTURE_TAG = "physmend.model.structure"
SOURCE_HASH_TAG = "physmend.model.source"
STRUCTURE_FILE = "model_structure.txt"


def _current(cfg: DictConfig) -> Any:
    from physmend.modeling.fingerprint import known

    builder = OmegaConf.select(cfg, "model.builder", default=None)
    if builder is None:
        return None
    return known(str(builder), OmegaConf.select(cfg, "model.options", default=None) or {})


def fingerprint_tags(cfg: DictConfig) -> tuple[dict[str, str], str | None]:
    """Tags and structure text for a run about to be made with ``cfg`` (empty when no model was built)."""
    found = _current(cfg)
    if found is None:
        return {}, None
    return {STRUCTURE_TAG: found.structure, SOURCE_HASH_TAG: found.source}, found.text


def check_same_model(store: Store, run: Any, cfg: DictConfig) -> None:
    """Raise :class:`TrackingError` when ``run`` was made with a model other than the one ``cfg`` builds.

    Call after the user's model was built (``load_problem(cfg)``)."""
    from physmend.modeling.fingerprint import difference

    run_id = run.info.run_id
    theirs = run.data.tags.get(STRUCTURE_TAG)
    mine = _current(cfg)
    if not theirs or mine is None:
        return
    if theirs != mine.structure:
        what = ""
        try:
            with tempfile.TemporaryDirectory(prefix="physmend-") as tmp:
                text = Path(store.client.download_artifacts(run_id, STRUCTURE_FILE, tmp)).read_text()
            what = difference(text, mine.text)
        except Exception:  # noqa: BLE001 - the hash alone says it: the description is a courtesy
            what = ""
        raise TrackingError(
            f"run {run_id!r} was made with another model than the one model.builder "
            f"{str(cfg.model.builder)!r} builds now ({what or 'structure ' + theirs[:12] + ' vs ' + mine.structure[:12]}): "
            "start again from a sweep with this model, or restore the model file the run was made with"
        )
    source = run.data.tags.get(SOURCE_HASH_TAG, "")
    if source and mine.source and source != mine.source:
        print(f"physmend: note: the model file changed since run {run_id} was made, but it builds the same "
              "equations; going on", file=sys.stderr)

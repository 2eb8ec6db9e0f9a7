"""Reading a run's plain-file artifacts back (JSON, text, PNG), and figures and formulas made from them."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from typing import Any

from physmend.tracking import Store, download_artifact


def quiet_mlflow() -> None:
    """What the command line sets before any stage: no progress bar per artifact, no store notices."""
    import logging
    import os

    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")  # no "View run" lines
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)


@dataclass(frozen=True)
class RunFiles:
    """The artifacts of run ``run_id`` in ``store`` (downloaded on each read, nothing kept on disk)."""

    store: Store
    run_id: str

    def read_bytes(self, path: str) -> bytes:
        """The bytes of artifact ``path`` (relative to the run's artifact root).

        Raises:
            TrackingError: the run has no such artifact.
        """
        quiet_mlflow()
        local = download_artifact(self.store, self.run_id, path)
        try:
            return local.read_bytes()
        finally:
            shutil.rmtree(local.parent, ignore_errors=True)

    def read_text(self, path: str) -> str:
        return self.read_bytes(path).decode("utf-8")

    def read_json(self, path: str) -> Any:
        return json.loads(self.read_text(path))

    def listing(self, folder: str) -> tuple[str, ...]:
        """The artifact paths directly inside ``folder`` (sorted; empty when there is none)."""
        try:
            return tuple(sorted(f.path for f in self.store.client.list_artifacts(self.run_id, folder) if not f.is_dir))
        except Exception:  # noqa: BLE001 - a run without the folder: no files
            return ()

    def tags(self) -> dict[str, str]:
        return dict(self.store.client.get_run(self.run_id).data.tags)

    def metrics(self) -> dict[str, float]:
        return dict(self.store.client.get_run(self.run_id).data.metrics)


def figure_of_png(png: bytes, title: str = "") -> Any:
    """A matplotlib figure showing the image ``png`` at its own size (100 dpi), axes hidden; in Jupyter it
    shows itself as that PNG (no pyplot needed)."""
    import io

    import matplotlib.image as mpimg
    from matplotlib.figure import Figure

    class StoredFigure(Figure):
        """A figure read back from a run's PNG artifact."""

        def _repr_png_(self) -> bytes:
            return png

    image = mpimg.imread(io.BytesIO(png), format="png")
    height, width = image.shape[:2]
    fig = StoredFigure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(image)
    ax.set_axis_off()
    if title:
        fig.text(0.5, 0.99, title, ha="center", va="top", fontsize=7, color="0.4")
    return fig


def formula(text: str, constants: dict[str, float] | None = None, *, where: str = "formula") -> Any:
    """The sympy expression of a stored formula (restricted parser: numbers, names, whitelisted
    functions), its ``constants`` substituted by their values."""
    import sympy as sp

    from physmend.modeling.safe_parse import parse_safe

    expr = parse_safe(str(text), where=where, new_symbols=True)
    if constants:
        expr = expr.subs({sp.Symbol(k): sp.Float(float(v)) for k, v in constants.items()})
    return expr


def lineage(files: RunFiles) -> dict[str, str]:
    """Stage name -> run ID of ``files``'s run and every run it was built on (its source tags)."""
    from physmend.tracking import SOURCE_TAG, STAGE_TAG

    out: dict[str, str] = {}
    run_id: str | None = files.run_id
    while run_id and len(out) < 12:
        run = files.store.client.get_run(run_id)
        stage = run.data.tags.get(STAGE_TAG, "")
        if stage == "trial":
            out.setdefault("trial", run_id)
            run_id = run.data.tags.get("mlflow.parentRunId")
            continue
        out.setdefault(stage, run_id)
        run_id = run.data.tags.get(SOURCE_TAG) or None
    return out

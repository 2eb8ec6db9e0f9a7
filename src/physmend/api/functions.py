"""One function per stage: compose the configuration as the command line does, run the stage, read
its run back into a typed result.

Each call is ``physmend STAGE [--config-dir D] [RUN_ID] key=value …`` from Python: the same
composition, checks and errors (:class:`physmend.PhysmendError` subclasses such as ``ConfigError``
and ``DataError``; nothing is written when they are raised before the stage starts), the same
MLflow store (``tracking.uri``, default ``sqlite:///mlflow.db`` in the working directory) and the
same runs. A later stage given an earlier *result* (not only its run ID) continues with that
result's model, data and settings; settings given to it are added on top.
"""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from physmend.api.discovery import Discovery
from physmend.api.inputs import Inputs, prepare
from physmend.api.results import (
    Decision,
    Diagnosis,
    ExportResult,
    MaskResult,
    Proposal,
    SensitivityResult,
    StageResult,
    SweepResult,
    SymbolicResult,
)
from physmend.settings import group_settings

Source = str | StageResult | None


class _Tee(io.TextIOBase):
    """Writes to every stream it holds (the caller's console and a buffer)."""

    def __init__(self, *streams: Any) -> None:
        self.streams = streams

    def write(self, text: str) -> int:
        for s in self.streams:
            s.write(text)
        return len(text)

    def flush(self) -> None:
        for s in self.streams:
            s.flush()

    def isatty(self) -> bool:
        return bool(getattr(self.streams[0], "isatty", lambda: False)())


@contextlib.contextmanager
def _captured(quiet: bool | None) -> Iterator[io.StringIO]:
    """What the stage prints, kept; shown as well unless ``quiet`` (then its progress bars are hidden
    too); ``None``: the streams left exactly as they are (the command line), nothing kept."""
    buffer = io.StringIO()
    if quiet is None:
        yield buffer
        return
    out = buffer if quiet else _Tee(sys.stdout, buffer)
    with contextlib.redirect_stdout(out):  # type: ignore[type-var]
        if quiet:
            with contextlib.redirect_stderr(io.StringIO()):
                yield buffer
        else:
            yield buffer


#: command -> (result type, ``module:function`` of :mod:`physmend.stages`, whether it composes trial configs)
STAGES: dict[str, tuple[type[StageResult], str, bool]] = {
    "diagnose": (Diagnosis, "physmend.stages.diagnose:run", False),
    "sweep": (SweepResult, "physmend.stages.sweep:run", True),
    "mask": (MaskResult, "physmend.stages.mask:run", False),
    "sensitivity": (SensitivityResult, "physmend.stages.sensitivity:run", False),
    "symbolic": (SymbolicResult, "physmend.stages.symbolic:run", False),
    "propose": (Proposal, "physmend.stages.propose:run", False),
    "accept": (Decision, "physmend.stages.decide:accept", False),
    "reject": (Decision, "physmend.stages.decide:reject", False),
    "export": (ExportResult, "physmend.stages.export:run", False),
    "discover": (Discovery, "physmend.stages.discover:run", True),
}


def run_composed(command: str, cfg: Any, source_id: str | None, *, call: Inputs,
                 quiet: bool | None = None) -> StageResult:
    """Run stage ``command`` on the composed ``cfg`` (from ``call``'s overrides and config directory) and
    read its run back: what the command line runs after parsing and composing. ``quiet``: True keeps
    what the stage prints (``printed``) and shows nothing, False shows and keeps it, None (the command
    line) leaves stdout and stderr as they are."""
    import importlib

    from physmend.api.artifacts import RunFiles, quiet_mlflow
    from physmend.tracking import open_store

    quiet_mlflow()
    kind, target, composed = STAGES[command]
    module_name, func = target.split(":")
    stage = getattr(importlib.import_module(module_name), func)
    out_dir = Path(group_settings(cfg, "export").output_dir).expanduser() if command == "export" else None
    before = set(out_dir.iterdir()) if out_dir is not None and out_dir.is_dir() else set()
    with _captured(quiet) as printed:
        if composed:  # sweep and discover compose each trial's config from the overrides, as the CLI does
            run_id = stage(cfg, source_id, overrides=list(call.overrides), config_dir=call.config_dir)
        else:
            run_id = stage(cfg, source_id)
    files = RunFiles(open_store(cfg.tracking), run_id)
    if out_dir is not None:
        return _exported(files, out_dir, before, printed=printed.getvalue(), call=call)
    return kind.read(files, printed=printed.getvalue(), call=call)


def _exported(files: Any, out_dir: Path, before: set[Path], **common: Any) -> ExportResult:
    """What ``export`` wrote into ``out_dir`` (the entries not there ``before``), by format."""
    from physmend.modeling.export import FORMATS

    written = sorted(set(out_dir.iterdir()) - before) if out_dir.is_dir() else []
    paths: dict[str, str] = {}
    for path in written:
        if path.is_dir():
            paths.setdefault("petab", str(path.resolve()))
            continue
        fmt = next((f for f, s in sorted(FORMATS.items(), key=lambda kv: -len(kv[1])) if path.name.endswith(s)), None)
        if fmt is not None:
            paths.setdefault(fmt, str(path.resolve()))
    return ExportResult(files.run_id, files=files, paths=paths, written=tuple(str(p.resolve()) for p in written),
                        **common)


def _run(command: str, source: Source, *, model: Any, data: Any, overrides: Sequence[str] | str,
         config_dir: str | Path | None, quiet: bool, settings: dict[str, Any]) -> Any:
    """Prepare the inputs, compose as the command line does, run stage ``command``, read its run."""
    from physmend.config import compose

    base = source.call if isinstance(source, StageResult) else None
    source_id = source.run_id if isinstance(source, StageResult) else source
    if source_id is not None and not isinstance(source_id, str):
        from physmend.config import ConfigError

        raise ConfigError(f"run must be a run ID (text) or a physmend result, but got {type(source_id).__name__}")
    inputs = prepare(model, data, settings=settings, overrides=overrides, config_dir=config_dir, base=base)
    fresh = inputs.workspace is not None and (base is None or inputs.workspace is not base.workspace)
    try:
        cfg = compose(list(inputs.overrides), user_config_dir=inputs.config_dir)
        return run_composed(command, cfg, source_id, call=inputs, quiet=quiet)
    except BaseException:
        if fresh:
            inputs.workspace.remove()  # type: ignore[union-attr]
        raise


def discover(model: Any = None, data: Any = None, *, overrides: Sequence[str] | str = (),
             config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> Discovery:
    """Every stage with default choices, end to end (``physmend discover``): diagnose, sweep, mask,
    sensitivity, symbolic, propose. The proposal is left for you to :func:`accept` or :func:`reject`.

    Arguments as :func:`diagnose`; ``discover={"n_trials": 1, "budget": None}`` makes the sweep small.
    Returns a :class:`Discovery` (its ``run_id`` is the proposal's; ``formulas``, ``fit``, and every
    stage's result as an attribute).

    Example::

        import physmend
        d = physmend.discover("cstr", "cstr", discover={"n_trials": 1, "budget": None})
        d.formulas      # {'reactor.A': -0.0202*reactor.A*reactor.B, ...}
        physmend.accept(d)
    """
    return _run("discover", None, model=model, data=data, overrides=overrides,
                config_dir=config_dir, quiet=quiet, settings=settings)


def diagnose(model: Any = None, data: Any = None, *, overrides: Sequence[str] | str = (),
             config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> Diagnosis:
    """Simulate the model as written against the telemetry (``physmend diagnose``).

    Args:
        model: a :class:`physmend.modeling.Model`, a function that builds one, ``"path/file.py:function"``,
            or the name of a model config (``"cstr"``); None: the configuration's ``model``.
        data: a data config (a YAML file's path or a mapping), the name of one, a :class:`physmend.Dataset`
            or a list of :class:`physmend.Experiment` tables; None: the configuration's ``data``.
        overrides: Hydra overrides as on the command line (``["sweep.n_trials=4"]``); they win over ``settings``.
        config_dir: your own config folder (``--config-dir``), searched before the shipped one.
        quiet: keep what the stage prints (in the result's ``printed``) instead of printing it.
        **settings: configuration values, per group (``train={"epochs": 60}``) or dotted
            (``**{"train.epochs": 60}``), or top-level (``seed=1``).

    Raises:
        PhysmendError: bad input (unknown setting, wrong type, bad data or model); nothing is written.
    """
    return _run("diagnose", None, model=model, data=data, overrides=overrides,
                config_dir=config_dir, quiet=quiet, settings=settings)


def sweep(model: Any = None, data: Any = None, *, source: Source = None, overrides: Sequence[str] | str = (),
          config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> SweepResult:
    """Train many UDEs, one MLflow run per trial, and select the best (``physmend sweep``).

    ``source``: an optional run (ID or result, e.g. a :class:`Diagnosis`) the sweep builds on; given a
    result, its model, data and settings are used unless given here. Other arguments: :func:`diagnose`.
    """
    return _run("sweep", source, model=model, data=data, overrides=overrides,
                config_dir=config_dir, quiet=quiet, settings=settings)


def mask(run: Source = None, *, model: Any = None, data: Any = None, overrides: Sequence[str] | str = (),
         config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> MaskResult:
    """Keep only the corrections that matter (``physmend mask [RUN_ID]``).

    ``run``: a trial run ID, or a :class:`SweepResult` (its selected trial); None: the current selection.
    """
    if isinstance(run, SweepResult):
        run = _continuing(run, run.selected_run_id)
    return _run("mask", run, model=model, data=data, overrides=overrides,
                config_dir=config_dir, quiet=quiet, settings=settings)


def sensitivity(run: Source = None, *, model: Any = None, data: Any = None, overrides: Sequence[str] | str = (),
                config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> SensitivityResult:
    """Which inputs the kept corrections depend on (``physmend sensitivity [RUN_ID]``); ``run``: a mask
    run (ID or :class:`MaskResult`), None: the latest."""
    return _run("sensitivity", run, model=model, data=data,
                overrides=overrides, config_dir=config_dir, quiet=quiet, settings=settings)


def symbolic(run: Source = None, *, model: Any = None, data: Any = None, overrides: Sequence[str] | str = (),
             config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> SymbolicResult:
    """Symbolic regression: the network becomes formulas (``physmend symbolic [RUN_ID]``); ``run``: a
    sensitivity run (ID or :class:`SensitivityResult`), None: the latest."""
    return _run("symbolic", run, model=model, data=data, overrides=overrides,
                config_dir=config_dir, quiet=quiet, settings=settings)


def propose(run: Source = None, *, model: Any = None, data: Any = None, overrides: Sequence[str] | str = (),
            config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> Proposal:
    """The corrected model, validated on held-out experiments (``physmend propose [RUN_ID]``); ``run``:
    a symbolic run (ID or :class:`SymbolicResult`), None: the latest."""
    return _run("propose", run, model=model, data=data, overrides=overrides,
                config_dir=config_dir, quiet=quiet, settings=settings)


def accept(run: str | StageResult, *, model: Any = None, data: Any = None, overrides: Sequence[str] | str = (),
           config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> Decision:
    """Accept a proposal: write its corrections file into ``decide.output_dir`` (``physmend accept RUN_ID``).

    ``run``: the proposal's run ID, a :class:`Proposal` or a :class:`Discovery` (whose model, data and
    settings are used unless given here); other arguments as :func:`diagnose`.
    """
    return _run("accept", _required(run, "accept"), model=model, data=data,
                overrides=overrides, config_dir=config_dir, quiet=quiet, settings=settings)


def reject(run: str | StageResult, *, reason: str | None = None, model: Any = None, data: Any = None,
           overrides: Sequence[str] | str = (), config_dir: str | Path | None = None, quiet: bool = True,
           **settings: Any) -> Decision:
    """Reject a proposal, with an optional ``reason`` (``physmend reject RUN_ID decide.reason=…``)."""
    if reason is not None:
        settings["decide.reason"] = reason
    return _run("reject", _required(run, "reject"), model=model, data=data,
                overrides=overrides, config_dir=config_dir, quiet=quiet, settings=settings)


def export(run: str | StageResult, *, model: Any = None, data: Any = None, overrides: Sequence[str] | str = (),
           config_dir: str | Path | None = None, quiet: bool = True, **settings: Any) -> ExportResult:
    """Write a proposal's corrected model as files (``physmend export RUN_ID``; ``export.format``,
    ``export.output_dir``): LaTeX, sympy, a Python module … The result's ``paths`` maps each format to
    its file (PEtab: its folder), ``written`` lists every file and folder written."""
    return _run("export", _required(run, "export"), model=model, data=data, overrides=overrides,
                config_dir=config_dir, quiet=quiet, settings=settings)


def _required(run: Any, command: str) -> Any:
    if run is None or run == "":
        from physmend.tracking import TrackingError

        raise TrackingError(f"{command} needs the run ID of a proposal (or a Proposal or Discovery result)")
    return run


def _continuing(result: StageResult, run_id: str | None) -> StageResult:
    """``result``'s inputs with another run ID (a sweep's selected trial)."""
    if run_id is None:
        return result
    return StageResult(run_id, call=result.call)


__all__ = ["accept", "diagnose", "discover", "export", "mask", "propose", "reject", "sensitivity", "sweep", "symbolic"]

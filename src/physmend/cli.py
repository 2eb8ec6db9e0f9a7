"""The ``physmend`` command line. Thin: heavy libraries are imported inside the command that needs them."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

STAGES = {
    "diagnose": ("physmend.stages.diagnose:run", "simulate the model as written against the telemetry: where does it miss?"),
    "sweep": ("physmend.stages.sweep:run", "train many UDEs (an Optuna study, one MLflow run per trial); resumable"),
    "mask": ("physmend.stages.mask:run", "keep only the corrections that matter, retrain"),
    "sensitivity": ("physmend.stages.sensitivity:run", "which inputs the kept corrections depend on"),
    "symbolic": ("physmend.stages.symbolic:run", "symbolic regression: the network becomes formulas"),
    "propose": ("physmend.stages.propose:run", "the corrected model, validated on held-out experiments, with a report"),
    "accept": ("physmend.stages.decide:accept", "accept a proposal: write its corrections file"),
    "reject": ("physmend.stages.decide:reject", "reject a proposal (decide.reason='...')"),
    "export": ("physmend.stages.export:run", "write a proposal's corrected model: LaTeX, sympy, Python, network, PEtab"),
    "discover": ("physmend.stages.discover:run", "all of the above with default choices, end to end"),
}
# what each stage's optional run ID means
SOURCE_HELP = {
    "sweep": "optional source run this sweep builds on (e.g. a diagnose run)",
    "mask": "trial run ID (default: the current selection)",
    "sensitivity": "mask run ID (default: the latest mask run)",
    "symbolic": "sensitivity run ID (default: the latest sensitivity run)",
    "propose": "symbolic run ID (default: the latest symbolic run)",
    "accept": "the proposal's run ID",
    "reject": "the proposal's run ID",
    "export": "the proposal's run ID",
}

EPILOG = """\
Trailing key=value arguments are Hydra overrides of the composed configuration, e.g.
  physmend diagnose data=my_plant model=my_plant simulate.rtol=1e-6
Your own config groups (model/, data/ ...) go in a folder passed with --config-dir.
Defaults: MLflow store sqlite:///mlflow.db in the working directory (browse with `physmend ui`).
"""

EXPORT_FORMATS = """Formats (export.format=NAME; all: every one this machine can write), into export.output_dir:
  latex    NAME.tex                 standalone LaTeX document (pdflatex): corrected equations, the
                                    found terms marked, constants with units and standard errors
  sympy    NAME.sympy.json          sympy expressions (srepr text), constants with units
  python   NAME.py                  plain Python module: rhs(t, x, u, p) for scipy's solve_ivp
  network  NAME.network.json        the correcting network: architecture (PEtab-SciML layout) and
           NAME.network.safetensors its weights (safetensors)
  petab    NAME.petab/              PEtab v1 problem: SBML model and tables (needs python-libsbml)
"""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="physmend",
        description="Find the physics your model is missing.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in STAGES.items():
        p = sub.add_parser(name, help=help_text, description=help_text,
                           epilog=(EXPORT_FORMATS + "\n" if name == "export" else "") + EPILOG,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        _common(p)
        if name not in ("diagnose", "discover"):
            p.add_argument("run_id", nargs="?", default=None,
                           help=SOURCE_HELP.get(name, "source run ID (default: the current selection)"))
    p = sub.add_parser("runs", help="list sweeps, their trials and stage runs; the selection marked",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--sweep", metavar="RUN_ID", default=None, help="only this sweep (its parent run ID)")
    _common(p)
    p = sub.add_parser("select", help="choose a trial run (override the automatic choice)",
                       epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_id", help="the trial's run ID (see `physmend runs`)")
    _common(p)
    p = sub.add_parser("config", help="print the composed configuration", epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    _common(p)
    p = sub.add_parser("ui", help="open the MLflow UI on the configured store")
    _common(p)
    p.add_argument("--port", type=int, default=5000)
    p.add_argument("--host", default="127.0.0.1")
    return parser


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config-dir", default=None, help="a folder with your own config groups (searched first)")
    p.add_argument("overrides", nargs="*", help="Hydra overrides, key=value")


def _split_run_id(args: argparse.Namespace) -> None:
    """``physmend STAGE [--config-dir D] k=v RUN_ID`` in any order: argparse hands RUN_ID to the
    overrides when it comes first or after an option; take it back (the first word without '=')."""
    run_id = getattr(args, "run_id", "-")
    if run_id is not None and run_id != "-" and _is_override(run_id):  # ``~key`` first: Hydra's deletion
        args.overrides = [run_id, *args.overrides]
        args.run_id = run_id = None
    if run_id is None:
        words = [i for i, o in enumerate(args.overrides) if not _is_override(o)]
        if words:
            args.run_id = args.overrides.pop(words[0])


def _is_override(word: str) -> bool:
    """``key=value``, ``+key=value`` or Hydra's deletion ``~key`` (``~key=value``)."""
    return "=" in word or word.startswith("~")


def parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line: options, overrides and a stage's run ID in any order (exits 2 on a bad one)."""
    # positionals after an option (``RUN_ID --config-dir D k=v``) come back unparsed: they are overrides
    args, extra = parser.parse_known_args(argv)
    stray = [e for e in extra if e.startswith("-") or not hasattr(args, "overrides")]
    if stray:
        parser.error(f"unrecognized arguments: {' '.join(stray)}")
    if extra:
        args.overrides = list(args.overrides) + extra
    if args.command is not None:
        _split_run_id(args)
        bad = [o for o in args.overrides if not _is_override(o)]
        if bad:
            parser.error(f"overrides must look like key=value (or ~key to delete one), but got {bad}")
    return args


def _compose(args: argparse.Namespace):  # noqa: ANN202
    from physmend.config import compose

    return compose(args.overrides, user_config_dir=args.config_dir)


def _ui(args: argparse.Namespace) -> int:
    from physmend.tracking.ui import ui

    return ui(_compose(args), host=args.host, port=args.port)


#: characters at most of an error message: one that quotes a whole file or cell is cut in the middle
MAX_MESSAGE = 1000


def bounded(message: str, limit: int = MAX_MESSAGE) -> str:
    """``message`` if at most ``limit`` characters, else its start and end around a note of the cut
    (every error quotes a little of what it found; this holds where one would quote too much)."""
    if len(message) <= limit:
        return message
    head, tail = message[: limit * 2 // 3], message[-(limit // 4):]
    return f"{head} … [{len(message) - len(head) - len(tail)} characters cut] … {tail}"


#: what a store library says when the disk under it is full or cannot be written (sqlite, via MLflow)
_DISK_WORDS = ("database or disk is full", "disk i/o error", "attempt to write a readonly database")


def disk_trouble(exc: BaseException) -> str | None:
    """One line for a full or unwritable disk anywhere in ``exc``'s chain (a store's SQL error, an
    artifact copy, a figure), naming the file where known; None when the error is something else."""
    import errno

    seen: set[int] = set()
    todo: list[BaseException | None] = [exc]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS):
            where = f" writing {e.filename!r}" if e.filename else ""
            return f"{e.strerror or e}{where}"
        text = str(e).lower()
        word = next((w for w in _DISK_WORDS if w in text), None)
        if word is not None:
            return f"the tracking store says: {word}"
        todo += [e.__cause__, e.__context__]
    return None


def _start_standby() -> None:
    """discover's sweep runs its first trials side by side wherever a second CPU is there
    (``discover.workers: auto``): the first extra worker starts importing now, before the
    configuration is composed (:mod:`physmend.prestart`; discover ends it where it asks for none)."""
    from physmend import prestart
    from physmend.cpus import usable_cpus

    prestart.start_early(1 if usable_cpus() > 1 else 0)


def main(argv: Sequence[str] | None = None) -> int:
    import os

    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # keep stage output readable
    import logging

    # MLflow logs every store error with its SQL and stack before raising it; physmend reports the
    # error as one line (tracking.store, disk_trouble) — and the table-creation notices are noise
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)
    os.environ.setdefault("MLFLOW_SUPPRESS_PRINTING_URL_TO_STDOUT", "true")  # no "🏃 View run" lines (tracking.store)
    parser = _parser()
    args = parse(parser, argv)
    if args.version:
        from physmend import __version__

        print(__version__)
        return 0
    if args.command is None:
        parser.print_help()
        return 0
    from physmend.errors import is_user_error

    if args.command == "discover":
        _start_standby()
    try:
        if args.command == "ui":
            return _ui(args)
        cfg = _compose(args)
        if args.command == "config":
            from physmend.config import to_yaml

            from physmend.redact import redact

            print(redact(to_yaml(cfg)))
            return 0
        if args.command == "runs":
            from physmend.stages.select import runs

            runs(cfg, as_json=args.json, sweep_run_id=args.sweep)
            return 0
        if args.command == "select":
            from physmend.stages.select import run as select

            select(cfg, args.run_id)
            return 0
        from physmend.api.functions import run_composed
        from physmend.api.inputs import Inputs

        # the Python API's own call (physmend.api): the stage prints as it goes; its result is read back
        run_composed(args.command, cfg, getattr(args, "run_id", None),
                     call=Inputs(tuple(args.overrides), args.config_dir))
        return 0
    except KeyboardInterrupt:
        print(f"physmend {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if is_user_error(exc):  # your input is wrong: one line
            from physmend.redact import redact

            print(bounded(redact(f"physmend {args.command}: error: {exc}")), file=sys.stderr)
            return 2
        why = disk_trouble(exc)
        if why is None:
            raise
        from physmend.redact import redact

        print(redact(f"physmend {args.command}: error: {why} — the disk under the working directory or the store "
                     f"(tracking.uri) is full or read-only; free space or point them elsewhere (runs it could not "
                     f"finish are left FAILED or RUNNING, nothing else is changed)"), file=sys.stderr)
        return 2
    finally:
        from physmend import prestart

        prestart.release_early()  # not taken: the configuration asked for no extra worker, or it failed first


if __name__ == "__main__":
    raise SystemExit(main())

"""Two worker processes asking a sqlite study for its enqueued trials at the same moment each get
their own (:func:`physmend.sweep.storage.asking`): without the lock Optuna hands one waiting trial
to both (sqlite has no row lock), and both would train it. Real processes, a real sqlite storage."""

from __future__ import annotations

import multiprocessing
from pathlib import Path
from typing import Any

import optuna

ASKS = 8


def _ask_many(url: str, go: Any, out: Any) -> None:
    from physmend.sweep.storage import asking, open_storage

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = open_storage(url)
    study = optuna.load_study(study_name="race", storage=storage)
    got = []
    go.wait()  # both start asking together
    for _ in range(ASKS):
        with asking(storage):
            got.append(study.ask().number)
    out.put(got)


def test_two_workers_asking_at_once_never_get_the_same_waiting_trial(tmp_path: Path) -> None:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    study = optuna.create_study(study_name="race", storage=url)
    for i in range(2 * ASKS):
        study.enqueue_trial({"x": float(i)})
    ctx = multiprocessing.get_context("spawn")
    go, out = ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_ask_many, args=(url, go, out)) for _ in range(2)]
    for proc in procs:
        proc.start()
    try:
        go.set()
        got = [out.get(timeout=300) for _ in procs]
    finally:
        for proc in procs:
            proc.join(timeout=60)
    numbers = sorted(got[0] + got[1])
    assert numbers == list(range(2 * ASKS)), got  # every waiting trial to exactly one worker
    assert not list(tmp_path.glob("*lock*"))  # the lock is on the folder: no file left beside the database


def test_a_folder_that_cannot_be_locked_asks_as_optuna_alone(tmp_path: Path) -> None:
    from types import SimpleNamespace

    from physmend.sweep.storage import asking

    entered = []
    with asking(SimpleNamespace(url=f"sqlite:///{tmp_path / 'gone' / 'optuna.db'}")):  # no such folder: no lock
        entered.append(1)
    with asking(SimpleNamespace(url="postgresql://db.example/optuna")):  # a server locks its rows itself
        entered.append(2)
    assert entered == [1, 2]

"""Two workers writing the same new tags on one run at the same moment (a sweep's parent when both
finish: its best, selection and name): MLflow's database store reads that a tag is absent, then
inserts it, and the second writer's insert broke the unique key (``UNIQUE constraint failed:
tags.key, tags.run_uuid``; ``duplicate key`` on PostgreSQL) — a worker's sweep ended in a traceback
after all its trials finished (seen in CI). Plain ``MlflowClient.set_tag`` in this same set-up fails
in most runs; :func:`physmend.tracking.write_tags` must not."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

WORKER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from mlflow.tracking import MlflowClient
    from physmend.tracking import write_tags

    uri, run_id, folder, me = sys.argv[1:5]
    client = MlflowClient(tracking_uri=uri)
    (Path(folder) / f"ready{me}").touch()
    while not (Path(folder) / "go").exists():
        time.sleep(0.001)
    for i in range(40):
        write_tags(client, run_id, {f"key{i}": f"value{i}", f"by{me}.{i}": me})
""")


def test_two_workers_setting_the_same_new_tags_at_once_both_succeed(tmp_path: Path) -> None:
    from omegaconf import OmegaConf

    from physmend.tracking import open_store

    store = open_store(OmegaConf.create({"uri": f"sqlite:///{tmp_path / 'mlflow.db'}", "experiment": "physmend"}))
    run_id = store.client.create_run(store.experiment_id).info.run_id
    script = tmp_path / "worker.py"
    script.write_text(WORKER)
    procs = [subprocess.Popen([sys.executable, str(script), store.uri, run_id, str(tmp_path), str(me)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for me in range(2)]
    deadline = time.monotonic() + 120
    while not all((tmp_path / f"ready{me}").exists() for me in range(2)):
        assert time.monotonic() < deadline and all(p.poll() is None for p in procs), [p.communicate() for p in procs]
        time.sleep(0.01)
    (tmp_path / "go").touch()
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err[-2000:] for _, err in outs]
    tags = store.client.get_run(run_id).data.tags
    assert {k: tags[k] for k in tags if k.startswith("key")} == {f"key{i}": f"value{i}" for i in range(40)}
    assert sum(k.startswith("by") for k in tags) == 80

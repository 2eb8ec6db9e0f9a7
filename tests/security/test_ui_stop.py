"""``physmend ui`` stops MLflow's server with itself: a SIGTERM (``kill``, a service manager, a
container stopping) or a SIGINT (Ctrl-C) to the real ``physmend ui`` process ends every process it
started — the ``mlflow ui`` launcher and its web server — within seconds, and the port is free again."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from .conftest import physmend_command

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: shared helpers  # noqa: E402
from mlflow_servers import free_port  # noqa: E402

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").is_file(), reason="reads processes from /proc")


def _running(pid: int) -> bool:
    """``pid`` exists and has not ended (a zombie waiting for its new parent to reap it has)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _descendants(root: int) -> set[int]:
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parents[int(stat.parent.name)] = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
    found, todo = set(), [root]
    while todo:
        pid = todo.pop()
        children = {c for c, p in parents.items() if p == pid} - found
        found |= children
        todo += children
    return found


def _answers(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])  # SIGINT: Ctrl-C reaches physmend alone
def test_a_stop_signal_stops_the_mlflow_server_too(tmp_path: Path, signum: signal.Signals) -> None:
    port = free_port()
    log = tmp_path / "ui.log"
    with open(log, "w") as out:
        ui = subprocess.Popen([*physmend_command(), "ui", "--port", str(port), f"tracking.uri=sqlite:///{tmp_path}/mlflow.db"],
                              cwd=tmp_path, stdout=out, stderr=subprocess.STDOUT)
    started: set[int] = set()
    try:
        deadline = time.monotonic() + 120
        while not _answers(port):
            assert ui.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.3)
        started = _descendants(ui.pid)
        assert len(started) >= 1, started  # the launcher and its web server (one process or two)
        ui.send_signal(signum)
        status = ui.wait(20)
        deadline = time.monotonic() + 5
        while any(_running(pid) for pid in started) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [pid for pid in started if _running(pid)], log.read_text()[-2000:]
        assert not _answers(port)
        assert status == 128 + signum, log.read_text()[-2000:]
        assert f"stopped by {signum.name}" in log.read_text()
    finally:
        for pid in [ui.pid, *started]:  # only what this test started, should it fail half-way
            if _running(pid):
                os.kill(pid, signal.SIGKILL)

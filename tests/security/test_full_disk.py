"""A full disk under the working directory: whatever the stage was writing when space ran out (the
store's database, an artifact, a figure), the user gets one line naming the trouble — no traceback,
no SQL — exit status 2, and the user's own files are untouched.

A real filesystem runs out: a small tmpfs, filled to leave a little space (root may mount it; the
test says so and skips where the machine forbids mounting)."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest


def _tree(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture
def small_disk(tmp_path: Path):  # noqa: ANN201
    import shutil

    if shutil.which("mount") is None or shutil.which("umount") is None:
        pytest.skip("this machine has no mount/umount command to make a small tmpfs")
    mount = tmp_path / "disk"
    mount.mkdir()
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mount)], capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"this machine does not let the test mount a small tmpfs: {made.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _fill(disk: Path, leave_kib: int) -> None:
    """Write a filler file so that about ``leave_kib`` KiB stay free on ``disk``."""
    st = os.statvfs(disk)
    size = st.f_bavail * st.f_frsize - leave_kib * 1024
    if size > 0:
        with (disk / f"filler{len(list(disk.glob('filler*')))}").open("wb") as f:
            f.write(b"\0" * size)


def _diagnose(user_project: Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "physmend.cli", "diagnose", "--config-dir", str(user_project / "my_conf"),
         "model=oscillator", "data=oscillator", "diagnose.plots=true"],
        cwd=cwd, capture_output=True, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"}, timeout=300)


def _one_line(done: subprocess.CompletedProcess[str]) -> str:
    lines = [ln for ln in done.stderr.splitlines() if ln.strip()]
    assert done.returncode == 2 and len(lines) == 1, (done.returncode, done.stderr[-3000:])
    assert "Traceback" not in done.stderr and "SQL" not in done.stderr
    assert any(w in lines[0] for w in ("disk is full", "No space left")), lines[0]
    return lines[0]


def test_a_full_disk_is_one_line(user_project: Path, small_disk: Path) -> None:
    before = _tree(user_project / "recordings") | _tree(user_project / "my_conf")
    # no room for the store itself
    first = small_disk / "first"
    first.mkdir()
    _fill(small_disk, 0)
    assert "tracking.uri" in _one_line(_diagnose(user_project, first))
    for p in small_disk.glob("filler*"):
        p.unlink()
    # a store made with room to spare; then the disk fills up: the next run cannot write its run,
    # artifacts and figures — one line again, and the earlier run is still in the store
    work = small_disk / "work"
    work.mkdir()
    ok = _diagnose(user_project, work)
    assert ok.returncode == 0, ok.stderr[-3000:]
    _fill(small_disk, 16)
    line = _one_line(_diagnose(user_project, work))
    assert "working directory or the store" in line
    assert _tree(user_project / "recordings") | _tree(user_project / "my_conf") == before
    import sqlite3

    with sqlite3.connect(work / "mlflow.db") as db:
        finished = db.execute("select count(*) from runs where status = 'FINISHED'").fetchone()[0]
    assert finished >= 1

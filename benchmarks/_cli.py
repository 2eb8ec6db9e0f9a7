"""Start-up time of the command line: ``physmend -h`` in fresh processes."""

from __future__ import annotations

import statistics
import subprocess
import time
from typing import Any

from _sweep import physmend_cli


def help_seconds(repeats: int = 5) -> dict[str, Any]:
    """Wall time (s) of ``physmend -h`` in ``repeats`` fresh processes: median, min, max, all."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run([*physmend_cli(), "-h"], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        times.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "runs_s": times}

"""Equal budgets in samples for runs that share one GPU: a run reports its samples in a small
progress file, and a run paced by it never trains more than one step ahead of it.

Two runs on one GPU share it by time-slicing, so the faster one (``action-vector``: its
model costs less a sample) trains more samples in the same minutes: 1.18M against
0.86M in the sixth GPU run. A paced run waits instead, and the time it waits goes to the
others; when the run it follows has finished, it stops at that run's final count. A
progress file that stops changing for ``stale_s`` (a run that died) frees the paced run.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from imac_data.errors import InputError

STALE_S = 300.0  # longer than any first step (a compilation took at most 167 s on the GPU loans)
POLL_S = 0.5


def report_progress(path: str | Path, samples: int, done: bool = False) -> None:
    """Write ``{"samples", "done"}`` to ``path`` at once (a reader never sees half a file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"samples": int(samples), "done": bool(done)}))
    os.replace(tmp, path)


def read_progress(path: str | Path) -> dict | None:
    """What a run last reported in ``path``; None before it wrote anything."""
    try:
        progress = json.loads(Path(path).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: unreadable progress file: {e}") from None
    if not isinstance(progress, dict) or not {"samples", "done"} <= set(progress):
        raise InputError(f"{path}: a progress file holds 'samples' and 'done', got {progress!r}")
    return progress


class Pace:
    """Keeps a run's samples at most one step ahead of the run that reports to ``theirs``."""

    def __init__(self, theirs: str | Path, *, stale_s: float = STALE_S, poll_s: float = POLL_S):
        self.theirs, self.stale_s, self.poll_s = Path(theirs), float(stale_s), float(poll_s)
        self.waited_s = 0.0
        self.freed = None  # why the run stopped following, if it did: "stale"

    def may_step(self, ours: int, deadline: float) -> bool:
        """Wait while the other run is behind ``ours`` samples (until ``deadline``, a ``time.time()``);
        False once this run should stop: the other has finished and ``ours`` has reached its count, or the
        deadline passed while waiting."""
        t0 = changed = time.time()
        last = None
        while True:
            now = time.time()
            if self.freed:
                return True
            progress = read_progress(self.theirs)
            if progress != last:
                last, changed = progress, now
            if progress is not None and progress["done"]:
                ok = ours < progress["samples"]
                break
            if progress is not None and ours <= progress["samples"]:
                ok = True
                break
            if now - changed > self.stale_s:
                self.freed, ok = "stale", True
                break
            if now >= deadline:
                ok = False
                break
            time.sleep(self.poll_s)
        self.waited_s += time.time() - t0
        return ok

    def summary(self) -> dict:
        return {"paced_with": str(self.theirs), "paced_wait_s": round(self.waited_s, 1), "pace_freed": self.freed}


__all__ = ["Pace", "read_progress", "report_progress"]

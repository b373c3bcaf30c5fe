"""Wall and CPU seconds per pipeline stage, added up over chunks, episodes and workers."""

from __future__ import annotations

import contextlib
import time
from collections import defaultdict

__all__ = ["StageTimer", "STAGES"]

STAGES = ("read", "fk", "render", "depth", "contact", "encode", "write")


class StageTimer:
    """Wall and CPU seconds per stage (``with timer("render"): ...``); CPU is the process
    time, so a stage's own threads count. Nested or overlapping stages are not supported."""

    def __init__(self):
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.frames = 0

    @contextlib.contextmanager
    def __call__(self, stage: str):
        w, c = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            self.wall[stage] += time.perf_counter() - w
            self.cpu[stage] += time.process_time() - c

    def add(self, other: StageTimer | dict) -> None:
        d = other.to_dict() if isinstance(other, StageTimer) else other
        for stage, v in d.get("wall_s", {}).items():
            self.wall[stage] += v
        for stage, v in d.get("cpu_s", {}).items():
            self.cpu[stage] += v
        self.frames += int(d.get("frames", 0))

    def to_dict(self) -> dict:
        return {"frames": self.frames, "wall_s": dict(self.wall), "cpu_s": dict(self.cpu)}

    def table(self, title: str = "stage") -> str:
        """Per stage: wall s, CPU s, and ms per frame."""
        n = max(self.frames, 1)
        lines = [f"{title:<10} {'wall s':>8} {'cpu s':>8} {'wall ms/frame':>14} {'cpu ms/frame':>13}"]
        for stage in sorted(self.wall, key=lambda s: -self.wall[s]):
            lines.append(f"{stage:<10} {self.wall[stage]:>8.2f} {self.cpu[stage]:>8.2f} "
                         f"{1e3 * self.wall[stage] / n:>14.1f} {1e3 * self.cpu[stage] / n:>13.1f}")
        lines.append(f"{'total':<10} {sum(self.wall.values()):>8.2f} {sum(self.cpu.values()):>8.2f} "
                     f"{1e3 * sum(self.wall.values()) / n:>14.1f} {1e3 * sum(self.cpu.values()) / n:>13.1f}"
                     f"   ({self.frames} frames)")
        return "\n".join(lines)

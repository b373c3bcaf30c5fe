"""What a benchmark run builds, and where it runs: the workload of ``python -m benchmarks.run`` (its CLI flags), the
recorded episodes and recipe it builds, and the machine, commit and versions every result file names. Shared with
the runs that build the same episodes with other code (``benchmarks.same_host``, ``benchmarks.renderer_build``)."""

from __future__ import annotations

import contextlib
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 (LeRobot's encoder): errors only

from benchmarks.run_report import STREAM_GROUPS, tag

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"
VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")  # view order: head, left, right wrist
TASK = "transfer_cube"


@dataclass
class Workload:
    """What one run measures (the CLI flags)."""

    quick: bool = False
    sizes: tuple[tuple[int, int], ...] = ((240, 320), (480, 640))
    episodes: int = 4
    max_steps: int | None = None  # 50 Hz control steps per episode (None: the whole script, ~125 frames)
    workers: tuple[int, ...] = (1, 2)
    ray_workers: int = 2
    long_frames: int = 1000
    short_frames: int = 100
    long_size: tuple[int, int] = (480, 640)
    render_episodes: int = 1  # render_vs_mujoco: scripted episodes per task (accuracy)
    render_frames: int = 32  # render_vs_mujoco: timing frames per size
    contact_steps: int | None = None  # contact_speed: 50 Hz steps (None: its default)
    contact_reference_frames: int | None = 8
    depth_episodes: int = 1
    depth_max_steps: int | None = 120
    seed: int = 0
    noise: float = 0.3
    sizes_episodes: dict = field(default_factory=dict)  # size tag -> episodes (default: episodes)
    baseline: str | None = None  # a revision whose CLI builds the same episodes beside ours (benchmarks.same_host)

    @classmethod
    def quick_default(cls) -> Workload:
        return cls(quick=True, sizes=((48, 64), (96, 128)), episodes=2, max_steps=12, workers=(1,), ray_workers=0,
                   long_frames=24, short_frames=8, long_size=(48, 64), render_frames=4, contact_steps=16,
                   contact_reference_frames=1, depth_max_steps=8)

    @property
    def small(self) -> tuple[int, int]:
        return self.sizes[0]

    def episodes_at(self, size) -> int:
        return int(self.sizes_episodes.get(tag(size), self.episodes))

    def builds(self) -> list[tuple[tuple[int, int], int, str]]:
        """(size, workers, executor) of every whole build, in run order."""
        plan = []
        for size in self.sizes:
            if self.quick and size != self.small:
                continue
            plan += [(size, w, "local") for w in self.workers]
            if size == self.small and self.ray_workers:
                plan.append((size, self.ray_workers, "ray"))
        return plan




# ----------------------------------------------------------------------------- environment


def machine() -> str:
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    mem = ""
    with contextlib.suppress(OSError, ValueError, IndexError):
        kb = int(Path("/proc/meminfo").read_text().split("MemTotal:")[1].split()[0])
        mem = f", {kb / 2**20:.0f} GiB RAM"
    return (f"{os.cpu_count()} cores, {model}{mem}, {platform.system()} {platform.machine()}, "
            f"Python {platform.python_version()}")


def commit() -> tuple[str, list[str]]:
    """HEAD and the tracked files that differ from it (read-only git: no index refresh)."""
    def git(*args):
        return subprocess.run(["git", "--no-optional-locks", *args], cwd=REPO, capture_output=True, text=True,
                              timeout=30).stdout
    try:
        head = git("rev-parse", "HEAD").strip() or "unknown"
        dirty = [line[3:] for line in git("status", "--porcelain", "--untracked-files=no").splitlines() if line]
    except (OSError, subprocess.SubprocessError):
        head, dirty = "unknown", []
    return head, dirty


def versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("torch", "numpy", "open3d", "mujoco", "lerobot", "av", "scipy", "trimesh"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def load_avg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def log(msg: str) -> None:
    print(f"[bench {time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.1f}] {msg}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- workload


def write_recipe(path: Path, size, episodes: int, seed: int, noise: float) -> Path:
    """The shipped transfer-cube recipe at ``size`` (recorded and augmented)."""
    import yaml

    from imac_data.recipes import RECIPES_DIR

    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["name"] = f"bench_{tag(size)}"
    data["source"]["episodes"] = episodes
    data["source"]["sim"].update(height=size[0], width=size[1], seed=seed, noise=noise)
    data.setdefault("augment", {}).update(height=size[0], width=size[1])
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def record(work: Workload, size, out: Path) -> float:
    from imac_data.sources.sim.recorder import SimConfig, record_dataset

    t = time.perf_counter()
    record_dataset(SimConfig(task=TASK, num_episodes=work.episodes_at(size), height=size[0], width=size[1],
                             seed=work.seed, noise=work.noise, max_steps=work.max_steps), out, progress=False,
                   overwrite=True)
    return time.perf_counter() - t


def tree_bytes(root: Path) -> dict:
    """Bytes of a dataset: total, per stream group (videos/<key>/), tabular (data + meta)."""
    out = {"total": 0, "tabular": 0, **{g: 0 for g in STREAM_GROUPS}}
    for f in root.rglob("*"):
        if not f.is_file():
            continue
        n = f.stat().st_size
        out["total"] += n
        rel = f.relative_to(root).parts
        if rel[0] == "videos" and len(rel) > 1:
            for group, prefix in STREAM_GROUPS.items():
                if rel[1].startswith(prefix):
                    out[group] += n
        elif rel[0] in ("data", "meta"):
            out["tabular"] += n
    return out

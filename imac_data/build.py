"""The main job: ``python -m imac_data.build --repo local/<name>``.

Flow (one way): recipe -> source episodes (recorded in simulation when the recipe
says so) -> checks -> base LeRobot dataset (:mod:`imac_data.ingest`) -> validation.
The augmentation stages (motion, depth, contact streams) plug in after ingest.

The output lands where LeRobot looks for ``repo_id`` (``$HF_LEROBOT_HOME/<repo>``)
unless ``--root`` says otherwise; it is assembled in a staging directory and
moved into place only when complete. The source data is only read.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from imac_data.errors import InputError
from imac_data.recipes import Recipe, find_recipe, load_recipe, missing_inputs


@dataclass(frozen=True)
class BuildRequest:
    repo_id: str
    recipe: Recipe
    root: Path
    source_path: Path | None = None  # overrides recipe.source.path
    episodes: int | None = None  # overrides recipe.source.episodes
    overwrite: bool = False
    progress: bool = True


def default_root(repo_id: str) -> Path:
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME) / repo_id


def cache_home() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "imac"


# --------------------------------------------------------------------------- stages


def robot_of(recipe: Recipe):
    from imac_data.robot import GripperMap, RobotConfig, RobotModel

    r = recipe.robot
    if r.platform == "aloha_sim":
        from imac_data import aloha

        return RobotModel(aloha.robot_config())
    urdf = recipe.resolve_path(r.urdf)
    if not urdf.is_file():
        raise InputError(f"{recipe.file}: robot.urdf: file not found: {urdf}")
    joint_map = tuple(
        entry if isinstance(entry, str) else GripperMap(i, entry.gripper, scale=entry.scale, offset=entry.offset)
        for i, entry in enumerate(r.joint_map)
    )
    config = RobotConfig(
        name=recipe.name, urdf_path=urdf, joint_map=joint_map, gripper_links=r.gripper_links,
        package_dirs={k: recipe.resolve_path(v) for k, v in r.package_dirs.items()},
    )
    return RobotModel(config)


def source_episodes(req: BuildRequest) -> tuple[list[Path], Path]:
    """The episode files to ingest and the calibration file that goes with them."""
    from imac_data.aloha_hdf5 import episode_paths

    recipe, src = req.recipe, req.recipe.source
    n = req.episodes if req.episodes is not None else src.episodes
    path = req.source_path or recipe.resolve_path(src.path)
    if src.type == "aloha_sim" and (path is None or not path.exists()):
        path = record_sim_episodes(recipe, n, path, req.progress)
    if path is None or not path.exists():
        raise InputError(f"source path does not exist: {path}")
    paths = episode_paths(path)
    if n is not None:
        if n > len(paths):
            raise InputError(f"{path}: asked for {n} episodes, the directory has {len(paths)}")
        paths = paths[:n]
    calibration = recipe.resolve_path(recipe.cameras.calibration) or path / "calibration.json"
    if not calibration.is_file():
        raise InputError(
            f"calibration file not found: {calibration} (set cameras.calibration in {recipe.file or 'the recipe'})"
        )
    return paths, calibration


def record_sim_episodes(recipe: Recipe, n: int | None, path: Path | None, progress: bool) -> Path:
    """Record the recipe's simulated episodes (once; later builds reuse them)."""
    from imac_data.simulate import SimConfig, record_dataset

    sim = recipe.source.sim
    config = SimConfig(task=sim.task, num_episodes=n or 2, width=sim.width, height=sim.height, seed=sim.seed,
                       noise=sim.noise, frame_stride=sim.frame_stride, with_segmentation=sim.segmentation)
    if path is None:
        key = hashlib.sha256(json.dumps(asdict(config), sort_keys=True).encode()).hexdigest()[:12]
        path = cache_home() / "sim" / f"{recipe.name}-{key}"
    if (path / "calibration.json").is_file() and len(list(path.glob("episode_*.hdf5"))) >= config.num_episodes:
        return path
    print(f"[build] recording {config.num_episodes} simulated {sim.task} episodes into {path}", file=sys.stderr)
    record_dataset(config, path, progress=progress, overwrite=True)
    return path


def build(req: BuildRequest):
    """Run the whole build; returns the loaded LeRobotDataset."""
    from imac_data.cameras import load_calibration
    from imac_data.ingest import IngestOptions, ingest_episodes

    recipe = req.recipe
    if req.root.exists() and not req.overwrite:
        raise InputError(f"output {req.root} already exists; pass --overwrite to replace it")
    problems = missing_inputs(recipe, req.source_path)
    if problems:
        raise InputError(f"recipe {recipe.file} needs inputs that are not there:\n  - " + "\n  - ".join(problems))
    robot = robot_of(recipe)
    paths, calibration_path = source_episodes(req)
    calibration = load_calibration(calibration_path)
    fps = recipe.fps or _fps_of(paths[0]) or None
    if fps is None:
        raise InputError(f"{recipe.file}: fps: the episodes do not record their rate; set fps in the recipe")
    defaults = recipe.source.episode_defaults
    options = IngestOptions(
        fps=fps, task=recipe.task, source=defaults.source, policy_name=defaults.policy_name,
        checkpoint=defaults.checkpoint, robot_type=robot.name, state_names=_state_names(recipe, robot),
    )
    return ingest_episodes(paths, calibration=calibration, robot=robot, repo_id=req.repo_id, root=req.root,
                           options=options, overwrite=req.overwrite, progress=req.progress)


def _fps_of(path: Path) -> float | None:
    import h5py

    with h5py.File(path, "r") as f:
        return float(f.attrs["fps"]) if "fps" in f.attrs else None


def _state_names(recipe: Recipe, robot) -> tuple[str, ...] | None:
    if recipe.robot.platform == "aloha_sim":
        from imac_data.aloha import STATE_NAMES

        return STATE_NAMES
    return None


def validate(dataset, sample: int = 4) -> None:
    """Load a few frames through LeRobot's own loader and check every stream decodes."""
    import numpy as np

    n = len(dataset)
    if n != dataset.meta.total_frames:
        raise RuntimeError(f"dataset has {n} frames, metadata says {dataset.meta.total_frames}")
    for i in np.linspace(0, n - 1, min(sample, n)).astype(int):
        item = dataset[int(i)]
        for key in dataset.meta.video_keys:
            if key not in item or item[key].ndim != 3:
                raise RuntimeError(f"frame {i}: video stream {key} did not decode")


# --------------------------------------------------------------------------- CLI


def quiet_libraries() -> None:
    """Keep the console to our progress bars: SVT-AV1 banners, libav muxer notes and
    the datasets library's per-file bars say nothing a user acts on."""
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1: errors only
    import av
    import datasets

    av.logging.set_level(av.logging.ERROR)
    datasets.disable_progress_bars()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m imac_data.build",
        description="Build a LeRobot dataset with iMaC control streams from a recipe.",
    )
    p.add_argument("--repo", required=True, help="dataset repo id, e.g. local/aloha_sim_transfer_cube")
    p.add_argument("--recipe", type=Path, help="recipe YAML (default: recipes/<name of --repo>.yaml)")
    p.add_argument("--root", type=Path, help="output directory (default: $HF_LEROBOT_HOME/<repo>)")
    p.add_argument("--source", type=Path, help="directory of raw episodes (overrides the recipe's source.path)")
    p.add_argument("--episodes", type=int, help="use the first N episodes (overrides the recipe)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output dataset")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = p.parse_args(argv)

    quiet_libraries()
    t0 = time.perf_counter()
    try:
        if "/" not in args.repo:
            raise InputError(f"--repo must look like <user>/<name>, got {args.repo!r}")
        recipe_path = args.recipe or find_recipe(args.repo.split("/", 1)[1])
        recipe = load_recipe(recipe_path)
        if args.episodes is not None and args.episodes <= 0:
            raise InputError(f"--episodes must be positive, got {args.episodes}")
        if args.source is not None and not args.source.exists():
            raise InputError(f"--source: path does not exist: {args.source}")
        req = BuildRequest(
            repo_id=args.repo, recipe=recipe, root=args.root or default_root(args.repo),
            source_path=args.source, episodes=args.episodes, overwrite=args.overwrite,
            progress=not args.no_progress,
        )
        dataset = build(req)
        validate(dataset)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    dt = time.perf_counter() - t0
    size = sum(f.stat().st_size for f in req.root.rglob("*") if f.is_file())
    frames = dataset.meta.total_frames
    print(
        f"built {args.repo}: {dataset.meta.total_episodes} episodes, {frames} frames in {dt:.1f} s "
        f"({frames / dt:.1f} frames/s), {size / 1e6:.1f} MB at {req.root}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

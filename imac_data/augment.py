"""``python -m imac_data.augment``: add the control streams to an existing LeRobot dataset.

For a dataset that already holds an episode's base features (e.g. one downloaded from
the hub, or a base dataset written by :mod:`imac_data.ingest`), this adds, per camera,
``observation.depth.{cam}``, ``control.motion.{cam}``, ``control.contact_r2s.{cam}`` and
``control.contact_s2g.{cam}``, the per-frame ``control.contact_cap`` column, the rig and
stream settings in ``info["imac"]`` and the robot description under ``meta/imac/robot/``.
The streams are made by the same streamed pipeline as the build's
(:class:`imac_data.pipeline.EpisodePipeline`), episode by episode, chunk by chunk.

The dataset is changed only by a staged swap at the end: the streams are written into a
copy whose videos are hard links (:func:`imac_data.dataset.files.staged_dataset`), which
is validated and then renamed into place. The original camera videos are never rewritten,
and the raw episodes it reads depth from are only read.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from imac_data.errors import InputError

__all__ = ["augment_existing", "main"]


def augment_existing(root: Path, recipe, source_dir: Path, *, progress: bool = True) -> None:
    """Add the control streams to the LeRobot dataset at ``root``, in place and atomically.

    Depth and the rig's image sizes come from the raw episodes in ``source_dir`` (episode
    ``i`` of the dataset = the ``i``-th file in natural order); their states must equal the
    dataset's, which is checked for every episode before any work starts.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from imac_data.aloha_hdf5 import EpisodeReader, episode_paths
    from imac_data.dataset.files import staged_dataset
    from imac_data.dataset.info import base_block, update_imac_info
    from imac_data.dataset.validate import validate_dataset
    from imac_data.lock import output_lock
    from imac_data.pipeline import add_episode_streams
    from imac_data.rig import Rig
    from imac_data.robot_files import DESCRIPTION_DIR, write_description
    from imac_data.safety import refuse_overlap

    refuse_overlap(root, {"raw episodes": source_dir,
                          "calibration": recipe.resolve_path(recipe.cameras.calibration)}, what="dataset")
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise InputError(f"{root} is not a LeRobot dataset ({info_path} is missing)")
    info = json.loads(info_path.read_text())
    existing = [k for k in info["features"] if k.startswith(("control.", "observation.depth."))]
    if existing:
        raise InputError(f"{root} already has control/depth streams {existing[:3]}...; start from the base dataset")
    if recipe.cameras.calibration is not None:
        rig = Rig.from_recipe(recipe)
    elif "cameras" in info.get("imac", {}):
        rig = Rig.from_recipe(recipe, Rig.from_info(info, root).cameras)
    else:
        raise InputError(f"{root}: no calibration: set cameras.calibration in {recipe.file}")
    dataset = LeRobotDataset(info.get("repo_id", "local/dataset"), root=root)
    n = dataset.meta.total_episodes
    paths = episode_paths(source_dir)
    if len(paths) < n:
        raise InputError(f"{source_dir}: {len(paths)} raw episodes for a dataset of {n}")
    paths = paths[:n]
    data = dataset.hf_dataset.with_format("numpy")
    states = []
    for ep, path in enumerate(paths):  # every episode is checked before any work
        lo, hi = dataset.meta.episodes["dataset_from_index"][ep], dataset.meta.episodes["dataset_to_index"][ep]
        state = np.asarray(data[lo:hi]["observation.state"], dtype=np.float64)
        action = np.asarray(data[lo:hi]["action"], dtype=np.float64)
        with EpisodeReader(path) as raw:
            if state.shape != raw.qpos.shape or not np.allclose(state, raw.qpos, atol=1e-5):
                raise InputError(f"{path}: its qpos does not match episode {ep} of {root} "
                                 f"({raw.qpos.shape} vs {state.shape}); the raw episodes must be the dataset's")
            if ep == 0:
                rig = rig.with_image_sizes(raw.image_hw)
        states.append((state, action))
    with output_lock(root), staged_dataset(root) as work:  # one writer per dataset (imac_data.lock)
        write_description(rig.robot, work / DESCRIPTION_DIR)
        update_imac_info(work, base_block(rig))
        add_episode_streams(work, (EpisodeReader(p) for p in paths), rig, recipe.augment, states=states,
                            progress=progress)
        validate_dataset(work).raise_if_invalid()


def main(argv: list[str] | None = None) -> int:
    import argparse

    from imac_data.cli import default_root, quiet_libraries, run_command, silence_progress_bars
    from imac_data.recipes import find_recipe, load_recipe

    p = argparse.ArgumentParser(prog="python -m imac_data.augment",
                                description="Add iMaC control streams to an existing LeRobot dataset.")
    p.add_argument("--repo", required=True, help="dataset repo id (looked up under $HF_LEROBOT_HOME unless --root)")
    p.add_argument("--root", type=Path, help="dataset directory")
    p.add_argument("--recipe", type=Path, required=True, help="recipe YAML: robot, calibration, augment settings")
    p.add_argument("--source", type=Path, required=True, help="raw HDF5 episodes of the dataset (recorded depth)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    quiet_libraries()
    if args.no_progress:
        silence_progress_bars()

    def run() -> None:
        recipe = load_recipe(args.recipe if args.recipe.suffix else find_recipe(str(args.recipe)))
        root = args.root or default_root(args.repo)
        augment_existing(root, recipe, args.source, progress=not args.no_progress)
        print(f"augmented {args.repo} at {root}")

    return run_command(run)


if __name__ == "__main__":
    from imac_data.cli import exit_process

    exit_process(main())

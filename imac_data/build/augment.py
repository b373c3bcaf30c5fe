"""Add the control streams to an existing LeRobot dataset (one built without them, or one
from the hub), in place and atomically: the streams are written into an edited copy whose
videos are hard links, validated, and swapped in. The original camera videos are never
rewritten, and the raw episodes that give the depth are only read."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imac_data.build.staging import staged_output
from imac_data.build.streams import add_episode_streams
from imac_data.core.render import check_device
from imac_data.core.rig import Rig
from imac_data.core.robot.lerobot_units import units_refusal
from imac_data.dataset.info import read_info, update_imac_info
from imac_data.dataset.ingest import write_rig
from imac_data.dataset.output import refuse_overlap
from imac_data.errors import InputError
from imac_data.layout import ACTION, STATE, is_added_stream
from imac_data.metadata import unchecked_imac_block
from imac_data.recipes import joint_units
from imac_data.sources.hdf5 import EpisodeReader, episode_paths
from imac_data.sources.lerobot_dataset import SourceDataset, episode_states

__all__ = ["augment_existing"]


def augment_existing(root: Path, recipe, source_dir: Path, *, progress: bool = True, device: str = "cpu") -> None:
    """Add the control streams to the dataset at ``root``, in place and atomically; ``device``: where the robot
    is rendered and contact painted (:attr:`~imac_data.core.rig.Rig.device`).

    Depth and the rig's image sizes come from the raw episodes in ``source_dir`` (episode
    ``i`` of the dataset = the ``i``-th file in natural order); their states must equal the
    dataset's, which is checked for every episode before any work starts.
    """
    root = Path(root)
    check_device(device)  # before anything is read
    refuse_overlap(root, {"raw episodes": source_dir,
                          "calibration": recipe.resolve_path(recipe.cameras.calibration)}, what="dataset")
    info = read_info(root)
    existing = [k for k in info["features"] if is_added_stream(k)]
    if existing:
        raise InputError(f"{root} already has control/depth streams {existing[:3]}...; start from the base dataset")
    if recipe.cameras.calibration is not None:
        rig = Rig.from_recipe(recipe)
    elif "cameras" in unchecked_imac_block(info):
        rig = Rig.from_recipe(recipe, Rig.from_info(info, root).cameras)
    else:
        raise InputError(f"{root}: no calibration: set cameras.calibration in {recipe.file}")
    rig.device = device
    dataset = SourceDataset.open(root)
    n = len(dataset.episodes)
    paths = episode_paths(source_dir)
    if len(paths) < n:
        raise InputError(f"{source_dir}: {len(paths)} raw episodes for a dataset of {n}")
    paths = paths[:n]
    recorded = zip(episode_states(root, dataset.episodes, STATE), episode_states(root, dataset.episodes, ACTION))
    states = []
    for ep, (path, (state, action)) in enumerate(zip(paths, recorded)):  # every episode is checked before any work
        with EpisodeReader(path) as raw:
            if state.shape != raw.qpos.shape or not np.allclose(state, raw.qpos, atol=1e-5):
                raise InputError(f"{path}: its qpos does not match episode {ep} of {root} "
                                 f"({raw.qpos.shape} vs {state.shape}); the raw episodes must be the dataset's")
            if ep == 0:
                rig = rig.with_image_sizes(raw.image_hw)
        states.append((state, action))
    units = joint_units(recipe)  # as the build: values the joint map's LeRobot units cannot record are refused
    if units and states:
        recorded = np.concatenate([s for s, _ in states])
        refusal = units_refusal(units, recorded.min(axis=0), recorded.max(axis=0), source=f"{root} ({STATE})",
                                recipe=str(recipe.file or "the recipe"))
        if refusal:
            raise InputError(refusal)
    with staged_output(root, edit=True, sample=4) as stage:
        write_rig(stage.dataset, rig)
        add_episode_streams(stage.dataset, (EpisodeReader(p) for p in paths), rig, recipe.augment, states=states,
                            progress=progress)
        if units:
            update_imac_info(stage.dataset, {"joint_units": units})

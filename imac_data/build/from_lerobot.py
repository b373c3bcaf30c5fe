"""A build whose source is a LeRobot dataset (``source.type: lerobot``).

The source is located (a local root, a hub download, a v2.1 dataset converted by LeRobot on
a staged copy) and checked against the recipe, copied byte for byte with its cameras renamed
to the calibrated names, given the base columns our datasets have, and then the streams,
episode by episode in this process (there are no shards to merge). The source is only read.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from imac_data.augment.timing import StageTimer
from imac_data.build.staging import BuildRequest, staged_output
from imac_data.build.streams import add_episode_streams
from imac_data.build.workers import pin_threads, threads_per_worker
from imac_data.core.rig import Rig
from imac_data.core.robot.joint_ranges import joint_range_warning
from imac_data.core.robot.lerobot_units import units_refusal
from imac_data.dataset.card import write_card
from imac_data.dataset.columns import add_episode_columns, add_frame_column
from imac_data.dataset.files import copy_source
from imac_data.dataset.info import update_imac_info
from imac_data.dataset.ingest import episode_column_types, write_rig
from imac_data.dataset.output import refuse_overlap
from imac_data.errors import InputError
from imac_data.layout import POSE_NAMES, image_key, pose_key
from imac_data.recipes import joint_units
from imac_data.sources.depth import check_depth_inputs, make_depth_source
from imac_data.sources.lerobot_dataset import (
    SourceDataset,
    camera_map,
    check_joint_layout,
    episode_metadata,
    episode_states,
    locate_source,
)
from imac_data.sources.lerobot_episodes import DepthFeature, LeRobotEpisodeReader

__all__ = ["build_from_lerobot"]


def build_from_lerobot(req: BuildRequest, robot) -> None:
    """Build ``req`` (source type lerobot) with the recipe's ``robot`` already loaded."""
    t0 = time.perf_counter()
    threads = threads_per_worker(1)
    pin_threads(threads)  # this process is the build's one worker
    recipe, src_cfg, where = req.recipe, req.recipe.source, req.recipe.file or "<recipe>"
    rig = Rig.from_recipe(recipe, robot=robot)
    rig.device = req.device
    check_depth_inputs(recipe.depth, recipe.file, len(rig.names))  # a missing model directory fails here
    path = req.source_path or recipe.resolve_path(src_cfg.path)
    refuse_overlap(req.root, {"source dataset": path})  # the user's; staged copies are ours
    timer = StageTimer()
    with staged_output(req.root, overwrite=req.overwrite, wait=req.wait, timer=timer) as stage:
        root, origin = locate_source(path, src_cfg.repo_id, stage.dir)
        src = SourceDataset.open(root)
        cameras = camera_map(src, src_cfg.cameras, rig.names, where)  # source key -> camera
        check_joint_layout(src, src_cfg.state_key, src_cfg.action_key, src_cfg.action_space, robot.dof, where)
        n = req.episodes if req.episodes is not None else src_cfg.episodes
        if n is not None and n != len(src.episodes):
            raise InputError(f"{where}: source.episodes {n}: a LeRobot source is used whole (dataset {src.root} has "
                             f"{len(src.episodes)} episodes; its video files hold several episodes each)")
        if recipe.fps is not None and abs(recipe.fps - src.fps) > 1e-6:
            raise InputError(f"{where}: fps {recipe.fps} differs from dataset {src.root}'s {src.fps}")
        depth_feature = None
        if recipe.depth.source == "recorded":
            depth_feature = DepthFeature(recipe.depth.feature, recipe.depth.format, recipe.depth.codec)
            depth_feature.check(src, rig.names, where)
        depth_videos = [depth_feature.key(c) for c in rig.names] if depth_feature and depth_feature.is_video else []
        src.check_files([*cameras, *depth_videos])  # before any work: LeRobot would try the hub for a missing file
        if depth_feature:
            depth_feature.check_streams(src, rig.names, where)
        src.check_videos([*cameras, *depth_videos], progress=req.progress)
        meta_rows = episode_metadata(recipe.resolve_path(src_cfg.metadata), len(src.episodes),
                                     src_cfg.episode_defaults)
        states = episode_states(src.root, src.episodes, src_cfg.state_key)
        actions = episode_states(src.root, src.episodes, src_cfg.action_key)
        recorded = np.concatenate(states) if states else np.zeros((0, rig.robot.dof))
        warning = joint_range_warning(rig.robot, recorded.min(axis=0), recorded.max(axis=0),
                                      source=f"{src.root} ({src_cfg.state_key})", recipe=where)
        if warning:
            print(warning, file=sys.stderr)
        units = joint_units(recipe)  # the LeRobot units the joint map takes: values they cannot record are refused
        refusal = units and units_refusal(units, recorded.min(axis=0), recorded.max(axis=0),
                                          source=f"{src.root} ({src_cfg.state_key})", recipe=where)
        if refusal:
            raise InputError(refusal)
        by_cam = {cam: key for key, cam in cameras.items()}
        rig = rig.with_image_sizes({cam: src.image_hw(key) for cam, key in by_cam.items()})
        depth_source = make_depth_source(recipe.depth, recipe.file, len(rig.names))

        # the byte copy and the base columns
        work = stage.dataset
        copy_source(src, work, cameras)
        out = SourceDataset.open(work)
        for v, cam in enumerate(rig.names):
            poses = [rig.camera_poses(s, dtype=torch.float64)[:, v].numpy().reshape(len(s), 16) for s in states]
            add_frame_column(work, pose_key(cam), poses, names=POSE_NAMES)
        add_episode_columns(work, meta_rows, episode_column_types())
        write_rig(work, rig)

        # the streams, episode by episode, chunk by chunk
        out_cams = {cam: image_key(cam) for cam in rig.names}
        readers = (LeRobotEpisodeReader(out, row, out_cams, states[i], actions[i], depth_feature)
                   for i, row in enumerate(out.episodes))
        add_episode_streams(work, readers, rig, recipe.augment, depth_source=depth_source,
                            states=list(zip(states, actions)), timer=timer, threads=threads, progress=req.progress)
        update_imac_info(work, {**({"joint_units": units} if units else {}), "build": {
            "recipe": recipe.name, "episodes": len(src.episodes),
            "command": f"python -m imac_data.build --repo {req.repo_id}",
            "source": {"type": "lerobot", **origin, "cameras": cameras, "state_key": src_cfg.state_key,
                       "action_key": src_cfg.action_key, "videos": "copied byte-identical from the source"}}})
        write_card(work, req.repo_id, recipe)
    # the table is the build's report, not a progress bar: --no-progress keeps it
    print(timer.table("[build] stage"), file=sys.stderr)
    print(f"[build] {len(states)} episodes, {sum(len(s) for s in states)} frames from the LeRobot dataset "
          f"{origin} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)

"""The build of a recipe whose source is a LeRobot dataset (``source.type: lerobot``).

Flow, all in a staging directory next to the output (``.<name>.staging``), renamed into
place only when the result validates; the source is only read:

1. locate the source (:func:`imac_data.lerobot_source.locate_source`: a local root, a hub
   download, a v2.1 dataset converted by LeRobot on a staged copy) and check it against
   the recipe: camera keys, joint layout, joint-space actions, depth feature, episode
   metadata, fps;
2. copy it byte for byte (:func:`~imac_data.lerobot_source.copy_source`: the camera
   features renamed to the calibrated names, the video files themselves unchanged);
3. add the base columns the build's datasets have: ``camera_pose.<cam>`` per frame (FK of
   the state for mounted cameras), ``imac/source`` ... ``imac/success`` per episode, the
   rig in ``info["imac"]`` and the robot description under ``meta/imac/robot/``;
4. add the streams with the streamed pipeline, episode by episode and chunk by chunk,
   frames read by :class:`~imac_data.lerobot_reader.LeRobotEpisodeReader`
   (:func:`imac_data.pipeline.add_episode_streams`, as ``augment`` does);
5. the card, the validation, the rename.

The episodes are built one after the other in this process (their base features already
exist, so there are no shards to merge); the pipeline's thread pools use the cores.
"""

from __future__ import annotations

import shutil
import sys
import time

import pyarrow as pa

from imac_data.errors import InputError

__all__ = ["build_from_lerobot"]

POSE_NAMES = [f"m{r}{c}" for r in range(4) for c in range(4)]


def build_from_lerobot(req, robot):
    """Build ``req`` (:class:`imac_data.build.BuildRequest`, source type lerobot) with the
    recipe's ``robot`` already loaded; returns the loaded ``LeRobotDataset``."""
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from imac_data.dataset.columns import add_episode_columns, add_frame_column
    from imac_data.dataset.info import base_block, update_imac_info
    from imac_data.dataset.validate import validate_dataset
    from imac_data.dataset_card import write_card
    from imac_data.depth_choice import check_depth_inputs, make_depth_source
    from imac_data.ingest import EPISODE_COLUMNS, camera_poses, staging_dir
    from imac_data.joint_ranges import joint_range_warning
    from imac_data.lerobot_reader import DepthFeature, LeRobotEpisodeReader
    from imac_data.lerobot_source import (SourceDataset, camera_map, check_joint_layout, copy_source,
                                          episode_metadata, episode_states, locate_source)
    from imac_data.pipeline import StageTimer, add_episode_streams
    from imac_data.rig import Rig
    from imac_data.robot_files import DESCRIPTION_DIR, write_description
    from imac_data.safety import make_sibling_dir, refuse_overlap, remove_sibling, swap_into_place
    from imac_data.workers import pin_threads, threads_per_worker

    t0 = time.perf_counter()
    threads = threads_per_worker(1)
    pin_threads(threads)  # this process is the build's one worker
    recipe, src_cfg, where = req.recipe, req.recipe.source, req.recipe.file or "<recipe>"
    rig = Rig.from_recipe(recipe, robot=robot)
    check_depth_inputs(recipe.depth, recipe.file, len(rig.names))  # a missing model directory fails here
    staging = staging_dir(req.root)
    remove_sibling(staging)
    make_sibling_dir(staging)
    try:
        path = req.source_path or recipe.resolve_path(src_cfg.path)
        refuse_overlap(req.root, {"source dataset": path})  # the user's; staged copies are ours
        root, origin = locate_source(path, src_cfg.repo_id, staging)
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
        depth_videos = [depth_feature.key(c) for c in rig.names] if depth_feature and depth_feature.codec else []
        src.check_files([*cameras, *depth_videos])  # before any work: LeRobot would try the hub for a missing file
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
        by_cam = {cam: key for key, cam in cameras.items()}
        rig = rig.with_image_sizes({cam: src.image_hw(key) for cam, key in by_cam.items()})
        depth_source = make_depth_source(recipe.depth, recipe.file, len(rig.names))

        # 2-3: the byte copy and the base columns
        work = staging / "dataset"
        copy_source(src, work, cameras)
        out = SourceDataset.open(work)
        for cam in rig.names:
            poses = [camera_poses({cam: rig.cameras[cam]}, rig.robot, s)[cam].reshape(len(s), 16) for s in states]
            add_frame_column(work, f"camera_pose.{cam}", poses, names=POSE_NAMES)
        add_episode_columns(work, meta_rows, {k: pa.bool_() if k == "imac/success" else pa.string()
                                              for k in EPISODE_COLUMNS})
        write_description(rig.robot, work / DESCRIPTION_DIR)
        update_imac_info(work, base_block(rig))

        # 4: the streams, episode by episode, chunk by chunk
        timer = StageTimer()
        out_cams = {cam: f"observation.images.{cam}" for cam in rig.names}
        readers = (LeRobotEpisodeReader(out, row, out_cams, states[i], actions[i], depth_feature)
                   for i, row in enumerate(out.episodes))
        add_episode_streams(work, readers, rig, recipe.augment, depth_source=depth_source,
                            states=list(zip(states, actions)), timer=timer, threads=threads,
                            progress=req.progress)
        update_imac_info(work, {"build": {
            "recipe": recipe.name, "episodes": len(src.episodes),
            "command": f"python -m imac_data.build --repo {req.repo_id}",
            "source": {"type": "lerobot", **origin, "cameras": cameras, "state_key": src_cfg.state_key,
                       "action_key": src_cfg.action_key, "videos": "copied byte-identical from the source"}}})
        write_card(work, req.repo_id, recipe)
        with timer("validate"):
            validate_dataset(work, sample=2).raise_if_invalid()
        if req.progress:
            print(timer.table("[build] stage"), file=sys.stderr)

        # 5: into place; the old output (--overwrite) is removed only once the new one is complete
        swap_into_place(work, req.root)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    if req.progress:
        print(f"[build] {len(states)} episodes, {sum(len(s) for s in states)} frames from the LeRobot dataset "
              f"{origin} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return LeRobotDataset(req.repo_id, root=req.root)

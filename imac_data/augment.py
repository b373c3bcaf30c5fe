"""Per-episode augmentation: the control streams of one episode, and writing them.

For one episode (joint states, actions, calibration, metric depth) this computes,
per camera at the stream resolution (DESIGN.md sections 3 and 4):

* ``control.motion.{cam}``: the robot rendered at the frame's commanded
  configuration (:func:`imac_data.motion.frame_configurations`), wrist cameras posed
  by FK of that configuration;
* ``observation.depth.{cam}``: the depth, stored with the colour codec;
* ``control.contact_r2s.{cam}`` / ``control.contact_s2g.{cam}``: the contact heatmaps,
  chunk by chunk (reference = chunk start, :func:`imac_data.contact.chunk_plan`);
* the per-frame column ``control.contact_cap`` (the two caps of the frame's chunk).

:func:`augment_dataset` writes them into a LeRobot dataset that already holds the
episode's base features (``ingest``), in place: callers give it a staging copy.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch

from imac_data.cameras import Camera
from imac_data.contact import iter_episode_contact
from imac_data.depth import DepthCodec, add_depth_streams, resize_depth
from imac_data.errors import InputError
from imac_data.recipes import AugmentSettings
from imac_data.video_streams import VideoEncoding, add_video_streams

CAP_KEY = "control.contact_cap"
MOTION, R2S, S2G = "control.motion", "control.contact_r2s", "control.contact_s2g"


@dataclass
class EpisodeStreams:
    """The added streams of one episode: uint8 frames per key, metric depth per camera."""

    frames: dict[str, np.ndarray]  # key -> (T, H, W, 3) uint8
    depth: dict[str, np.ndarray]  # cam -> (T, H, W) float32 metres
    caps: np.ndarray  # (T, 2) float32 metres: (r2s, s2g) of the frame's chunk


def episode_streams(state: np.ndarray, action: np.ndarray, depth: dict[str, np.ndarray],
                    cameras: dict[str, Camera], rig, settings: AugmentSettings) -> EpisodeStreams:
    """All control streams of one episode (``state``, ``action`` ``(T, D)``; ``depth``
    ``{cam: (T, h, w)}`` metres at any resolution registered to the camera) for the
    :class:`~imac_data.rig.Rig` ``rig`` with the episode's ``cameras``."""
    rig = rig.with_image_sizes({n: (c.height, c.width) for n, c in cameras.items()})
    names = rig.names
    missing = [n for n in names if n not in depth]
    if missing:
        raise InputError(f"no depth for camera(s) {missing}")
    T = len(state)
    H, W = settings.resolution
    q_state = torch.as_tensor(state, dtype=torch.float32)
    q_motion = torch.as_tensor(rig.frame_configurations(state, action, source=settings.motion_source),
                               dtype=torch.float32)
    seen = rig.robot_views(q_state, resolution=settings.resolution, gripper=False)
    drawn = rig.robot_views(q_motion, resolution=settings.resolution)
    depth_hw = {n: resize_depth(np.asarray(depth[n], dtype=np.float32), (H, W), name=f"depth of {n}") for n in names}
    for n, d in depth_hw.items():
        if len(d) != T:
            raise InputError(f"depth of {n} has {len(d)} frames, the episode has {T}")
    # Chunk by chunk, keeping only the colour frames and caps (not the float distance maps).
    r2s_rgb, s2g_rgb, caps = [], [], np.zeros((T, 2), np.float32)
    for _, frames_of_chunk, chunk in iter_episode_contact(
        torch.as_tensor(np.stack([depth_hw[n] for n in names], axis=1)), rig.intrinsics(settings.resolution),
        seen.T_world_cam, seen.mask, drawn.depth, drawn.T_world_cam, drawn.gripper_points,
        chunk_size=settings.contact_chunk, cap=settings.contact_cap, percentile=settings.contact_percentile,
        dilate_px=settings.robot_mask_dilate_px,
    ):
        r2s_rgb.append(chunk.r2s_rgb.cpu().numpy())
        s2g_rgb.append(chunk.s2g_rgb.cpu().numpy())
        caps[frames_of_chunk] = chunk.caps.cpu().numpy()
    r2s_rgb, s2g_rgb = np.concatenate(r2s_rgb), np.concatenate(s2g_rgb)
    frames = {}
    for v, n in enumerate(names):
        frames[f"{MOTION}.{n}"] = drawn.rgb[:, v].numpy()
        frames[f"{R2S}.{n}"] = r2s_rgb[:, v]
        frames[f"{S2G}.{n}"] = s2g_rgb[:, v]
    return EpisodeStreams(frames=frames, depth=depth_hw, caps=caps)


# --------------------------------------------------------------------------- writing


def augment_dataset(root: Path, episodes: list[EpisodeStreams], cameras: dict[str, Camera],
                    settings: AugmentSettings, depth_source: dict) -> None:
    """Write the streams of ``episodes`` (in episode order) into the dataset at ``root``."""
    codec = DepthCodec.preset(settings.depth_codec)
    add_depth_streams(root, (e.depth for e in episodes), cameras=list(cameras), codec=codec,
                      size=settings.resolution, source=depth_source)
    keys = list(episodes[0].frames)
    add_video_streams(root, (e.frames for e in episodes), keys=keys, encodings=VideoEncoding.lossless_rgb(),
                      info_extra={k: {"imac.stream": k.rsplit(".", 1)[0]} for k in keys})
    add_frame_column(root, CAP_KEY, [e.caps for e in episodes], names=["r2s", "s2g"])
    _merge_imac_info(root, {
        "augment": asdict(settings),
        "motion": {"source": settings.motion_source,
                   "frame_rule": "frame t shows phi(state[t-1], action[t-1]); frame 0 shows state[0]"
                                 if settings.motion_source == "action" else "frame t shows state[t]"},
        "contact": {
            "chunk_size": settings.contact_chunk,
            "reference_rule": "chunk c covers frames c*H+1..c*H+H with reference frame c*H; frame 0 is step 0",
            "cap": settings.contact_cap if settings.contact_cap is not None
            else f"p{settings.contact_percentile:g} per chunk and stream",
            "cap_column": CAP_KEY,
            "colormap": "jet of 1 - d/cap (near = red), black = no value",
            "tolerance": "painted distance d' satisfies d <= d' <= d + max(1 mm, 3% d) (contact.DEFAULT_TOLERANCE)",
        },
    })


def add_frame_column(root: Path, key: str, per_episode: list[np.ndarray], names: list[str]) -> None:
    """Add a float32 per-frame feature ``key`` (values ``(T_e, N)`` per episode, in episode
    order) to the data parquet files, ``info.json`` and the stats."""
    from lerobot.datasets.compute_stats import aggregate_stats, get_feature_stats

    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    if key in info["features"]:
        raise InputError(f"{root}: feature {key} already exists")
    values = {ep: np.asarray(v, dtype=np.float32).reshape(len(v), -1) for ep, v in enumerate(per_episode)}
    width = len(names)
    lengths = np.array([len(values[ep]) for ep in range(len(values))])
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    flat = np.concatenate([values[ep] for ep in range(len(values))])
    for file in sorted((root / "data").rglob("*.parquet")):
        table = pq.read_table(file)
        eps = table.column("episode_index").to_numpy()
        frame = table.column("frame_index").to_numpy()
        column = flat[offsets[eps] + frame]
        arr = pa.array(list(column), type=pa.list_(pa.float32()))
        pq.write_table(table.append_column(key, arr), file)
    info["features"][key] = {"dtype": "float32", "shape": [width], "names": names}
    info_path.write_text(json.dumps(info, indent=4))
    # stats: per episode (meta/episodes columns) and global (meta/stats.json), as LeRobot computes them
    ep_stats = {ep: get_feature_stats(v, axis=0, keepdims=v.ndim == 1) for ep, v in values.items()}
    for file in sorted((root / "meta" / "episodes").rglob("*.parquet")):
        table = pq.read_table(file)
        idx = table.column("episode_index").to_pylist()
        for stat in ep_stats[idx[0]]:
            col = [np.asarray(ep_stats[i][stat]).reshape(-1).tolist() for i in idx]
            table = table.append_column(f"stats/{key}/{stat}", pa.array(col))
        pq.write_table(table, file)
    stats_path = root / "meta" / "stats.json"
    stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
    total = aggregate_stats([{key: s} for s in ep_stats.values()])[key]
    stats[key] = {k: np.asarray(v).tolist() for k, v in total.items()}
    stats_path.write_text(json.dumps(stats, indent=4))


def _merge_imac_info(root: Path, block: dict) -> None:
    from imac_data.ingest import update_imac_info

    update_imac_info(root, block)


# --------------------------------------------------------------------------- CLI: existing datasets


def augment_existing(root: Path, recipe, source_dir: Path, *, progress: bool = True) -> None:
    """Add the control streams to the LeRobot dataset at ``root`` (e.g. one downloaded from
    the hub, or a base dataset built by ``ingest``), in place and atomically: the streams
    are written into a staging copy whose videos are hard links, swapped in at the end.
    The original camera videos are never rewritten.

    Depth and the episodes' joint data come from the raw episodes in ``source_dir``
    (episode ``i`` of the dataset = the ``i``-th file in natural order); their states
    must equal the dataset's, which is checked.
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from tqdm.auto import tqdm

    from imac_data.aloha_hdf5 import episode_paths, read_episode
    from imac_data.build import validate
    from imac_data.dataset.info import base_block
    from imac_data.depth_sources import RecordedDepth, episode_views
    from imac_data.rig import Rig
    from imac_data.robot_files import DESCRIPTION_DIR, write_description
    from imac_data.safety import refuse_overlap
    from imac_data.video_streams import staged_dataset

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
    paths = episode_paths(source_dir)
    if len(paths) < dataset.meta.total_episodes:
        raise InputError(f"{source_dir}: {len(paths)} raw episodes for a dataset of {dataset.meta.total_episodes}")
    data = dataset.hf_dataset.with_format("numpy")
    source = RecordedDepth()
    streams = []
    for ep in tqdm(range(dataset.meta.total_episodes), desc="augment episodes", unit="ep", disable=not progress):
        raw = read_episode(paths[ep])
        lo, hi = dataset.meta.episodes["dataset_from_index"][ep], dataset.meta.episodes["dataset_to_index"][ep]
        state = np.asarray(data[lo:hi]["observation.state"], dtype=np.float64)
        if state.shape != raw.qpos.shape or not np.allclose(state, raw.qpos, atol=1e-5):
            raise InputError(f"{paths[ep]}: its qpos does not match episode {ep} of {root} "
                             f"({raw.qpos.shape} vs {state.shape}); the raw episodes must be the dataset's")
        action = np.asarray(data[lo:hi]["action"], dtype=np.float64)
        views = episode_views(raw, rig.cameras, rig.robot, name=str(paths[ep]))
        streams.append(episode_streams(state, action, source.depth(views), dict(views.cameras), rig, recipe.augment))
    rig = rig.with_image_sizes({n: (c.height, c.width) for n, c in views.cameras.items()})
    with staged_dataset(root) as work:
        write_description(rig.robot, work / DESCRIPTION_DIR)
        _merge_imac_info(work, base_block(rig))
        augment_dataset(work, streams, dict(views.cameras), recipe.augment, source.describe())
        validate(LeRobotDataset(info.get("repo_id", "local/dataset"), root=work))


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys

    from imac_data.build import default_root, quiet_libraries
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
    try:
        recipe = load_recipe(args.recipe if args.recipe.suffix else find_recipe(str(args.recipe)))
        root = args.root or default_root(args.repo)
        augment_existing(root, recipe, args.source, progress=not args.no_progress)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"augmented {args.repo} at {root}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

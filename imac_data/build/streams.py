"""The pipeline's chunks into a dataset: one raw episode into a complete shard, or the added
streams of an existing dataset's episodes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from imac_data.augment.pipeline import EpisodePipeline
from imac_data.augment.timing import StageTimer
from imac_data.dataset.columns import add_frame_column
from imac_data.dataset.depth_streams import depth_imac_block, depth_info_extra, depth_map_imac_block
from imac_data.dataset.files import atomic_write_text
from imac_data.dataset.info import update_imac_info
from imac_data.dataset.ingest import BaseWriter
from imac_data.dataset.streams import StreamWriter
from imac_data.dataset.videos import VideoEncoding
from imac_data.layout import CAP_KEY, depth_key, depth_map_key, info_path
from imac_data.metadata import unchecked_imac_block
from imac_data.sources.hdf5 import EpisodeReader

__all__ = ["stream_writer", "write_episode_dataset", "add_episode_streams", "write_timings"]


def stream_writer(pipe: EpisodePipeline, root: Path, calibration: dict) -> StreamWriter:
    """A :class:`~imac_data.dataset.streams.StreamWriter` for the pipeline's streams in the
    dataset at ``root`` (``calibration``: the cameras' ``info.json`` entries)."""
    encoding = VideoEncoding.lossless_rgb()
    names = pipe.rig.names
    depth_keys = [depth_key(c) for c in names]
    maps = {depth_map_key(c): pipe.depth_map for c in names} if pipe.depth_map is not None else {}
    extra = {k: depth_info_extra(pipe.codec) if k in depth_keys else {"imac.stream": k.rsplit(".", 1)[0]}
             for k in pipe.keys if k not in maps}
    encodings = {k: VideoEncoding.depth_map() if k in maps else encoding for k in pipe.keys}
    source = pipe.depth_source.describe()
    if not pipe.with_depth:
        return StreamWriter(root, pipe.keys, encoding, info_extra=extra, threads=pipe.threads)

    def imac_info(features):
        block = depth_imac_block(features, names, calibration, pipe.codec, encoding, source)
        if maps:
            block["depth"]["depth_maps"] = depth_map_imac_block(names, pipe.depth_map, VideoEncoding.depth_map())
        return block

    return StreamWriter(root, pipe.keys, encodings, info_extra=extra, threads=pipe.threads, depth_maps=maps,
                        imac_info=imac_info)


def write_episode_dataset(path: Path, root: Path, repo_id: str, rig, settings, options, *,
                          timer: StageTimer | None = None, threads: int = 1, with_description: bool = True,
                          depth_source=None) -> None:
    """One raw episode -> a complete one-episode dataset at ``root`` (must not exist): the
    base features and every added stream, in one pass over the episode's chunks. The
    build's shard."""
    timer = timer if timer is not None else StageTimer()
    pipe = EpisodePipeline(rig, settings, depth_source, timer=timer, threads=threads, fps=options.fps)
    base = streams = None
    with EpisodeReader(path) as ep:
        rig = rig.with_image_sizes(ep.image_hw)
        try:
            with timer("write"):
                base = BaseWriter(root, repo_id, image_hw=ep.image_hw, dof=ep.qpos.shape[1],
                                  with_velocity=ep.qvel is not None, options=options, threads=threads)
                streams = stream_writer(pipe, root, {n: c.to_dict() for n, c in rig.cameras.items()})
                base.begin_episode(ep.num_frames, ep.info)
                streams.begin_episode(0, ep.num_frames)
            caps = np.zeros((ep.num_frames, 2), np.float32)
            for out in pipe.chunks(ep, images=True):
                with timer("encode"):
                    lo, hi = out.start, out.stop
                    base.add(ep.qpos[lo:hi], ep.action[lo:hi], None if ep.qvel is None else ep.qvel[lo:hi],
                             out.images, out.poses)
                    streams.write(out.streams)
                    if out.caps is not None:
                        caps[lo:hi] = out.caps
            with timer("write"):
                base.end_episode()
                streams.end_episode()
                base.finish(rig, with_description=with_description)
                streams.commit()
                if pipe.with_depth:
                    add_frame_column(root, CAP_KEY, [caps], names=["r2s", "s2g"])
                update_imac_info(root, pipe.imac_block())
        except BaseException:
            if streams is not None:
                streams.abort()
            if base is not None:
                base.abort()
            raise


def add_episode_streams(root: Path, readers, rig, settings, *, depth_source=None, states=None,
                        timer: StageTimer | None = None, threads: int = 1, progress: bool = False) -> None:
    """The added streams of every episode of the dataset at ``root`` (in place: callers give
    a staged copy); episode ``i`` from ``readers[i]`` (:class:`~imac_data.sources.episode.EpisodeSource`,
    opened one at a time) with joint vectors ``states[i] = (state, action)`` (default: the readers')."""
    timer = timer if timer is not None else StageTimer()
    fps = json.loads(info_path(root).read_text()).get("fps")  # the dataset's: cameras' time offsets need it
    pipe = EpisodePipeline(rig, settings, depth_source, timer=timer, threads=threads, fps=fps)
    calibration = unchecked_imac_block(root).get("cameras") or {n: c.to_dict() for n, c in rig.cameras.items()}
    caps = []
    with stream_writer(pipe, root, calibration) as streams:
        for i, reader in enumerate(tqdm(readers, desc="augment episodes", unit="ep", disable=not progress)):
            with reader as ep:
                state, action = states[i] if states is not None else (None, None)
                streams.begin_episode(i, ep.num_frames)
                ep_caps = np.zeros((ep.num_frames, 2), np.float32)
                for out in pipe.chunks(ep, state=state, action=action):
                    with timer("encode"):
                        streams.write(out.streams)
                        if out.caps is not None:
                            ep_caps[out.start:out.stop] = out.caps
                streams.end_episode()
                caps.append(ep_caps)
        with timer("write"):
            streams.commit()
    with timer("write"):
        if pipe.with_depth:
            add_frame_column(root, CAP_KEY, caps, names=["r2s", "s2g"])
        update_imac_info(root, pipe.imac_block())


def write_timings(path: Path, timer: StageTimer, **extra) -> None:
    """A stage-timing side file (never inside a dataset); atomic, so a full disk never leaves
    a truncated one for a resumed build to read."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({**timer.to_dict(), **extra}, indent=1))

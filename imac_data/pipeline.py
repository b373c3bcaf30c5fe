"""The episode pipeline, streamed: a raw episode -> every added stream, chunk by chunk.

The unit of work is a contact chunk (:func:`imac_data.contact.chunk_plan`): its reference
frame plus the up to H frames after it (chunk 0 also holds frame 0, as its step 0). Each
chunk goes through

====================  ===========================================================================
``read``              its frames of the raw episode: RGB and recorded depth (the episode's joint
                      vectors are read once: ``T x D`` floats)
``fk``                link poses at the frames' drawn configurations (phi of the actions, or the
                      measured state), at the reference state, camera poses, gripper samples
``render``            the robot at the drawn configurations (motion images, robot depth), and at the
                      measured state of the reference only (the robot mask removed from the scene)
``depth``             depth -> metres -> stream resolution -> colour codec
``contact``           both contact streams and the chunk's caps (:func:`imac_data.contact.contact_chunk`)
``encode``            every stream's frames to its encoder, and the base dataset's frames (RGB with
                      LeRobot's settings, state, action, camera poses) to LeRobot's writer
====================  ===========================================================================

so peak memory is one chunk's frames, renders and distance maps plus the encoders' own
buffers: it depends on the resolution and the chunk size, never on the episode's length
(``tests/test_memory.py``). The robot at the measured state is rendered only where the
contact streams need it, once per chunk.

Each stage's wall and CPU seconds are added up in a :class:`StageTimer` (CPU = the process's,
so threads a stage starts count for it); the build writes them to a side file in its
staging directory and prints them, never into the dataset.

Who calls what: :func:`write_episode_dataset` (the build: one episode -> one complete
dataset, base features and streams in one pass) and :func:`add_episode_streams` (``augment``:
the streams of an existing dataset's episodes) both drive :class:`EpisodePipeline`; the
world model calls the same :class:`~imac_data.rig.Rig` and contact functions online.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError
from imac_data.workers import raise_if_interrupted

__all__ = ["StageTimer", "ChunkOutput", "EpisodePipeline", "stream_keys", "write_episode_dataset",
           "add_episode_streams", "CAP_KEY", "MOTION", "R2S", "S2G", "STAGES"]

CAP_KEY = "control.contact_cap"
MOTION, R2S, S2G = "control.motion", "control.contact_r2s", "control.contact_s2g"
STAGES = ("read", "fk", "render", "depth", "contact", "encode", "write")


# ----------------------------------------------------------------------------- timings


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


# ----------------------------------------------------------------------------- the pipeline


def stream_keys(cameras, *, depth: bool = True) -> list[str]:
    """The added video streams in the dataset's order: depth per camera, then per camera
    motion, robot-to-scene, scene-to-gripper (``depth=False``: motion only)."""
    from imac_data.depth import depth_stream_key

    if not depth:
        return [f"{MOTION}.{c}" for c in cameras]
    return [depth_stream_key(c) for c in cameras] + [f"{k}.{c}" for c in cameras for k in (MOTION, R2S, S2G)]


@dataclass
class ChunkOutput:
    """What one chunk produces, for episode frames ``start .. stop - 1`` (n frames)."""

    start: int
    stop: int
    streams: dict[str, np.ndarray]  # key -> (n, h, w, 3) uint8, keys as stream_keys()
    caps: np.ndarray | None  # (n, 2) float32 metres: (r2s, s2g) of the chunk; None without depth
    images: dict[str, np.ndarray]  # cam -> (n, H, W, 3) uint8 recorded RGB ({} unless asked for)
    poses: dict[str, np.ndarray]  # cam -> (n, 4, 4) float64 camera-to-world at the measured state


class EpisodePipeline:
    """Every added stream of an episode, chunk by chunk (see the module docstring).

    ``rig``: the :class:`~imac_data.rig.Rig`; ``settings``: the recipe's
    :class:`~imac_data.recipes.AugmentSettings`; ``depth_source``: a
    :class:`~imac_data.depth_sources.DepthSource` (default: the recorded depth;
    :class:`~imac_data.depth_sources.NoDepth`: the motion streams only).
    ``threads``: the worker's share of the cores (renderer, contact, KD-tree queries).
    """

    def __init__(self, rig, settings, depth_source=None, *, timer: StageTimer | None = None, threads: int = 1):
        from imac_data.depth import DepthCodec
        from imac_data.depth_sources import RecordedDepth

        self.rig, self.settings = rig, settings
        self.depth_source = depth_source if depth_source is not None else RecordedDepth()
        self.timer = timer if timer is not None else StageTimer()
        self.threads = max(1, int(threads))
        self.codec = DepthCodec.preset(settings.depth_codec)
        self.with_depth = getattr(self.depth_source, "describe", dict)().get("kind") != "none"
        rig.set_threads(self.threads)

    @property
    def keys(self) -> list[str]:
        return stream_keys(self.rig.names, depth=self.with_depth)

    def chunks(self, reader, *, state=None, action=None, images: bool = False) -> Iterator[ChunkOutput]:
        """Stream the episode of ``reader`` (:class:`~imac_data.aloha_hdf5.EpisodeReader`).
        ``state``/``action`` ``(T, D)`` replace the reader's joint vectors (an existing
        dataset's, for ``augment``); ``images``: also pass the recorded RGB on."""
        from imac_data.contact import chunk_plan, contact_chunk
        from imac_data.depth import resize_depth
        from imac_data.depth_sources import EpisodeViews
        from imac_data.ingest import camera_poses

        s, timer = self.settings, self.timer
        rig = self.rig.with_image_sizes(reader.image_hw)
        names = rig.names
        missing = [c for c in names if c not in reader.image_hw]
        if missing:
            raise InputError(f"{reader.path}: no images for calibrated camera(s) {missing}")
        state = reader.qpos if state is None else np.asarray(state, dtype=np.float64)
        action = reader.action if action is None else np.asarray(action, dtype=np.float64)
        T = len(state)
        if T != reader.num_frames:
            raise InputError(f"{reader.path}: {reader.num_frames} frames, the joint vectors give {T}")
        res = s.resolution
        with timer("fk"):
            q_state = torch.as_tensor(state, dtype=torch.float32)
            q_drawn = torch.as_tensor(rig.frame_configurations(state, action, source=s.motion_source),
                                      dtype=torch.float32)
            K = rig.intrinsics(res)
        need_images = images or getattr(self.depth_source, "needs_images", True)
        carry = None  # stream-resolution depth of the previous chunk's last frame: the next reference
        for ref, frames in chunk_plan(T, s.contact_chunk):
            raise_if_interrupted()  # a Ctrl-C that a library swallowed stops here
            lo, hi = frames[0], frames[-1] + 1
            with timer("read"):
                rgb = {c: reader.images(c, lo, hi) for c in names} if need_images else {}
                mm = {c: d for c in names if self.with_depth and (d := reader.depth_mm(c, lo, hi)) is not None}
            with timer("fk"):
                poses = camera_poses(rig.cameras, rig.robot, state[lo:hi])
                links = rig.link_poses(q_drawn[lo:hi])
                links_ref = rig.link_poses(q_state[ref:ref + 1])
            if not self.with_depth:  # motion streams only
                with timer("render"):
                    motion = rig.robot_views(link_poses=links, resolution=res, gripper=False).rgb.numpy()
                timer.frames += hi - lo
                out = ChunkOutput(lo, hi, {f"{MOTION}.{c}": motion[:, v] for v, c in enumerate(names)}, None,
                                  rgb if images else {}, poses)
                del rgb, mm, links, links_ref, motion
                yield out
                del out
                continue
            with timer("render"):
                drawn = rig.robot_views(link_poses=links, resolution=res)
                seen = rig.robot_views(link_poses=links_ref, resolution=res, gripper=False)
            with timer("depth"):
                views = EpisodeViews(images=rgb, cameras=rig.cameras, poses=poses, depth_mm=mm,
                                     name=f"{reader.path} frames {lo}:{hi}")
                metres = self.depth_source.depth(views)
                depth_hw = np.stack([np.asarray(resize_depth(np.asarray(metres[c], dtype=np.float32), res,
                                                             name=f"depth of {c}")) for c in names], axis=1)
                if depth_hw.shape[0] != hi - lo:
                    raise InputError(f"{reader.path}: the depth source gave {depth_hw.shape[0]} frames for "
                                     f"frames {lo}:{hi}")
                streams = {f"observation.depth.{c}": self.codec.encode_uint8(depth_hw[:, v], name=f"depth of {c}")
                           for v, c in enumerate(names)}
                ref_depth = depth_hw[ref - lo] if ref >= lo else carry
                carry = depth_hw[-1]
            with timer("contact"):
                try:
                    chunk = contact_chunk(torch.as_tensor(ref_depth), K, seen.T_world_cam[0], seen.mask[0],
                                          drawn.depth, drawn.T_world_cam, drawn.gripper_points, cap=s.contact_cap,
                                          percentile=s.contact_percentile, dilate_px=s.robot_mask_dilate_px,
                                          workspace=rig.workspace, workers=self.threads, parallel=self.threads,
                                          allow_empty_scene=s.empty_reference_scene == "no_contact")
                except InputError as e:  # which episode and frame: the contact functions know only tensors
                    raise InputError(f"{reader.path}: contact images of frames {lo}:{hi} (reference frame {ref}, "
                                     f"cameras {names}): {e}. To build such chunks without contact, set "
                                     "augment.empty_reference_scene: no_contact in the recipe") from None
            r2s, s2g = chunk.r2s_rgb.cpu().numpy(), chunk.s2g_rgb.cpu().numpy()
            motion = drawn.rgb.numpy()
            for v, c in enumerate(names):
                streams[f"{MOTION}.{c}"] = motion[:, v]
                streams[f"{R2S}.{c}"] = r2s[:, v]
                streams[f"{S2G}.{c}"] = s2g[:, v]
            caps = np.repeat(chunk.caps.cpu().numpy()[None].astype(np.float32), hi - lo, axis=0)
            timer.frames += hi - lo
            out = ChunkOutput(lo, hi, {k: streams[k] for k in self.keys}, caps, rgb if images else {}, poses)
            # only the reference depth carries over: drop this chunk's arrays before the next
            # one is made, so that no more than one chunk is alive at a time
            del rgb, mm, links, links_ref, drawn, seen, views, metres, depth_hw, streams, chunk, r2s, s2g, motion
            yield out
            del out

    def imac_block(self) -> dict:
        """The stream settings' part of ``info["imac"]`` (``augment``, ``motion``, ``contact``)."""
        s = self.settings
        if not self.with_depth:
            return {"augment": asdict(s), "motion": self._motion_block(), "contact": None,
                    "depth": {"source": self.depth_source.describe()}}
        return {
            "augment": asdict(s),
            "motion": self._motion_block(),
            "contact": {
                "chunk_size": s.contact_chunk,
                "reference_rule": "chunk c covers frames c*H+1..c*H+H with reference frame c*H; frame 0 is step 0",
                "cap": s.contact_cap if s.contact_cap is not None else f"p{s.contact_percentile:g} per chunk and stream",
                "scene_crop": "imac.workspace" if self.rig.workspace is not None else None,
                "cap_column": CAP_KEY,
                "colormap": "jet of 1 - d/cap (near = red), black = no value",
                "tolerance": "painted distance d' satisfies d <= d' <= d + max(1 mm, 3% d) (contact.DEFAULT_TOLERANCE)",
            },
        }

    def _motion_block(self) -> dict:
        s = self.settings
        return {"source": s.motion_source,
                "frame_rule": "frame t shows phi(state[t-1], action[t-1]); frame 0 shows state[0]"
                              if s.motion_source == "action" else "frame t shows state[t]"}

    def stream_writer(self, root: Path, calibration: dict):
        """A :class:`~imac_data.dataset.streams.StreamWriter` for this pipeline's streams in
        the dataset at ``root`` (``calibration``: the cameras' ``info.json`` entries)."""
        from imac_data.dataset.depth_streams import depth_imac_block, depth_info_extra
        from imac_data.dataset.streams import StreamWriter
        from imac_data.dataset.videos import VideoEncoding

        encoding = VideoEncoding.lossless_rgb()
        names = self.rig.names
        depth_keys = [f"observation.depth.{c}" for c in names]
        extra = {k: depth_info_extra(self.codec) if k in depth_keys else {"imac.stream": k.rsplit(".", 1)[0]}
                 for k in self.keys}
        source = self.depth_source.describe()
        if not self.with_depth:
            return StreamWriter(root, self.keys, encoding, info_extra=extra, threads=self.threads)
        return StreamWriter(root, self.keys, encoding, info_extra=extra, threads=self.threads,
                            imac_info=lambda f: depth_imac_block(f, names, calibration, self.codec, encoding, source))


# ----------------------------------------------------------------------------- writing


def write_episode_dataset(path: Path, root: Path, repo_id: str, rig, settings, options, *,
                          timer: StageTimer | None = None, threads: int = 1, with_description: bool = True,
                          depth_source=None) -> None:
    """One raw episode -> a complete one-episode dataset at ``root`` (must not exist): the
    base features (LeRobot's writer, our streaming encoder) and every added stream, written
    in one pass over the episode's chunks. The build's shard."""
    from imac_data.aloha_hdf5 import EpisodeReader
    from imac_data.dataset.columns import add_frame_column
    from imac_data.dataset.info import update_imac_info
    from imac_data.ingest import BaseWriter

    timer = timer if timer is not None else StageTimer()
    pipe = EpisodePipeline(rig, settings, depth_source, timer=timer, threads=threads)
    base = streams = None
    with EpisodeReader(path) as ep:
        rig = rig.with_image_sizes(ep.image_hw)
        try:
            with timer("write"):
                base = BaseWriter(root, repo_id, rig=rig, image_hw=ep.image_hw, dof=ep.qpos.shape[1],
                                  with_velocity=ep.qvel is not None, options=options, threads=threads)
                streams = pipe.stream_writer(root, {n: c.to_dict() for n, c in rig.cameras.items()})
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
    a staged copy), episode ``i`` from ``readers[i]`` (an iterable of
    :class:`~imac_data.aloha_hdf5.EpisodeReader`, opened one at a time) with joint vectors
    ``states[i] = (state, action)`` (default: the readers')."""
    from tqdm.auto import tqdm

    from imac_data.dataset.columns import add_frame_column
    from imac_data.dataset.info import read_info, update_imac_info

    timer = timer if timer is not None else StageTimer()
    pipe = EpisodePipeline(rig, settings, depth_source, timer=timer, threads=threads)
    calibration = read_info(root).get("imac", {}).get("cameras") or {n: c.to_dict() for n, c in rig.cameras.items()}
    caps = []
    with pipe.stream_writer(root, calibration) as streams:
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
    a truncated one for the resumed build to read."""
    from imac_data.dataset.files import atomic_write_text

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({**timer.to_dict(), **extra}, indent=1))

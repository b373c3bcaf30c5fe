"""The episode pipeline: a source episode -> every added stream, one contact chunk at a time.

A chunk is a reference frame plus the up to H frames after it. Each goes through ``read``
(RGB, recorded depth), ``fk`` (configurations, camera poses), ``render`` (the robot at the
drawn configurations, and at the reference's measured state for its mask), ``depth``
(metres, stream size, colour codec; LeRobot depth-map codes when asked for) and ``contact``
(both streams and the chunk's caps), and
comes out as a :class:`ChunkOutput`. Nothing is written here (the build writes the outputs,
:mod:`imac_data.build.streams`), and only one chunk is alive at a time, so memory does not
grow with the episode's length.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, dataclass

import numpy as np
import torch

from imac_data.augment.timing import StageTimer
from imac_data.console import raise_if_interrupted, release_freed_memory
from imac_data.core.contact.images import chunk_plan
from imac_data.core.depth import DepthCodec
from imac_data.core.metric_depth import resize_depth
from imac_data.core.motion import joints_at
from imac_data.core.rig import RobotViews
from imac_data.errors import InputError
from imac_data.layout import CAP_KEY, MOTION, R2S, S2G, depth_key, depth_map_key, stream_keys
from imac_data.sources.depth import EpisodeViews, RecordedDepth

__all__ = ["ChunkOutput", "EpisodePipeline"]


class _CameraTimes:
    """Each camera at its own time: a camera whose frame stamped ``t`` shows the robot at the joint
    states of ``t + time_offset_s`` is rendered and posed at the joint vectors (measured and drawn)
    interpolated there (:func:`~imac_data.core.motion.joints_at`: Catmull-Rom, clamped at the
    episode's ends). Cameras of one offset are rendered together. The s2g stream's gripper, one for all
    views, is placed at the median of the cameras' offsets. ``shifted`` is False when every offset is
    0: the pipeline then runs as it always did (byte-identical output)."""

    def __init__(self, rig, state: np.ndarray, drawn: np.ndarray, fps: float | None, *, where: str):
        offsets = {c: cam.time_offset_s for c, cam in rig.cameras.items()}
        self.shifted = any(offsets.values())
        if not self.shifted:
            return
        if not fps:
            raise InputError(f"{where}: camera time offsets {offsets} need the episodes' frame rate (set fps in "
                             "the recipe)")
        self.rig, self.names = rig, rig.names
        frames = np.arange(len(state), dtype=np.float64)
        groups: dict[float, list[str]] = {}
        for c, d in offsets.items():
            groups.setdefault(d, []).append(c)
        self.groups = []  # (sub-rig of the cameras of one offset, measured (T, D), drawn (T, D))
        for d, cams in groups.items():
            sub = rig.for_views(cams)
            sub._renderer, sub._gripper = rig.renderer, rig.gripper  # one renderer and gripper surface
            self.groups.append((sub, joints_at(state, frames + d * fps), joints_at(drawn, frames + d * fps)))
        self.gripper_q = joints_at(drawn, frames + float(np.median(list(offsets.values()))) * fps)
        order = [c for sub, _, _ in self.groups for c in sub.names]
        self.order = torch.as_tensor([order.index(c) for c in self.names])

    def poses(self, lo: int, hi: int) -> dict[str, np.ndarray]:
        """Camera-to-world ``(n, 4, 4)`` float64 per camera at the measured state of its own time."""
        out = {}
        for sub, measured, _ in self.groups:
            T = sub.camera_poses(measured[lo:hi], dtype=torch.float64).numpy()
            out.update({c: T[:, v] for v, c in enumerate(sub.names)})
        return {c: out[c] for c in self.names}

    def views(self, lo: int, hi: int, res, *, gripper: bool = True, measured: bool = False):
        """:meth:`Rig.robot_views` of frames ``lo .. hi - 1``, each camera at its own time (drawn
        configurations, or the measured state), views in the rig's order."""
        parts = [sub.robot_views(link_poses=sub.link_poses(torch.as_tensor((m if measured else d)[lo:hi],
                                                                           dtype=torch.float32)),
                                 resolution=res, gripper=False) for sub, m, d in self.groups]

        def cat(attr):
            if getattr(parts[0], attr) is None:
                return None
            return torch.cat([getattr(p, attr) for p in parts], dim=1).index_select(1, self.order)

        points = None
        if gripper:
            points = self.rig.gripper.points(self.rig.link_poses(torch.as_tensor(self.gripper_q[lo:hi],
                                                                                 dtype=torch.float32)))
        return RobotViews(rgb=cat("rgb"), mask=cat("mask"), depth=cat("depth"), link_id=cat("link_id"),
                          T_world_cam=cat("T_world_cam"), gripper_points=points)


@dataclass
class ChunkOutput:
    """What one chunk produces, for episode frames ``start .. stop - 1`` (n frames)."""

    start: int
    stop: int
    streams: dict[str, np.ndarray]  # key -> (n, h, w, 3) uint8 (depth maps: (n, h, w) uint16), keys as stream_keys()
    caps: np.ndarray | None  # (n, 2) float32 metres: (r2s, s2g) of the chunk; None without depth
    images: dict[str, np.ndarray]  # cam -> (n, H, W, 3) uint8 recorded RGB ({} unless asked for)
    poses: dict[str, np.ndarray]  # cam -> (n, 4, 4) float64 camera-to-world at the measured state


class EpisodePipeline:
    """Every added stream of an episode, chunk by chunk (see the module docstring).

    ``rig``: the :class:`~imac_data.core.rig.Rig`; ``settings``: the recipe's
    :class:`~imac_data.recipes.AugmentSettings`; ``depth_source``: a
    :class:`~imac_data.sources.depth.DepthSource` (default: the recorded depth;
    :class:`~imac_data.sources.depth.NoDepth`: the motion streams only).
    ``threads``: the worker's share of the cores (renderer, contact, KD-tree queries).
    ``fps``: the episodes' frame rate, needed only when a camera has a time offset
    (``Camera.time_offset_s``): its renders and poses then use the joint vectors interpolated at the
    frame's time plus the offset (:class:`_CameraTimes`).
    """

    def __init__(self, rig, settings, depth_source=None, *, timer: StageTimer | None = None, threads: int = 1,
                 fps: float | None = None):
        self.rig, self.settings, self.fps = rig, settings, fps
        self.depth_source = depth_source if depth_source is not None else RecordedDepth()
        self.timer = timer if timer is not None else StageTimer()
        self.threads = max(1, int(threads))
        self.codec = DepthCodec.preset(settings.depth_codec)
        self.with_depth = getattr(self.depth_source, "describe", dict)().get("kind") != "none"
        output = getattr(settings, "lerobot_depth_map", None)  # LeRobot depth maps: their quantiser, or None
        self.depth_map = output.params() if output is not None and output.enabled and self.with_depth else None
        rig.use_cpu_renderer(getattr(settings, "renderer", "open3d"))
        rig.set_threads(self.threads)

    @property
    def keys(self) -> list[str]:
        return stream_keys(self.rig.names, depth=self.with_depth, depth_maps=self.depth_map is not None)

    def chunks(self, reader, *, state=None, action=None, images: bool = False) -> Iterator[ChunkOutput]:
        """Stream the episode of ``reader`` (an :class:`~imac_data.sources.episode.EpisodeSource`).
        ``state``/``action`` ``(T, D)`` replace the reader's joint vectors (an existing
        dataset's, for ``augment``); ``images``: also pass the recorded RGB on."""
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
            drawn_q = rig.frame_configurations(state, action, source=s.motion_source)
            q_state = torch.as_tensor(state, dtype=torch.float32)
            q_drawn = torch.as_tensor(drawn_q, dtype=torch.float32)
        times = _CameraTimes(rig, state, drawn_q, self.fps if self.fps is not None else getattr(reader, "fps", None),
                             where=str(reader.path))
        need_images = images or getattr(self.depth_source, "needs_images", True)
        carry = None  # stream-resolution depth of the previous chunk's last frame: the next reference
        for ref, frames in chunk_plan(T, s.contact_chunk):
            raise_if_interrupted()  # a Ctrl-C that a library swallowed stops here
            lo, hi = frames[0], frames[-1] + 1
            with timer("read"):
                rgb = {c: reader.images(c, lo, hi) for c in names} if need_images else {}
                mm = {c: d for c in names if self.with_depth and (d := reader.depth_mm(c, lo, hi)) is not None}
            if times.shifted:  # cameras out of step with the joint states: each at its own time
                with timer("fk"):
                    poses = times.poses(lo, hi)
                links = links_ref = None
            else:
                with timer("fk"):
                    poses_t = rig.camera_poses(state[lo:hi], dtype=torch.float64).numpy()
                    poses = {c: poses_t[:, v] for v, c in enumerate(names)}
                    links = rig.link_poses(q_drawn[lo:hi])
                    links_ref = rig.link_poses(q_state[ref:ref + 1])
            if not self.with_depth:  # motion streams only
                with timer("render"):
                    motion = (times.views(lo, hi, res, gripper=False) if times.shifted else
                              rig.robot_views(link_poses=links, resolution=res, gripper=False)).rgb.numpy()
                timer.frames += hi - lo
                out = ChunkOutput(lo, hi, {f"{MOTION}.{c}": motion[:, v] for v, c in enumerate(names)}, None,
                                  rgb if images else {}, poses)
                del rgb, mm, links, links_ref, motion
                yield out
                del out
                release_freed_memory()
                continue
            with timer("render"):
                if times.shifted:
                    drawn = times.views(lo, hi, res)
                    seen = times.views(ref, ref + 1, res, gripper=False, measured=True)
                else:
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
                streams = {depth_key(c): self.codec.encode_uint8(depth_hw[:, v], name=f"depth of {c}")
                           for v, c in enumerate(names)}
                if self.depth_map is not None:
                    streams.update({depth_map_key(c): self.depth_map.quantize(depth_hw[:, v])
                                    for v, c in enumerate(names)})
                ref_depth = depth_hw[ref - lo] if ref >= lo else carry
                carry = depth_hw[-1]
            with timer("contact"):
                try:
                    chunk = rig.contact_images(ref_depth, seen, drawn, **s.contact_options(), threads=self.threads,
                                        device=None if rig.device == "cpu" else rig.device)
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
            release_freed_memory()  # the chunk's arrays are gone: their pages go back

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

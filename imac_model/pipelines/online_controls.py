"""Control videos rebuilt online from a predicted frame: what a rollout needs at a chunk boundary.

The last generated mosaic frame becomes the next reference; its depth row is decoded with
the dataset's codec (colours far from the codec's walk, black and non-finite colours are
invalid depth, never an error), and the next chunk's motion and contact images are made from
it and the chunk's actions with the same :class:`~imac_data.core.rig.Rig` and contact
functions the build used, with the dataset's settings and workspace crop::

    online = OnlineControls.from_dataset(root, spec)
    out = online.controls(reference_mosaic, q_ref, actions, streams=spec.conditioning.streams)
    batch = ChunkBatch(reference=reference_mosaic, actions=actions, controls=out.controls)
    q_next = out.next_state                     # the last commanded configuration

``docs/world-model.md`` ("Rollouts: controls rebuilt online") has the details and the checks."""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from imac_data.core.contact.clouds import DEFAULT_DILATE_PX
from imac_data.core.metric_depth import resize_depth
from imac_data.core.rig import Rig
from imac_data.errors import InputError
from imac_data.recipes import AugmentSettings
from imac_model.data import meta as dataset_meta
from imac_model.data import mosaic
from imac_model.data.depth import DEFAULT_MAX_WALK_DISTANCE, decode_depth
from imac_model.data.scene_warp import SceneWarp
from imac_model.modes import CONTACT_STREAMS, CONTROL_STREAMS, DERIVED_STREAMS, SCENE_WARP

RESOLUTIONS = ("model", "dataset")


# --------------------------------------------------------------------------- results


@dataclass
class ContactControls:
    """Contact images of B chunks: ``r2s``, ``s2g`` ``(B, S, V, 3, h, w)`` float in [0, 1] at
    the model's view size; ``caps (B, 2)`` metres (r2s, s2g); ``distances``: the raw
    :class:`~imac_data.core.contact.images.ContactChunk` of each item at the compute resolution."""

    r2s: torch.Tensor
    s2g: torch.Tensor
    caps: torch.Tensor
    distances: list = field(default_factory=list)


@dataclass
class OnlineChunkControls:
    """Everything :meth:`OnlineControls.controls` rebuilt for B chunks."""

    controls: dict[str, torch.Tensor]  # stream -> (B, H, 3, 2h, V w) control mosaics in [0, 1]
    configurations: torch.Tensor  # (B, H, D) phi(q_ref, actions)
    next_state: torch.Tensor  # (B, D) the last commanded configuration
    depth: torch.Tensor | None  # (B, V, h, w) decoded reference depth, metres (0 = invalid)
    invalid_fraction: torch.Tensor | None  # (B,) share of reference depth pixels that are invalid
    caps: torch.Tensor | None  # (B, 2) contact caps


# --------------------------------------------------------------------------- the rebuilder


def warn_about_time_offsets(cameras: Mapping) -> None:
    """A warning when a camera has a time offset (``time_offset_s``): the build drew its controls at the joint
    states of the image's own time, interpolated over the whole episode, and a rollout has no such states (not
    before its reference, not past its chunk), so the online controls draw every camera at the joint states' time."""
    offsets = {name: cam.time_offset_s for name, cam in cameras.items() if cam.time_offset_s}
    if offsets:
        warnings.warn(f"camera time offsets {offsets} s: online motion and contact images draw every camera at the "
                      "joint states' time, while the dataset's were drawn at each image's own time (t + offset); "
                      "for these cameras the rollout's controls are off by that much (docs/world-model.md, "
                      "\"Rollouts: controls rebuilt online\")", stacklevel=3)


class OnlineControls:
    """A dataset's rig, depth codec and contact settings, bound to a model's views and size.

    ``rig``: :class:`~imac_data.core.rig.Rig` (its cameras are reordered to ``views``);
    ``codec``: the dataset's :class:`~imac_data.core.depth.DepthCodec`; ``view_hw``: the model's
    per-view size; ``source_hw``: the dataset's stream resolution; ``contact``: keyword
    options of :meth:`~imac_data.core.rig.Rig.contact_images`, the build's own function
    (:meth:`imac_data.recipes.AugmentSettings.contact_options` of the dataset's settings).
    """

    def __init__(self, rig, codec, views: Sequence[str], view_hw: tuple[int, int], source_hw: tuple[int, int], *,
                 contact: Mapping | None = None, resolution: str = "model",
                 max_walk_distance: float = DEFAULT_MAX_WALK_DISTANCE, device=None):
        if resolution not in RESOLUTIONS:
            raise InputError(f"rollout.resolution: must be one of {list(RESOLUTIONS)}, got {resolution!r}")
        if not 0 < max_walk_distance:
            raise InputError(f"rollout.max_walk_distance: must be > 0, got {max_walk_distance}")
        self.rig = rig.for_views(views)
        warn_about_time_offsets(self.rig.cameras)
        self.scene = SceneWarp(self.rig, codec, views, view_hw, dilate_px=dict(contact or {}).get("dilate_px", DEFAULT_DILATE_PX),
                               max_walk_distance=max_walk_distance)
        self.codec = codec
        self.views = tuple(views)
        self.view_hw = tuple(int(x) for x in view_hw)
        self.source_hw = tuple(int(x) for x in source_hw)
        self.contact_options = dict(contact or {})
        self.resolution = resolution
        self.max_walk_distance = float(max_walk_distance)
        self.device = None if device is None else torch.device(device)

    @classmethod
    def from_dataset(cls, root: str | Path, spec, *, info=None, resolution: str = "model",
                     max_walk_distance: float = DEFAULT_MAX_WALK_DISTANCE, device=None) -> OnlineControls:
        """The rebuilder of the dataset at ``root`` (its ``imac`` block and the robot description
        under ``meta/imac/``) for a model of ``spec`` (:class:`~imac_model.config.ModelSpec`).
        ``info``: the metadata already at hand (``ds.meta`` or the ``dataset_info`` dict)."""
        root = Path(root)
        meta = info if info is not None else root
        rig = Rig.from_info(meta, root)
        augment = AugmentSettings.from_info(meta)
        contact = augment.contact_options()
        if augment.motion_source != "action":
            warnings.warn(f"{root}: motion images were drawn from the measured state; online motion images are "
                          "drawn from the commanded configurations (no future state exists in a rollout)")
        return cls(rig, dataset_meta.depth_codec(meta), spec.views, (spec.view_height, spec.view_width),
                   augment.resolution, contact=contact, resolution=resolution,
                   max_walk_distance=max_walk_distance, device=device)

    # ------------------------------------------------------------------ parts

    @property
    def compute_hw(self) -> tuple[int, int]:
        """Where the controls are computed: the model's view size or the dataset's."""
        return self.view_hw if self.resolution == "model" else self.source_hw

    def cameras(self) -> dict:
        """The cameras at the compute resolution (K rescaled as the mosaic resizes views)."""
        return mosaic.rescale_cameras(self.rig.cameras, self.compute_hw)

    def configurations(self, q_ref: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """phi: ``(B, H, D)`` configurations after each action of ``actions (B, H, D)`` from ``q_ref (B, D)``."""
        q = self.rig.rollout(torch.as_tensor(q_ref).float().cpu(), torch.as_tensor(actions).float().cpu())
        return q.float()

    def _to_model_size(self, images_u8: torch.Tensor) -> torch.Tensor:
        """uint8 ``(..., h, w, 3)`` at the compute resolution -> float ``(..., 3, h', w')`` at the
        model's view size, quantised to 8 bits as stored controls are."""
        n = images_u8.ndim
        x = images_u8.permute(*range(n - 3), n - 1, n - 3, n - 2).float() / 255.0
        if tuple(x.shape[-2:]) != self.view_hw:
            x = mosaic.resize_frames(x, self.view_hw)
            x = (x * 255.0).round() / 255.0
        return x

    def motion(self, q_future: torch.Tensor) -> torch.Tensor:
        """Motion images ``(B, S, V, 3, h, w)`` in [0, 1] of configurations ``q_future (B, S, D)``."""
        q = torch.as_tensor(q_future).float().cpu()
        B, S = q.shape[:2]
        views = self.rig.robot_views(q.reshape(B * S, -1), resolution=self.compute_hw, gripper=False)
        return self._to_model_size(views.rgb).reshape(B, S, len(self.views), 3, *self.view_hw)

    def contact(self, depth: torch.Tensor, q_ref: torch.Tensor, q_future: torch.Tensor, *,
                include_reference_step: bool = False, device=None) -> ContactControls:
        """Both contact streams of B chunks: reference depth ``(B, V, h, w)`` metres (any
        resolution; resized nearest-pixel to the compute resolution), reference states
        ``q_ref (B, D)`` (robot mask, camera poses) and future configurations ``q_future (B, S, D)``.

        ``include_reference_step``: the chunk's reference is an episode's frame 0, whose chunk
        the build gives one more step (the reference configuration itself, step k = 0) that
        counts towards the caps; it is computed and dropped. All B x (1 + S) configurations
        are rendered in one batched call; the contact queries run per chunk (each chunk has
        its own scene cloud and caps), with :func:`contact_chunk`'s own CPU threads.
        """
        depth = torch.as_tensor(depth)
        q_ref = torch.as_tensor(q_ref).float().cpu()
        q_future = torch.as_tensor(q_future).float().cpu()
        B, V = depth.shape[:2]
        if depth.ndim != 4 or V != len(self.views):
            raise InputError(f"online contact: depth must be (B, V={len(self.views)}, h, w), got {tuple(depth.shape)}")
        if q_ref.shape[0] != B or q_future.shape[0] != B:
            raise InputError(f"online contact: {B} depth maps but q_ref {tuple(q_ref.shape)}, "
                             f"q_future {tuple(q_future.shape)}")
        dev = torch.device(device) if device is not None else (self.device or depth.device)
        hw = self.compute_hw
        if tuple(depth.shape[-2:]) != hw:
            depth = resize_depth(depth, hw, name="predicted depth")
        if include_reference_step:
            q_future = torch.cat([q_ref[:, None], q_future], dim=1)
        S = q_future.shape[1]
        # one batched FK + render for every item's reference and future configurations
        seen = self.rig.robot_views(q_ref, resolution=hw, gripper=False)
        drawn = self.rig.robot_views(q_future.reshape(B * S, -1), resolution=hw)
        # a generated reference may leave no scene: no contact then, never an error
        options = {**self.contact_options, "allow_empty_scene": True}
        chunks = [self.rig.contact_images(depth[b], seen.rows(b, b + 1), drawn.rows(b * S, (b + 1) * S), device=dev,
                                          **options) for b in range(B)]
        first = 1 if include_reference_step else 0
        r2s = torch.stack([c.r2s_rgb[first:] for c in chunks])  # (B, S', V, h, w, 3) uint8
        s2g = torch.stack([c.s2g_rgb[first:] for c in chunks])
        caps = torch.stack([c.caps for c in chunks])
        return ContactControls(r2s=self._to_model_size(r2s), s2g=self._to_model_size(s2g), caps=caps,
                               distances=chunks)

    # ------------------------------------------------------------------ the whole step

    def reference_depth(self, reference: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Decoded depth ``(B, V, h, w)`` metres and the invalid mask of reference mosaics
        ``(B, 3, 2h, V w)`` (:func:`decode_depth`)."""
        _, colour = mosaic.split(reference, len(self.views))
        return decode_depth(colour, self.codec, max_walk_distance=self.max_walk_distance)

    def controls(self, reference: torch.Tensor, q_ref: torch.Tensor, actions: torch.Tensor,
                 streams: Sequence[str] = CONTROL_STREAMS, *, motion: torch.Tensor | None = None,
                 include_reference_step: bool = False) -> OnlineChunkControls:
        """The control mosaics of the chunks that start at ``reference`` ``(B, 3, 2h, V w)`` (a
        generated or recorded mosaic frame in [0, 1]) from the reference states ``q_ref (B, D)``
        and the chunk's actions ``(B, H, D)``: ``streams`` of ``motion``, ``contact_s2g``,
        ``contact_r2s``, ``scene_warp`` (always at the model's view size). ``motion``: per-view motion
        images ``(B, H, V, 3, h, w)`` to use instead of rendering them (e.g. a dataset's stored ones,
        which are the same function of the actions). Outputs are on the reference's device."""
        unknown = [s for s in streams if s not in CONTROL_STREAMS + DERIVED_STREAMS]
        if unknown:
            raise InputError(f"online controls: unknown stream(s) {unknown}")
        dev = reference.device
        q_future = self.configurations(q_ref, actions)
        out: dict[str, torch.Tensor] = {}
        if "motion" in streams:
            views = motion if motion is not None else self.motion(q_future)
            out["motion"] = mosaic.controls(views.to(dev))
        depth = invalid_fraction = caps = None
        if any(s in streams for s in CONTACT_STREAMS):
            depth, invalid = self.reference_depth(reference.detach())
            invalid_fraction = invalid.flatten(1).float().mean(dim=1)
            c = self.contact(depth, q_ref, q_future, include_reference_step=include_reference_step)
            out["contact_s2g"] = mosaic.controls(c.s2g.to(dev))
            out["contact_r2s"] = mosaic.controls(c.r2s.to(dev))
            caps = c.caps
        if SCENE_WARP in streams:
            warp = self.scene.images(reference, q_ref, actions, q_future=q_future, depth=depth)  # depth decoded once
            out[SCENE_WARP] = mosaic.controls(warp.to(dev))
        return OnlineChunkControls(controls={s: out[s] for s in streams}, configurations=q_future,
                                   next_state=q_future[:, -1], depth=depth, invalid_fraction=invalid_fraction,
                                   caps=caps)

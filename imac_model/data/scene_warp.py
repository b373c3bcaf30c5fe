"""The scene-warp control stream (not in the paper): a chunk's reference scene seen from the
cameras at its future configurations.

The reference mosaic's RGB and decoded depth, the robot removed, are splatted into every view's
camera at each future configuration (:meth:`imac_data.core.rig.Rig.scene_warp`). A wrist camera
that moves over the object is told where the object lands, which no other control image says.
It is derived from what every chunk already carries (reference frame, state, actions), so the
dataset does not store it: training derives it from the recorded reference, a rollout from the
generated one, through this one function::

    warp = SceneWarp.from_dataset(meta, root, spec.views, (h, w))
    images = warp.images(reference, q_ref, actions)   # (B, H, V, 3, h, w) in [0, 1]

``docs/world-model.md`` ("The scene-warp stream") has the design and its measurements."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from imac_data.core.contact.clouds import DEFAULT_DILATE_PX
from imac_data.core.rig import Rig
from imac_data.recipes import AugmentSettings
from imac_model.data import meta as dataset_meta
from imac_model.data import mosaic
from imac_model.data.depth import DEFAULT_MAX_WALK_DISTANCE, decode_depth

__all__ = ["SceneWarp"]


class SceneWarp:
    """A dataset's rig (cameras reordered to ``views``) and depth codec at a model's view size
    ``view_hw``; ``dilate_px``: how far the reference robot's mask grows before it is removed
    (the dataset's contact setting)."""

    def __init__(self, rig: Rig, codec, views: Sequence[str], view_hw: tuple[int, int], *,
                 dilate_px: int = DEFAULT_DILATE_PX, max_walk_distance: float = DEFAULT_MAX_WALK_DISTANCE):
        self.rig = rig.for_views(views)
        self.codec = codec
        self.views = tuple(views)
        self.view_hw = tuple(int(x) for x in view_hw)
        self.dilate_px = int(dilate_px)
        self.max_walk_distance = float(max_walk_distance)

    @classmethod
    def from_dataset(cls, meta, root: str | Path, views: Sequence[str], view_hw: tuple[int, int],
                     **options) -> SceneWarp:
        """The warp of the dataset at ``root`` (``meta``: its ``meta/info.json`` dict or LeRobot metadata)."""
        dilate = AugmentSettings.from_info(meta).contact_options().get("dilate_px", DEFAULT_DILATE_PX)
        return cls(Rig.from_info(meta, root), dataset_meta.depth_codec(meta), views, view_hw,
                   dilate_px=dilate, **options)

    def images(self, reference: torch.Tensor, q_ref: torch.Tensor, actions: torch.Tensor, *,
               q_future: torch.Tensor | None = None, depth: torch.Tensor | None = None) -> torch.Tensor:
        """The warps of B chunks, ``(B, H, V, 3, h, w)`` float in [0, 1] (8-bit levels, as stored
        controls are): reference mosaics ``(B, 3, 2h, V w)`` in [0, 1], reference states
        ``q_ref (B, D)`` and actions ``(B, H, D)`` (or their configurations ``q_future (B, H, D)``);
        ``depth (B, V, h, w)``: the references' depth already decoded by :func:`decode_depth`."""
        reference = torch.as_tensor(reference).detach().float().cpu()
        q_ref = torch.as_tensor(q_ref).float().cpu()
        if q_future is None:
            q_future = self.rig.rollout(q_ref, torch.as_tensor(actions).float().cpu())
        q_future = torch.as_tensor(q_future).float().cpu()
        B, V = reference.shape[0], len(self.views)
        rgb, colour = mosaic.split(reference, V)  # (B, V, 3, h, w) each
        if depth is None:
            depth, _ = decode_depth(colour, self.codec, max_walk_distance=self.max_walk_distance)
        depth = torch.as_tensor(depth).float().cpu()
        rgb = (rgb.clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 1, 3, 4, 2)  # (B, V, h, w, 3)
        seen = self.rig.robot_views(q_ref, resolution=self.view_hw, gripper=False)
        poses = self.rig.camera_poses(q_future)  # (B, H, V, 4, 4)
        warped = torch.stack([self.rig.scene_warp(rgb[b], depth[b], seen.rows(b, b + 1), poses[b],
                                                  dilate_px=self.dilate_px) for b in range(B)])
        return warped.permute(0, 1, 2, 5, 3, 4).float() / 255.0

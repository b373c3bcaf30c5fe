"""Contact images rebuilt without the renderer: training-time rollout on a machine that has torch
alone (the GPU preset), from the model's own reference frames.

A chunk's contact images are a function of its reference depth and of geometry that the recorded
states and actions fix: the robot at the reference state (its mask, the camera poses) and at each
future configuration (its depth, the camera poses, the gripper links' poses). Here, where the
renderer is, :func:`contact_geometry` renders that geometry at the model's view size and the tensor
pack carries it (``geometry.*``). On the GPU, :class:`PackedContact` decodes a reference frame's
depth and paints both streams for a whole batch of chunks with
:func:`~imac_data.core.contact.batched.contact_batch`: the function
:meth:`~imac_model.pipelines.online_controls.OnlineControls.contact` computes, on the same inputs,
batched. ``docs/ranking.md`` ("The GPU preset") says where it is used."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence

import numpy as np
import torch

from imac_data.core.contact.batched import contact_batch
from imac_data.core.contact.clouds import posed_samples
from imac_data.core.contact.images import DEFAULT_FILL_PX
from imac_data.core.contact.workspace import Workspace, as_workspace
from imac_data.core.depth import DepthCodec
from imac_data.errors import InputError
from imac_model.data import mosaic
from imac_model.data.depth import decode_depth
from imac_model.data.pack import GEOMETRY_KEY  # the pack member with the settings (arrays: ``geometry.<name>``)
from imac_model.modes import CONTACT_STREAMS

__all__ = ["GEOMETRY_KEY", "PackedContact", "contact_geometry", "geometry_constants"]

PER_CHUNK = ("ref_pose", "ref_mask", "robot_depth", "pose", "gripper_pose")


def geometry_constants(online) -> dict[str, np.ndarray]:
    """The pack members every chunk shares: intrinsics at the model's size, the gripper's surface
    samples (link frames, link after link) and the settings (``online``: an
    :class:`~imac_model.pipelines.online_controls.OnlineControls`)."""
    if online.resolution != "model":
        raise InputError("pack geometry: contact images are rebuilt at the model's view size "
                         f"(rollout.resolution 'model'), not {online.resolution!r}")
    surface = online.rig.gripper
    options = online.contact_options
    workspace = as_workspace(options.get("workspace", online.rig.workspace))
    settings = {
        "views": list(online.views), "view_hw": list(online.view_hw), "links": list(surface.links),
        "cap": options.get("cap"), "percentile": float(options.get("percentile", 99.0)),
        "dilate_px": int(options.get("dilate_px", 2)), "fill_px": int(options.get("fill_px", DEFAULT_FILL_PX)),
        "workspace": None if workspace is None else workspace.to_dict(),
        "codec": online.codec.to_dict(), "max_walk_distance": online.max_walk_distance,
    }
    return {
        "geometry.K": online.rig.intrinsics(online.view_hw).numpy(),
        "geometry.gripper_samples": np.concatenate([surface.samples[k] for k in surface.links]).astype(np.float32),
        "geometry.gripper_counts": np.array([surface.counts[k] for k in surface.links], dtype=np.int64),
        GEOMETRY_KEY: np.array(json.dumps(settings)),
    }


def contact_geometry(online, q_ref: torch.Tensor, actions: torch.Tensor) -> dict[str, np.ndarray]:
    """Per chunk, what its contact images need besides the reference depth, for reference states
    ``q_ref (B, D)`` and actions ``(B, S, D)``: ``ref_pose (B, V, 4, 4)`` and ``ref_mask (B, V, h, w)``
    at the reference state; ``robot_depth (B, S, V, h, w)``, ``pose (B, S, V, 4, 4)`` and
    ``gripper_pose (B, S, L, 4, 4)`` at the configurations the actions command (as
    :meth:`OnlineControls.controls` draws them)."""
    hw = online.view_hw
    q_ref = torch.as_tensor(q_ref).float()
    q_future = online.configurations(q_ref, actions)
    B, S = q_future.shape[:2]
    flat = q_future.reshape(B * S, -1)
    seen = online.rig.robot_views(q_ref, resolution=hw, gripper=False)
    drawn = online.rig.robot_views(flat, resolution=hw, gripper=False)
    links = online.rig.link_poses(flat)
    gripper = torch.stack([links[k] for k in online.rig.gripper.links], dim=1)
    V = len(online.views)
    return {
        "geometry.ref_pose": seen.T_world_cam.float().numpy(),
        "geometry.ref_mask": seen.mask.numpy(),
        "geometry.robot_depth": drawn.depth.float().reshape(B, S, V, *hw).numpy(),
        "geometry.pose": drawn.T_world_cam.float().reshape(B, S, V, 4, 4).numpy(),
        "geometry.gripper_pose": gripper.float().reshape(B, S, -1, 4, 4).numpy(),
    }


class PackedContact:
    """A pack's contact geometry on its device: :meth:`controls` paints the contact images of
    chunks ``index`` from any reference frames (the model's own in a rollout)."""

    def __init__(self, tensors: Mapping[str, torch.Tensor], settings: Mapping, *, method: str = "auto"):
        missing = [f"geometry.{k}" for k in (*PER_CHUNK, "K", "gripper_samples", "gripper_counts")
                   if f"geometry.{k}" not in tensors]
        if missing:
            raise InputError(f"the pack carries no contact geometry {missing}: rebuilding contact images needs a pack "
                             "written with it (imac-model ranking --stages pack)")
        self.t = {k[len("geometry."):]: v for k, v in tensors.items() if k.startswith("geometry.")}
        chunks = {k: len(self.t[k]) for k in PER_CHUNK}
        if "reference" in tensors and set(chunks.values()) != {len(tensors["reference"])}:
            raise InputError(f"the pack's contact geometry covers {chunks} chunks, the pack holds "
                             f"{len(tensors['reference'])}; the pack is damaged")
        self.settings = dict(settings)
        self.method = method  # the searches: contact_batch's (brute force on a GPU, KD-trees on a CPU)
        self.views = tuple(settings["views"])
        self.codec = DepthCodec.from_dict(settings["codec"], where="pack geometry codec")
        self.workspace = Workspace.from_dict(settings["workspace"], where="pack geometry workspace")
        # the gripper's samples, link by link, as GripperSurface keeps them
        self.samples = torch.split(self.t["gripper_samples"], self.t["gripper_counts"].tolist())

    @classmethod
    def from_pack(cls, pack, *, method: str = "auto") -> PackedContact:
        """The geometry of a :class:`~imac_model.data.pack.Pack`."""
        if pack.geometry is None:
            raise InputError("the pack carries no contact geometry: rebuilding contact images needs a pack written "
                             "with it (imac-model ranking --stages pack)")
        return cls(pack.tensors, pack.geometry, method=method)

    def gripper_points(self, poses: torch.Tensor) -> torch.Tensor:
        """World points ``(..., M, 3)`` of the gripper samples for link poses ``(..., L, 4, 4)``."""
        return posed_samples(self.samples, poses.unbind(dim=-3))

    def contact(self, depth: torch.Tensor, index: torch.Tensor):
        """Both streams (:class:`~imac_data.core.contact.images.ContactChunk`, leading B) of chunks
        ``index (B,)`` from reference depth ``(B, V, h, w)`` metres."""
        t = self.t
        return contact_batch(depth, t["K"], t["ref_pose"][index], t["ref_mask"][index],
                             t["robot_depth"][index].float(), t["pose"][index],
                             self.gripper_points(t["gripper_pose"][index]), cap=self.settings["cap"],
                             percentile=self.settings["percentile"], dilate_px=self.settings["dilate_px"],
                             fill_px=self.settings["fill_px"], workspace=self.workspace, method=self.method)

    def controls(self, reference: torch.Tensor, index: torch.Tensor,
                 streams: Sequence[str] = CONTACT_STREAMS) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """The contact control mosaics ``(B, S, 3, 2h, V w)`` in [0, 1] of chunks ``index (B,)``
        starting at reference mosaics ``(B, 3, 2h, V w)``, and each reference's share of invalid
        depth ``(B,)`` (decoded as :meth:`OnlineControls.reference_depth` decodes it)."""
        unknown = [s for s in streams if s not in CONTACT_STREAMS]
        if unknown:
            raise InputError(f"packed contact: rebuilds {list(CONTACT_STREAMS)}, not {unknown}")
        _, colour = mosaic.split(reference.detach().float(), len(self.views))
        depth, invalid = decode_depth(colour, self.codec, max_walk_distance=self.settings["max_walk_distance"])
        c = self.contact(depth, index)
        out = {}
        for stream, rgb in (("contact_s2g", c.s2g_rgb), ("contact_r2s", c.r2s_rgb)):
            if stream in streams:  # uint8 (B, S, V, h, w, 3) -> (B, S, V, 3, h, w) in [0, 1], as stored
                out[stream] = mosaic.controls(rgb.permute(0, 1, 2, 5, 3, 4).float() / 255.0)
        return out, invalid.flatten(1).float().mean(dim=1)

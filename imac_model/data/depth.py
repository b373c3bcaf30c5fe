"""Depth in a mosaic frame: the colour-coded depth row decoded to metres, with what is not depth.

A generated frame's colours may leave the codec's colour walk; those pixels, (near-)black ones
and non-finite values are invalid depth (0 m and flagged), never an error. The online controls
(:mod:`imac_model.pipelines.online_controls`) and the scene warp (:mod:`imac_model.data.scene_warp`)
read depth through here."""

from __future__ import annotations

import torch

from imac_data.core.depth import walk_distance
from imac_data.errors import InputError

__all__ = ["decode_depth", "DEFAULT_MAX_WALK_DISTANCE", "DEFAULT_INVALID_CODES"]

DEFAULT_MAX_WALK_DISTANCE = 0.1  # RGB units in [0, 1]: about 25 8-bit levels off the codec's colour walk
DEFAULT_INVALID_CODES = 2.0  # walk positions within 2 codes of black (depth < 0.6 mm, manipulation) = invalid


def decode_depth(colour: torch.Tensor, codec, *, max_walk_distance: float = DEFAULT_MAX_WALK_DISTANCE,
                 invalid_codes: float = DEFAULT_INVALID_CODES) -> tuple[torch.Tensor, torch.Tensor]:
    """Generated colour depth ``(..., 3, h, w)`` (float, nominally [0, 1]) -> ``(metres (..., h, w)
    float32, invalid (..., h, w) bool)``: metres are 0 wherever ``invalid``, which holds for
    colours farther than ``max_walk_distance`` from the codec's walk, (near-)black colours and
    non-finite values. Never NaN."""
    if not 0 < max_walk_distance:
        raise InputError(f"max_walk_distance must be > 0 (RGB units), got {max_walk_distance}")
    colour = torch.as_tensor(colour)
    if colour.ndim < 3 or colour.shape[-3] != 3:
        raise InputError(f"decode_depth: colours must be (..., 3, h, w), got {tuple(colour.shape)}")
    if not colour.is_floating_point():
        colour = colour.float() / 255.0
    colour = colour.float()
    finite = torch.isfinite(colour).all(dim=-3)
    safe = torch.where(finite[..., None, :, :], colour, torch.zeros_like(colour))
    off_walk = ~(walk_distance(safe, channel_axis=-3) <= max_walk_distance)
    metres = codec.decode(safe, channel_axis=-3, invalid_codes=invalid_codes).float()
    invalid = ~finite | off_walk | ~(metres > 0) | ~torch.isfinite(metres)
    return torch.where(invalid, torch.zeros_like(metres), metres), invalid

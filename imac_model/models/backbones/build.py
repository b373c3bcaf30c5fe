"""Video backbones behind one small interface (:class:`~imac_model.models.backbones.base.Backbone`),
in a registry: a new backbone is one :class:`BackboneEntry` here plus its module.

* ``small`` (:mod:`.small_dit`): a CPU-sized video DiT on a pixel-unshuffle latent;
* ``unet`` (:mod:`.unet`): a pixel-space convolutional U-Net (DIAMOND's design) with depth as
  a channel of its own;
* ``wan`` (:mod:`.wan`): Wan2.2-TI2V through diffusers' ``WanTransformer3DModel`` and
  ``AutoencoderKLWan`` (diffusers is imported only when a Wan backbone is built).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from imac_model.config import BackboneConfig
from imac_model.models.backbones.base import Backbone
from imac_model.models.backbones.small_dit import SmallVideoDiT
from imac_model.models.backbones.unet import UNetBackbone
from imac_model.models.backbones.wan import WanBackbone, wan_configs, wan_spatial_multiple


@dataclass(frozen=True)
class BackboneEntry:
    """How to build one kind of backbone from :class:`BackboneConfig`, and the two facts the data
    layout needs before it is built (the mosaic's side multiple, frames per latent frame)."""

    build: Callable[..., Backbone]  # (config, *, with_context, num_frames) -> Backbone
    spatial_multiple: Callable[[BackboneConfig], int]
    temporal_factor: Callable[[BackboneConfig], int]


BACKBONES: dict[str, BackboneEntry] = {
    "small": BackboneEntry(
        build=lambda c, *, with_context, num_frames: SmallVideoDiT(c.small, with_context=with_context),
        spatial_multiple=lambda c: c.small.unshuffle * c.small.patch,
        temporal_factor=lambda c: 1),
    "unet": BackboneEntry(
        build=lambda c, *, with_context, num_frames: UNetBackbone(c.unet, num_frames=num_frames,
                                                                  with_context=with_context),
        spatial_multiple=lambda c: 2 ** len(c.unet.channels),
        temporal_factor=lambda c: 1),
    "wan": BackboneEntry(
        build=lambda c, *, with_context, num_frames: WanBackbone.from_config(c.wan, with_context=with_context),
        spatial_multiple=lambda c: wan_spatial_multiple(c.wan),
        temporal_factor=lambda c: int(wan_configs(c.wan)[1].get("scale_factor_temporal", 4))),
}


def _entry(config: BackboneConfig) -> BackboneEntry:
    return BACKBONES[config.kind]


def build_backbone(config: BackboneConfig, *, with_context: bool = False, num_frames: int = 9) -> Backbone:
    """The configured backbone; ``with_context`` adds the action-vector baseline's context input;
    ``num_frames``: frames per chunk (1 + H), which a backbone that stacks them in channels needs."""
    return _entry(config).build(config, with_context=with_context, num_frames=num_frames)


def spatial_multiple(config: BackboneConfig) -> int:
    """The multiple the mosaic sides must have, known before the backbone is built."""
    return _entry(config).spatial_multiple(config)


def temporal_factor(config: BackboneConfig) -> int:
    """Frames per latent frame after the first (a chunk is 1 + k * factor frames)."""
    return _entry(config).temporal_factor(config)


__all__ = ["BACKBONES", "Backbone", "BackboneEntry", "build_backbone", "spatial_multiple", "temporal_factor"]

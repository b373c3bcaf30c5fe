"""Video backbones behind one small interface (:class:`~imac_model.models.backbones.base.Backbone`):

* ``small`` (:mod:`.small_dit`): a CPU-sized video DiT on a pixel-unshuffle latent;
* ``wan`` (:mod:`.wan`): Wan2.2-TI2V through diffusers' ``WanTransformer3DModel`` and
  ``AutoencoderKLWan``.
"""

from __future__ import annotations

from imac_model.config import BackboneConfig
from imac_model.models.backbones.base import Backbone
from imac_model.models.backbones.small_dit import SmallVideoDiT
from imac_model.models.backbones.wan import WanBackbone, wan_configs, wan_spatial_multiple


def build_backbone(config: BackboneConfig, *, with_context: bool = False) -> Backbone:
    """The configured backbone; ``with_context`` adds cross-attention context input
    (the action-vector baseline)."""
    if config.kind == "small":
        return SmallVideoDiT(config.small, with_context=with_context)

    return WanBackbone.from_config(config.wan, with_context=with_context)


def spatial_multiple(config: BackboneConfig) -> int:
    """The multiple the mosaic sides must have, known before the backbone is built."""
    if config.kind == "small":
        return config.small.unshuffle * config.small.patch

    return wan_spatial_multiple(config.wan)


def temporal_factor(config: BackboneConfig) -> int:
    """Frames per latent frame after the first (a chunk is 1 + k * factor frames)."""
    if config.kind == "small":
        return 1

    return int(wan_configs(config.wan)[1].get("scale_factor_temporal", 4))


__all__ = ["Backbone", "build_backbone", "spatial_multiple", "temporal_factor"]

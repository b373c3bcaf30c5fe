"""Video backbones behind one small interface (:class:`~imac_model.models.backbones.base.Backbone`):

* ``small`` (:mod:`.small_dit`): a CPU-sized video DiT on a pixel-unshuffle latent;
* ``wan`` (:mod:`.wan`): Wan2.2-TI2V through diffusers' ``WanTransformer3DModel`` and
  ``AutoencoderKLWan``.

Each is one entry of :data:`BACKBONES`, looked up by ``backbone.kind``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from imac_data.errors import InputError
from imac_model.config import BackboneConfig
from imac_model.models.backbones.base import Backbone
from imac_model.models.backbones.small_dit import SmallVideoDiT
from imac_model.models.backbones.wan import WanBackbone, wan_configs, wan_spatial_multiple


@dataclass(frozen=True)
class BackboneKind:
    """What a ``backbone.kind`` is: ``build(config, with_context)``, the backbone; and, known
    before it is built, ``spatial_multiple(config)`` (the multiple the mosaic sides must have)
    and ``temporal_factor(config)`` (frames per latent frame after the first)."""

    build: Callable[[BackboneConfig, bool], Backbone]
    spatial_multiple: Callable[[BackboneConfig], int]
    temporal_factor: Callable[[BackboneConfig], int]


# backbone.kind -> its kind. A new backbone is its module, its section of BackboneConfig and one entry here.
BACKBONES: dict[str, BackboneKind] = {
    "small": BackboneKind(build=lambda c, context: SmallVideoDiT(c.small, with_context=context),
                          spatial_multiple=lambda c: c.small.unshuffle * c.small.patch,
                          temporal_factor=lambda c: 1),
    "wan": BackboneKind(build=lambda c, context: WanBackbone.from_config(c.wan, with_context=context),
                        spatial_multiple=lambda c: wan_spatial_multiple(c.wan),
                        temporal_factor=lambda c: int(wan_configs(c.wan)[1].get("scale_factor_temporal", 4))),
}


def backbone_kind(config: BackboneConfig) -> BackboneKind:
    if config.kind not in BACKBONES:
        raise InputError(f"backbone.kind: unknown backbone {config.kind!r}; known: {sorted(BACKBONES)}")
    return BACKBONES[config.kind]


def build_backbone(config: BackboneConfig, *, with_context: bool = False) -> Backbone:
    """The configured backbone; ``with_context`` adds cross-attention context input
    (the action-vector baseline)."""
    return backbone_kind(config).build(config, with_context)


def spatial_multiple(config: BackboneConfig) -> int:
    """The multiple the mosaic sides must have, known before the backbone is built."""
    return backbone_kind(config).spatial_multiple(config)


def temporal_factor(config: BackboneConfig) -> int:
    """Frames per latent frame after the first (a chunk is 1 + k * factor frames)."""
    return backbone_kind(config).temporal_factor(config)


__all__ = ["Backbone", "BackboneKind", "BACKBONES", "build_backbone", "spatial_multiple", "temporal_factor"]

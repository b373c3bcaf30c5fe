"""Wan2.2-TI2V as a backbone, through diffusers 0.35 (``WanTransformer3DModel`` +
``AutoencoderKLWan``), with no copy of diffusers' ``forward``.

The frozen Wan2.2 VAE (48 channels, 16x spatial, 4x causal temporal: 1 + 4k frames) gives the
latent; control tokens are added to ``patch_embedding``'s output by the backbone's forward hook;
timesteps are per token (0 on the reference); Wan predicts ``noise - data``, so the output is
negated into the paper's velocity; a learned null prompt replaces T5. Real weights come from a
local directory or hub id laid out as ``Wan-AI/Wan2.2-TI2V-5B-Diffusers`` (``docs/world-model.md``)."""

from __future__ import annotations

import torch
from torch import nn

from imac_data.errors import InputError
from imac_model.config import WanConfig
from imac_model.models.backbones.base import Backbone

# The shapes of Wan2.2-TI2V-5B (Wan-AI/Wan2.2-TI2V-5B-Diffusers). The VAE's latents_mean /
# latents_std come with real weights; a randomly initialised VAE uses 0 / 1.
TI2V_TRANSFORMER = dict(
    patch_size=(1, 2, 2), num_attention_heads=24, attention_head_dim=128, in_channels=48, out_channels=48,
    text_dim=4096, freq_dim=256, ffn_dim=14336, num_layers=30, cross_attn_norm=True,
    qk_norm="rms_norm_across_heads", eps=1e-6, rope_max_seq_len=1024,
)
TI2V_VAE = dict(
    base_dim=160, decoder_base_dim=256, z_dim=48, dim_mult=[1, 2, 4, 4], num_res_blocks=2, attn_scales=[],
    temperal_downsample=[False, True, True], dropout=0.0, is_residual=True, in_channels=12, out_channels=12,
    patch_size=2, scale_factor_spatial=16, scale_factor_temporal=4,
    latents_mean=[0.0] * 48, latents_std=[1.0] * 48,
)


def wan_configs(config: WanConfig) -> tuple[dict, dict]:
    """The constructor arguments of the configured transformer and VAE, without building
    them: the TI2V shapes, a local pretrained directory's ``config.json`` files over them, the
    config's own values over those (as ``from_pretrained`` applies them). Keys a class does not
    take (the Hub VAE's ``clip_output``, diffusers' ``_class_name``) are dropped, as
    ``from_pretrained`` drops them. A hub id is not fetched: the config's values stand."""
    import inspect
    import json
    from pathlib import Path

    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    out = []
    for sub, cls, base, own in (("transformer", WanTransformer3DModel, TI2V_TRANSFORMER, config.transformer),
                                ("vae", AutoencoderKLWan, TI2V_VAE, config.vae)):
        values = dict(base)
        path = Path(config.pretrained) / sub / "config.json" if config.pretrained else None
        if path is not None and path.is_file():
            values.update(json.loads(path.read_text()))
        values.update(own)
        accepted = set(inspect.signature(cls.__init__).parameters) - {"self"}
        out.append({k: v for k, v in values.items() if k in accepted})
    return out[0], out[1]


def wan_spatial_multiple(config: WanConfig) -> int:
    """Spatial compression x patch of the configured Wan (32 for Wan2.2 TI2V), without
    building it (read from the pretrained directory's configs when local)."""
    tr, vae = wan_configs(config)
    return int(vae["scale_factor_spatial"]) * int(tr["patch_size"][1])


class WanBackbone(Backbone):
    temporal_factor = 4

    def __init__(self, transformer, vae, *, context_tokens: int = 16, with_context: bool = False,
                 train_vae: bool = False):
        super().__init__()
        self.transformer = transformer
        self.vae = vae
        tc, vc = transformer.config, vae.config
        if tc.in_channels != vc.z_dim or (tc.out_channels or tc.in_channels) != vc.z_dim:
            raise InputError(f"backbone.wan: transformer in/out channels ({tc.in_channels}/{tc.out_channels}) "
                             f"must equal the VAE's z_dim ({vc.z_dim})")
        self.latent_channels = vc.z_dim
        self.temporal_factor = int(vc.scale_factor_temporal)
        self.spatial_multiple = int(vc.scale_factor_spatial) * int(tc.patch_size[1])
        self.token_dim = tc.num_attention_heads * tc.attention_head_dim
        self.context_dim = tc.text_dim if with_context else None
        self.null_context = nn.Parameter(torch.zeros(1, context_tokens, tc.text_dim))
        self.register_buffer("latents_mean", torch.tensor(vc.latents_mean, dtype=torch.float32).view(1, -1, 1, 1, 1),
                             persistent=False)
        self.register_buffer("latents_std", torch.tensor(vc.latents_std, dtype=torch.float32).view(1, -1, 1, 1, 1),
                             persistent=False)
        self.train_vae = train_vae
        vae.requires_grad_(train_vae)
        # the transformer's compute dtype; None: its parameters' dtype. Sharded training with a bf16
        # policy keeps fp32 parameters between steps and computes in bf16 (training/sharding.py)
        self.compute_dtype: torch.dtype | None = None
        self._install_control_hook()

    @property
    def patch_embedding(self) -> nn.Conv3d:  # the transformer's own layer (one set of weights)
        return self.transformer.patch_embedding

    @classmethod
    def from_config(cls, config: WanConfig, *, with_context: bool = False) -> WanBackbone:
        from diffusers import AutoencoderKLWan, WanTransformer3DModel

        if config.pretrained:
            try:
                transformer = WanTransformer3DModel.from_pretrained(config.pretrained, subfolder="transformer",
                                                                    **config.transformer)
                vae = AutoencoderKLWan.from_pretrained(config.pretrained, subfolder="vae", **config.vae)
            except (OSError, ValueError) as e:
                raise InputError(f"backbone.wan.pretrained: cannot load Wan weights from {config.pretrained!r} "
                                 f"(a local directory or hub id with transformer/ and vae/): {e}") from None
        else:
            try:
                transformer = WanTransformer3DModel(**{**TI2V_TRANSFORMER, **config.transformer})
                vae = AutoencoderKLWan(**{**TI2V_VAE, **config.vae})
            except TypeError as e:
                raise InputError(f"backbone.wan.transformer / backbone.wan.vae: {e}") from None
        if config.num_layers is not None:
            if config.num_layers > len(transformer.blocks):
                raise InputError(f"backbone.wan.num_layers: {config.num_layers} > the model's "
                                 f"{len(transformer.blocks)} blocks")
            transformer.blocks = transformer.blocks[:config.num_layers]
            transformer.register_to_config(num_layers=config.num_layers)
        if config.gradient_checkpointing:
            transformer.enable_gradient_checkpointing()
        if config.vae_slicing:
            vae.enable_slicing()
        return cls(transformer, vae, context_tokens=config.context_tokens, with_context=with_context,
                   train_vae=config.train_vae)

    # --------------------------------------------------------------------- latent space

    def encode(self, video: torch.Tensor) -> torch.Tensor:
        x = video.transpose(1, 2) * 2.0 - 1.0  # (B, 3, T, H, W) in [-1, 1]
        with torch.set_grad_enabled(self.train_vae and torch.is_grad_enabled()):
            z = self.vae.encode(x.to(self.vae.dtype)).latent_dist.mode()
        return (z.float() - self.latents_mean) / self.latents_std

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        z = latents.float() * self.latents_std + self.latents_mean
        x = self.vae.decode(z.to(self.vae.dtype)).sample  # (B, 3, T, H, W) in [-1, 1]
        return ((x.float().transpose(1, 2) + 1.0) / 2.0).clamp(0.0, 1.0)

    # --------------------------------------------------------------------- denoiser

    def _denoise(self, latents, timesteps, context):
        B, _, Fr, h, w = latents.shape
        _, ph, pw = self.transformer.config.patch_size
        per_frame = (h // ph) * (w // pw)
        t = timesteps.repeat_interleave(per_frame, dim=1)  # (B, seq): one timestep per token
        ctx = self.null_context.expand(B, -1, -1)
        if context is not None:
            ctx = torch.cat([context.to(ctx.dtype), ctx], dim=1)
        dtype = self.compute_dtype or self.transformer.dtype
        out = self.transformer(latents.to(dtype), timestep=t, encoder_hidden_states=ctx.to(dtype),
                               return_dict=False)[0]
        return -out.float()  # Wan predicts noise - data; the paper's velocity is data - noise

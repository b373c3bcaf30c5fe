"""The one small interface every video backbone implements.

A backbone owns three things:

* a **latent space**: :meth:`Backbone.encode` maps frames ``(B, T, 3, H, W)`` in [0, 1]
  to latents ``(B, C, F, h, w)`` and :meth:`Backbone.decode` maps them back. Latent
  frame 0 is the first frame alone; each later latent frame covers
  ``temporal_factor`` frames (Wan's causal VAE: 4; pixel-unshuffle: 1), so a chunk
  of 1 + H frames needs ``H % temporal_factor == 0``;
* a **patch embedding** ``patch_embedding`` (a ``Conv3d``) that turns latents into
  tokens ``(B, D, F, h', w')``. :meth:`Backbone.make_patchify_layer` builds a layer of
  the same shape for a control stream (paper eq. 2: ``P_m``, ``P_s2g``, ``P_r2s``);
* a **denoiser** :meth:`Backbone.denoise` that takes latents, one timestep per latent
  frame (Wan units, 0 = clean) and returns the velocity in the paper's convention
  (``x1 - x0``: towards data). Control tokens passed to it are added to the output of
  ``patch_embedding`` by a forward hook, so the backbone's own forward (diffusers'
  Wan included) is used as is; cross-attention ``context`` tokens carry the
  action-vector baseline.
"""

from __future__ import annotations

import abc

import torch
from torch import nn

from imac_data.errors import InputError


class Backbone(nn.Module, abc.ABC):
    latent_channels: int
    spatial_multiple: int  # mosaic sides must be multiples of this (spatial compression x patch)
    temporal_factor: int  # frames per latent frame after the first
    token_dim: int  # width of the patch-embedded tokens
    context_dim: int | None  # width of cross-attention context tokens (None: no context)
    patch_embedding: nn.Conv3d

    def __init__(self) -> None:
        super().__init__()
        self._control_tokens: torch.Tensor | None = None

    def _install_control_hook(self) -> None:
        """Call once ``patch_embedding`` exists: its output gets the pending control tokens."""
        self.patch_embedding.register_forward_hook(self._add_control_tokens)

    def _add_control_tokens(self, module, inputs, output):
        tokens = self._control_tokens
        if tokens is None:
            return output
        if tokens.shape != output.shape:
            raise ValueError(f"control tokens {tuple(tokens.shape)} do not match the patch embedding "
                             f"{tuple(output.shape)}")
        return output + tokens.to(output.dtype)

    # ----------------------------------------------------------------- frames and latents

    def check_num_frames(self, num_frames: int, field: str = "data.chunk") -> None:
        """1 + H frames per chunk: the first alone, then whole latent frames."""
        if (num_frames - 1) % self.temporal_factor or num_frames < 1 + self.temporal_factor:
            raise InputError(f"{field}: {num_frames - 1} future frames per chunk cannot be encoded: this backbone "
                             f"compresses time by {self.temporal_factor} (chunks of 1 + {self.temporal_factor}k "
                             f"frames)")

    def latent_frames(self, num_frames: int) -> int:
        return 1 + (num_frames - 1) // self.temporal_factor

    def latent_frame_mask(self, frame_valid: torch.Tensor) -> torch.Tensor:
        """``(B, 1 + H)`` frame validity -> ``(B, F)`` latent-frame validity: a latent frame
        is valid only when every frame it covers is (padded frames are never trained on)."""
        first, rest = frame_valid[:, :1], frame_valid[:, 1:]
        rest = rest.reshape(rest.shape[0], -1, self.temporal_factor).all(dim=-1)
        return torch.cat([first, rest], dim=1)

    @abc.abstractmethod
    def encode(self, video: torch.Tensor) -> torch.Tensor:
        """``(B, T, 3, H, W)`` in [0, 1] -> latents ``(B, C, F, h, w)``."""

    def encode_control(self, video: torch.Tensor) -> torch.Tensor:
        """A control video ``(B, T, 3, H, W)`` -> latents; the frames' encoder unless a backbone
        encodes controls apart (the U-Net's depth channel has no meaning for a control)."""
        return self.encode(video)

    @abc.abstractmethod
    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """Latents ``(B, C, F, h, w)`` -> frames ``(B, T, 3, H, W)`` in [0, 1]."""

    # ----------------------------------------------------------------- denoiser

    def make_patchify_layer(self) -> nn.Conv3d:
        """A zero-initialised layer shaped like ``patch_embedding`` (a control stream's P)."""
        pe = self.patch_embedding
        layer = nn.Conv3d(pe.in_channels, pe.out_channels, kernel_size=pe.kernel_size, stride=pe.stride)
        nn.init.zeros_(layer.weight)
        nn.init.zeros_(layer.bias)
        return layer

    @abc.abstractmethod
    def _denoise(self, latents: torch.Tensor, timesteps: torch.Tensor, context: torch.Tensor | None) -> torch.Tensor:
        """The backbone's forward: velocity (paper convention) for every latent."""

    def denoise(self, latents: torch.Tensor, timesteps: torch.Tensor, *, control_tokens: torch.Tensor | None = None,
                context: torch.Tensor | None = None) -> torch.Tensor:
        """Velocity ``(B, C, F, h, w)`` for ``latents`` at ``timesteps`` ``(B, F)`` (Wan units,
        0 = clean), with ``control_tokens`` ``(B, D, F, h', w')`` added after the patch
        embedding and optional cross-attention ``context`` ``(B, L, context_dim)``."""
        if timesteps.shape != latents.shape[:1] + latents.shape[2:3]:
            raise ValueError(f"timesteps {tuple(timesteps.shape)} must be (B, F) for latents {tuple(latents.shape)}")
        self._control_tokens = control_tokens
        try:
            return self._denoise(latents, timesteps, context)
        finally:
            self._control_tokens = None

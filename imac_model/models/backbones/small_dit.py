"""A small video DiT that trains on the CPU: the backbone of tests, CI and experiments here.

* **Latent:** pixel-unshuffle of the [-1, 1] frames by ``unshuffle`` (exact and
  invertible, no training): 48 channels for ``unshuffle = 4``, like Wan2.2's latent.
  One latent frame per frame (``temporal_factor = 1``).
* **Tokens:** a ``Conv3d`` patch embedding with kernel ``(1, patch, patch)`` (Wan's
  shape), fixed sin-cos position embeddings for (frame, row, column).
* **Blocks:** factorised attention, spatial (within a frame) then temporal (across
  frames at one position), then an MLP; each is modulated by adaLN-Zero from the
  per-frame timestep embedding (reference frame: t = 0, as Wan2.2 TI2V's per-token
  timesteps). Queries and keys are RMS-normalised. With ``context_dim`` set, each
  block also cross-attends to context tokens (the action-vector baseline).
* **Output:** adaLN + linear back to latent patches; zero-initialised, as DiT.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from imac_model.config import SmallDiTConfig
from imac_model.models.backbones.base import Backbone


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[..., None] * freqs
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


def sincos_1d(n: int, dim: int, device) -> torch.Tensor:
    return timestep_embedding(torch.arange(n, device=device, dtype=torch.float32), dim)


class Attention(nn.Module):
    def __init__(self, dim: int, heads: int, kv_dim: int | None = None):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(kv_dim or dim, 2 * dim)
        self.q_norm = nn.RMSNorm(dim // heads, eps=1e-6)
        self.k_norm = nn.RMSNorm(dim // heads, eps=1e-6)
        self.out = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, kv: torch.Tensor | None = None) -> torch.Tensor:
        """``x`` ``(N, L, D)`` attends to ``kv`` ``(N, S, D_kv)`` (default: itself)."""
        N, L, D = x.shape
        kv = x if kv is None else kv
        q = self.q_norm(self.q(x).view(N, L, self.heads, -1)).transpose(1, 2)
        k, v = self.kv(kv).view(N, kv.shape[1], 2, self.heads, -1).unbind(2)
        k = self.k_norm(k).transpose(1, 2)
        out = F.scaled_dot_product_attention(q, k, v.transpose(1, 2))
        return self.out(out.transpose(1, 2).reshape(N, L, D))


def _modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale) + shift


class Block(nn.Module):
    """Spatial attention, temporal attention, [cross-attention,] MLP; adaLN-Zero."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, context_dim: int | None):
        super().__init__()
        self.norm_s = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.attn_s = Attention(dim, heads)
        self.norm_t = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.attn_t = Attention(dim, heads)
        self.norm_m = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(approximate="tanh"), nn.Linear(hidden, dim))
        self.cross = None
        if context_dim is not None:
            self.norm_c = nn.LayerNorm(dim, eps=1e-6)
            self.cross = Attention(dim, heads, kv_dim=context_dim)
            nn.init.zeros_(self.cross.out.weight)
            nn.init.zeros_(self.cross.out.bias)
        self.ada = nn.Sequential(nn.SiLU(), nn.Linear(dim, 9 * dim))
        nn.init.zeros_(self.ada[1].weight)
        nn.init.zeros_(self.ada[1].bias)

    def forward(self, x: torch.Tensor, cond: torch.Tensor, context: torch.Tensor | None) -> torch.Tensor:
        """``x`` ``(B, F, S, D)`` tokens, ``cond`` ``(B, F, D)`` per-frame conditioning."""
        B, Fr, S, D = x.shape
        mods = self.ada(cond)[:, :, None, :].chunk(9, dim=-1)  # each (B, F, 1, D)
        h = _modulate(self.norm_s(x), mods[0], mods[1])
        x = x + mods[2] * self.attn_s(h.reshape(B * Fr, S, D)).view(B, Fr, S, D)
        h = _modulate(self.norm_t(x), mods[3], mods[4]).transpose(1, 2).reshape(B * S, Fr, D)
        x = x + mods[5] * self.attn_t(h).view(B, S, Fr, D).transpose(1, 2)
        if self.cross is not None and context is not None:
            ctx = context.repeat_interleave(Fr, dim=0)
            x = x + self.cross(self.norm_c(x).reshape(B * Fr, S, D), ctx).view(B, Fr, S, D)
        x = x + mods[8] * self.mlp(_modulate(self.norm_m(x), mods[6], mods[7]))
        return x


class SmallVideoDiT(Backbone):
    temporal_factor = 1

    def __init__(self, config: SmallDiTConfig, *, with_context: bool = False):
        super().__init__()
        self.config = config
        s, p, D = config.unshuffle, config.patch, config.dim
        self.latent_channels = 3 * s * s
        self.spatial_multiple = s * p
        self.token_dim = D
        self.context_dim = config.context_dim if with_context else None
        self.patch_embedding = nn.Conv3d(self.latent_channels, D, kernel_size=(1, p, p), stride=(1, p, p))
        self.time_mlp = nn.Sequential(nn.Linear(256, D), nn.SiLU(), nn.Linear(D, D))
        self.blocks = nn.ModuleList(Block(D, config.heads, config.mlp_ratio, self.context_dim)
                                    for _ in range(config.depth))
        self.norm_out = nn.LayerNorm(D, elementwise_affine=False, eps=1e-6)
        self.ada_out = nn.Sequential(nn.SiLU(), nn.Linear(D, 2 * D))
        self.proj_out = nn.Linear(D, self.latent_channels * p * p)
        for layer in (self.ada_out[1], self.proj_out):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)
        self._install_control_hook()

    # --------------------------------------------------------------------- latent space

    def encode(self, video: torch.Tensor) -> torch.Tensor:
        B, T = video.shape[:2]
        x = F.pixel_unshuffle(video.flatten(0, 1) * 2.0 - 1.0, self.config.unshuffle)
        return x.view(B, T, *x.shape[1:]).transpose(1, 2)

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        B, C, T = latents.shape[:3]
        x = F.pixel_shuffle(latents.transpose(1, 2).flatten(0, 1), self.config.unshuffle)
        return ((x.view(B, T, *x.shape[1:]) + 1.0) / 2.0).clamp(0.0, 1.0)

    # --------------------------------------------------------------------- denoiser

    def _positions(self, Fr: int, h: int, w: int, device) -> torch.Tensor:
        D = self.token_dim
        d_t = 2 * (D // 8)  # frame part; the rest splits (evenly) between rows and columns
        d_s = (D - d_t) // 2 // 2 * 2
        d_w = D - d_t - d_s
        pt = sincos_1d(Fr, d_t, device)[:, None, None, :].expand(Fr, h, w, d_t)
        ph = sincos_1d(h, d_s, device)[None, :, None, :].expand(Fr, h, w, d_s)
        pw = sincos_1d(w, d_w, device)[None, None, :, :].expand(Fr, h, w, d_w)
        return torch.cat([pt, ph, pw], dim=-1).reshape(Fr, h * w, D)

    def _denoise(self, latents, timesteps, context):
        B, _, Fr, _, _ = latents.shape
        p = self.config.patch
        tokens = self.patch_embedding(latents)  # (B, D, F, h', w'), controls added by the hook
        _, D, _, hp, wp = tokens.shape
        x = tokens.permute(0, 2, 3, 4, 1).reshape(B, Fr, hp * wp, D)
        x = x + self._positions(Fr, hp, wp, x.device).to(x.dtype)
        cond = self.time_mlp(timestep_embedding(timesteps, 256).to(x.dtype))  # (B, F, D)
        for block in self.blocks:
            x = block(x, cond, context)
        shift, scale = self.ada_out(cond)[:, :, None, :].chunk(2, dim=-1)
        x = self.proj_out(_modulate(self.norm_out(x), shift, scale))  # (B, F, S, C p p)
        C = self.latent_channels
        x = x.view(B, Fr, hp, wp, C, p, p).permute(0, 4, 1, 2, 5, 3, 6)
        return x.reshape(B, C, Fr, hp * p, wp * p)

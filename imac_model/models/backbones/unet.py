"""A convolutional U-Net that paints small things: the pixel-space backbone of the CPU and
short-GPU ranking presets (DIAMOND's design, adapted to chunks of frames).

* **Latent:** the mosaic's pixels at full resolution, no compression. The RGB row becomes
  three channels in [-1, 1]; the colour-depth row becomes one channel of its own, the walk
  position of the depth colour (:func:`imac_data.core.depth.path_position`, monotonic in
  metres for every codec). :meth:`UNetBackbone.decode` paints that channel back onto the
  codec's colour walk, so every generated depth pixel decodes to metres (black, position 0,
  stays "invalid"), and the dataset's colour codec stays the storage format.
* **Frames in channels:** ``patch_embedding`` embeds each of the ``1 + H`` frames with a
  3x3 convolution (the shape a control stream's zero-initialised projection copies, so the
  iMaC controls are added per future frame as in paper eq. 2); the embedded frames are then
  stacked in channels, and one 2-D U-Net predicts every frame at once.
* **Conditioning:** adaptive group norm on the flow time of the future frames; in the
  action-vector mode the action tokens are flattened into the same embedding (DIAMOND
  conditions on actions this way).
* **Output:** a zero-initialised convolution to ``4 (1 + H)`` channels: full resolution.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from imac_data.core.depth import N_SEGMENTS, path_position, walk_colour
from imac_model.config import UNetConfig
from imac_model.models.backbones.base import Backbone

LATENT_CHANNELS = 4  # RGB + the depth colour's walk position


def _time_features(t: torch.Tensor, dim: int = 256, max_period: float = 10000.0) -> torch.Tensor:
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[..., None] * freqs
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


def _groups(channels: int) -> int:
    return math.gcd(channels, 32)


class ResBlock(nn.Module):
    """GroupNorm modulated by the conditioning (scale and shift), SiLU, 3x3 conv; twice."""

    def __init__(self, c_in: int, c_out: int, emb: int):
        super().__init__()
        self.norm1 = nn.GroupNorm(_groups(c_in), c_in, affine=False)
        self.ada1 = nn.Linear(emb, 2 * c_in)
        self.conv1 = nn.Conv2d(c_in, c_out, 3, padding=1)
        self.norm2 = nn.GroupNorm(_groups(c_out), c_out, affine=False)
        self.ada2 = nn.Linear(emb, 2 * c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1)
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    @staticmethod
    def _modulate(x, norm, ada, cond):
        scale, shift = ada(cond)[:, :, None, None].chunk(2, dim=1)
        return F.silu(norm(x) * (1 + scale) + shift)

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        h = self.conv1(self._modulate(x, self.norm1, self.ada1, cond))
        h = self.conv2(self._modulate(h, self.norm2, self.ada2, cond))
        return self.skip(x) + h


class UNetBackbone(Backbone):
    temporal_factor = 1
    latent_channels = LATENT_CHANNELS

    def __init__(self, config: UNetConfig, *, num_frames: int, with_context: bool = False):
        super().__init__()
        self.config = c = config
        self.num_frames = int(num_frames)
        levels = len(c.channels)
        self.spatial_multiple = 2 ** levels  # the mosaic is two rows of the latent's height
        self.token_dim = c.frame_dim
        self.context_dim = c.context_dim if with_context else None
        self.patch_embedding = nn.Conv3d(LATENT_CHANNELS, c.frame_dim, kernel_size=(1, 3, 3), padding=(0, 1, 1))
        emb = 4 * c.channels[0]
        self.time_mlp = nn.Sequential(nn.Linear(256, emb), nn.SiLU(), nn.Linear(emb, emb))
        self.context_proj = None
        if self.context_dim is not None:  # the action tokens, flattened in order, into the conditioning
            self.context_proj = nn.Linear((self.num_frames - 1) * self.context_dim, emb)
        self.conv_in = nn.Conv2d(c.frame_dim * self.num_frames, c.channels[0], 3, padding=1)
        self.down = nn.ModuleList()
        self.downsample = nn.ModuleList()
        skips = [c.channels[0]]
        ch = c.channels[0]
        for i, width in enumerate(c.channels):
            blocks = nn.ModuleList()
            for _ in range(c.blocks):
                blocks.append(ResBlock(ch, width, emb))
                ch = width
                skips.append(ch)
            self.down.append(blocks)
            self.downsample.append(nn.Conv2d(ch, ch, 3, stride=2, padding=1) if i < levels - 1 else nn.Identity())
            if i < levels - 1:
                skips.append(ch)
        self.mid = nn.ModuleList([ResBlock(ch, ch, emb), ResBlock(ch, ch, emb)])
        self.up = nn.ModuleList()
        self.upsample = nn.ModuleList()
        for i, width in reversed(list(enumerate(c.channels))):
            blocks = nn.ModuleList()
            for _ in range(c.blocks + 1):
                blocks.append(ResBlock(ch + skips.pop(), width, emb))
                ch = width
            self.up.append(blocks)
            self.upsample.append(nn.Upsample(scale_factor=2, mode="nearest") if i > 0 else nn.Identity())
        self.norm_out = nn.GroupNorm(_groups(ch), ch)
        self.conv_out = nn.Conv2d(ch, LATENT_CHANNELS * self.num_frames, 3, padding=1)
        nn.init.zeros_(self.conv_out.weight)
        nn.init.zeros_(self.conv_out.bias)
        self._install_control_hook()

    # --------------------------------------------------------------------- latent space

    def encode(self, video: torch.Tensor) -> torch.Tensor:
        """Mosaic frames ``(B, T, 3, 2h, W)`` -> ``(B, 4, T, h, W)``: RGB and the depth's walk
        position, each in [-1, 1]."""
        h = video.shape[-2] // 2
        rgb, depth = video[..., :h, :], video[..., h:, :]
        s = path_position(depth.float(), channel_axis=-3) / N_SEGMENTS
        x = torch.cat([rgb.to(s.dtype), s[..., None, :, :]], dim=-3) * 2.0 - 1.0
        return x.transpose(1, 2)

    def encode_control(self, video: torch.Tensor) -> torch.Tensor:
        """A control mosaic (one row duplicated) -> its top row's RGB and a zero depth channel."""
        h = video.shape[-2] // 2
        rgb = video[..., :h, :].float() * 2.0 - 1.0
        return torch.cat([rgb, torch.zeros_like(rgb[..., :1, :, :])], dim=-3).transpose(1, 2)

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        x = ((latents.float().transpose(1, 2) + 1.0) / 2.0).clamp(0.0, 1.0)  # (B, T, 4, h, W)
        colour = walk_colour(x[:, :, 3] * N_SEGMENTS).movedim(-1, -3)
        return torch.cat([x[:, :, :3], colour], dim=-2)

    def make_patchify_layer(self) -> nn.Conv3d:
        layer = nn.Conv3d(LATENT_CHANNELS, self.token_dim, kernel_size=(1, 3, 3), padding=(0, 1, 1))
        nn.init.zeros_(layer.weight)
        nn.init.zeros_(layer.bias)
        return layer

    # --------------------------------------------------------------------- denoiser

    def _denoise(self, latents, timesteps, context):
        B, C, Fr, h, w = latents.shape
        if Fr != self.num_frames:
            raise ValueError(f"the U-Net was built for {self.num_frames} frames per chunk, got {Fr}")
        tokens = self.patch_embedding(latents)  # (B, D, F, h, w), controls added by the hook
        x = self.conv_in(tokens.transpose(1, 2).reshape(B, -1, h, w))
        cond = self.time_mlp(_time_features(timesteps[:, -1]).to(x.dtype))  # the future frames' flow time
        if self.context_proj is not None and context is not None:
            cond = cond + self.context_proj(context.reshape(B, -1).to(x.dtype))
        return self.trunk(x, cond).view(B, Fr, C, h, w).transpose(1, 2)

    def trunk(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """The U-Net from ``conv_in``'s output to ``conv_out``'s: tensors in, tensor out, so it is
        the part ``torch.compile`` takes (``train.compile``, :func:`imac_model.training.train.compile_trunk`)."""
        skips = [x]
        for blocks, down in zip(self.down, self.downsample):
            for block in blocks:
                x = block(x, cond)
                skips.append(x)
            if not isinstance(down, nn.Identity):
                x = down(x)
                skips.append(x)
        for block in self.mid:
            x = block(x, cond)
        for blocks, up in zip(self.up, self.upsample):
            for block in blocks:
                x = block(torch.cat([x, skips.pop()], dim=1), cond)
            x = up(x)
        return self.conv_out(F.silu(self.norm_out(x)))

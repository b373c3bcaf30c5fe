"""The action-conditioned world model: a backbone, the conditioning, and flow matching.

:class:`WorldModel` takes a :class:`~imac_model.data.batch.ChunkBatch` (tensors only) and

* :meth:`WorldModel.forward` (training): encodes the reference and the recorded future
  together, noises only the future latents (``x_tau = (1 - tau) x0 + tau x1``), runs the
  backbone with the reference latent clean at timestep 0 and the controls added to the
  future tokens, and returns a :class:`FlowOutput`: the flow loss over the valid future
  latent frames, and everything the training-time rollout needs (the one-step clean
  estimate :attr:`FlowOutput.clean_estimate`, the reference latent);
* :meth:`WorldModel.sample`: integrates the flow from noise with Euler steps and
  returns the future frames;
* :meth:`WorldModel.decode_future`: latents -> future mosaic frames; with
  :func:`imac_model.data.mosaic.split` they become per-view RGB and colour depth, so the
  last frame of a chunk can be the next chunk's reference.

Conditioning modes (``ModelSpec.conditioning.mode``): ``none``, ``motion``,
``motion+contact`` (control images, :class:`~imac_model.models.controls.ControlInjector`) and
``action-vector`` (raw actions through an MLP, cross-attended). With
``conditioning.first_frame`` the episode's first recorded frame goes in as one more clean frame
ahead of the reference (memory beyond one frame; a backbone that keeps every frame). With
``conditioning.dropout`` a share of the training samples goes without its controls (or action
tokens), and :meth:`WorldModel.sample` can guide by them (``conditioning.guidance``,
classifier-free guidance).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from imac_data.errors import InputError
from imac_model.config import ModelSpec
from imac_model.data.batch import ChunkBatch
from imac_model.models.backbones.build import Backbone, build_backbone, temporal_factor
from imac_model.models.controls import ActionEncoder, ControlInjector
from imac_model.modes import conditioning_mode
from imac_model.schedulers import flow


@dataclass
class FlowOutput:
    loss: torch.Tensor  # scalar: MSE over the valid future latent frames
    tau: torch.Tensor  # (B,)
    x_tau: torch.Tensor  # (B, C, F-1, h, w) noised future latents
    velocity: torch.Tensor  # predicted velocity of the future latents
    target: torch.Tensor  # x1 - x0
    reference_latent: torch.Tensor  # (B, C, 1, h, w), clean
    frame_mask: torch.Tensor  # (B, F-1) valid future latent frames

    @property
    def clean_estimate(self) -> torch.Tensor:
        """One-step estimate of the future latents, ``x_tau + (1 - tau) v`` (paper 3.4)."""
        return flow.clean_estimate(self.x_tau, self.velocity, self.tau)


@dataclass
class SampleOutput:
    frames: torch.Tensor  # (B, H, 3, 2h, V w) generated future mosaics in [0, 1]
    latents: torch.Tensor  # (B, C, F-1, h, w)
    reference_latent: torch.Tensor  # (B, C, 1, h, w)


class WorldModel(nn.Module):
    def __init__(self, spec: ModelSpec, backbone: Backbone | None = None):
        super().__init__()
        self.spec = spec
        mode = conditioning_mode(spec.conditioning.mode)
        self.clean_frames = 2 if spec.conditioning.first_frame else 1  # [first frame,] reference
        factor = backbone.temporal_factor if backbone is not None else temporal_factor(spec.backbone)
        if self.clean_frames > 1 and factor != 1:
            raise InputError(f"conditioning.first_frame: needs a backbone that keeps every frame (unet, small); "
                             f"{spec.backbone.kind} compresses time by {factor}")
        self.backbone = backbone or build_backbone(spec.backbone, with_context=mode.action_vector,
                                                   num_frames=spec.chunk + self.clean_frames)
        m = self.backbone.spatial_multiple
        H, W = spec.mosaic_hw
        if H % m or W % m:
            raise InputError(f"data.view_height / view_width: a {H}x{W} mosaic ({spec.view_height}x{spec.view_width} "
                             f"per view) cannot be patchified: both sides must be multiples of {m}")
        self.backbone.check_num_frames(spec.chunk + 1)
        self.streams = spec.conditioning.streams
        self.controls = (ControlInjector(self.backbone, self.streams, init=spec.conditioning.control_init,
                                         on_reference=spec.conditioning.control_on_reference)
                         if self.streams else None)
        self.action_encoder = None
        if mode.action_vector:
            if self.backbone.context_dim is None:
                raise InputError(f"conditioning.mode: {spec.conditioning.mode} needs a backbone built with context "
                                 "input")
            self.action_encoder = ActionEncoder(spec.action_dim, spec.chunk, self.backbone.context_dim,
                                                hidden=spec.conditioning.action_hidden,
                                                layers=spec.conditioning.action_layers,
                                                mean=spec.action_mean, std=spec.action_std)

    @property
    def num_views(self) -> int:
        return len(self.spec.views)

    # --------------------------------------------------------------------- encoding

    def encode_chunk(self, reference: torch.Tensor, future: torch.Tensor | None = None):
        """``(z_ref (B, C, 1, h, w), x1 (B, C, F-1, h, w) or None)``: the reference alone, or
        the reference and its future encoded together (Wan's causal VAE gives the same
        reference latent either way)."""
        if future is None:
            return self.backbone.encode(reference[:, None]), None
        z = self.backbone.encode(torch.cat([reference[:, None], future], dim=1))
        return z[:, :, :1], z[:, :, 1:]

    def encode_controls(self, controls: dict[str, torch.Tensor],
                        streams: tuple[str, ...] | None = None) -> dict[str, torch.Tensor]:
        """``{stream: (B, H, 3, ., .)}`` -> ``{stream: latents (B, C, F, h, w)}``, each video
        given a black frame in the reference slot first (``streams``: default all of the model's)."""
        out = {}
        for s in self.streams if streams is None else streams:
            c = controls[s]
            black = torch.zeros_like(c[:, :1])
            out[s] = self.backbone.encode_control(torch.cat([black, c], dim=1))
        return out

    def encode_first_frame(self, batch: ChunkBatch) -> torch.Tensor | None:
        """The latent ``(B, C, 1, h, w)`` of the batch's first frame, for a model conditioned on it."""
        return self.backbone.encode(batch.first_frame[:, None]) if self.clean_frames > 1 else None

    def context(self, actions: torch.Tensor) -> torch.Tensor | None:
        return None if self.action_encoder is None else self.action_encoder(actions)

    def decode_future(self, reference_latent: torch.Tensor, future_latents: torch.Tensor) -> torch.Tensor:
        """Future mosaic frames ``(B, H, 3, 2h, V w)`` in [0, 1] of ``future_latents``
        (decoded after the reference latent, which a causal decoder needs)."""
        frames = self.backbone.decode(torch.cat([reference_latent, future_latents.to(reference_latent.dtype)], dim=2))
        return frames[:, 1:]

    # --------------------------------------------------------------------- the denoiser

    def velocity(self, x_future: torch.Tensor, tau: torch.Tensor, *, reference_latent: torch.Tensor,
                 control_latents: dict[str, torch.Tensor] | None = None,
                 context: torch.Tensor | None = None, first_latent: torch.Tensor | None = None,
                 keep: torch.Tensor | None = None) -> torch.Tensor:
        """Predicted velocity of the future latents at ``tau`` ``(B,)``: the reference
        latent (after ``first_latent``, for a model conditioned on the first frame) goes in
        clean at timestep 0, the controls onto the future tokens. ``keep (B,)``: 1 keeps a
        sample's controls and action tokens, 0 drops them (the unconditional velocity)."""
        if (first_latent is not None) != (self.clean_frames > 1):
            raise ValueError("first_latent: given exactly when the model is conditioned on the first frame "
                             f"(conditioning.first_frame: {self.clean_frames > 1})")
        clean = [reference_latent] if first_latent is None else [first_latent.to(reference_latent.dtype),
                                                                 reference_latent]
        latents = torch.cat([*clean, x_future.to(reference_latent.dtype)], dim=2)
        B, Fr, k = latents.shape[0], latents.shape[2], len(clean)
        t = flow.wan_timestep(tau.float())[:, None].expand(B, Fr).clone()
        t[:, :k] = 0.0
        dropped = keep is not None and not bool(keep.any())  # guidance's unconditional pass: no tokens to build
        tokens = (self.controls(control_latents, tuple(control_latents))
                  if self.controls is not None and not dropped else None)  # (added: none is the same as zeros)
        if keep is not None:
            keep = keep.to(latents.dtype)
            tokens = None if tokens is None else tokens * keep.view(B, *[1] * (tokens.ndim - 1))
            context = None if context is None else context * keep.view(B, *[1] * (context.ndim - 1))
        if tokens is not None and k > 1:  # no control on the first frame
            tokens = torch.cat([torch.zeros_like(tokens[:, :, :k - 1]), tokens], dim=2)
        out = self.backbone.denoise(latents, t, control_tokens=tokens, context=context)[:, :, k:]
        if self.spec.flow.prediction == "data":  # the network predicts x1: v = (x1_hat - x_tau) / (1 - tau)
            gap = (1.0 - tau.float()).clamp_min(self.spec.flow.data_prediction_min_gap).view(B, 1, 1, 1, 1)
            return (out.float() - x_future.float()) / gap
        return out

    def active_streams(self, streams: tuple[str, ...] | None) -> tuple[str, ...]:
        """The control streams a call uses: all of the model's (None), or a non-empty subset
        (training stage one: ``("motion",)``)."""
        if streams is None:
            return self.streams
        streams = tuple(streams)
        if not streams or any(s not in self.streams for s in streams):
            raise ValueError(f"streams {list(streams)}: must be a non-empty subset of the model's {self.streams}")
        return streams

    def _inputs(self, batch: ChunkBatch, *, with_future: bool, streams: tuple[str, ...] | None = None):
        streams = self.active_streams(streams)
        batch.check(mosaic_hw=self.spec.mosaic_hw, horizon=self.spec.chunk, action_dim=self.spec.action_dim,
                    streams=streams, first_frame=self.clean_frames > 1)
        z_ref, x1 = self.encode_chunk(batch.reference, batch.future if with_future else None)
        controls = self.encode_controls(batch.controls, streams) if streams else None
        return z_ref, x1, controls, self.context(batch.actions), self.encode_first_frame(batch)

    def forward(self, batch: ChunkBatch, *, generator: torch.Generator | None = None,
                tau: torch.Tensor | None = None, noise: torch.Tensor | None = None,
                streams: tuple[str, ...] | None = None, rows: tuple[int, int] = (0, 1)) -> FlowOutput:
        """The flow-matching loss of a batch (training). ``tau`` / ``noise`` default to
        draws from ``generator`` (``tau ~ U(0, 1)``, shifted by ``flow.train_shift``).
        ``streams``: the active control streams (default all; stage one: motion only).
        ``rows = (r, n)``: this batch is rows ``r::n`` of a global batch of ``n x B`` rows
        (data-parallel rank r of n); the draws are those of the global batch, sliced, so
        they do not depend on how the global batch is split."""
        if batch.future is None:
            raise ValueError("ChunkBatch.future is needed for the loss")
        z_ref, x1, controls, context, z_first = self._inputs(batch, with_future=True, streams=streams)
        B, dev = x1.shape[0], x1.device
        r, n = rows
        Bg = B * n
        gen_dev = generator.device if generator is not None else dev
        if tau is None:
            tau = flow.sample_tau(Bg, shift=self.spec.flow.train_shift, generator=generator, device=gen_dev)[r::n]
        tau = tau.to(dev, torch.float32)
        if noise is None:
            noise = torch.randn((Bg, *x1.shape[1:]), generator=generator, device=gen_dev)[r::n]
        x0 = noise.to(dev, x1.dtype)
        fc = self.spec.flow
        weight = (flow.focus_weight(z_ref, x1, fc.focus_weight, fc.focus_threshold, fc.focus_dilation)
                  if fc.focus_weight > 0 else None)  # from the clean reference, before its noise
        if self.training and self.spec.flow.reference_noise > 0:  # release option: jitter the clean reference
            # (the first frame stays clean: it is always a recorded one)
            scale = torch.rand(Bg, generator=generator, device=gen_dev)[r::n].to(dev) * self.spec.flow.reference_noise
            eps = torch.randn((Bg, *z_ref.shape[1:]), generator=generator, device=gen_dev)[r::n].to(dev, z_ref.dtype)
            z_ref = z_ref + scale.view(B, 1, 1, 1, 1) * eps
        keep = None
        if self.training and self.spec.conditioning.dropout > 0:  # the unconditional velocity guidance needs
            drop = torch.rand(Bg, generator=generator, device=gen_dev)[r::n].to(dev) < self.spec.conditioning.dropout
            keep = (~drop).float()
        x_tau = flow.interpolate(x0, x1, tau)
        v = self.velocity(x_tau, tau, reference_latent=z_ref, control_latents=controls, context=context,
                          first_latent=z_first, keep=keep)
        target = flow.target_velocity(x0, x1)
        valid = torch.cat([torch.ones_like(batch.valid_mask()[:, :1]), batch.valid_mask()], dim=1)
        mask = self.backbone.latent_frame_mask(valid)[:, 1:]
        return FlowOutput(loss=flow.masked_mse(v, target, mask, weight), tau=tau, x_tau=x_tau, velocity=v, target=target,
                          reference_latent=z_ref, frame_mask=mask)

    @torch.no_grad()
    def sample(self, batch: ChunkBatch, *, steps: int | None = None, shift: float | None = None,
               generator: torch.Generator | None = None, noise: torch.Tensor | None = None,
               streams: tuple[str, ...] | None = None) -> SampleOutput:
        """Generate the future chunk of ``batch`` (its ``future`` is ignored)."""
        z_ref, _, controls, context, z_first = self._inputs(batch, with_future=False, streams=streams)
        B = z_ref.shape[0]
        F_future = self.backbone.latent_frames(self.spec.chunk + 1) - 1
        shape = (B, z_ref.shape[1], F_future, *z_ref.shape[3:])
        if noise is None:
            gen_dev = generator.device if generator is not None else z_ref.device
            noise = torch.randn(shape, generator=generator, device=gen_dev)
        x0 = noise.to(z_ref.device, z_ref.dtype)

        guidance = self.spec.conditioning.guidance

        def velocity(x, tau):
            v = self.velocity(x, tau, reference_latent=z_ref, control_latents=controls, context=context,
                              first_latent=z_first)
            if guidance == 1:
                return v
            v_uncond = self.velocity(x, tau, reference_latent=z_ref, control_latents=controls, context=context,
                                     first_latent=z_first, keep=torch.zeros(B, device=x.device))
            return v_uncond + guidance * (v - v_uncond)

        latents = flow.euler_sample(velocity, x0, steps=steps or self.spec.flow.sample_steps,
                                    shift=shift if shift is not None else self.spec.flow.sample_shift)
        return SampleOutput(frames=self.decode_future(z_ref, latents), latents=latents, reference_latent=z_ref)

"""Flow matching in the paper's time convention, and the Euler sampler.

* ``tau = 0`` is noise ``x0 ~ N(0, I)``, ``tau = 1`` is data ``x1``;
  ``x_tau = (1 - tau) x0 + tau x1`` and the velocity is ``v = x1 - x0`` (paper eq. 3-4).
* Backbones receive Wan's timestep ``t = 1000 (1 - tau)`` (Wan's sigma is ``1 - tau``);
  clean reference latents get ``t = 0``.
* One-step clean estimate (paper section 3.4): ``x1_hat = x_tau + (1 - tau) v``; it is
  exact when ``v`` is the true velocity.
* Timestep shift (as SD3 and Wan; 1 = none): ``sigma' = s sigma / (1 + (s - 1) sigma)``
  with ``sigma = 1 - tau``; ``s > 1`` spends more time near noise.

Everything here is plain tensor math, shared by training (:mod:`imac_model.models.world_model`)
and sampling; nothing knows about backbones or data.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

WAN_TIMESTEPS = 1000.0


def shift_tau(tau: torch.Tensor, shift: float) -> torch.Tensor:
    """Apply the timestep shift to ``tau`` (identity for ``shift == 1``)."""
    if shift == 1.0:
        return tau
    sigma = 1.0 - tau
    return 1.0 - shift * sigma / (1.0 + (shift - 1.0) * sigma)


def sample_tau(n: int, *, shift: float = 1.0, generator: torch.Generator | None = None,
               device=None) -> torch.Tensor:
    """``n`` training times: ``tau ~ U(0, 1)``, then shifted."""
    tau = torch.rand(n, generator=generator, device=generator.device if generator is not None else device)
    return shift_tau(tau.to(device) if device is not None else tau, shift)


def _bcast(tau: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    tau = torch.as_tensor(tau, dtype=like.dtype, device=like.device)
    return tau.reshape(tau.shape + (1,) * (like.ndim - tau.ndim))


def interpolate(x0: torch.Tensor, x1: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """``x_tau = (1 - tau) x0 + tau x1`` (``tau`` per sample, broadcast)."""
    t = _bcast(tau, x1)
    return (1.0 - t) * x0 + t * x1


def target_velocity(x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
    return x1 - x0


def clean_estimate(x_tau: torch.Tensor, velocity: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """One-step estimate of the data, ``x1_hat = x_tau + (1 - tau) v``."""
    return x_tau + (1.0 - _bcast(tau, x_tau)) * velocity


def wan_timestep(tau: torch.Tensor) -> torch.Tensor:
    """Wan's timestep of ``tau``: ``1000 (1 - tau)`` (0 = clean)."""
    return WAN_TIMESTEPS * (1.0 - tau)


def masked_mse(pred: torch.Tensor, target: torch.Tensor, frame_mask: torch.Tensor,
               weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error over the latent frames where ``frame_mask`` ``(B, F)`` is true;
    ``pred``/``target`` are ``(B, C, F, h, w)``. Masked frames add nothing, not even to
    the count. ``weight`` ``(B, 1, F, h, w)``: a per-latent-pixel weight, the mean becoming a
    weighted mean. Returns 0 (with a graph) when nothing is valid."""
    m = frame_mask.to(pred.dtype)[:, None, :, None, None]
    m = m.expand(-1, 1, -1, *pred.shape[3:]) if weight is None else m * weight.to(pred.dtype)
    err = (pred.float() - target.float()) ** 2 * m
    return err.sum() / (m.sum() * pred.shape[1]).clamp_min(1.0)


def focus_weight(reference: torch.Tensor, future: torch.Tensor, weight: float, threshold: float,
                 dilation: int) -> torch.Tensor:
    """``(B, 1, F, h, w)`` loss weights: ``1 + weight`` where a future latent differs from the
    reference latent ``(B, C, 1, h, w)`` by more than ``threshold`` in any channel, dilated by
    ``dilation`` pixels, else 1. What moves in a chunk (the arm, a lifted object) is a few per
    cent of the pixels; a uniform loss lets the model leave it out."""
    changed = ((future.float() - reference.float()).abs().amax(dim=1) > threshold).float()  # (B, F, h, w)
    if dilation > 0:
        B, Fr, h, w = changed.shape
        changed = torch.nn.functional.max_pool2d(changed.reshape(B * Fr, 1, h, w), 2 * dilation + 1, stride=1,
                                                 padding=dilation).reshape(B, Fr, h, w)
    return (1.0 + weight * changed)[:, None]


def schedule(steps: int, shift: float = 1.0, *, device=None) -> torch.Tensor:
    """``steps + 1`` increasing times from 0 (noise) to 1 (data), shifted."""
    return shift_tau(torch.linspace(0.0, 1.0, steps + 1, device=device), shift)


def euler_sample(velocity: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], x0: torch.Tensor, *,
                 steps: int, shift: float = 1.0) -> torch.Tensor:
    """Integrate ``dx/dtau = velocity(x, tau)`` from ``x0`` (tau = 0) to tau = 1 with
    ``steps`` Euler steps; ``tau`` is passed per sample, shape ``(B,)``."""
    taus = schedule(steps, shift, device=x0.device)
    x = x0
    for i in range(steps):
        tau = taus[i].expand(x.shape[0])
        x = x + (taus[i + 1] - taus[i]) * velocity(x, tau)
    return x

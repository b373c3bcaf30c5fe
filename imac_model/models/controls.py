"""How actions enter the model: control-image injection (paper eq. 2) and the action-vector
baseline.

:class:`ControlInjector`: each control video (a black frame in the reference slot) is encoded
by the backbone's own encoder, patchified by its own zero-initialised layer shaped like
``patch_embedding``, and added to the future tokens::

    h_tau = [P_v(z_ref) ; P_v(x_tau) + P_m(E(C_m)) + P_s2g(E(C_s2g)) + P_r2s(E(C_r2s))]

:class:`ActionEncoder`: the raw actions through an MLP to one context token per future step,
cross-attended. The public release's choices are options (``docs/world-model.md``)."""

from __future__ import annotations

import copy

import torch
from torch import nn

from imac_model.models.backbones.base import Backbone


class ControlInjector(nn.Module):
    def __init__(self, backbone: Backbone, streams: tuple[str, ...], *, init: str = "zeros",
                 on_reference: bool = False):
        super().__init__()
        self.streams = tuple(streams)
        self.on_reference = on_reference
        self.layers = nn.ModuleDict({s: backbone.make_patchify_layer() for s in self.streams})
        if init == "copy_patch_embedding" and "motion" in self.layers:
            self.layers["motion"] = copy.deepcopy(backbone.patch_embedding)
            self.layers["motion"].requires_grad_(True)
        elif init != "zeros" and init != "copy_patch_embedding":
            raise ValueError(f"unknown control init {init!r}")

    def forward(self, control_latents: dict[str, torch.Tensor],
                streams: tuple[str, ...] | None = None) -> torch.Tensor:
        """Summed control tokens ``(B, D, F, h', w')`` from ``{stream: latents (B, C, F, h, w)}``;
        zero on latent frame 0 (the reference) unless ``on_reference``. ``streams``: the
        active subset (default all; training stage one uses the motion stream alone)."""
        streams = self.streams if streams is None else tuple(streams)
        unknown = [s for s in streams if s not in self.streams]
        if unknown or not streams:
            raise ValueError(f"active control streams {list(streams)}: must be a non-empty subset of {self.streams}")
        missing = [s for s in streams if s not in control_latents]
        if missing:
            raise ValueError(f"control streams {missing} are missing from the batch")
        tokens = sum(self.layers[s](control_latents[s].to(self.layers[s].weight.dtype)) for s in streams)
        if not self.on_reference:
            keep = torch.ones(tokens.shape[2], device=tokens.device, dtype=tokens.dtype)
            keep[0] = 0.0
            tokens = tokens * keep[:, None, None]
        return tokens


class ActionEncoder(nn.Module):
    """Raw future actions ``(B, H, D)`` -> context tokens ``(B, H, context_dim)``."""

    def __init__(self, action_dim: int, chunk: int, context_dim: int, *, hidden: int = 256, layers: int = 3,
                 mean=None, std=None):
        super().__init__()
        # the dataset's action statistics (joint angles and gripper openings differ in scale)
        mean = torch.zeros(action_dim) if mean is None or len(mean) == 0 else torch.as_tensor(mean, dtype=torch.float32)
        std = torch.ones(action_dim) if std is None or len(std) == 0 else torch.as_tensor(std, dtype=torch.float32)
        self.register_buffer("mean", mean.float(), persistent=False)
        self.register_buffer("std", std.float().clamp_min(1e-3), persistent=False)
        dims = [action_dim] + [hidden] * (layers - 1) + [context_dim]
        mods: list[nn.Module] = []
        for i in range(layers):
            mods.append(nn.Linear(dims[i], dims[i + 1]))
            if i < layers - 1:
                mods.append(nn.SiLU())
        self.mlp = nn.Sequential(*mods)
        self.step_embedding = nn.Parameter(torch.zeros(1, chunk, context_dim))
        nn.init.normal_(self.step_embedding, std=0.02)

    def forward(self, actions: torch.Tensor) -> torch.Tensor:
        a = (actions.float() - self.mean) / self.std
        return self.mlp(a.to(self.step_embedding.dtype)) + self.step_embedding[:, :actions.shape[1]]

"""Sharded training with torch's FSDP2 (``fully_shard``) and ``torch.distributed.checkpoint``:
the same code on gloo (CPU) and NCCL (GPU).

:func:`shard_world_model` puts every Wan transformer block in its own group, the rest of the
transformer in one, and the control layers and the null prompt in the root group; the frozen
VAE is left out (replicated). :class:`ShardedRuntime` is what the trainer needs around it: the
process group, mixed precision by the sharding policy, checkpoints through DCP, collectives
for the loss and the stop decision. ``docs/scale.md`` has the reasoning."""

from __future__ import annotations

import contextlib
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import torch
import torch.distributed as dist

from imac_data.errors import InputError
from imac_model.config import ModelSpec, RunConfig
from imac_model.models import checkpoint as ckpt
from imac_model.models.world_model import WorldModel
from imac_model.training.runtime import LocalRuntime

# FSDP and DTensor are imported where used: most of a second, which every unsharded training
# process (the trainer imports this module) would pay for nothing
if TYPE_CHECKING:
    from torch.distributed.tensor import Shard


def shard_placement(param: torch.nn.Parameter, world: int) -> Shard | None:
    """Dim 0 (FSDP2's default, ``None``) when it splits evenly over ``world`` ranks; else the
    largest dim that does: Wan's per-block ``scale_shift_table`` (1, 6, D) would otherwise sit
    whole on rank 0."""
    from torch.distributed.tensor import Shard  # heavy: only when sharding

    if param.ndim == 0 or param.shape[0] % world == 0:
        return None
    even = [d for d in range(param.ndim) if param.shape[d] % world == 0]
    return Shard(max(even, key=lambda d: param.shape[d])) if even else None


def shard_world_model(model: WorldModel, mesh, *, bf16: bool, reshard_after_forward: bool = True,
                      cpu_offload: bool = False) -> None:
    """Apply FSDP2 to a Wan world model in place (``docs/scale.md``, "How the model is sharded").

    bf16: parameters are gathered and computed in bf16, gradients reduced in fp32, the master
    weights stay fp32 shards. ``cast_forward_inputs`` is off (FSDP2 skips its input cast when a
    checkpointed block recomputes, so forward and recompute would differ; and it would round
    Wan's float timesteps): the adapter casts latents and context to ``compute_dtype`` itself.
    The time embedder keeps fp32, as diffusers' ``_keep_in_fp32_modules`` asks."""
    from torch.distributed.fsdp import (  # heavy: only when sharding
        CPUOffloadPolicy,
        MixedPrecisionPolicy,
        OffloadPolicy,
        fully_shard,
        register_fsdp_forward_method,
    )

    world = mesh.size()
    backbone = model.backbone
    tr = backbone.transformer
    policy = (MixedPrecisionPolicy(param_dtype=torch.bfloat16, reduce_dtype=torch.float32, cast_forward_inputs=False)
              if bf16 else MixedPrecisionPolicy())
    kw = dict(mesh=mesh, shard_placement_fn=partial(shard_placement, world=world), mp_policy=policy,
              offload_policy=CPUOffloadPolicy(pin_memory=True) if cpu_offload else OffloadPolicy())
    if bf16:
        fp32 = MixedPrecisionPolicy(param_dtype=torch.float32, reduce_dtype=torch.float32, cast_forward_inputs=False)
        fully_shard(tr.condition_embedder.time_embedder, **{**kw, "mp_policy": fp32})
    for block in tr.blocks:
        fully_shard(block, reshard_after_forward=reshard_after_forward, **kw)
    fully_shard(tr, reshard_after_forward=reshard_after_forward, **kw)
    device = torch.device(mesh.device_type, torch.cuda.current_device()) if mesh.device_type == "cuda" else \
        torch.device(mesh.device_type)
    backbone.vae.to(device, dtype=torch.bfloat16 if bf16 else None)  # ignored parameters are not moved by FSDP2
    fully_shard(model, ignored_params=set(backbone.vae.parameters()), **kw)
    register_fsdp_forward_method(model, "sample")  # sampling gathers the root group's weights as forward does
    if bf16:
        backbone.compute_dtype = torch.bfloat16


def shard_report(model: WorldModel, world: int) -> dict:
    """What every rank holds: parameters per group (each block, the rest of the transformer,
    the root's trainable weights, the VAE), in full and per rank (a collective)."""
    from torch.distributed.tensor import DTensor  # heavy: only when sharding

    tr = model.backbone.transformer
    in_blocks = {id(p) for p in tr.blocks.parameters()}
    vae = {id(p) for p in model.backbone.vae.parameters()}
    in_tr = {id(p) for p in tr.parameters()}
    groups = {f"transformer.blocks.{i}": list(b.parameters()) for i, b in enumerate(tr.blocks)}
    groups["transformer (outside the blocks)"] = [p for p in tr.parameters() if id(p) not in in_blocks]
    groups["root (controls, null prompt, action encoder)"] = [p for p in model.parameters()
                                                             if id(p) not in in_tr and id(p) not in vae]
    groups["vae (replicated)"] = list(model.backbone.vae.parameters())
    local = [sum(p.to_local().numel() if isinstance(p, DTensor) else p.numel() for p in ps) for ps in groups.values()]
    every = [None] * world
    dist.all_gather_object(every, local)
    return {"world": world, "groups": {name: {"parameters": sum(p.numel() for p in ps),
                                             "per_rank": [every[r][i] for r in range(world)]}
                                       for i, (name, ps) in enumerate(groups.items())}}


class ShardedRuntime(LocalRuntime):
    """The trainer's side of FSDP2: one process per GPU (``torchrun`` or ``accelerate launch``
    set the environment), or a one-process group when started alone. accelerate serves the
    trackers only; it never wraps the model. Backward and clipping are torch's (FSDP2 reduce-scatters the
    gradients; the norm is DTensor-aware), the collectives the base class's."""

    sharded = True

    def __init__(self, run: RunConfig, out: Path):
        if run.train.sharding.cpu_offload and not torch.cuda.is_available():
            raise InputError("train.sharding.cpu_offload: offloads from a CUDA device to host memory; there is no "
                             "CUDA device here")
        super().__init__(run, out, group=True)  # the device mesh needs a group, of one process too
        self.mesh = dist.device_mesh.init_device_mesh(self.device.type, (self.world,))
        self.sharding = run.train.sharding

    def wrap(self, model: WorldModel) -> WorldModel:
        shard_world_model(model, self.mesh, bf16=self.bf16, reshard_after_forward=self.sharding.reshard_after_forward,
                          cpu_offload=self.sharding.cpu_offload)
        return model

    def prepare(self, model, optimizer):
        return model, optimizer  # placed by wrap (cpu_offload keeps the weights in host memory)

    def autocast(self):
        return contextlib.nullcontext()  # the sharding policy casts

    # ----------------------------------------------------------------- checkpoints

    @staticmethod
    def check_format(path: Path) -> None:
        if not ckpt.is_sharded(path):
            raise InputError(f"train.sharding.strategy: {path} is an unsharded checkpoint ({ckpt.WEIGHTS}); resume "
                             f"it with train.sharding.strategy none, or use another output directory")

    def save(self, directory: Path, *, model, optimizer, scheduler, ema, spec: ModelSpec, run: RunConfig,
             step: int) -> Path:
        return ckpt.save_sharded_checkpoint(directory, model=model, optimizer=optimizer, spec=spec, run=run,
                                            ema=ema.shadow if ema is not None else None,
                                            trainer={"step": step, "scheduler": scheduler.state_dict()})

    def load(self, path: Path, *, model, optimizer, scheduler, ema, spec: ModelSpec) -> int:
        state, has_ema = ckpt.load_sharded_checkpoint(path, model=model, optimizer=optimizer, spec=spec,
                                                      ema=ema.shadow if ema is not None else None,
                                                      trainer={"step": 0, "scheduler": scheduler.state_dict()})
        scheduler.load_state_dict(state["scheduler"])
        return int(state["step"])

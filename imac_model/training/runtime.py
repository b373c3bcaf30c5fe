"""Where the trainer's steps run: :class:`LocalRuntime`, one process or several data-parallel under ``torchrun``
or ``accelerate launch`` (DDP; gloo on a machine without a GPU), with torch alone, which is all the GPU machine
has; :class:`imac_model.training.sharding.ShardedRuntime` extends it with FSDP2. Both give the loop the same few
calls. ``accelerate`` serves the trackers only."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from imac_data.errors import InputError
from imac_model.config import ModelSpec, RunConfig
from imac_model.models import checkpoint as ckpt


def mixed_precision(run: RunConfig) -> str:
    """``train.mixed_precision`` resolved: ``auto`` is bf16 on a CUDA device that has it."""
    precision = run.train.mixed_precision
    if precision == "auto":
        precision = "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "no"
    return precision


def fast_kernels() -> None:
    """TF32 matrix products and cuDNN's autotuned convolutions: how a run trains on a GPU."""
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True
    torch.backends.cudnn.benchmark = True


class LocalRuntime:
    """The processes ``torchrun`` started (``WORLD_SIZE``), or this one alone: a process group where there are
    several (or ``group``), each on its GPU (``LOCAL_RANK``) or the CPU; bf16 autocast where asked, clipping,
    checkpoints as safetensors."""

    sharded = False

    def __init__(self, run: RunConfig, out: Path, *, group: bool = False):
        cuda = torch.cuda.is_available()
        self.bf16 = mixed_precision(run) == "bf16"
        self.owns_group = (group or int(os.environ.get("WORLD_SIZE", "1")) > 1) and not dist.is_initialized()
        if self.owns_group:
            backend = "cpu:gloo,cuda:nccl" if cuda else "gloo"
            if "MASTER_ADDR" in os.environ and "WORLD_SIZE" in os.environ:  # torchrun / accelerate launch
                dist.init_process_group(backend)
            else:
                dist.init_process_group(backend, store=dist.HashStore(), rank=0, world_size=1)
        self.rank, self.world = (dist.get_rank(), dist.get_world_size()) if dist.is_initialized() else (0, 1)
        self.main = self.rank == 0
        if cuda:
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
            self.device = torch.device("cuda", torch.cuda.current_device())
            fast_kernels()
        else:
            self.device = torch.device("cpu")
        self.tracker = None
        if run.train.tracker:
            from accelerate import Accelerator  # trackers only; accelerate is slow to import

            self.tracker = Accelerator(cpu=not cuda, log_with=run.train.tracker, project_dir=str(out))

    def wrap(self, model):
        return model

    def prepare(self, model, optimizer):
        model = model.to(self.device)
        if self.world > 1:  # gradients averaged over the processes
            model = DistributedDataParallel(model, device_ids=[self.device.index] if self.device.type == "cuda" else None)
        return model, optimizer

    def unwrap(self, model):
        return model.module if isinstance(model, DistributedDataParallel) else model

    def autocast(self):
        if not self.bf16:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=torch.bfloat16)

    def backward(self, loss: torch.Tensor) -> None:
        loss.backward()

    def clip_grad_norm_(self, params, max_norm: float) -> None:
        torch.nn.utils.clip_grad_norm_(params, max_norm)

    def all_reduce_sum(self, tensor: torch.Tensor) -> torch.Tensor:
        if self.world > 1:
            dist.all_reduce(tensor)
        return tensor

    def any(self, flag: bool) -> bool:
        """The same stop decision on every process (timers differ between them)."""
        if self.world == 1:
            return flag
        t = torch.tensor([float(flag)], device=self.device)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t.item())

    def wait(self) -> None:
        if self.world > 1:
            dist.barrier()

    @staticmethod
    def check_format(path: Path) -> None:
        if ckpt.is_sharded(path):
            raise InputError(f"train.sharding.strategy: {path} is a sharded checkpoint ({ckpt.SHARDED}/); resume "
                             f"it with train.sharding.strategy fsdp2, or use another output directory")

    def save(self, directory: Path, *, model, optimizer, scheduler, ema, spec: ModelSpec, run: RunConfig,
             step: int) -> Path | None:
        self.wait()
        if not self.main:
            return None
        return ckpt.save_checkpoint(directory, model=self.unwrap(model), spec=spec, run=run,
                                    ema=ema.state() if ema else None,
                                    trainer_state={"optimizer": optimizer.state_dict(),
                                                   "scheduler": scheduler.state_dict(), "step": step})

    def load(self, path: Path, *, model, optimizer, scheduler, ema, spec: ModelSpec) -> int:
        ckpt.load_weights_into(model, path / ckpt.WEIGHTS)
        state = ckpt.read_trainer_state(path)
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        if ema is not None and (path / ckpt.EMA).is_file():
            ema.shadow = {k: v.float() for k, v in ckpt.read_weights(path / ckpt.EMA).items()}
        return int(state["step"])

    def close(self) -> None:
        if self.tracker is not None:
            self.tracker.end_training()
        if self.owns_group and dist.is_initialized():
            dist.destroy_process_group()


__all__ = ["LocalRuntime", "fast_kernels", "mixed_precision"]

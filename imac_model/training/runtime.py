"""Where the trainer's steps run: one process (:class:`LocalRuntime`, torch alone: what the GPU machine has),
or several under ``accelerate launch`` / ``torchrun`` (:class:`AccelerateRuntime`); the sharded runtime,
:class:`imac_model.training.sharding.ShardedRuntime`, is a third kind. All give the loop the same few calls."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import torch

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
    """One process on one device (the first GPU, else the CPU): bf16 autocast where asked, clipping,
    checkpoints as safetensors."""

    sharded = False
    tracker = None
    main, rank, world = True, 0, 1

    def __init__(self, run: RunConfig, out: Path):
        self.device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        self.bf16 = mixed_precision(run) == "bf16"
        if self.device.type == "cuda":
            fast_kernels()

    def wrap(self, model):
        return model

    def prepare(self, model, optimizer):
        return model.to(self.device), optimizer

    def unwrap(self, model):
        return model

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
            torch.distributed.all_reduce(tensor)
        return tensor

    def any(self, flag: bool) -> bool:
        """The same stop decision on every process (timers differ between them)."""
        if self.world == 1:
            return flag
        t = torch.tensor([float(flag)], device=self.device)
        torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MAX)
        return bool(t.item())

    def wait(self) -> None:
        pass

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
        pass


class AccelerateRuntime(LocalRuntime):
    """Several processes, data-parallel (``accelerate launch`` or ``torchrun``; gloo on a machine without a GPU),
    or a tracker: the same calls through ``accelerate``."""

    def __init__(self, run: RunConfig, out: Path):
        from accelerate import Accelerator

        # several processes and no GPU (torchrun on a CPU machine): accelerate runs data-parallel over gloo only
        # when told to use the CPU; otherwise every process would train alone, into the same directory
        cpu = not torch.cuda.is_available() and int(os.environ.get("WORLD_SIZE", "1")) > 1
        self.accelerator = Accelerator(mixed_precision=mixed_precision(run), log_with=run.train.tracker,
                                       project_dir=str(out), cpu=cpu)
        self.tracker = self.accelerator if run.train.tracker else None
        self.main = self.accelerator.is_main_process
        self.rank, self.world = self.accelerator.process_index, self.accelerator.num_processes
        self.device = self.accelerator.device

    def prepare(self, model, optimizer):
        return self.accelerator.prepare(model, optimizer)

    def unwrap(self, model):
        return self.accelerator.unwrap_model(model)

    def autocast(self):
        return self.accelerator.autocast()

    def backward(self, loss: torch.Tensor) -> None:
        self.accelerator.backward(loss)

    def clip_grad_norm_(self, params, max_norm: float) -> None:
        self.accelerator.clip_grad_norm_(params, max_norm)

    def wait(self) -> None:
        self.accelerator.wait_for_everyone()

    def close(self) -> None:
        if self.tracker is not None:
            self.accelerator.end_training()


__all__ = ["AccelerateRuntime", "LocalRuntime", "fast_kernels", "mixed_precision"]

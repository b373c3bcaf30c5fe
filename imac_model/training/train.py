"""Train the world model (``imac-model train``): on ``accelerate``, one process on the CPU or
several GPUs (the global batch split over processes), bf16 where the device has it; or, with
``train.sharding.strategy: fsdp2``, sharded over the processes (:mod:`.sharding`).

Everything is checked before the first step (config, the dataset's streams, chunk length,
view size). Held-out episodes are never trained on; their flow loss is measured at fixed
times and noise. Checkpoints are written every ``train.checkpoint_every`` steps and at the
end, and a resumed run ends with the same weights as an uninterrupted one (batches and noise
are functions of (seed, step)). With ``rollout.chunks`` R > 1, steps train clips of R chunks
(:mod:`imac_model.pipelines.rollout`). Logs: ``log.jsonl``, ``log.csv``, an optional tracker."""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError
from imac_data.metadata import dataset_info
from imac_model.config import REBUILT_STREAMS, ModelSpec, RunConfig, save_config
from imac_model.data.chunks import ChunkDataset, action_stats, open_metadata, resolve_layout, split_episodes
from imac_model.models import checkpoint as ckpt
from imac_model.models.backbones.build import spatial_multiple, temporal_factor
from imac_model.models.world_model import WorldModel
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.rollout import rollout_loss
from imac_model.training.log import append_log, read_log, write_log
from imac_model.training.sharding import ShardedRuntime, shard_report

EVAL_TAUS = (0.1, 0.3, 0.5, 0.7, 0.9)  # fixed times of the held-out loss


@dataclass
class TrainResult:
    output_dir: Path
    step: int
    checkpoint: Path | None
    log: list[dict]
    stopped: str  # "max_steps", "time" (max_minutes / max_cpu_minutes) or "interrupted"
    main: bool = True  # the process that writes the logs (rank 0)


# --------------------------------------------------------------------------- setup


def model_spec(run: RunConfig, meta) -> tuple[ModelSpec, object]:
    """The resolved model of a run on a dataset (checks the dataset against the run)."""
    layout = resolve_layout(dataset_info(meta), run.data, run.conditioning.streams,
                            spatial_multiple=spatial_multiple(run.backbone),
                            temporal_factor=temporal_factor(run.backbone), mode=run.conditioning.mode)
    mean, std = action_stats(meta)
    spec = ModelSpec(backbone=run.backbone, conditioning=run.conditioning, flow=run.flow, views=layout.views,
                     view_height=layout.view_hw[0], view_width=layout.view_hw[1], chunk=layout.chunk,
                     action_dim=layout.action_dim, fps=layout.fps, dataset=run.data.dataset,
                     action_mean=tuple(mean), action_std=tuple(std))
    return spec, layout


def batch_indices(step: int, n: int, batch_size: int, seed: int) -> list[int]:
    """The global batch of ``step``: epochs are seeded permutations of the ``n`` items
    (the last partial batch of an epoch is dropped), a pure function of (seed, step)."""
    per_epoch = max(n // batch_size, 1)
    epoch, pos = divmod(step, per_epoch)
    perm = np.random.default_rng([seed, epoch]).permutation(n)
    if n < batch_size:
        perm = np.resize(perm, batch_size)
    return perm[pos * batch_size:(pos + 1) * batch_size].tolist()


class RolloutSchedule:
    """Which kind of step ``step`` is, and where it is in epochs (passes over the training
    chunks). Without rollout (``rollout.chunks`` = 1) every step trains a batch of chunks.
    With rollout, the first ``rollout.warmup_epochs`` train single chunks from their recorded
    (clean) references: a clip with clean references is R independent chunks, and training
    them as single chunks keeps the optimizer steps of an ordinary run. Every later step
    trains a batch of R-chunk clips, which counts as R batches of chunks."""

    def __init__(self, n_chunks: int, batch_size: int, rollout):
        self.R = rollout.chunks
        self.per_epoch = max(n_chunks // batch_size, 1)  # chunk batches per epoch, as batch_indices counts them
        self.warmup_steps = math.ceil(rollout.warmup_epochs * self.per_epoch) if self.R > 1 else 0

    def at(self, step: int) -> tuple[str, int, float]:
        """``(phase, step within the phase, epoch)``; phase ``chunk`` or ``clip``."""
        if self.R == 1 or step < self.warmup_steps:
            return "chunk", step, step / self.per_epoch
        k = step - self.warmup_steps
        return "clip", k, (self.warmup_steps + k * self.R) / self.per_epoch


def step_generator(seed: int, step: int) -> torch.Generator:
    """The draws of a step's whole global batch (every process slices its rows from them)."""
    return torch.Generator().manual_seed(int(np.random.SeedSequence([seed, step, 0]).generate_state(1)[0]))


def lr_lambda(warmup: int):
    return lambda step: min(1.0, (step + 1) / warmup) if warmup > 0 else 1.0


class EMA:
    """Exponential moving average of the trainable weights (float32 copies)."""

    def __init__(self, model: torch.nn.Module, decay: float):
        self.decay = decay
        self.shadow = {k: p.detach().float().clone() for k, p in model.named_parameters() if p.requires_grad}

    @torch.no_grad()
    def update(self, model: torch.nn.Module, step: int) -> None:
        d = min(self.decay, (1 + step) / (10 + step))  # fast start, as is usual
        for k, p in model.named_parameters():
            if k in self.shadow:
                self.shadow[k].mul_(d).add_(p.detach().float(), alpha=1 - d)

    def state(self) -> dict[str, torch.Tensor]:
        return self.shadow


@torch.no_grad()
def heldout_loss(model: WorldModel, dataset: ChunkDataset, items: list[int], batch_size: int, device,
                 autocast, runtime=None) -> float:
    """Flow loss of fixed held-out chunks at fixed times and noise: comparable across steps.
    With a sharded ``runtime`` every rank takes its rows of each batch (``len(items)`` a
    multiple of the world size) and the batch's masked mean is the global one."""
    rank, world = (runtime.rank, runtime.world) if runtime is not None else (0, 1)
    was_training = model.training
    model.eval()
    total, count = 0.0, 0
    for start in range(0, len(items), batch_size):
        idx = items[start:start + batch_size]
        batch = dataset.batch(idx[rank::world]).to(device)
        tau = torch.tensor([EVAL_TAUS[(start + i) % len(EVAL_TAUS)] for i in range(len(idx))])[rank::world]
        gen = torch.Generator().manual_seed(12345 + start)
        with autocast():
            out = model(batch, generator=gen, tau=tau, rows=(rank, world))
        if world == 1:
            loss = float(out.loss)
        else:
            n = out.frame_mask.sum().double()
            sums = runtime.all_reduce_sum(torch.stack([out.loss.detach().double() * n, n]))
            loss = float(sums[0] / sums[1]) if sums[1] > 0 else 0.0
        total += loss * len(idx)
        count += len(idx)
    model.train(was_training)
    return total / max(count, 1)


def balanced_loss(out, runtime) -> torch.Tensor:
    """The loss a data-parallel process trains on: its masked mean, rescaled so that the mean
    over processes (how gradients are averaged) is the global batch's masked mean even when
    the processes hold different numbers of valid (unpadded) frames."""
    if runtime.world == 1:
        return out.loss
    n = out.frame_mask.sum().double()
    total = runtime.all_reduce_sum(n.clone())
    if total == 0:
        return out.loss
    return out.loss * (n * runtime.world / total).to(out.loss.dtype)


class AccelerateRuntime:
    """The unsharded trainer's side of ``accelerate``: one process, or DDP over several
    (``accelerate launch`` or ``torchrun``; gloo on a machine without a GPU), bf16 autocast, clipping,
    checkpoints as safetensors."""

    sharded = False

    def __init__(self, run: RunConfig, out: Path):
        from accelerate import Accelerator

        precision = run.train.mixed_precision
        if precision == "auto":
            precision = "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "no"
        # several processes and no GPU (torchrun on a CPU machine): accelerate runs data-parallel over gloo only
        # when told to use the CPU; otherwise every process would train alone, into the same directory
        cpu = not torch.cuda.is_available() and int(os.environ.get("WORLD_SIZE", "1")) > 1
        self.accelerator = Accelerator(mixed_precision=precision, log_with=run.train.tracker, project_dir=str(out),
                                       cpu=cpu)
        self.tracker = self.accelerator if run.train.tracker else None
        self.main = self.accelerator.is_main_process
        self.rank, self.world = self.accelerator.process_index, self.accelerator.num_processes
        self.device = self.accelerator.device

    def wrap(self, model):
        return model

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

    def all_reduce_sum(self, tensor: torch.Tensor) -> torch.Tensor:
        if self.world > 1:
            torch.distributed.all_reduce(tensor)
        return tensor

    def any(self, flag: bool) -> bool:
        if self.world == 1:
            return flag
        t = torch.tensor([float(flag)], device=self.device)
        torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MAX)
        return bool(t.item())

    def wait(self) -> None:
        self.accelerator.wait_for_everyone()

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
            self.accelerator.end_training()


def _evaluation_items(dataset: ChunkDataset, n: int) -> list[int]:
    if len(dataset) == 0:
        return []
    return sorted(set(np.linspace(0, len(dataset) - 1, min(n, len(dataset))).round().astype(int).tolist()))


# --------------------------------------------------------------------------- the loop


def train(run: RunConfig, *, resume: bool | None = None, progress: bool = True,
          stop_after_steps: int | None = None) -> TrainResult:
    """Train ``run``; ``resume`` None = continue when the output directory has checkpoints
    of the same model, True = require that, False = refuse a directory with checkpoints.
    ``stop_after_steps`` interrupts the run (with a checkpoint) after that many steps."""
    from tqdm.auto import tqdm

    tc = run.train
    sharded = tc.sharding.strategy != "none"
    meta = open_metadata(run.data)
    spec, layout = model_spec(run, meta)
    train_eps, held_eps = split_episodes(meta.total_episodes, run.data.held_out_episodes)
    out = Path(tc.output_dir)
    existing = ckpt.list_checkpoints(out)
    if existing:
        if resume is False:
            raise InputError(f"train.output_dir: {out} already holds checkpoints; use another directory or --resume")
        old = ckpt.read_spec(existing[-1])
        if ckpt.spec_json(old) != ckpt.spec_json(spec):
            raise InputError(f"train.output_dir: {out} holds checkpoints of another model ({existing[-1]}); "
                             f"use another output directory")
        (ShardedRuntime if sharded else AccelerateRuntime).check_format(existing[-1])
    elif resume is True:
        raise InputError(f"--resume: no checkpoints under {out / 'checkpoints'}")

    if tc.tracker:
        import importlib.util

        module = {"tensorboard": "tensorboard", "wandb": "wandb"}[tc.tracker]
        if importlib.util.find_spec(module) is None:
            raise InputError(f"train.tracker: {tc.tracker} is not installed (pip install {module})")
    runtime = ShardedRuntime(run, out) if sharded else AccelerateRuntime(run, out)
    try:
        result = _train(run, runtime, spec, layout, meta, train_eps, held_eps, existing, progress, stop_after_steps,
                        tqdm)
        runtime.wait()  # every rank done before the group goes: Gloo torn down mid-talk aborted a rank at exit once
        return result
    finally:
        runtime.close()


def _train(run, runtime, spec, layout, meta, train_eps, held_eps, existing, progress, stop_after_steps,
           tqdm) -> TrainResult:
    tc = run.train
    out = Path(tc.output_dir)
    main, rank, world = runtime.main, runtime.rank, runtime.world
    if tc.batch_size % world:
        raise InputError(f"train.batch_size: {tc.batch_size} does not split over {world} processes")

    if tc.cpu_threads is not None:
        torch.set_num_threads(tc.cpu_threads)
    torch.manual_seed(tc.seed)  # the same initial weights for the same seed
    model = runtime.wrap(WorldModel(spec))
    trainable = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(trainable, lr=tc.lr, betas=tuple(tc.adam_betas), eps=tc.adam_eps,
                                  weight_decay=tc.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lr_lambda(tc.warmup_steps))
    ema = EMA(model, tc.ema_decay) if tc.ema_decay > 0 else None
    report = shard_report(model, world) if runtime.sharded else None
    step = 0
    if existing:
        step = runtime.load(existing[-1], model=model, optimizer=optimizer, scheduler=scheduler, ema=ema, spec=spec)
        if main:
            print(f"[train] resuming from {existing[-1]} (step {step})", file=sys.stderr)

    train_set = ChunkDataset(run.data.dataset, layout, root=run.data.root, episodes=train_eps,
                             cache=run.data.cache, cache_dir=run.data.cache_dir, video_backend=run.data.video_backend)
    held_set = (ChunkDataset(run.data.dataset, layout, root=run.data.root, episodes=held_eps, cache=run.data.cache,
                             cache_dir=run.data.cache_dir, video_backend=run.data.video_backend)
                if held_eps else None)
    if len(train_set) == 0:
        raise InputError(f"data: no training chunks (episodes {train_eps})")
    rc = run.rollout
    clips = train_set.clips(rc.chunks) if rc.chunks > 1 else None
    if clips is not None and not clips:
        raise InputError(f"rollout.chunks: no training episode has {rc.chunks} chunks")
    schedule = RolloutSchedule(len(train_set), tc.batch_size, rc)
    eval_items = _evaluation_items(held_set, tc.eval_batches * tc.batch_size) if held_set is not None else []
    if runtime.sharded and eval_items and len(eval_items) % world:  # every rank evaluates its rows of each batch
        eval_items = np.resize(eval_items, -(-len(eval_items) // world) * world).tolist()
    if run.data.cache == "memory":
        train_set.preload(num_workers=run.data.num_workers, progress=progress and main)
        if held_set is not None:
            held_set.preload(num_workers=run.data.num_workers, progress=progress and main)

    model, optimizer = runtime.prepare(model, optimizer)
    device = runtime.device
    online = None
    if rc.chunks > 1 and any(s in spec.conditioning.streams for s in REBUILT_STREAMS):
        contact_device = device if rc.device == "auto" else torch.device(rc.device)
        online = OnlineControls.from_dataset(train_set.lerobot.root, spec, info=dataset_info(meta),
                                             resolution=rc.resolution, max_walk_distance=rc.max_walk_distance,
                                             device=contact_device)
        online.rig.renderer, online.rig.gripper  # noqa: B018 - built before the clock starts
    t_wall, t_cpu = time.time(), time.process_time()  # train.max_minutes and the logged times count from here
    if main:
        out.mkdir(parents=True, exist_ok=True)
        save_config(run, out / "config.yaml")
        save_config(spec, out / "model.json")
        if report is not None:
            (out / "sharding.json").write_text(json.dumps(report, indent=1) + "\n")
        if runtime.tracker is not None:
            runtime.tracker.init_trackers("imac_model", config=_flat(run.to_dict()))
    log_rows: list[dict] = read_log(out, upto=step) if main and existing else []
    if main:
        write_log(out, log_rows)
    if log_rows:  # a resumed run: the logged times continue
        t_wall -= log_rows[-1].get("wall_s", 0.0)
    # the run's CPU time so far, summed over its processes (only the main one reads the log)
    cpu_before = float(runtime.all_reduce_sum(torch.tensor(
        [log_rows[-1].get("cpu_s", 0.0) if log_rows else 0.0], dtype=torch.float64, device=device))[0])

    def cpu_seconds() -> float:
        """Process CPU seconds of the run, every process's summed (train.max_cpu_minutes and the log's cpu_s):
        a collective where the run has several processes, so every process calls it at the same steps."""
        mine = torch.tensor([time.process_time() - t_cpu], dtype=torch.float64, device=device)
        return cpu_before + float(runtime.all_reduce_sum(mine)[0])

    def save(at: int) -> Path | None:
        path = runtime.save(out / "checkpoints" / f"step_{at:06d}", model=model, optimizer=optimizer,
                            scheduler=scheduler, ema=ema, spec=spec, run=run, step=at)
        if main:
            ckpt.prune_checkpoints(out, tc.keep_checkpoints)
        return path if main else None

    def evaluate() -> dict:
        if not eval_items:
            return {}
        if runtime.sharded:  # every rank takes part (the forward gathers parameters)
            return {"heldout_loss": heldout_loss(model, held_set, eval_items, tc.batch_size, device,
                                                 runtime.autocast, runtime=runtime)}
        if not main:
            return {}
        return {"heldout_loss": heldout_loss(runtime.unwrap(model), held_set, eval_items, tc.batch_size, device,
                                             runtime.autocast)}

    def emit(row: dict) -> None:
        if not main:
            return
        log_rows.append(row)
        append_log(out, row)
        write_log(out, log_rows, csv_only=True)
        if runtime.tracker is not None:
            runtime.tracker.log({k: v for k, v in row.items() if k != "step"}, step=row["step"])

    model.train()
    if step == 0:
        row = evaluate()
        emit({"step": 0, **row, "wall_s": 0.0, "cpu_s": 0.0})
    bar = tqdm(total=tc.max_steps, initial=step, desc="training", unit="step", disable=not (progress and main))
    loss_of = partial(balanced_loss, runtime=runtime)
    timed = tc.max_minutes is not None or tc.max_cpu_minutes is not None
    window: list[float] = []
    extras: dict[str, list] = {}
    t_window = time.time()
    stopped, last_ckpt, start_step = "max_steps", None, step
    while step < tc.max_steps:
        phase, k, epoch = schedule.at(step)
        streams = ("motion",) if epoch < rc.stage_one_epochs else None  # stage one: motion images alone
        gen = step_generator(tc.seed, step)  # the global batch's draws; every process keeps its rows
        if phase == "chunk":  # an ordinary step, also the clean-reference warm-up of a rollout run
            idx = batch_indices(k, len(train_set), tc.batch_size, tc.seed)[rank::world]
            batch = train_set.batch(idx).to(device)
            with runtime.autocast():
                result = model(batch, generator=gen, streams=streams, rows=(rank, world))
                loss = loss_of(result)
            runtime.backward(loss)
        else:
            idx = batch_indices(k, len(clips), tc.batch_size, tc.seed + 1)[rank::world]
            clip = [train_set.batch([clips[i][r] for i in idx]).to(device) for r in range(rc.chunks)]
            result = rollout_loss(model, clip, online, generator=gen, streams=streams,
                                  commanded_state=rc.reference_state == "commanded",
                                  backward=runtime.backward, autocast=runtime.autocast, rows=(rank, world),
                                  loss_of=loss_of, reference_steps=rc.reference_steps)
            loss = result.loss
            extras.setdefault("chunk_losses", []).append([float(x) for x in result.chunk_losses])
            if result.invalid_depth:
                extras.setdefault("invalid_depth", []).append(float(np.mean(result.invalid_depth)))
        if tc.grad_clip > 0:
            runtime.clip_grad_norm_(trainable, tc.grad_clip)
        optimizer.step()
        scheduler.step()
        optimizer.zero_grad(set_to_none=True)
        step += 1
        if ema is not None:
            ema.update(runtime.unwrap(model), step)
        window.append(float(loss.detach()))
        bar.update(1)
        bar.set_postfix(loss=f"{window[-1]:.4f}")
        timed_out = ((tc.max_minutes is not None and time.time() - t_wall > 60 * tc.max_minutes)
                     or (tc.max_cpu_minutes is not None and cpu_seconds() > 60 * tc.max_cpu_minutes))
        if timed:
            timed_out = runtime.any(timed_out)
        interrupted = stop_after_steps is not None and step - start_step >= stop_after_steps
        done = step >= tc.max_steps or timed_out or interrupted
        if step % tc.log_every == 0 or step % tc.eval_every == 0 or done:
            now = time.time()
            mean_loss = float(np.mean(window))
            if world > 1:  # the mean over processes of their rebalanced losses: the global batch's loss
                mean_loss = float(runtime.all_reduce_sum(torch.tensor([mean_loss], device=device))[0]) / world
            row = {"step": step, "loss": mean_loss, "lr": scheduler.get_last_lr()[0],
                   "steps_per_s": len(window) / max(now - t_window, 1e-9), "epoch": round(schedule.at(step)[2], 4)}
            if rc.stage_one_epochs > 0:
                row["stage"] = 1 if streams is not None else 2
            if clips is not None:
                row["phase"] = "rollout" if phase == "clip" else "warmup"
                if extras.get("chunk_losses"):
                    row["chunk_losses"] = np.mean(extras["chunk_losses"], axis=0).round(6).tolist()
                if extras.get("invalid_depth"):
                    row["invalid_depth"] = round(float(np.mean(extras["invalid_depth"])), 6)
            extras = {}
            if step % tc.eval_every == 0 or done:
                row.update(evaluate())
            row.update(wall_s=round(now - t_wall, 3), cpu_s=round(cpu_seconds(), 3),
                       load=round(os.getloadavg()[0], 2), processes=world)
            emit(row)
            window, t_window = [], time.time()
        if step % tc.checkpoint_every == 0 or done:
            last_ckpt = save(step)
        if timed_out or interrupted:
            stopped = "time" if timed_out else "interrupted"
            break
    bar.close()
    if step == start_step and main:  # nothing to do (already finished)
        last_ckpt = ckpt.list_checkpoints(out)[-1] if ckpt.list_checkpoints(out) else None
    return TrainResult(output_dir=out, step=step, checkpoint=last_ckpt, log=log_rows, stopped=stopped, main=main)


# --------------------------------------------------------------------------- tracker


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v if isinstance(v, (int, float, str, bool)) or v is None else str(v)
    return out

"""Train the world model (``imac-model train``): on ``accelerate``, one process on the CPU or
several GPUs (the global batch split over processes), bf16 where the device has it.

Everything is checked before the first step (config, the dataset's streams, chunk length,
view size). Held-out episodes are never trained on; their flow loss is measured at fixed
times and noise. Checkpoints are written every ``train.checkpoint_every`` steps and at the
end, and a resumed run ends with the same weights as an uninterrupted one (batches and noise
are functions of (seed, step)). With ``rollout.chunks`` R > 1, steps train clips of R chunks
(:mod:`imac_model.pipelines.rollout`). Logs: ``log.jsonl``, ``log.csv``, an optional tracker."""

from __future__ import annotations

import csv
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from imac_data import lerobot_compat as lr
from imac_data.errors import InputError
from imac_model.config import ModelSpec, RunConfig, save_config
from imac_model.data.chunks import ChunkDataset, action_stats, open_metadata, resolve_layout, split_episodes
from imac_model.models import checkpoint as ckpt
from imac_model.models.backbones.build import spatial_multiple, temporal_factor
from imac_model.models.world_model import WorldModel
from imac_model.pipelines.online_controls import CONTACT_STREAMS, OnlineControls
from imac_model.pipelines.rollout import rollout_loss

EVAL_TAUS = (0.1, 0.3, 0.5, 0.7, 0.9)  # fixed times of the held-out loss


@dataclass
class TrainResult:
    output_dir: Path
    step: int
    checkpoint: Path | None
    log: list[dict]
    stopped: str  # "max_steps", "time" (max_minutes / max_cpu_minutes) or "interrupted"


# --------------------------------------------------------------------------- setup


def model_spec(run: RunConfig, meta) -> tuple[ModelSpec, object]:
    """The resolved model of a run on a dataset (checks the dataset against the run)."""
    layout = resolve_layout(lr.dataset_info(meta), run.data, run.conditioning.streams,
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


def step_generator(seed: int, step: int, rank: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(np.random.SeedSequence([seed, step, rank]).generate_state(1)[0]))


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
                 autocast) -> float:
    """Flow loss of fixed held-out chunks at fixed times and noise: comparable across steps."""
    was_training = model.training
    model.eval()
    total, count = 0.0, 0
    for start in range(0, len(items), batch_size):
        idx = items[start:start + batch_size]
        batch = dataset.batch(idx).to(device)
        tau = torch.tensor([EVAL_TAUS[(start + i) % len(EVAL_TAUS)] for i in range(len(idx))])
        gen = torch.Generator().manual_seed(12345 + start)
        with autocast():
            out = model(batch, generator=gen, tau=tau)
        total += float(out.loss) * len(idx)
        count += len(idx)
    model.train(was_training)
    return total / max(count, 1)


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
    from accelerate import Accelerator
    from tqdm.auto import tqdm

    tc = run.train
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
    elif resume is True:
        raise InputError(f"--resume: no checkpoints under {out / 'checkpoints'}")

    if tc.tracker:
        import importlib.util

        module = {"tensorboard": "tensorboard", "wandb": "wandb"}[tc.tracker]
        if importlib.util.find_spec(module) is None:
            raise InputError(f"train.tracker: {tc.tracker} is not installed (pip install {module})")
    precision = tc.mixed_precision
    if precision == "auto":
        precision = "bf16" if torch.cuda.is_available() and torch.cuda.is_bf16_supported() else "no"
    accelerator = Accelerator(mixed_precision=precision, log_with=tc.tracker, project_dir=str(out))
    main = accelerator.is_main_process
    if tc.batch_size % accelerator.num_processes:
        raise InputError(f"train.batch_size: {tc.batch_size} does not split over {accelerator.num_processes} "
                         f"processes")

    if tc.cpu_threads is not None:
        torch.set_num_threads(tc.cpu_threads)
    torch.manual_seed(tc.seed)  # the same initial weights for the same seed
    model = WorldModel(spec)
    trainable = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(trainable, lr=tc.lr, weight_decay=tc.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lr_lambda(tc.warmup_steps))
    ema = EMA(model, tc.ema_decay) if tc.ema_decay > 0 else None
    step = 0
    if existing:
        last = existing[-1]
        ckpt.load_weights_into(model, last / ckpt.WEIGHTS)
        state = ckpt.read_trainer_state(last)
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        step = int(state["step"])
        if ema is not None and (last / ckpt.EMA).is_file():
            ema.shadow = {k: v.float() for k, v in ckpt.read_weights(last / ckpt.EMA).items()}
        if main:
            print(f"[train] resuming from {last} (step {step})", file=sys.stderr)

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
    if run.data.cache == "memory":
        train_set.preload(num_workers=run.data.num_workers, progress=progress and main)
        if held_set is not None:
            held_set.preload(num_workers=run.data.num_workers, progress=progress and main)

    model, optimizer = accelerator.prepare(model, optimizer)
    device = accelerator.device
    online = None
    if rc.chunks > 1 and any(s in spec.conditioning.streams for s in CONTACT_STREAMS):
        contact_device = device if rc.device == "auto" else torch.device(rc.device)
        online = OnlineControls.from_dataset(train_set.lerobot.root, spec, info=lr.dataset_info(meta),
                                             resolution=rc.resolution, max_walk_distance=rc.max_walk_distance,
                                             device=contact_device)
        online.rig.renderer, online.rig.gripper  # noqa: B018 - built before the clock starts
    t_wall, t_cpu = time.time(), time.process_time()  # train.max_minutes and the logged times count from here
    if main:
        out.mkdir(parents=True, exist_ok=True)
        save_config(run, out / "config.yaml")
        save_config(spec, out / "model.json")
        if tc.tracker:
            accelerator.init_trackers("imac_model", config=_flat(run.to_dict()))
    log_rows: list[dict] = _read_log(out / "log.jsonl", upto=step) if main and existing else []
    if main:
        _rewrite_log(out, log_rows)
    if log_rows:  # a resumed run: the logged times continue
        t_wall -= log_rows[-1].get("wall_s", 0.0)
        t_cpu -= log_rows[-1].get("cpu_s", 0.0)

    def save(at: int) -> Path | None:
        accelerator.wait_for_everyone()
        if not main:
            return None
        path = ckpt.save_checkpoint(out / "checkpoints" / f"step_{at:06d}", model=accelerator.unwrap_model(model),
                                    spec=spec, run=run, ema=ema.state() if ema else None,
                                    trainer_state={"optimizer": optimizer.state_dict(),
                                                   "scheduler": scheduler.state_dict(), "step": at})
        ckpt.prune_checkpoints(out, tc.keep_checkpoints)
        return path

    def evaluate() -> dict:
        if not eval_items or not main:
            return {}
        return {"heldout_loss": heldout_loss(accelerator.unwrap_model(model), held_set, eval_items, tc.batch_size,
                                             device, accelerator.autocast)}

    def emit(row: dict) -> None:
        if not main:
            return
        log_rows.append(row)
        with open(out / "log.jsonl", "a") as f:
            f.write(json.dumps(row) + "\n")
        _rewrite_log(out, log_rows, csv_only=True)
        if tc.tracker:
            accelerator.log({k: v for k, v in row.items() if k != "step"}, step=row["step"])

    model.train()
    if step == 0:
        emit({"step": 0, **evaluate(), "wall_s": 0.0, "cpu_s": 0.0})
    bar = tqdm(total=tc.max_steps, initial=step, desc="training", unit="step", disable=not (progress and main))
    rank, world = accelerator.process_index, accelerator.num_processes
    window: list[float] = []
    extras: dict[str, list] = {}
    t_window = time.time()
    stopped, last_ckpt, start_step = "max_steps", None, step
    while step < tc.max_steps:
        phase, k, epoch = schedule.at(step)
        streams = ("motion",) if epoch < rc.stage_one_epochs else None  # stage one: motion images alone
        gen = step_generator(tc.seed, step, rank)
        if phase == "chunk":  # an ordinary step, also the clean-reference warm-up of a rollout run
            idx = batch_indices(k, len(train_set), tc.batch_size, tc.seed)[rank::world]
            batch = train_set.batch(idx).to(device)
            with accelerator.autocast():
                result = model(batch, generator=gen, streams=streams)
            accelerator.backward(result.loss)
        else:
            idx = batch_indices(k, len(clips), tc.batch_size, tc.seed + 1)[rank::world]
            clip = [train_set.batch([clips[i][r] for i in idx]).to(device) for r in range(rc.chunks)]
            result = rollout_loss(model, clip, online, generator=gen, streams=streams,
                                  commanded_state=rc.reference_state == "commanded",
                                  backward=accelerator.backward, autocast=accelerator.autocast)
            extras.setdefault("chunk_losses", []).append([float(x) for x in result.chunk_losses])
            if result.invalid_depth:
                extras.setdefault("invalid_depth", []).append(float(np.mean(result.invalid_depth)))
        if tc.grad_clip > 0:
            accelerator.clip_grad_norm_(trainable, tc.grad_clip)
        optimizer.step()
        scheduler.step()
        optimizer.zero_grad(set_to_none=True)
        step += 1
        if ema is not None:
            ema.update(accelerator.unwrap_model(model), step)
        window.append(float(result.loss.detach()))
        bar.update(1)
        bar.set_postfix(loss=f"{window[-1]:.4f}")
        timed_out = ((tc.max_minutes is not None and time.time() - t_wall > 60 * tc.max_minutes)
                     or (tc.max_cpu_minutes is not None and time.process_time() - t_cpu > 60 * tc.max_cpu_minutes))
        interrupted = stop_after_steps is not None and step - start_step >= stop_after_steps
        done = step >= tc.max_steps or timed_out or interrupted
        if step % tc.log_every == 0 or step % tc.eval_every == 0 or done:
            now = time.time()
            row = {"step": step, "loss": float(np.mean(window)), "lr": scheduler.get_last_lr()[0],
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
            row.update(wall_s=round(now - t_wall, 3), cpu_s=round(time.process_time() - t_cpu, 3),
                       load=round(os.getloadavg()[0], 2))
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
    if tc.tracker:
        accelerator.end_training()
    return TrainResult(output_dir=out, step=step, checkpoint=last_ckpt, log=log_rows, stopped=stopped)


# --------------------------------------------------------------------------- logs


LOG_FIELDS = ("step", "loss", "heldout_loss", "lr", "steps_per_s", "wall_s", "cpu_s", "load", "epoch")


def _read_log(path: Path, upto: int) -> list[dict]:
    if not path.is_file():
        return []
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in rows if r["step"] <= upto]


def _rewrite_log(out: Path, rows: list[dict], csv_only: bool = False) -> None:
    """log.csv from the rows (and log.jsonl unless ``csv_only``): a resumed run drops the
    rows after its checkpoint, so the logs hold one row per step."""
    out.mkdir(parents=True, exist_ok=True)
    if not csv_only:
        (out / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    with open(out / "log.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=LOG_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            writer.writerow(r)


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v if isinstance(v, (int, float, str, bool)) or v is None else str(v)
    return out

"""Train the world model (``imac-model train``): one loop, fed by a data source (:mod:`.sources`): the
LeRobot dataset here, or a tensor pack on a machine with torch and numpy alone (the GPU machine). One
process on the CPU or a GPU, several under ``torchrun`` / ``accelerate launch`` (DDP, the global batch split
over them), or sharded (``train.sharding.strategy: fsdp2``, :mod:`.sharding`); bf16 where the device has it.

Everything is checked before the first step (config, the data's streams, chunk length, view size).
Held-out chunks are never trained on; their flow loss is measured at fixed times and noise. Checkpoints
are written every ``train.checkpoint_every`` steps and at the end, and a resumed run ends with the same
weights as an uninterrupted one (batches and noise are functions of (seed, step)). The budget is
``train.max_steps``, ``max_minutes`` (wall) or ``max_cpu_minutes``. With ``rollout.chunks`` R > 1,
steps train clips of R chunks (:mod:`imac_model.pipelines.rollout`). ``train.init`` starts from another
run's weights; ``train.compile`` compiles the U-Net's trunk. Logs: ``log.jsonl``, ``log.csv``, an
optional tracker."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

try:
    from tqdm.auto import tqdm
except ImportError:  # the GPU machine has torch and numpy alone: no progress bar there
    tqdm = None

from imac_data.errors import InputError
from imac_model.config import ModelSpec, RunConfig, save_config
from imac_model.models import checkpoint as ckpt
from imac_model.models.world_model import WorldModel
from imac_model.modes import CONTACT_STREAMS, REBUILT_STREAMS
from imac_model.pipelines.rollout import rollout_loss
from imac_model.training.archive import run_name, unpack_checkpoint
from imac_model.training.log import append_log, read_log, write_log
from imac_model.training.runtime import LocalRuntime
from imac_model.training.sharding import ShardedRuntime, shard_report
from imac_model.training.sources import open_source

EVAL_TAUS = (0.1, 0.3, 0.5, 0.7, 0.9)  # fixed times of the held-out loss


@dataclass
class TrainResult:
    output_dir: Path
    step: int
    checkpoint: Path | None
    log: list[dict]
    stopped: str  # "max_steps", "time" (max_minutes / max_cpu_minutes) or "interrupted"
    main: bool = True  # the process that writes the logs (rank 0)


# --------------------------------------------------------------------------- pieces


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


def step_generator(seed: int, step: int, device: torch.device | str = "cpu") -> torch.Generator:
    """The draws of a step's whole global batch (every process slices its rows from them); on a GPU
    they are drawn there."""
    seed = int(np.random.SeedSequence([seed, step, 0]).generate_state(1)[0])
    return torch.Generator(device=device).manual_seed(seed)


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
        params = {k: p for k, p in model.named_parameters() if k in self.shadow}
        if any(self.shadow[k].device != p.device for k, p in params.items()):  # made before the model moved (prepare)
            self.shadow = {k: s.to(params[k].device) for k, s in self.shadow.items()}
        named = [(self.shadow[k], p.detach().float()) for k, p in params.items()]
        shadow, params = [s for s, _ in named], [p for _, p in named]
        torch._foreach_mul_(shadow, d)  # one fused update: a loop over tensors launches kernels per parameter
        torch._foreach_add_(shadow, params, alpha=1 - d)

    def state(self) -> dict[str, torch.Tensor]:
        return self.shadow


@torch.no_grad()
def heldout_loss(model: WorldModel, source, items: list[int], batch_size: int, device, autocast,
                 runtime=None) -> float:
    """Flow loss of fixed held-out chunks (``items``, positions in the source's held-out set) at fixed
    times and noise: comparable across steps and runs. Item i of the list is measured at time
    ``EVAL_TAUS[i % 5]``, each batch's noise from seed ``12345 + its start``. With a sharded
    ``runtime`` every rank takes its rows of each batch (``len(items)`` a multiple of the world size)
    and the batch's masked mean is the global one."""
    rank, world = (runtime.rank, runtime.world) if runtime is not None and runtime.sharded else (0, 1)
    was_training = model.training
    model.eval()
    total, count = 0.0, 0
    for start in range(0, len(items), batch_size):
        idx = items[start:start + batch_size]
        batch = source.held_batch(idx[rank::world]).to(device)
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


def evaluation_items(n_held: int, n: int) -> list[int]:
    """``n`` held-out positions spread evenly over the ``n_held`` (all of them when fewer)."""
    if n_held == 0:
        return []
    return sorted(set(np.linspace(0, n_held - 1, min(n, n_held)).round().astype(int).tolist()))


def compile_trunk(model: WorldModel, backend: str = "inductor"):
    """Put a ``torch.compile``d U-Net trunk in the backbone's place and return it; the backbone
    must have a ``trunk`` (tensors in, tensor out: the U-Net). Fusing its group norms, modulations
    and SiLUs is what a small pixel-space U-Net needs on a GPU (docs/ranking.md, "The GPU preset")."""
    backbone = model.backbone
    if not callable(getattr(backbone, "trunk", None)):
        raise InputError(f"compile: the {type(backbone).__name__} backbone has no trunk to compile (the U-Net has)")
    compiled = torch.compile(backbone.trunk, backend=backend)
    backbone.trunk = compiled  # an instance attribute: it shadows the method and leaves the weights' names alone
    return compiled


def _eager(model: WorldModel):
    """The backbone's own trunk back (held-out losses run eager: other shapes, no gradient,
    not worth a compile); returns the compiled one to put back."""
    return model.backbone.__dict__.pop("trunk", None)


def _init_checkpoint(init: str | Path, spec: ModelSpec, scratch: Path) -> Path:
    """The checkpoint ``init`` names (a run archive is unpacked into ``scratch``), refused unless it shows
    the run's views and mode; weights of another shape are refused when they load (the flow's settings may
    differ: they are training's)."""
    path = unpack_checkpoint(init, scratch) if run_name(init) and Path(init).is_file() else ckpt.resolve_checkpoint(init)
    theirs = ckpt.read_spec(path)
    for name, of in (("conditioning.mode", lambda s: s.conditioning.mode), ("backbone.kind", lambda s: s.backbone.kind),
                     ("views", lambda s: s.views), ("view size", lambda s: (s.view_height, s.view_width)),
                     ("chunk", lambda s: s.chunk), ("action_dim", lambda s: s.action_dim)):
        if of(theirs) != of(spec):
            raise InputError(f"train.init {path}: its {name} is {of(theirs)}, this run's {of(spec)}")
    return path


def _load_init(model: WorldModel, path: Path) -> list[str]:
    """Load the checkpoint at ``path`` into ``model`` (its own loader: EMA weights where it kept them apart).
    Layers the checkpoint lacks may stay as built only where they are all zeros (a control stream's
    zero-initialised projection, added as the paper adds streams: the model starts as the checkpoint's);
    returns their names. Any other difference is an :class:`InputError` naming the keys."""
    theirs = ckpt.load_world_model(path)[0].state_dict()
    ours = model.state_dict()
    added = sorted(k for k in ours if k not in theirs)
    extra, live = sorted(k for k in theirs if k not in ours), [k for k in added if ours[k].count_nonzero()]
    if extra or live:
        raise InputError(f"train.init {path}: its weights do not fit this run's model: "
                         + "; ".join(f"{what}: {keys[:6]}" for what, keys in
                                     (("this run lacks", extra), ("the checkpoint lacks", live)) if keys))
    try:
        model.load_state_dict(theirs, strict=False)
    except RuntimeError as e:  # a layer of another shape
        raise InputError(f"train.init {path}: its weights do not fit this run's model: {e}") from None
    return added


def make_runtime(run: RunConfig, out: Path):
    """The runtime ``run`` asks for: sharded (``train.sharding.strategy``), else data-parallel or one process."""
    return ShardedRuntime(run, out) if run.train.sharding.strategy != "none" else LocalRuntime(run, out)


# --------------------------------------------------------------------------- the loop


def train(run: RunConfig, *, resume: bool | None = None, progress: bool = True,
          stop_after_steps: int | None = None) -> TrainResult:
    """Train ``run``; ``resume`` None = continue when the output directory has checkpoints
    of the same model, True = require that, False = refuse a directory with checkpoints.
    ``stop_after_steps`` interrupts the run (with a checkpoint) after that many steps."""
    tc = run.train
    source = open_source(run)
    spec = source.spec
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
    if tc.tracker and importlib.util.find_spec(tc.tracker) is None:  # tensorboard and wandb are their modules' names
        raise InputError(f"train.tracker: {tc.tracker} is not installed (pip install {tc.tracker})")
    runtime = make_runtime(run, out)
    if existing:
        runtime.check_format(existing[-1])
    try:
        with tempfile.TemporaryDirectory() as scratch:  # where a run archive's checkpoint is unpacked (train.init)
            result = _train(run, runtime, source, spec, existing, progress, stop_after_steps, Path(scratch))
        runtime.wait()  # every rank done before the group goes: Gloo torn down mid-talk aborted a rank at exit once
        return result
    finally:
        runtime.close()


def _train(run: RunConfig, runtime, source, spec: ModelSpec, existing: list[Path], progress: bool,
           stop_after_steps: int | None, scratch: Path) -> TrainResult:
    tc, rc = run.train, run.rollout
    out = Path(tc.output_dir)
    main, rank, world = runtime.main, runtime.rank, runtime.world
    if tc.batch_size % world:
        raise InputError(f"train.batch_size: {tc.batch_size} does not split over {world} processes")
    init = _init_checkpoint(tc.init, spec, scratch) if tc.init and not existing else None

    if tc.cpu_threads is not None:
        torch.set_num_threads(tc.cpu_threads)
    torch.manual_seed(tc.seed)  # the same initial weights for the same seed
    model = WorldModel(spec)
    added = _load_init(model, init) if init is not None else []  # before sharding: the whole weights go in
    model = runtime.wrap(model)
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

    source.load(runtime.device, progress and main)
    clips = source.clips(rc.chunks) if rc.chunks > 1 else None
    if clips is not None and not clips:
        raise InputError(f"rollout.chunks: no training episode has {rc.chunks} chunks")
    streams_in = spec.conditioning.streams
    contact = tuple(s for s in streams_in if s in CONTACT_STREAMS)
    kept = [s for s in streams_in if s in REBUILT_STREAMS and (rc.contact == "recorded" or s not in contact)]
    if rc.chunks > 1 and rc.reference_steps > 0 and kept and main:
        # measured: motion+contact stopped drawing the lift this way (docs/ranking.md, "The GPU preset")
        print(f"[train] warning: rollout from {rc.reference_steps} sampler steps keeps the recorded {kept} images, "
              f"which then describe a scene the sampled reference may not show", file=sys.stderr)
    schedule = RolloutSchedule(source.n_train, tc.batch_size, rc)
    eval_items = evaluation_items(source.n_held, tc.eval_batches * tc.batch_size)
    if runtime.sharded and eval_items and len(eval_items) % world:  # every rank evaluates its rows of each batch
        eval_items = np.resize(eval_items, -(-len(eval_items) // world) * world).tolist()

    model, optimizer = runtime.prepare(model, optimizer)
    device = runtime.device
    compiled = compile_trunk(runtime.unwrap(model)) if tc.compile else None
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
        if not eval_items or not (main or runtime.sharded):  # sharded: every rank takes part (the forward gathers)
            return {}
        trunk = _eager(runtime.unwrap(model))  # other shapes, no gradient: not worth a compile
        loss = heldout_loss(model if runtime.sharded else runtime.unwrap(model), source, eval_items, tc.batch_size,
                            device, runtime.autocast, runtime=runtime)
        if trunk is not None:
            runtime.unwrap(model).backbone.trunk = trunk
        return {"heldout_loss": loss}

    def emit(row: dict) -> None:
        if not main:
            return
        log_rows.append(row)
        append_log(out, row)
        write_log(out, log_rows, csv_only=True)
        if runtime.tracker is not None:
            runtime.tracker.log({k: v for k, v in row.items() if k != "step"}, step=row["step"])

    def forward_backward(step: int, phase: str, k: int, streams) -> tuple[torch.Tensor, dict]:
        gen = step_generator(tc.seed, step, device if device.type == "cuda" else "cpu")  # every process keeps its rows
        if phase == "chunk":  # an ordinary step, also the clean-reference warm-up of a rollout run
            idx = batch_indices(k, source.n_train, tc.batch_size, tc.seed)[rank::world]
            batch = source.train_batch(idx).to(device)
            with runtime.autocast():
                result = model(batch, generator=gen, streams=streams, rows=(rank, world))
                loss = loss_of(result)
            runtime.backward(loss)
            return loss, {}
        idx = batch_indices(k, len(clips), tc.batch_size, tc.seed + 1)[rank::world]
        items = [clips[i] for i in idx]
        clip = [source.train_batch([c[r] for c in items]).to(device) for r in range(rc.chunks)]
        inputs = source.rollout_inputs(items, contact)
        result = rollout_loss(model, clip, inputs.get("online"), generator=gen, streams=streams,
                              commanded_state=rc.reference_state == "commanded", backward=runtime.backward,
                              autocast=runtime.autocast, rows=(rank, world), loss_of=loss_of,
                              reference_steps=rc.reference_steps, stored_contact=rc.contact == "recorded",
                              rebuild=inputs.get("rebuild"))
        extra = {"chunk_losses": [float(x) for x in result.chunk_losses]}
        if result.invalid_depth:
            extra["invalid_depth"] = float(np.mean(result.invalid_depth))
        return result.loss, extra

    model.train()
    if step == 0:
        row = evaluate()
        emit({"step": 0, **row, "wall_s": 0.0, "cpu_s": 0.0, **({"init_added": added} if added else {})})
    bar = tqdm(total=tc.max_steps, initial=step, desc="training", unit="step",
               disable=not (progress and main)) if tqdm is not None else None
    loss_of = partial(balanced_loss, runtime=runtime)
    timed = tc.max_minutes is not None or tc.max_cpu_minutes is not None
    window: list[float] = []
    extras: dict[str, list] = {}
    t_window = time.time()
    stopped, last_ckpt, start_step = "max_steps", None, step
    samples = log_rows[-1].get("samples", 0) if log_rows else 0  # a resumed run counts on
    device_name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    while step < tc.max_steps:
        phase, k, epoch = schedule.at(step)
        streams = ("motion",) if epoch < rc.stage_one_epochs else None  # stage one: motion images alone
        try:
            loss, extra = forward_backward(step, phase, k, streams)
        except Exception as error:  # noqa: BLE001 - a compiler that fails on this machine: eager, said once
            if compiled is None or step > start_step:
                raise
            compiled = None
            _eager(runtime.unwrap(model))
            optimizer.zero_grad(set_to_none=True)
            if main:
                print(f"[train] torch.compile failed, training eager: {type(error).__name__}: {error}"[:2000],
                      file=sys.stderr)
            loss, extra = forward_backward(step, phase, k, streams)
        for key, value in extra.items():
            extras.setdefault(key, []).append(value)
        if tc.grad_clip > 0:
            runtime.clip_grad_norm_(trainable, tc.grad_clip)
        optimizer.step()
        scheduler.step()
        optimizer.zero_grad(set_to_none=True)
        step += 1
        if ema is not None:
            ema.update(runtime.unwrap(model), step)
        samples += tc.batch_size * (rc.chunks if phase == "clip" else 1)  # chunks trained, every process's
        window.append(float(loss.detach()))
        if bar is not None:
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
            row.update(wall_s=round(now - t_wall, 3), cpu_s=round(cpu_seconds(), 3), samples=samples,
                       load=round(os.getloadavg()[0], 2), processes=world, device=device_name)
            if tc.compile:
                row["compiled"] = compiled is not None
            emit(row)
            window, t_window = [], time.time()
        if step % tc.checkpoint_every == 0 or done:
            last_ckpt = save(step)
        if timed_out or interrupted:
            stopped = "time" if timed_out else "interrupted"
            break
    if bar is not None:
        bar.close()
    if step == start_step and main:  # nothing to do (already finished)
        last_ckpt = ckpt.list_checkpoints(out)[-1] if ckpt.list_checkpoints(out) else None
        if last_ckpt is None:  # no time to train at all: the weights it started from, as a checkpoint
            last_ckpt = save(step)
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

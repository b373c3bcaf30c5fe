"""Training from a tensor pack: the GPU preset's training, on a machine that has torch and numpy
and nothing else of ours (no LeRobot, MuJoCo, Open3D or diffusers).

Here, on the CPU, :func:`export_pack` writes a run's decoded training and held-out chunks (the
chunk cache the benchmark's ``decode`` stage made) into one LZMA-compressed ``.npz`` with the model's
spec; the control rows the mosaic duplicates are stored once. On the GPU machine
:func:`train_pack` trains one conditioning mode from it for a wall-clock budget and writes a
checkpoint that :func:`imac_model.models.checkpoint.load_world_model` reads back here, with
its log. Draws are a function of (seed, step), as in :mod:`.train`; the held-out loss is measured
at fixed times and noise. ``docs/ranking.md`` ("The GPU preset") has the commands::

    python -m imac_model.training.pack train --pack ranking_pack.npz --mode motion+contact \\
        --minutes 2.5 --output OUT/motion_contact
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError
from imac_model.config import CONTACT_STREAMS, REBUILT_STREAMS, ModelSpec, parse
from imac_model.data.batch import ChunkBatch
from imac_model.models.checkpoint import (
    load_world_model,
    read_spec,
    resolve_checkpoint,
    save_checkpoint,
    weights_sha256,
)
from imac_model.models.world_model import WorldModel
from imac_model.pipelines.packed_contact import GEOMETRY_KEY, PackedContact
from imac_model.pipelines.rollout import rollout_loss
from imac_model.training.archive import run_name, unpack_checkpoint
from imac_model.training.log import write_log
from imac_model.training.pace import Pace, report_progress

EVAL_TAUS = (0.1, 0.3, 0.5, 0.7, 0.9)  # fixed times of the held-out loss (as the trainer's)
SPEC_KEY = "spec_json"
REFERENCE_FOLLOWS = "reference_follows"  # see _shared_references


# --------------------------------------------------------------------------- the pack


def pack_arrays(items: list[dict], held_out: list[bool], spec: ModelSpec,
                geometry: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Chunk items (``ChunkDataset`` items, every control stream) -> a pack's arrays; ``held_out``
    flags the held-out episodes' items. Controls keep their top row (the mosaic duplicates it).
    ``geometry``: the items' contact geometry (:mod:`imac_model.pipelines.packed_contact`), so the
    pack's trainer can rebuild contact images from its own references."""
    h = spec.view_height
    arrays = {
        "reference": np.stack([it["reference"].numpy() for it in items]),
        "future": np.stack([it["future"].numpy() for it in items]),
        "future_valid": np.stack([it["future_valid"].numpy() for it in items]),
        "actions": np.stack([it["actions"].numpy() for it in items]).astype(np.float32),
        "episode_index": np.array([int(it["episode_index"]) for it in items]),
        "held_out": np.asarray(held_out, dtype=bool),
        SPEC_KEY: np.array(json.dumps(spec.to_dict())),
    }
    for key in [k for k in items[0] if k.startswith("control.")]:  # every stream the items carry, derived ones too
        arrays[key] = np.stack([it[key][:, :, :h].numpy() for it in items])
    arrays.update(geometry or {})
    return _shared_references(arrays)


def _shared_references(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Keep only the references that are not the previous chunk's last future frame (a chunk of an
    episode usually starts where the one before it ended): ``reference_follows`` flags the others,
    which :class:`Pack` takes back from ``future``. At 4 chunks an episode three quarters of the references
    go: 1.6 MB of a loan's 64 MiB."""
    ref, future, episode = arrays["reference"], arrays["future"], arrays["episode_index"]
    follows = np.zeros(len(ref), dtype=bool)
    if len(ref) > 1:
        follows[1:] = (episode[1:] == episode[:-1]) & (ref[1:] == future[:-1, -1]).reshape(len(ref) - 1, -1).all(1)
    return {**arrays, "reference": ref[~follows], REFERENCE_FOLLOWS: follows}


def _references(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """Every chunk's reference frame back from :func:`_shared_references`' form (or a pack without it)."""
    if REFERENCE_FOLLOWS not in arrays:
        return arrays["reference"]
    follows = np.asarray(arrays[REFERENCE_FOLLOWS], dtype=bool)
    stored, future = arrays["reference"], arrays["future"]
    if len(stored) != int((~follows).sum()) or (len(follows) and follows[0]):
        raise InputError(f"pack: {len(stored)} stored reference frames for {int((~follows).sum())} chunks that "
                         f"need one; the pack is damaged")
    ref = np.empty((len(follows), *stored.shape[1:]), dtype=stored.dtype)
    ref[~follows] = stored
    ref[follows] = future[np.flatnonzero(follows) - 1, -1]
    return ref


def export_pack(items: list[dict], held_out: list[bool], spec: ModelSpec, path: str | Path,
                geometry: dict[str, np.ndarray] | None = None) -> Path:
    """:func:`pack_arrays` written as one ``.npz``, atomically."""
    return write_pack(pack_arrays(items, held_out, spec, geometry), path)


def write_pack(arrays: dict[str, np.ndarray], path: str | Path) -> Path:
    """A pack's arrays as one ``.npz`` whose members are LZMA-compressed, written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    # an .npz whose members are LZMA-compressed: about 0.6 of deflate's size, which decides how many rollouts a GPU
    # loan's 64 MiB carry holds; np.load reads it as any .npz
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_LZMA) as zf:
        for name, array in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(array), allow_pickle=False)
    tmp.replace(path)
    return path


class Pack:
    """A pack's tensors on one device (uint8 frames, float actions) and its spec."""

    def __init__(self, path: str | Path, device: torch.device | str = "cpu"):
        with np.load(path) as data:
            self._load({k: data[k] for k in data.files}, device)

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], device: torch.device | str = "cpu") -> Pack:
        """A pack held in memory (:func:`pack_arrays`), never written."""
        pack = cls.__new__(cls)
        pack._load(arrays, device)
        return pack

    def _load(self, arrays: dict[str, np.ndarray], device) -> None:
        self.spec = parse(ModelSpec, json.loads(str(arrays[SPEC_KEY])), "")
        arrays = {**arrays, "reference": _references(arrays)}
        self.tensors = {k: torch.from_numpy(np.asarray(v)).to(device) for k, v in arrays.items()
                        if k not in (SPEC_KEY, REFERENCE_FOLLOWS, GEOMETRY_KEY)}
        # the contact geometry's settings (packs written before 2026-11-29 have none)
        self.geometry = json.loads(str(arrays[GEOMETRY_KEY])) if GEOMETRY_KEY in arrays else None
        held = self.tensors.pop("held_out").bool()
        self.train = torch.nonzero(~held).flatten()
        self.heldout = torch.nonzero(held).flatten()
        # each chunk's episode's first chunk (the pack keeps an episode's chunks together, in time order)
        episode = self.tensors["episode_index"]
        begins = torch.ones_like(episode, dtype=torch.bool)
        begins[1:] = episode[1:] != episode[:-1]
        position = torch.arange(len(episode), device=episode.device)
        self.first_chunk = torch.cummax(torch.where(begins, position, 0), dim=0).values

    def clips(self, length: int) -> torch.Tensor:
        """``(n, length)`` indices of every run of ``length`` consecutive training chunks of one
        episode (the pack keeps each episode's chunks in time order, as ``ChunkDataset.clips``)."""
        episode = self.tensors["episode_index"][self.train]
        starts = torch.arange(max(len(self.train) - length + 1, 0), device=episode.device)
        same = torch.stack([episode[starts + r] == episode[starts] for r in range(length)]).all(dim=0)
        first = starts[same]
        return self.train[first[:, None] + torch.arange(length, device=first.device)]

    def batch(self, index: torch.Tensor, streams: tuple[str, ...]) -> ChunkBatch:
        """Float mosaics in [0, 1], controls duplicated back into both rows; each chunk's
        episode's first frame."""
        t = self.tensors
        controls = {s: torch.cat([t[f"control.{s}"][index]] * 2, dim=-2).float() / 255.0 for s in streams}
        return ChunkBatch(reference=t["reference"][index].float() / 255.0, actions=t["actions"][index],
                          controls=controls, future=t["future"][index].float() / 255.0,
                          future_valid=t["future_valid"][index],
                          first_frame=t["reference"][self.first_chunk[index]].float() / 255.0)


def spec_for_mode(spec: ModelSpec, mode: str, *, focus_weight: float | None = None,
                  first_frame: bool | None = None, dropout: float | None = None,
                  scene_warp: bool | None = None, reference_noise: float | None = None) -> ModelSpec:
    """The pack's spec with another conditioning mode (and, for an ablation, another
    ``flow.focus_weight``, ``flow.reference_noise``, ``conditioning.first_frame``, ``dropout`` or ``scene_warp``)."""
    data = spec.to_dict()
    data["conditioning"]["mode"] = mode
    if scene_warp is not None:
        data["conditioning"]["scene_warp"] = bool(scene_warp)
    if focus_weight is not None:
        data["flow"]["focus_weight"] = float(focus_weight)
    if reference_noise is not None:
        data["flow"]["reference_noise"] = float(reference_noise)
    if first_frame is not None:
        data["conditioning"]["first_frame"] = bool(first_frame)
    if dropout is not None:
        data["conditioning"]["dropout"] = float(dropout)
    return parse(ModelSpec, data, "")


# --------------------------------------------------------------------------- training


def fast_kernels() -> None:
    """TF32 matrix products and cuDNN's autotuned convolutions, as the GPU preset trains."""
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True
    torch.backends.cudnn.benchmark = True


def _generator(seed: int, step: int, device) -> torch.Generator:
    return torch.Generator(device=device).manual_seed(int(np.random.SeedSequence([seed, step, 0]).generate_state(1)[0]))


@torch.no_grad()
def heldout_loss(model: WorldModel, pack: Pack, streams: tuple[str, ...], batch_size: int, seed: int) -> float:
    """The flow loss over the held-out chunks at :data:`EVAL_TAUS`, with fixed noise."""
    model.eval()
    losses = []
    for start in range(0, len(pack.heldout), batch_size):
        index = pack.heldout[start:start + batch_size]
        batch = pack.batch(index, streams)
        for j, tau in enumerate(EVAL_TAUS):
            g = _generator(seed, 10_000_000 + 1000 * start + j, index.device)
            tau_t = torch.full((len(index),), tau, device=index.device)
            losses.append(float(model(batch, generator=g, tau=tau_t, streams=streams or None).loss))
    model.train()
    return float(np.mean(losses)) if losses else float("nan")


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
    path = unpack_checkpoint(init, scratch) if run_name(init) and Path(init).is_file() else resolve_checkpoint(init)
    theirs = read_spec(path)
    for name, of in (("conditioning.mode", lambda s: s.conditioning.mode), ("backbone.kind", lambda s: s.backbone.kind),
                     ("views", lambda s: s.views), ("view size", lambda s: (s.view_height, s.view_width)),
                     ("chunk", lambda s: s.chunk), ("action_dim", lambda s: s.action_dim)):
        if of(theirs) != of(spec):
            raise InputError(f"init {path}: its {name} is {of(theirs)}, this run's {of(spec)}")
    return path


def _load_init(model: WorldModel, path: Path) -> list[str]:
    """Load the checkpoint at ``path`` into ``model`` (its own loader: EMA weights where it kept them apart).
    Layers the checkpoint lacks may stay as built only where they are all zeros (a control stream's
    zero-initialised projection, added as the paper adds streams: the model starts as the checkpoint's);
    returns their names. Any other difference is an :class:`InputError` naming the keys."""
    theirs = load_world_model(path)[0].state_dict()
    ours = model.state_dict()
    added = sorted(k for k in ours if k not in theirs)
    extra, live = sorted(k for k in theirs if k not in ours), [k for k in added if ours[k].count_nonzero()]
    if extra or live:
        raise InputError(f"init {path}: its weights do not fit this run's model: "
                         + "; ".join(f"{what}: {keys[:6]}" for what, keys in
                                     (("this run lacks", extra), ("the checkpoint lacks", live)) if keys))
    try:
        model.load_state_dict(theirs, strict=False)
    except RuntimeError as e:  # a layer of another shape
        raise InputError(f"init {path}: its weights do not fit this run's model: {e}") from None
    return added


def train_pack(pack: Pack, mode: str, output: str | Path, *, minutes: float, batch_size: int = 128,
               lr: float = 6e-4, warmup: int = 200, ema_decay: float = 0.999, seed: int = 0, eval_every: int = 500,
               log_every: int = 50, focus_weight: float | None = None, rollout_chunks: int = 1,
               first_frame: bool | None = None, dropout: float | None = None, scene_warp: bool | None = None,
               reference_noise: float | None = None, rollout_reference_steps: int = 0, compile: bool = False,
               init: str | Path | None = None, max_samples: int | None = None, report: str | Path | None = None,
               pace_with: str | Path | None = None, rebuild_contact: bool = False, progress=print) -> dict:
    """Train ``mode`` on the pack's training chunks for ``minutes`` of wall time; write the
    EMA weights (float16, so a 5 M-parameter model is an 11 MB file) as a checkpoint under
    ``output/checkpoints/`` and the log, its summary last, as ``output/log.jsonl``. Returns the summary.

    ``rollout_chunks`` R > 1: training-time rollout (:func:`imac_model.pipelines.rollout.rollout_loss`)
    over clips of R consecutive chunks, ``batch_size // R`` clips a step; chunk r > 1 starts from the
    model's own estimate of chunk r-1's last frame and keeps its recorded contact images; with
    ``rebuild_contact`` they are painted anew from that frame's depth and the pack's contact geometry
    (:class:`~imac_model.pipelines.packed_contact.PackedContact`), as the CPU trainer rebuilds them with its
    renderer. With ``rollout_reference_steps`` k > 0 chunk r starts from k sampler steps instead
    (``rollout.reference_steps``). ``compile``: train through :func:`compile_trunk`; the first step's
    compilation counts in the budget, and the log's ``first_step_s`` says how long it took.
    ``init``: a checkpoint (a run directory: its latest; a run archive, :mod:`.archive`: its own) of the same mode
    and architecture whose weights start the run, so training goes on over several loans; the optimizer starts
    afresh. A control stream the checkpoint lacks starts at its zero projection (``init_added`` in the summary).
    ``max_samples``: stop as well once this many samples are trained, so that runs of different speeds sharing a
    GPU get equal budgets in samples (the one that stops first leaves the GPU to the others). ``report``: a progress
    file this run keeps its samples in; ``pace_with``: another run's, which this run never gets more than a step
    ahead of, stopping at its final count (:mod:`.pace`: equal samples, and the waits go to the other run)."""
    device = pack.tensors["reference"].device
    spec = spec_for_mode(pack.spec, mode, focus_weight=focus_weight, first_frame=first_frame, dropout=dropout,
                         scene_warp=scene_warp, reference_noise=reference_noise)
    streams = spec.conditioning.streams
    missing = [s for s in streams if f"control.{s}" not in pack.tensors]
    if missing:
        raise InputError(f"the pack carries no {missing} stream(s) (it has "
                         f"{sorted(k[len('control.'):] for k in pack.tensors if k.startswith('control.'))})")
    if eval_every <= 0 or eval_every % log_every:
        raise InputError(f"eval_every {eval_every} must be a positive multiple of log_every {log_every}")
    if warmup < 0:
        raise InputError(f"warmup: must be >= 0 (got {warmup})")
    if rollout_reference_steps < 0:
        raise InputError(f"rollout_reference_steps: must be >= 0 (got {rollout_reference_steps})")
    if max_samples is not None and max_samples < 1:
        raise InputError(f"max_samples: must be >= 1 (got {max_samples})")
    packed = None
    if rebuild_contact:
        if rollout_chunks < 2 or not any(s in CONTACT_STREAMS for s in streams):
            raise InputError(f"rebuild_contact: only a rollout (rollout_chunks > 1, got {rollout_chunks}) of a mode "
                             f"with contact images ({mode}: {list(streams)}) rebuilds them")
        packed = PackedContact.from_pack(pack)
        if tuple(packed.views) != tuple(pack.spec.views):
            raise InputError(f"the pack's contact geometry is of views {list(packed.views)}, its model's "
                             f"{list(pack.spec.views)}")
    kept = [s for s in streams if s in REBUILT_STREAMS and not (packed is not None and s in CONTACT_STREAMS)]
    if rollout_chunks > 1 and rollout_reference_steps > 0 and kept:
        # measured: motion+contact stopped drawing the lift this way (the GPU runs' record,
        # benchmarks/results/ranking_gpu/README.md, "The sixth GPU run")
        warnings.warn(f"rollout from {rollout_reference_steps} sampler steps keeps the recorded {kept} images, which "
                      "then describe a scene the sampled reference may not show (docs/ranking.md)", stacklevel=2)
    with tempfile.TemporaryDirectory() as scratch:  # where a run archive's checkpoint is unpacked to load it
        init_path = _init_checkpoint(init, spec, Path(scratch)) if init is not None else None
        init_sha256 = weights_sha256(init_path) if init_path is not None else None  # of the weights loaded
        torch.manual_seed(seed)
        model = WorldModel(spec)
        added = _load_init(model, init_path) if init_path is not None else []
    init_label = None if init is None else str(init if Path(init).is_file() else init_path)
    model = model.to(device).train()
    compiled = compile_trunk(model) if compile else None
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr)
    ema = [p.detach().float().clone() for p in params]
    autocast = torch.autocast("cuda", dtype=torch.bfloat16) if device.type == "cuda" else torch.autocast(
        "cpu", enabled=False)
    clips = pack.clips(rollout_chunks) if rollout_chunks > 1 else None
    if clips is not None and (len(clips) == 0 or batch_size < rollout_chunks):
        raise InputError(f"rollout_chunks {rollout_chunks}: {len(clips)} training clips of that length, batch "
                         f"{batch_size}; a step needs at least one clip")
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    log = []
    t0, step, samples, first_step_s, compile_error = time.time(), 0, 0, None, None
    deadline = t0 + 60.0 * minutes
    pace = Pace(pace_with) if pace_with is not None else None
    if report is not None:
        report_progress(report, 0)
    n = len(pack.train)

    invalid_depth: list[float] = []  # per rebuilt chunk: its reference's share of invalid depth

    def forward_backward(step: int) -> tuple[torch.Tensor, int]:
        g = _generator(seed, step, device)
        opt.zero_grad(set_to_none=True)
        if clips is None:
            index = pack.train[torch.randint(n, (batch_size,), generator=g, device=device)]
            with autocast:
                loss = model(pack.batch(index, streams), generator=g, streams=streams or None).loss
            loss.backward()
            return loss, batch_size
        # backward runs per chunk inside, so memory stays that of one chunk
        index = clips[torch.randint(len(clips), (batch_size // rollout_chunks,), generator=g, device=device)]
        clip = [pack.batch(index[:, r], streams) for r in range(rollout_chunks)]
        rebuild = None if packed is None else (lambda r, reference: packed.controls(
            reference, index[:, r], [s for s in streams if s in CONTACT_STREAMS]))
        result = rollout_loss(model, clip, None, generator=g, streams=streams or None, stored_contact=packed is None,
                              backward=torch.Tensor.backward, autocast=lambda: autocast,
                              reference_steps=rollout_reference_steps, rebuild=rebuild)
        invalid_depth.extend(result.invalid_depth)
        return result.loss, index.numel()

    while time.time() < deadline and (max_samples is None or samples < max_samples):
        if pace is not None and not pace.may_step(samples, deadline):
            break
        for group in opt.param_groups:
            group["lr"] = lr * min(1.0, (step + 1) / max(warmup, 1))
        try:
            loss, drawn = forward_backward(step)
        except Exception as error:  # noqa: BLE001 - a compiler that fails on this machine: eager, said once
            if compiled is None or step > 0:
                raise
            compile_error = f"{type(error).__name__}: {error}"[:2000]
            progress(json.dumps({"mode": mode, "compile_failed": compile_error}))
            _eager(model)
            compiled = None
            loss, drawn = forward_backward(step)
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        d = min(ema_decay, (1 + step) / (10 + step))
        with torch.no_grad():  # one fused update: a loop over tensors launches a kernel per parameter
            torch._foreach_lerp_(ema, [p.detach().float() for p in params], 1 - d)
        step, samples = step + 1, samples + drawn
        if report is not None:
            report_progress(report, samples)
        if first_step_s is None:
            first_step_s = round(time.time() - t0, 1)
            progress(json.dumps({"mode": mode, "first_step_s": first_step_s, "compiled": compiled is not None}))
        if step % log_every == 0:
            row = {"step": step, "loss": float(loss), "lr": opt.param_groups[0]["lr"],
                   "elapsed_s": round(time.time() - t0, 1), "samples": samples}
            if invalid_depth:  # of the references contact images were painted from, since the last row
                row["rebuilt_invalid_depth"] = round(float(np.mean(invalid_depth)), 4)
                invalid_depth.clear()
            if step % eval_every == 0:
                _eager(model)
                row["heldout_loss"] = heldout_loss(model, pack, streams, batch_size, seed)
                if compiled is not None:
                    model.backbone.trunk = compiled
            log.append(row)
            progress(json.dumps({"mode": mode, **row}))
    elapsed = time.time() - t0
    if report is not None:  # a run paced by this one stops at this count now
        report_progress(report, samples, done=True)
    _eager(model)
    with torch.no_grad():  # the EMA weights become the checkpoint's weights
        for p, e in zip(params, ema):
            p.copy_(e)
    final = heldout_loss(model, pack, streams, batch_size, seed)
    log.append({"step": step, "heldout_loss": final, "elapsed_s": round(time.time() - t0, 1), "samples": samples,
                "weights": "ema"})
    save_checkpoint(out / "checkpoints" / f"step_{step:06d}", model=model.half(), spec=spec)
    summary = {"mode": mode, "focus_weight": spec.flow.focus_weight, "reference_noise": spec.flow.reference_noise,
               "rollout_chunks": rollout_chunks, "rollout_reference_steps": rollout_reference_steps,
               "rebuild_contact": rebuild_contact,
               "first_frame": spec.conditioning.first_frame, "dropout": spec.conditioning.dropout,
               "scene_warp": spec.conditioning.scene_warp, "compiled": compiled is not None, "first_step_s": first_step_s,
               "compile_error": compile_error, "init": init_label,
               "init_sha256": init_sha256, "init_added": added, "steps": step,
               "samples": samples, "max_samples": max_samples, "batch_size": batch_size, "lr": lr, "warmup": warmup,
               "train_s": round(elapsed, 1),
               "samples_per_s": round(samples / max(elapsed, 1e-9), 1),
               "samples_per_s_after_first_step": round((samples - samples / max(step, 1)) / max(
                   elapsed - (first_step_s or 0.0), 1e-9), 1), "heldout_loss": final,
               "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
               "torch": torch.__version__, "parameters": sum(p.numel() for p in params),
               **(pace.summary() if pace is not None else {})}
    # the summary is the log's last row: the GPU machine returns few files
    write_log(out, [*log, {"summary": summary}])
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m imac_model.training.pack",
                                description="train one conditioning mode from a tensor pack (the GPU preset)")
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train")
    t.add_argument("--pack", required=True)
    t.add_argument("--mode", required=True, choices=("none", "motion", "motion+contact", "action-vector"))
    t.add_argument("--output", required=True)
    t.add_argument("--minutes", type=float, required=True, help="wall-clock training budget")
    t.add_argument("--max-samples", type=int,
                   help="stop once this many samples are trained, if the minutes last (equal budgets in samples)")
    t.add_argument("--report", help="keep this run's trained samples in this progress file (for --pace-with)")
    t.add_argument("--pace-with", help="another run's --report file: never train more than a step ahead of it, and "
                                       "stop at its final count (equal samples on a shared GPU)")
    t.add_argument("--batch-size", type=int, default=128)
    t.add_argument("--lr", type=float, default=6e-4)
    t.add_argument("--warmup", type=int, default=200,
                   help="steps of linear learning-rate warm-up (keep its samples when scaling the batch)")
    t.add_argument("--eval-every", type=int, default=500, help="steps between held-out losses in the log")
    t.add_argument("--focus-weight", type=float, help="override the pack's flow.focus_weight (an ablation: 0)")
    t.add_argument("--reference-noise", type=float,
                   help="override the pack's flow.reference_noise (the CPU preset's best arm: 0.3; docs/ranking.md)")
    t.add_argument("--rollout-chunks", type=int, default=1,
                   help="training-time rollout over clips of this many chunks (1: none; docs/ranking.md)")
    t.add_argument("--rollout-reference-steps", type=int, default=0,
                   help="chunk r > 1 starts from this many sampler steps on chunk r-1 (0: its one-step estimate)")
    t.add_argument("--rebuild-contact", action="store_true",
                   help="in a rollout, paint chunk r > 1's contact images from its reference's depth (the pack's "
                        "contact geometry) instead of keeping the recorded ones")
    t.add_argument("--first-frame", action="store_true",
                   help="condition on the episode's first frame (conditioning.first_frame; docs/world-model.md)")
    t.add_argument("--scene-warp", action="store_true",
                   help="the scene-warp control stream (conditioning.scene_warp; docs/world-model.md)")
    t.add_argument("--dropout", type=float,
                   help="share of samples trained without controls, for guidance (conditioning.dropout)")
    t.add_argument("--compile", action="store_true",
                   help="torch.compile the U-Net's trunk (on a GPU: fused group norms; the first step compiles)")
    t.add_argument("--init", help="start from this checkpoint's weights (a run directory: its latest checkpoint; "
                                  "a run archive <run>.tar or <run>.tar.xz: its checkpoint)")
    t.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    t.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if not str(args.device).startswith("cuda"):
        torch.set_num_threads(1)  # the script runs its trainings at once: on a CPU, threads would only contend
    fast_kernels()
    pack = Pack(args.pack, args.device)
    summary = train_pack(pack, args.mode, args.output, minutes=args.minutes, batch_size=args.batch_size, lr=args.lr,
                         warmup=args.warmup, eval_every=args.eval_every, seed=args.seed,
                         focus_weight=args.focus_weight, rollout_chunks=args.rollout_chunks,
                         first_frame=args.first_frame or None, dropout=args.dropout,
                         scene_warp=args.scene_warp or None, reference_noise=args.reference_noise,
                         rollout_reference_steps=args.rollout_reference_steps, compile=args.compile,
                         init=args.init, max_samples=args.max_samples, report=args.report,
                         pace_with=args.pace_with, rebuild_contact=args.rebuild_contact)
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["Pack", "compile_trunk", "export_pack", "fast_kernels", "heldout_loss", "pack_arrays", "spec_for_mode",
           "train_pack", "write_pack"]

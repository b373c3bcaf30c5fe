"""Checkpoints: a directory per saved step, loadable without the dataset.

::

    <output_dir>/checkpoints/step_000500/
        model.json           ModelSpec: rebuilds the network (views, view size, chunk, backbone, mode)
        config.yaml          the whole RunConfig of the run
        model.safetensors    weights (a frozen pretrained Wan VAE is left out: it comes from `pretrained`)
        ema.safetensors      EMA of the trainable weights (when EMA is on)
        trainer_state.pt     optimizer, LR schedule, step (exact resume)

A sharded run (``train.sharding.strategy: fsdp2``) writes, instead of the last three, ``state/``:
one ``torch.distributed.checkpoint`` of the weights, the optimizer, the EMA and the trainer
(step, schedule), each rank writing its own shards. It loads on any number of ranks, or into
a plain model in one process (:func:`load_world_model`).

Every write goes to a temporary directory that is renamed into place, so a killed run
never leaves a half-written checkpoint. :func:`load_world_model` raises
:class:`~imac_data.errors.InputError` naming the file for anything unreadable.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import replace
from pathlib import Path

import torch

from imac_data.errors import InputError
from imac_model.config import ModelSpec, RunConfig, load_model_spec, save_config
from imac_model.models.world_model import WorldModel

SPEC, CONFIG, WEIGHTS, EMA, STATE = "model.json", "config.yaml", "model.safetensors", "ema.safetensors", \
    "trainer_state.pt"
SHARDED = "state"  # the torch.distributed.checkpoint directory of a sharded run
_STEP_DIR = re.compile(r"^step_(\d+)$")


def _kept(state: dict, spec: ModelSpec) -> dict:
    """The weights a checkpoint holds: all but a frozen pretrained Wan VAE (it comes from ``pretrained``)."""
    if spec.backbone.kind == "wan" and spec.backbone.wan.pretrained and not spec.backbone.wan.train_vae:
        return {k: v for k, v in state.items() if not k.startswith("backbone.vae.")}
    return state


def weights_to_save(model, spec: ModelSpec) -> dict[str, torch.Tensor]:
    return {k: v.detach().contiguous().cpu() for k, v in _kept(model.state_dict(), spec).items()}


def save_checkpoint(directory: str | Path, *, model, spec: ModelSpec, run: RunConfig | None = None,
                    ema: dict[str, torch.Tensor] | None = None, trainer_state: dict | None = None) -> Path:
    from safetensors.torch import save_file

    directory = Path(directory)
    tmp = directory.with_name(directory.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    save_config(spec, tmp / SPEC)
    if run is not None:
        save_config(run, tmp / CONFIG)
    save_file(weights_to_save(model, spec), str(tmp / WEIGHTS))
    if ema is not None:
        save_file({k: v.detach().contiguous().cpu() for k, v in ema.items()}, str(tmp / EMA))
    if trainer_state is not None:
        torch.save(trainer_state, tmp / STATE)
    if directory.exists():
        shutil.rmtree(directory)
    os.replace(tmp, directory)
    return directory


def is_sharded(path: Path) -> bool:
    return (Path(path) / SHARDED).is_dir()


def save_sharded_checkpoint(directory: str | Path, *, model, optimizer, spec: ModelSpec, run: RunConfig,
                            ema: dict[str, torch.Tensor] | None, trainer: dict) -> Path:
    """A sharded run's checkpoint (``state/``): every rank calls this, each writes its shards.
    ``trainer``: ``{"step": ..., "scheduler": ...}``."""
    import torch.distributed as dist
    import torch.distributed.checkpoint as dcp
    from torch.distributed.checkpoint.state_dict import get_state_dict

    directory = Path(directory)
    tmp = directory.with_name(directory.name + ".tmp")
    main = dist.get_rank() == 0
    if main:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        save_config(spec, tmp / SPEC)
        save_config(run, tmp / CONFIG)
    dist.barrier()
    weights, optim = get_state_dict(model, optimizer)
    state = {"model": _kept(weights, spec), "optim": optim, "trainer": trainer}
    if ema is not None:
        state["ema"] = ema
    dcp.save(state, checkpoint_id=tmp / SHARDED)
    dist.barrier()
    if main:
        if directory.exists():
            shutil.rmtree(directory)
        os.replace(tmp, directory)
    dist.barrier()
    return directory


def _sharded_keys(path: Path) -> set[str]:
    import torch.distributed.checkpoint as dcp

    try:
        return set(dcp.FileSystemReader(str(path / SHARDED)).read_metadata().state_dict_metadata)
    except (OSError, ValueError, RuntimeError, EOFError) as e:
        raise InputError(f"{path / SHARDED}: unreadable sharded checkpoint: {e}") from None


def _dcp_load(state: dict, path: Path) -> None:
    import torch.distributed.checkpoint as dcp
    from torch.distributed.checkpoint.api import CheckpointException

    try:
        dcp.load(state, checkpoint_id=path / SHARDED)
    except (CheckpointException, OSError, ValueError, RuntimeError, KeyError) as e:
        raise InputError(f"{path / SHARDED}: the sharded checkpoint does not fit the model its {SPEC} describes, "
                         f"or is damaged: {type(e).__name__}: {str(e)[:500]}") from None


def load_sharded_checkpoint(path: Path, *, model, optimizer, spec: ModelSpec, ema: dict[str, torch.Tensor] | None,
                            trainer: dict) -> tuple[dict, bool]:
    """Resume a sharded run (every rank calls this): weights and optimizer into ``model`` /
    ``optimizer`` (sharded or not), the EMA into ``ema``'s tensors, and ``(trainer state,
    whether the checkpoint had an EMA)``; ``trainer`` is the template (``{"step": 0,
    "scheduler": scheduler.state_dict()}``)."""
    from torch.distributed.checkpoint.state_dict import StateDictOptions, get_state_dict, set_state_dict

    path = Path(path)
    has_ema = any(k.startswith("ema.") for k in _sharded_keys(path))
    weights, optim = get_state_dict(model, optimizer)  # also creates the optimizer states to load into
    state = {"model": _kept(weights, spec), "optim": optim, "trainer": trainer}
    if ema is not None and has_ema:
        state["ema"] = ema
    _dcp_load(state, path)
    set_state_dict(model, optimizer, model_state_dict=state["model"], optim_state_dict=state["optim"],
                   options=StateDictOptions(strict=False))
    return state["trainer"], has_ema


def _load_sharded_weights(model, path: Path, *, ema: bool) -> None:
    """A sharded checkpoint's weights (or EMA) into a plain model, in one process."""
    if ema:
        template = {k: torch.empty(p.shape, dtype=torch.float32) for k, p in model.named_parameters()
                    if p.requires_grad}
    else:
        template = {k: torch.empty_like(v) for k, v in _kept(model.state_dict(), model.spec).items()}
    state = {"ema" if ema else "model": template}
    _dcp_load(state, path)
    model.load_state_dict(state["ema" if ema else "model"], strict=False)


def list_checkpoints(output_dir: str | Path) -> list[Path]:
    """Complete checkpoints under ``output_dir/checkpoints``, oldest first."""
    root = Path(output_dir) / "checkpoints"
    if not root.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in root.iterdir() if (m := _STEP_DIR.match(p.name)) and p.is_dir()]
    return [p for _, p in sorted(found)]


def resolve_checkpoint(path: str | Path) -> Path:
    """A checkpoint directory from itself, or from a run directory (its latest checkpoint)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"checkpoint not found: {path}")
    found = list_checkpoints(path)
    if found:  # a run directory
        return found[-1]
    if (path / SPEC).is_file() or (path / WEIGHTS).is_file() or is_sharded(path):
        return path
    raise InputError(f"{path}: not a checkpoint (no {SPEC} / {WEIGHTS}) and no checkpoints/step_* inside")


def read_spec(path: str | Path) -> ModelSpec:
    path = resolve_checkpoint(path)
    try:
        return load_model_spec(path / SPEC)
    except InputError as e:
        raise InputError(f"{path / SPEC}: unreadable model spec: {e}") from None


def read_weights(file: Path) -> dict[str, torch.Tensor]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    if not file.is_file():
        raise InputError(f"checkpoint file missing: {file}")
    try:
        return load_file(str(file))
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise InputError(f"{file}: unreadable weights (truncated or not a safetensors file): {e}") from None


def load_weights_into(model, file: Path, *, ema: bool = False) -> None:
    state = read_weights(file)
    own = model.state_dict()
    if ema:  # the EMA holds only trainable weights: the rest keep the model's values
        state = {**own, **state}
    missing = [k for k in own if k not in state]
    spec = getattr(model, "spec", None)
    if spec is not None and spec.backbone.kind == "wan" and spec.backbone.wan.pretrained:
        missing = [k for k in missing if not k.startswith("backbone.vae.")]
    unexpected = [k for k in state if k not in own]
    wrong = [k for k in state if k in own and state[k].shape != own[k].shape]
    if missing or unexpected or wrong:
        raise InputError(f"{file}: the weights do not fit the model its {SPEC} describes "
                         f"(missing {missing[:5]}, unexpected {unexpected[:5]}, wrong shape {wrong[:5]})")
    model.load_state_dict(state, strict=False)


def load_world_model(path: str | Path, *, weights: str = "ema", device=None, guidance: float | None = None):
    """``(WorldModel, ModelSpec)`` from a checkpoint directory (or a run directory: its
    latest checkpoint). ``weights``: ``ema`` (if saved, else the raw weights) or ``raw``.
    ``guidance``: sample with this ``conditioning.guidance`` instead of the saved one (refused
    for a model trained without ``conditioning.dropout``)."""
    path = resolve_checkpoint(path)
    spec = read_spec(path)
    if guidance is not None:
        spec = replace(spec, conditioning=replace(spec.conditioning, guidance=float(guidance)))
    if weights not in ("ema", "raw"):
        raise ValueError(f"weights must be 'ema' or 'raw', got {weights!r}")
    model = WorldModel(spec)
    if is_sharded(path):
        _load_sharded_weights(model, path, ema=False)
        if weights == "ema" and any(k.startswith("ema.") for k in _sharded_keys(path)):
            _load_sharded_weights(model, path, ema=True)
    else:
        load_weights_into(model, path / WEIGHTS)
        if weights == "ema" and (path / EMA).is_file():
            load_weights_into(model, path / EMA, ema=True)
    model.eval()
    return (model.to(device) if device is not None else model), spec


def read_trainer_state(path: Path) -> dict:
    file = path / STATE
    if not file.is_file():
        raise InputError(f"checkpoint file missing: {file} (cannot resume from {path})")
    try:
        return torch.load(file, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many kinds for a corrupt pickle/zip
        raise InputError(f"{file}: unreadable trainer state: {type(e).__name__}: {e}") from None


def prune_checkpoints(output_dir: str | Path, keep: int) -> None:
    for old in list_checkpoints(output_dir)[:-keep]:
        shutil.rmtree(old, ignore_errors=True)


def run_config_of(path: Path) -> dict | None:
    file = path / CONFIG
    if not file.is_file():
        return None
    import yaml

    try:
        return yaml.safe_load(file.read_text())
    except yaml.YAMLError:
        return None


def spec_json(spec: ModelSpec) -> str:
    return json.dumps(spec.to_dict(), sort_keys=True)

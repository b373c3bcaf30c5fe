"""Typed configuration of the world model and its training, validated at the boundary.

A run is one :class:`RunConfig` (YAML or JSON; sections ``data``, ``backbone``,
``conditioning``, ``flow``, ``train``, ``rollout``, each optional), parsed strictly: an unknown
key, a wrong type or a bad value raises :class:`~imac_data.errors.InputError` naming the file
and the dotted field. Every checkpoint stores the resolved :class:`ModelSpec` (the model
sections plus the facts taken from the dataset), so a model is rebuilt from its checkpoint
alone; both round-trip through ``to_dict`` and the loaders. Defaults follow the paper
(``docs/world-model.md``, "Configuration")."""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import yaml

from imac_data.config import parse_dataclass
from imac_data.errors import InputError
from imac_model.modes import MODES, SCENE_WARP, conditioning_mode

# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class DataConfig:
    dataset: str = ""  # LeRobot repo id, e.g. local/sim10
    root: str | None = None  # dataset directory; default $HF_LEROBOT_HOME/<dataset>
    view_height: int = 48  # per-view height at the model's resolution
    view_width: int | None = None  # None: keep the cameras' aspect ratio, rounded to the backbone's multiple
    chunk: int | None = None  # future frames per chunk; None = the dataset's contact chunk (must equal it)
    views: tuple[str, ...] | None = None  # camera order; None = head, left wrist, right wrist
    held_out_episodes: tuple[int, ...] = ()  # never trained on; the held-out loss is computed on them
    cache: Literal["memory", "none"] = "memory"  # keep decoded, resized chunks (uint8) in RAM
    cache_dir: str | None = None  # also persist that cache here (reused by later runs on the same data)
    num_workers: int = 0  # DataLoader workers that decode videos
    video_backend: str | None = None  # LeRobot's decoder (None: its default, torchcodec)
    # a tensor pack (imac_model.data.pack) to train from instead of the dataset: its spec's views, size and chunk,
    # its held-out chunks; the trainer then needs torch and numpy alone (the GPU machine)
    pack: str | None = None

    def __post_init__(self) -> None:
        _positive(self, "view_height")
        if self.view_width is not None:
            _positive(self, "view_width")
        if self.chunk is not None:
            _positive(self, "chunk")
        if self.num_workers < 0:
            raise InputError(f"data.num_workers: must be >= 0 (got {self.num_workers})")
        if self.views is not None and len(set(self.views)) != len(self.views):
            raise InputError(f"data.views: duplicate camera names in {list(self.views)}")
        if any(e < 0 for e in self.held_out_episodes):
            raise InputError(f"data.held_out_episodes: episode indices are >= 0 (got {list(self.held_out_episodes)})")


@dataclass(frozen=True)
class SmallDiTConfig:
    """The CPU-sized video DiT: pixel-unshuffle latent, factorised space/time attention."""

    unshuffle: int = 4  # latent = pixel-unshuffle of the [-1, 1] frames: 3 * unshuffle^2 channels
    patch: int = 2  # spatial patch on the latent (temporal patch 1, as Wan2.2)
    dim: int = 192
    depth: int = 6
    heads: int = 6
    mlp_ratio: float = 4.0
    context_dim: int = 256  # width of cross-attention context tokens (action-vector mode only)

    def __post_init__(self) -> None:
        for name in ("unshuffle", "patch", "dim", "depth", "heads", "context_dim"):
            _positive(self, name, "backbone.small")
        if self.dim % self.heads or (self.dim // self.heads) % 2:
            raise InputError(f"backbone.small.dim: {self.dim} must split into {self.heads} heads of even width")
        if self.mlp_ratio <= 0:
            raise InputError(f"backbone.small.mlp_ratio: must be > 0 (got {self.mlp_ratio})")


@dataclass(frozen=True)
class WanConfig:
    """Wan2.2-TI2V through diffusers (``WanTransformer3DModel`` + ``AutoencoderKLWan``)."""

    pretrained: str | None = None  # local directory or hub id with transformer/ and vae/ subfolders
    transformer: dict[str, typing.Any] = field(default_factory=dict)  # config (overrides) of the transformer
    vae: dict[str, typing.Any] = field(default_factory=dict)  # config (overrides) of the VAE
    num_layers: int | None = None  # keep only the first N transformer blocks (benchmarks, small runs)
    context_tokens: int = 16  # learned null text context (no T5 here): tokens of width text_dim
    gradient_checkpointing: bool = False
    train_vae: bool = False  # the VAE stays frozen unless asked
    vae_slicing: bool = False  # encode / decode one sample at a time (diffusers' slicing): the VAE's peak
    # memory stops growing with the micro-batch

    def __post_init__(self) -> None:
        if self.num_layers is not None:
            _positive(self, "num_layers", "backbone.wan")
        _positive(self, "context_tokens", "backbone.wan")


@dataclass(frozen=True)
class UNetConfig:
    """The pixel-space convolutional U-Net (DIAMOND's design): full-resolution output, a chunk's
    frames stacked in channels, adaptive group norm on the flow time."""

    channels: tuple[int, ...] = (32, 64, 96, 128)  # width per level; each level but the last halves the size
    blocks: int = 2  # residual blocks per level
    frame_dim: int = 16  # width of each frame's embedding (and of a control stream's projection)
    context_dim: int = 256  # width of the action tokens (action-vector mode only)

    def __post_init__(self) -> None:
        if not self.channels or any(isinstance(c, bool) or not isinstance(c, int) or c <= 0 for c in self.channels):
            raise InputError(f"backbone.unet.channels: positive integers, one per level (got {list(self.channels)})")
        for name in ("blocks", "frame_dim", "context_dim"):
            _positive(self, name, "backbone.unet")


@dataclass(frozen=True)
class BackboneConfig:
    kind: Literal["small", "unet", "wan"] = "small"
    small: SmallDiTConfig = field(default_factory=SmallDiTConfig)
    unet: UNetConfig = field(default_factory=UNetConfig)
    wan: WanConfig = field(default_factory=WanConfig)


@dataclass(frozen=True)
class ConditioningConfig:
    mode: str = "motion+contact"  # a name in imac_model.modes.MODES
    # paper: every control patchify layer zero-initialised; release: motion copies patch_embedding
    control_init: Literal["zeros", "copy_patch_embedding"] = "zeros"
    # paper: controls only on the noised future tokens; release: on the reference tokens too
    control_on_reference: bool = False
    action_hidden: int = 256  # action-vector baseline: MLP width
    action_layers: int = 3  # action-vector baseline: MLP depth (the release: 3 layers, SiLU)
    # memory beyond one frame (not in the paper): the episode's first recorded frame goes in as one more clean
    # frame ahead of the reference, so a chunk whose generated reference lost the object still sees where it began
    first_frame: bool = False
    # classifier-free guidance (not in the paper): in training, this share of the samples gets no controls (no
    # action tokens in the action-vector mode), so the model also learns the unconditional velocity; in sampling,
    # v = v_uncond + guidance (v_cond - v_uncond), so the controls' effect is scaled (1 = the conditional model)
    dropout: float = 0.0
    guidance: float = 1.0
    # one more control stream (not in the paper): the reference frame's scene, robot removed, splatted into each
    # view's camera at each future configuration, so a moving wrist camera is told where the scene lands
    scene_warp: bool = False

    def __post_init__(self) -> None:
        mode = conditioning_mode(self.mode)  # a registered mode, or the error naming them
        _positive(self, "action_hidden", "conditioning")
        if self.scene_warp and not mode.streams:
            with_images = " or ".join(name for name, m in MODES.items() if m.streams)
            raise InputError(f"conditioning.scene_warp: a control stream, so it needs a mode with control images "
                             f"({with_images}), not {self.mode!r}")
        _positive(self, "action_layers", "conditioning")
        if not 0 <= self.dropout < 1:
            raise InputError(f"conditioning.dropout: a share in [0, 1) (got {self.dropout})")
        if self.guidance < 0:
            raise InputError(f"conditioning.guidance: must be >= 0 (got {self.guidance})")
        if self.guidance != 1 and self.dropout == 0:
            raise InputError(f"conditioning.guidance: {self.guidance} needs a model trained with conditioning.dropout > 0 "
                             "(without it the unconditional velocity is never learned)")
        if mode.blind and (self.dropout or self.guidance != 1):
            raise InputError(f"conditioning.dropout / guidance: mode {self.mode} has no conditioning to drop or guide by")

    @property
    def streams(self) -> tuple[str, ...]:
        return conditioning_mode(self.mode).streams + ((SCENE_WARP,) if self.scene_warp else ())


@dataclass(frozen=True)
class FlowConfig:
    """Flow matching in the paper's time: tau = 0 noise, tau = 1 data."""

    train_shift: float = 1.0  # timestep shift of the training tau (1 = tau ~ U(0, 1), the paper; release: 5)
    sample_shift: float = 1.0  # timestep shift of the sampler's schedule
    sample_steps: int = 20  # Euler steps
    reference_noise: float = 0.0  # std of Gaussian noise on the clean reference latent in training (release: 0.1)
    # what the network outputs: the velocity (Wan's training; the paper), or the clean data, converted to the
    # velocity v = (x1_hat - x_tau) / (1 - tau) before the same loss (Li & He 2025, "Back to Basics": pixel-space
    # models with large patches cannot output full-rank noise through a narrow token; the small DiT's default)
    prediction: Literal["velocity", "data"] = "velocity"
    data_prediction_min_gap: float = 0.05  # the 1 - tau floor of that conversion
    # the loss's extra weight on latent pixels that change within the chunk (the arm, a moved object), dilated
    # by focus_dilation pixels; 0 = a uniform loss (docs/world-model.md, "A loss that looks where it matters")
    focus_weight: float = 0.0
    focus_threshold: float = 0.2  # a change larger than this in any latent channel (pixel space: [-1, 1] units)
    focus_dilation: int = 2

    def __post_init__(self) -> None:
        if self.train_shift <= 0 or self.sample_shift <= 0:
            raise InputError("flow.train_shift / flow.sample_shift: must be > 0")
        _positive(self, "sample_steps", "flow")
        if self.reference_noise < 0:
            raise InputError(f"flow.reference_noise: must be >= 0 (got {self.reference_noise})")
        if self.focus_weight < 0 or self.focus_threshold <= 0 or self.focus_dilation < 0:
            raise InputError(f"flow.focus_weight / focus_dilation: must be >= 0, flow.focus_threshold > 0 (got "
                             f"{self.focus_weight}, {self.focus_dilation}, {self.focus_threshold})")
        if not 0 < self.data_prediction_min_gap < 1:
            raise InputError(f"flow.data_prediction_min_gap: must be in (0, 1) (got {self.data_prediction_min_gap})")


@dataclass(frozen=True)
class ShardingConfig:
    """Sharded data-parallel training (``imac_model/training/sharding.py``, ``docs/scale.md``)."""

    strategy: Literal["none", "fsdp2"] = "none"  # fsdp2: torch's fully_shard per transformer block
    reshard_after_forward: bool = True  # false: parameters stay gathered from forward to backward (ZeRO-2-like)
    cpu_offload: bool = False  # fsdp2 on CUDA: weights, gradients and optimizer states live in host memory

    def __post_init__(self) -> None:
        if self.strategy == "none" and (self.cpu_offload or not self.reshard_after_forward):
            raise InputError("train.sharding.cpu_offload / reshard_after_forward: need train.sharding.strategy "
                             "fsdp2")


@dataclass(frozen=True)
class TrainConfig:
    output_dir: str = "runs/imac"
    seed: int = 0
    batch_size: int = 4  # global batch (split over processes under `accelerate launch` / `torchrun`)
    optimizer: Literal["adamw"] = "adamw"  # torch.optim.AdamW over the trainable weights
    lr: float = 3e-4
    adam_betas: tuple[float, ...] = (0.9, 0.999)
    adam_eps: float = 1e-8
    weight_decay: float = 0.0
    warmup_steps: int = 50
    grad_clip: float = 1.0
    max_steps: int = 1000
    max_minutes: float | None = None  # also stop (with a checkpoint) after this much training wall time
    max_cpu_minutes: float | None = None  # ... or this much CPU time, all processes summed (a budget on a shared machine)
    ema_decay: float = 0.999  # 0 disables EMA
    log_every: int = 10
    eval_every: int = 100  # held-out flow loss every N steps (and at the start and end)
    eval_batches: int = 4
    checkpoint_every: int = 500
    keep_checkpoints: int = 2
    mixed_precision: Literal["auto", "no", "bf16"] = "auto"  # auto: bf16 on a CUDA device that has it
    tracker: Literal["tensorboard", "wandb"] | None = None  # besides the CSV/JSONL log
    cpu_threads: int | None = None  # torch intra-op threads (None: torch's default; 1 is fastest on a busy CPU)
    compile: bool = False  # torch.compile the U-Net's trunk (a GPU's fused group norms; the first step compiles)
    # a checkpoint whose weights start a new run (a run directory: its latest; or a run archive); the optimizer starts
    # afresh, and a control stream it lacks starts at its zero projection
    init: str | None = None
    sharding: ShardingConfig = field(default_factory=ShardingConfig)

    def __post_init__(self) -> None:
        if len(self.adam_betas) != 2 or not all(0 <= b < 1 for b in self.adam_betas):
            raise InputError(f"train.adam_betas: two numbers in [0, 1) (got {list(self.adam_betas)})")
        if not self.adam_eps > 0:
            raise InputError(f"train.adam_eps: must be > 0 (got {self.adam_eps})")
        if not (isinstance(self.max_steps, int) and self.max_steps >= 0):  # 0: the starting weights as a checkpoint
            raise InputError(f"train.max_steps: must be an integer >= 0 (got {self.max_steps!r})")
        for name in ("batch_size", "log_every", "eval_every", "eval_batches", "checkpoint_every",
                     "keep_checkpoints"):
            _positive(self, name, "train")
        if self.lr <= 0:
            raise InputError(f"train.lr: must be > 0 (got {self.lr})")
        if not 0 <= self.ema_decay < 1:
            raise InputError(f"train.ema_decay: must be in [0, 1) (got {self.ema_decay})")
        if self.warmup_steps < 0 or self.grad_clip < 0 or self.weight_decay < 0:
            raise InputError("train.warmup_steps / grad_clip / weight_decay: must be >= 0")
        if self.cpu_threads is not None:
            _positive(self, "cpu_threads", "train")
        for name in ("max_minutes", "max_cpu_minutes"):
            if getattr(self, name) is not None and getattr(self, name) <= 0:
                raise InputError(f"train.{name}: must be > 0 (got {getattr(self, name)})")


@dataclass(frozen=True)
class RolloutConfig:
    """Training-time rollout (paper section 3.4) and the online rebuild of controls
    (:mod:`imac_model.pipelines.rollout`, :mod:`imac_model.pipelines.online_controls`).

    An epoch is one pass over the run's training items: chunks, or clips of ``chunks``
    consecutive chunks when ``chunks > 1``."""

    chunks: int = 1  # R: chunks per training clip; 1 = no rollout (every chunk from its recorded reference)
    warmup_epochs: float = 0.0  # the first epochs keep every chunk's recorded (clean) reference and stored controls
    stage_one_epochs: float = 0.0  # motion+contact: the first epochs inject the motion stream alone (stage one)
    resolution: Literal["model", "dataset"] = "model"  # where contact/motion images are rebuilt (online_controls)
    max_walk_distance: float = 0.1  # a predicted depth colour farther than this from the codec's walk is invalid
    reference_state: Literal["recorded", "commanded"] = "recorded"  # chunk r > 1's robot state: the dataset's,
    # or the previous chunk's last commanded configuration (what a closed loop knows)
    device: Literal["auto", "cpu", "cuda"] = "auto"  # the contact computation (auto: the model's device)
    reference_steps: int = 0  # chunk r > 1 starts from: 0, chunk r-1's one-step estimate (paper 3.4); k, the last
    # frame of k sampler steps on chunk r-1 (no gradient), the drift a replay has (docs/world-model.md)
    # chunk r > 1's contact images: painted from its own reference's depth (the paper), or the recorded ones
    contact: Literal["rebuilt", "recorded"] = "rebuilt"

    def __post_init__(self) -> None:
        _positive(self, "chunks", "rollout")
        if not (isinstance(self.reference_steps, int) and self.reference_steps >= 0):
            raise InputError(f"rollout.reference_steps: must be an integer >= 0 (got {self.reference_steps!r})")
        for name in ("warmup_epochs", "stage_one_epochs"):
            if not getattr(self, name) >= 0:
                raise InputError(f"rollout.{name}: must be >= 0 (got {getattr(self, name)})")
        if not 0 < self.max_walk_distance <= 1:
            raise InputError(f"rollout.max_walk_distance: must be in (0, 1] RGB units (got {self.max_walk_distance})")


@dataclass(frozen=True)
class RunConfig:
    data: DataConfig = field(default_factory=DataConfig)
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    conditioning: ConditioningConfig = field(default_factory=ConditioningConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    rollout: RolloutConfig = field(default_factory=RolloutConfig)

    def __post_init__(self) -> None:
        if self.rollout.stage_one_epochs > 0 and not conditioning_mode(self.conditioning.mode).staged:
            staged = " or ".join(name for name, m in MODES.items() if m.staged)
            raise InputError(f"rollout.stage_one_epochs: stage one (motion only, then contact added) needs "
                             f"conditioning.mode {staged} (got {self.conditioning.mode!r})")
        if self.train.sharding.strategy != "none":
            if self.backbone.kind != "wan":
                raise InputError(f"train.sharding.strategy: {self.train.sharding.strategy} shards the Wan "
                                 f"transformer's blocks; backbone.kind is {self.backbone.kind!r} (train it unsharded)")
            if self.backbone.wan.train_vae:
                raise InputError("backbone.wan.train_vae: the VAE is replicated, not sharded, under "
                                 "train.sharding.strategy fsdp2; train it unsharded or keep it frozen")

    def to_dict(self) -> dict:
        return to_dict(self)

    def replace(self, **dotted) -> RunConfig:
        """A copy with ``{"train.max_steps": 10, ...}`` changed (validated again)."""
        data = self.to_dict()
        for key, value in dotted.items():
            node = data
            *parents, leaf = key.split(".")
            for i, p in enumerate(parents):
                if not isinstance(node.get(p), dict):
                    raise InputError(f"{'.'.join(parents[:i + 1])}: unknown section (in override {key!r})")
                node = node[p]
            node[leaf] = value
        return parse(RunConfig, data, "")


@dataclass(frozen=True)
class ModelSpec:
    """Everything needed to rebuild a world model without its dataset: the model sections
    of the run plus the facts resolved from the dataset. Saved with every checkpoint."""

    backbone: BackboneConfig
    conditioning: ConditioningConfig
    flow: FlowConfig
    views: tuple[str, ...]  # camera names, mosaic order
    view_height: int
    view_width: int
    chunk: int  # H future frames; a chunk holds 1 + H frames
    action_dim: int
    fps: float
    dataset: str = ""  # the repo id it was trained on (informative)
    action_mean: tuple[float, ...] = ()  # the dataset's action statistics (action-vector input normalisation)
    action_std: tuple[float, ...] = ()

    @property
    def mosaic_hw(self) -> tuple[int, int]:
        """The six-panel mosaic: an RGB row over a colour-depth row, views side by side."""
        return 2 * self.view_height, len(self.views) * self.view_width

    def to_dict(self) -> dict:
        return to_dict(self)


# --------------------------------------------------------------------------- parsing


def _positive(obj, name: str, section: str = "data") -> None:
    value = getattr(obj, name)
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise InputError(f"{section}.{name}: must be a positive integer (got {value!r})")


def parse(cls, value, where: str = ""):
    """Build dataclass ``cls`` from a mapping, strictly (unknown keys are errors;
    :func:`imac_data.config.parse_dataclass`)."""
    return parse_dataclass(cls, value, where, root="config")


def to_dict(obj) -> dict:
    """Plain JSON/YAML data (tuples become lists) that :func:`parse` reads back."""

    def plain(v):
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return plain(obj)


def _read(path: Path) -> dict:
    if not path.is_file():
        raise InputError(f"config file not found: {path}")
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix == ".json" else yaml.safe_load(text)
    except (OSError, ValueError, yaml.YAMLError) as e:
        raise InputError(f"{path}: cannot read the config: {e}") from None
    return data if data is not None else {}


def load_run_config(path: str | Path | None = None, overrides: dict | None = None) -> RunConfig:
    """A :class:`RunConfig` from a YAML/JSON file (or the defaults), with ``overrides``
    (``{"train.max_steps": 10}``) applied; errors name the file and the field."""
    data: dict = _read(Path(path)) if path is not None else {}
    try:
        config = parse(RunConfig, data, "")
    except InputError as e:
        raise InputError(f"{path}: {e}" if path else str(e)) from None
    return config.replace(**overrides) if overrides else config


def save_config(obj, path: str | Path) -> None:
    """Write a config dataclass as YAML (``.yaml``) or JSON (anything else)."""
    path = Path(path)
    data = to_dict(obj)
    path.write_text(yaml.safe_dump(data, sort_keys=False) if path.suffix in (".yaml", ".yml")
                    else json.dumps(data, indent=2))


def load_model_spec(path: str | Path) -> ModelSpec:
    return parse(ModelSpec, _read(Path(path)), "")

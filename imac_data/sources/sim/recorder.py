"""Record simulated ALOHA episodes: the scripted policy run in gym-aloha's physics, rendered
by MuJoCo, written as ALOHA HDF5 files (:mod:`imac_data.sources.hdf5`), so the whole
pipeline runs on a fresh machine without real robot data.

Physics runs at 500 Hz with 50 Hz control. With ``frame_stride = s`` the policy is queried
every ``s`` control steps and its command held for them, so recorded frame ``k`` holds the
state *before* ``action[k]``, and ``action[k]`` is what drove the robot from frame ``k`` to
``k + 1``. Depth is MuJoCo's planar z-depth as uint16 millimetres (0 = nothing hit or beyond
65.535 m); segmentation is the geom id per pixel. ``docs/simulation.md`` has the details.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from imac_data.core.cameras import save_calibration
from imac_data.core.mujoco_gl import mujoco
from imac_data.errors import InputError
from imac_data.layout import CALIBRATION
from imac_data.sources.hdf5 import EpisodeInfo, RawEpisode, write_episode
from imac_data.sources.sim.env import FrameRenderer, SimEnv, segmentation_labels
from imac_data.sources.sim.rig import CONTROL_DT, camera_calibration, load_mujoco_model
from imac_data.sources.sim.scripts import ScriptedPolicy
from imac_data.sources.sim.tasks import TASK_INSTRUCTIONS, TASKS

__all__ = ["SimConfig", "EpisodeResult", "simulate_episode", "record_dataset"]


@dataclass
class EpisodeResult:
    qpos: np.ndarray  # (T, 14)
    qvel: np.ndarray  # (T, 14)
    action: np.ndarray  # (T, 14)
    success: bool
    max_reward: int
    fps: float
    images: dict[str, np.ndarray]
    depth_mm: dict[str, np.ndarray]
    segmentation: dict[str, np.ndarray]
    final_object_pos: dict[str, np.ndarray]

    @property
    def num_frames(self) -> int:
        return int(self.qpos.shape[0])


def simulate_episode(task: str, seed: int, *, noise: float = 0.0, frame_stride: int = 2,
                     max_steps: int | None = None, renderer: FrameRenderer | None = None,
                     model: mujoco.MjModel | None = None) -> EpisodeResult:
    """Roll out the scripted policy once. Without ``renderer`` nothing is rendered (fast:
    physics + IK only); with one, every recorded frame gets RGB (+ depth, segmentation)."""
    env = SimEnv(task, frame_stride=frame_stride, renderer=renderer, model=model)
    env.reset(seed)
    # The policy's noise stream is separate from the object-pose sampler (seeded with seed).
    rng = np.random.default_rng([int(seed), 0x51D])
    policy = ScriptedPolicy(task, env.model, env.data, rng, noise)
    n_steps = int(round(policy.duration / CONTROL_DT))
    if max_steps is not None:
        n_steps = min(n_steps, int(max_steps))
    n_frames = n_steps // frame_stride
    qpos = np.empty((n_frames, 14))
    qvel = np.empty((n_frames, 14))
    action = np.empty((n_frames, 14))
    frames: list[dict] = []
    for k in range(n_frames):
        qpos[k], qvel[k] = env.qpos(), env.qvel()
        if renderer is not None:
            frames.append(env.render())
        action[k] = policy(k * frame_stride * CONTROL_DT, env.data)
        env.step(action[k])
    layout, data = env.layout, env.data

    def stack(kind):
        if not frames or not frames[0][kind]:
            return {}
        return {cam: np.stack([f[kind][cam] for f in frames]) for cam in frames[0][kind]}

    return EpisodeResult(
        qpos=qpos, qvel=qvel, action=action, success=env.success, max_reward=env.max_reward,
        fps=1.0 / (frame_stride * CONTROL_DT),
        images=stack("rgb"), depth_mm=stack("depth_mm"), segmentation=stack("segmentation"),
        final_object_pos={n: data.xpos[b].copy() for n, b in layout.object_bodies.items()},
    )


# --------------------------------------------------------------------------- datasets


@dataclass(frozen=True)
class SimConfig:
    """What :func:`record_dataset` records. Validated on construction (:class:`InputError`
    naming the field)."""

    task: str = "transfer_cube"
    num_episodes: int = 2
    width: int = 320
    height: int = 240
    seed: int = 0  # episode i uses seed + i (object poses as gym-aloha's reset(seed=seed + i))
    noise: float = 0.0  # policy quality knob in [0, 1]; 0 = exact
    frame_stride: int = 2  # record every n-th 50 Hz control step (2 -> 25 fps)
    max_steps: int | None = None  # cap on 50 Hz control steps per episode (None: the whole script)
    with_depth: bool = True
    with_segmentation: bool = False
    compress: bool = False  # JPEG-compressed RGB (ALOHA's compressed variant)
    jpeg_quality: int = 95
    shadows: bool = False  # gym-aloha's shadow map (about 10x slower RGB on the CPU)
    antialias: bool = False  # 4x multisampling (about 2x slower RGB on the CPU)

    def __post_init__(self) -> None:
        def bad(name, why):
            raise InputError(f"SimConfig.{name}: {why} (got {getattr(self, name)!r})")

        def is_int(v):
            return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

        if self.task not in TASKS:
            bad("task", f"must be one of {TASKS}")
        for name, lo, hi in (("num_episodes", 1, None), ("width", 16, 4096), ("height", 16, 4096),
                             ("frame_stride", 1, 50), ("jpeg_quality", 1, 100), ("seed", 0, 2**32 - 1)):
            v = getattr(self, name)
            if not is_int(v):
                bad(name, "must be an integer")
            if v < lo or (hi is not None and v > hi):
                bad(name, f"must be in [{lo}, {hi if hi is not None else 'inf'}]")
        if self.seed + self.num_episodes - 1 > 2**32 - 1:
            bad("seed", "seed + num_episodes - 1 must fit in 32 bits (gym-aloha's samplers)")
        if self.max_steps is not None:
            if not is_int(self.max_steps):
                bad("max_steps", "must be an integer or None")
            if self.max_steps < self.frame_stride:
                bad("max_steps", f"must be at least frame_stride ({self.frame_stride}) to record a frame")
        if isinstance(self.noise, bool) or not isinstance(self.noise, (int, float, np.floating)):
            bad("noise", "must be a number in [0, 1]")
        if not (math.isfinite(self.noise) and 0.0 <= self.noise <= 1.0):
            bad("noise", "must be in [0, 1]")
        for f in fields(self):
            if f.type in ("bool",) and not isinstance(getattr(self, f.name), (bool, np.bool_)):
                bad(f.name, "must be a bool")

    @property
    def fps(self) -> float:
        return 1.0 / (self.frame_stride * CONTROL_DT)


def _episode_path(out_dir: Path, index: int) -> Path:
    return out_dir / f"episode_{index}.hdf5"


def record_dataset(config: SimConfig, out_dir: str | Path, progress: bool = True, *,
                   overwrite: bool = False) -> list[Path]:
    """Record ``config.num_episodes`` scripted episodes into ``out_dir`` as
    ``episode_{i}.hdf5`` plus ``calibration.json`` (the rig at the recorded resolution).

    Every file is written atomically (temporary name, then renamed), so an interrupted
    run leaves only complete episodes. A directory that already holds episodes is
    refused unless ``overwrite`` (which first deletes its ``episode_*.hdf5``).
    """
    if not isinstance(config, SimConfig):
        raise InputError(f"config must be a SimConfig, got {type(config).__name__}")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output path exists and is not a directory: {out_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    existing = sorted(out_dir.glob("episode_*.hdf5"))
    if existing:
        if not overwrite:
            raise InputError(
                f"{out_dir} already holds {len(existing)} episode file(s); choose an empty directory "
                "or pass overwrite=True (--overwrite)"
            )
        for p in existing:
            p.unlink()

    model = load_mujoco_model(config.task)
    calib_tmp = out_dir / ".calibration.json.tmp"
    save_calibration(calib_tmp, camera_calibration(model, config.width, config.height))
    calib_tmp.replace(out_dir / CALIBRATION)

    renderer = FrameRenderer(model, config.width, config.height, depth=config.with_depth,
                             segmentation=config.with_segmentation, shadows=config.shadows,
                             antialias=config.antialias)
    labels = segmentation_labels(model) if config.with_segmentation else {}
    paths = []
    bar = tqdm(range(config.num_episodes), desc=f"simulating {config.task}", unit="episode",
               disable=not progress)
    successes = 0
    try:
        for i in bar:
            result = simulate_episode(config.task, config.seed + i, noise=config.noise,
                                      frame_stride=config.frame_stride, max_steps=config.max_steps,
                                      renderer=renderer)
            successes += result.success
            episode = RawEpisode(
                qpos=result.qpos, qvel=result.qvel, action=result.action, images=result.images,
                depth_mm=result.depth_mm, segmentation=result.segmentation,
                segmentation_labels=labels,
                info=EpisodeInfo(task=TASK_INSTRUCTIONS[config.task], source="policy",
                                 policy_name=f"scripted_{config.task}", success=result.success,
                                 sim_task=config.task, sim_seed=config.seed + i),
                fps=result.fps,
            )
            path = _episode_path(out_dir, i)
            try:
                write_episode(path, episode, compress=config.compress, jpeg_quality=config.jpeg_quality)
            except BaseException:
                # write_episode writes to a temporary name first; don't leave it behind.
                path.with_name(f".{path.name}.tmp").unlink(missing_ok=True)
                raise
            paths.append(path)
            bar.set_postfix(success=f"{successes}/{i + 1}")
    finally:
        renderer.close()
        bar.close()
    return paths

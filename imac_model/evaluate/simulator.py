"""Policies in MuJoCo: the simulator's side of the world model's closed loop.

:class:`SimRunner` runs any policy (:mod:`imac_model.evaluate.policies`) in the simulated
ALOHA rig under the closed loop's contract: the policy sees the same observation (the RGB
views and their depth at the world model's view size, the state convention, the task) and is
asked again only when its action queue is empty, at chunk boundaries. Success is read off
MuJoCo. Episodes can be written as HDF5 episodes with their success labels
(:func:`run_policy`), which ``imac build`` turns into a LeRobot dataset like any recording.
``docs/evaluation.md`` ("The two runners") has the contract."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from imac_data.core.cameras import save_calibration
from imac_data.core.metric_depth import area_resize_depth
from imac_data.core.rig import Rig
from imac_data.core.robot.platforms import simulator_platform
from imac_data.errors import InputError
from imac_data.layout import CALIBRATION, depth_key, image_key
from imac_data.sources.hdf5 import EpisodeInfo, RawEpisode, write_episode
from imac_data.sources.sim.env import FrameRenderer, SimEnv
from imac_data.sources.sim.rig import CAMERA_NAMES, RIG_CAMERAS, camera_calibration, load_mujoco_model
from imac_data.sources.sim.tasks import TASK_INSTRUCTIONS, TASKS
from imac_model.data import mosaic
from imac_model.evaluate.policies import ActionQueue, Observation, check_task, make_observation, policy_name

ACTION_DIM = 14


@dataclass(frozen=True)
class SimRunConfig:
    """One simulated evaluation protocol: task, horizon and sizes."""

    task: str = "lift"
    chunks: int = 4  # policy chunks per episode
    chunk: int = 8  # actions per chunk: the world model's H
    frame_stride: int = 5  # 50 Hz control steps per frame (5: 10 fps)
    view_height: int = 48  # what the policy sees: the world model's view size
    view_width: int = 64
    render_height: int = 96  # what is rendered and recorded
    render_width: int = 128
    views: tuple[str, ...] = tuple(CAMERA_NAMES.values())  # what the policy sees; every rig camera is recorded
    settle_s: float = 0.0  # physics run before the first frame (gym-aloha's box starts 3 cm up; 0: its start as is)

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise InputError(f"simulator: task {self.task!r} is not one of {TASKS}")
        for name in ("chunks", "chunk", "frame_stride", "view_height", "view_width", "render_height",
                     "render_width"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"simulator: {name} must be >= 1, got {getattr(self, name)}")
        unknown = [v for v in self.views if v not in RIG_CAMERAS.values()]
        if unknown or not self.views:
            raise InputError(f"simulator: views {list(self.views)}; the simulated rig has {list(RIG_CAMERAS.values())}")

    @property
    def frames(self) -> int:
        """Frames per episode: the first one and one per action."""
        return 1 + self.chunks * self.chunk


@dataclass
class SimEpisode:
    """One policy episode in MuJoCo: what was recorded, what the policy saw, how it ended."""

    seed: int
    success: bool
    max_reward: int
    policy_calls: int
    settle_s: float  # the physics run before its first frame
    qpos: np.ndarray  # (T, 14) measured
    action: np.ndarray  # (T, 14); the last frame repeats the last action, as in the world model's datasets
    images: dict[str, np.ndarray]  # every rig camera -> (T, H, W, 3) uint8 at the render size
    depth_mm: dict[str, np.ndarray]  # camera -> (T, H, W) uint16
    observations: list[Observation] = field(default_factory=list)  # what the policy was given (with keep_observations)

    def raw_episode(self, task: str, name: str, fps: float) -> RawEpisode:
        """The episode as HDF5 content: its start seed and simulated task in its attributes, so
        it can be re-simulated from its own file."""
        return RawEpisode(qpos=self.qpos, action=self.action, images=self.images, depth_mm=self.depth_mm,
                          info=EpisodeInfo(task=TASK_INSTRUCTIONS[task], source="policy", policy_name=name,
                                           success=self.success, sim_task=task, sim_seed=self.seed,
                                           sim_settle_s=self.settle_s), fps=fps)


Intervention = Callable[[SimEnv, int], None]  # (env, chunk index) at each chunk boundary, before observing


class SimRunner:
    """A policy runner in MuJoCo (see the module docstring); one renderer, reused."""

    def __init__(self, config: SimRunConfig = SimRunConfig()):
        self.config = c = config
        model = load_mujoco_model(c.task)
        self.cameras = camera_calibration(model, c.render_width, c.render_height, RIG_CAMERAS)
        self.rig = Rig.from_platform(simulator_platform(), self.cameras, task=c.task)
        self.renderer = FrameRenderer(model, c.render_width, c.render_height, cameras=RIG_CAMERAS)
        self.env = SimEnv(c.task, frame_stride=c.frame_stride, renderer=self.renderer, settle_s=c.settle_s)

    def close(self) -> None:
        self.renderer.close()

    def __enter__(self) -> SimRunner:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def fps(self) -> float:
        return self.env.fps

    @property
    def target(self) -> str:
        """What the actions drive, as errors name it."""
        return f"the simulated ALOHA rig (task {self.config.task})"

    def observe(self, rendered: dict, state: torch.Tensor) -> Observation:
        """The policy's observation of one rendered frame at the view size: RGB resized as the
        world model's data are (antialiased), depth area-resized over its valid pixels, so that
        pixel i of both stands for the ray through view pixel i's centre, the ray the rig's
        intrinsics at the view size give it."""
        c = self.config
        hw = (c.view_height, c.view_width)
        rgb = torch.stack([torch.as_tensor(rendered["rgb"][v]).permute(2, 0, 1) for v in c.views]).float() / 255.0
        depth = np.stack([rendered["depth_mm"][v] for v in c.views]).astype(np.float32) / 1000.0
        return make_observation(mosaic.resize_frames(rgb, hw), torch.from_numpy(area_resize_depth(depth, hw)), state,
                                c.views, TASK_INSTRUCTIONS[c.task])

    def reference(self, rendered: dict, codec) -> torch.Tensor:
        """A rendered frame as the world model's reference mosaic ``(3, 2h, V w)``: the
        observation's RGB over its depth in ``codec``'s colours (an intervention's frame)."""
        obs = self.observe(rendered, torch.zeros(ACTION_DIM))
        rgb = torch.stack([obs[image_key(v)] for v in self.config.views])
        depth = torch.stack([codec.encode(obs[depth_key(v)], channel_axis=0).float() for v in self.config.views])
        return mosaic.assemble(rgb, depth)

    def run_episode(self, policy, seed: int, *, intervene: Intervention | None = None,
                    keep_observations: bool = False) -> SimEpisode:
        """Run ``policy`` (a callable or an :class:`ActionQueue`) from the start of ``seed``."""
        c, env = self.config, self.env
        queue = policy if isinstance(policy, ActionQueue) else ActionQueue(policy, ACTION_DIM, self.target)
        queue.reset(int(seed))
        env.reset(int(seed))
        T = c.frames
        qpos, action = np.empty((T, ACTION_DIM)), np.empty((T, ACTION_DIM))
        images = {v: np.empty((T, c.render_height, c.render_width, 3), np.uint8) for v in self.cameras}
        depth = {v: np.empty((T, c.render_height, c.render_width), np.uint16) for v in self.cameras}
        state = torch.as_tensor(env.qpos()).float()  # measured at the first frame, then commanded
        observations = []
        frame = 0

        def record() -> dict:
            rendered = env.render()
            qpos[frame] = env.qpos()
            for v in self.cameras:
                images[v][frame] = rendered["rgb"][v]
                depth[v][frame] = rendered["depth_mm"][v]
            return rendered

        rendered = record()
        for n in range(c.chunks):
            if intervene is not None and n > 0:
                intervene(env, n)
                rendered = env.render()  # the policy sees the scene as the intervention left it
            obs = self.observe(rendered, state)
            if keep_observations:
                observations.append(obs)
            actions = queue.take(obs, c.chunk)  # (H, 14)
            for k in range(c.chunk):
                action[frame] = actions[k].double().numpy()
                env.step(action[frame])
                frame += 1
                rendered = record()
            state = self.rig.rollout(state[None], actions[None].float())[0, -1].float()
        action[frame] = action[frame - 1]
        return SimEpisode(seed=int(seed), success=env.success, max_reward=env.max_reward, policy_calls=queue.calls,
                          settle_s=env.settle_s, qpos=qpos, action=action, images=images, depth_mm=depth,
                          observations=observations)


def parse_seeds(tokens: Sequence[str]) -> list[int]:
    """``--seeds``: integers and inclusive ranges ``A..B``, in order (``0..2 7`` is 0, 1, 2, 7)."""
    seeds = []
    for token in tokens:
        text = str(token).strip()
        lo, sep, hi = text.partition("..")
        try:
            a, b = int(lo), int(hi if sep else lo)
        except ValueError:
            raise InputError(f"--seeds {text!r}: expected an integer or a range A..B (both ends included)") \
                from None
        if not 0 <= a <= b <= 2**32 - 1:
            raise InputError(f"--seeds {text!r}: seeds are integers in [0, 2^32 - 1] and a range A..B needs A <= B "
                             "(gym-aloha's samplers)")
        seeds.extend(range(a, b + 1))
    if not seeds:
        raise InputError("--seeds: no seeds given")
    return seeds


def run_policy(policy, seeds: Sequence[int], out_dir: str | Path | None = None, *,
               config: SimRunConfig = SimRunConfig(), name: str | None = None, progress: bool = True,
               runner: SimRunner | None = None) -> list[dict]:
    """Run ``policy`` from each seed's start; with ``out_dir``, write ``episode_{i}.hdf5``
    (success, policy name, start seed and task in its attributes) and ``calibration.json``
    there, each file atomically. A policy made for another task is refused before any work; a
    run that fails removes what it wrote. Returns one outcome row per episode."""
    name = name or policy_name(policy)
    config = runner.config if runner is not None else config
    check_task(policy, TASK_INSTRUCTIONS[config.task], f"--task {config.task}")
    own = runner is None
    runner = runner or SimRunner(config)
    out = Path(out_dir) if out_dir is not None else None
    made_dir = out is not None and not out.exists()
    written: list[Path] = []
    rows = []
    try:
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            written.append(out / CALIBRATION)
            save_calibration(out / f".{CALIBRATION}.tmp", runner.cameras)
            (out / f".{CALIBRATION}.tmp").replace(out / CALIBRATION)
        for i, seed in enumerate(tqdm(list(seeds), desc=f"{name} in MuJoCo", unit="episode", disable=not progress)):
            ep = runner.run_episode(policy, seed)
            if out is not None:
                written.append(out / f"episode_{i}.hdf5")
                write_episode(written[-1], ep.raw_episode(runner.config.task, name, runner.fps))
            rows.append({"episode_index": i, "seed": int(seed), "success": ep.success, "max_reward": ep.max_reward,
                         "policy_calls": ep.policy_calls})
    except BaseException:
        for path in written:  # a refused or interrupted run leaves --output as it found it
            path.unlink(missing_ok=True)
            path.with_name(f".{path.name}.tmp").unlink(missing_ok=True)
        if made_dir:
            with contextlib.suppress(OSError):
                out.rmdir()
        raise
    finally:
        if own:
            runner.close()
    return rows


__all__ = ["SimEpisode", "SimRunConfig", "SimRunner", "parse_seeds", "run_policy"]

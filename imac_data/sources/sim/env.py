"""The simulator stepped one action at a time: gym-aloha's physics, each 14-D action held for
``frame_stride`` 50 Hz control steps (10 physics substeps each, as gym-aloha), observed by the
three cameras (:class:`FrameRenderer`). The recorder and the policy runner both drive it."""

from __future__ import annotations

import numpy as np
from gym_aloha.constants import START_ARM_POSE
from gym_aloha.utils import sample_box_pose, sample_insertion_pose

from imac_data.core.mujoco_gl import mujoco
from imac_data.core.robot.aloha import ARMS
from imac_data.errors import InputError
from imac_data.sources.sim.rig import CAMERA_NAMES, CONTROL_DT, load_mujoco_model
from imac_data.sources.sim.tasks import TASKS, TaskLayout, task_reward, task_success

__all__ = ["SimEnv", "FrameRenderer", "depth_to_mm", "segmentation_labels", "robot_mask", "reset_scene"]

ROBOT_PREFIXES = tuple(ARMS)  # bodies of the vx300s_left / vx300s_right subtrees


class FrameRenderer:
    """RGB / depth / segmentation of the three ALOHA cameras with one reused
    :class:`mujoco.Renderer` (one resolution)."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int, *, depth: bool = True,
                 segmentation: bool = False, shadows: bool = False, antialias: bool = False,
                 cameras: dict[str, str] = CAMERA_NAMES, keep_qpos: bool = False):
        # Render settings live in the model's visual options (read when the GL context
        # is made); load_mujoco_model returns a private copy, so changing them is safe.
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        if not shadows:
            model.vis.quality.shadowsize = 0
        if not antialias:
            model.vis.quality.offsamples = 0
        self.model = model
        self.width, self.height = width, height
        self.with_depth, self.with_segmentation = depth, segmentation
        self.cameras = dict(cameras)
        self.renderer = mujoco.Renderer(model, height=height, width=width)
        self._option = mujoco.MjvOption()
        self._option.sitegroup[:] = 0  # sites are invisible markers; keep them out of every pass
        self.far = float(model.vis.map.zfar * model.stat.extent)
        # MuJoCo's full qpos of every rendered frame (the cube's pose too): the oracles' scene state
        self.keep_qpos, self.qpos = keep_qpos, []

    def render(self, data: mujoco.MjData) -> dict[str, dict[str, np.ndarray]]:
        """``{"rgb": {cam: (H,W,3) uint8}, "depth_mm": {cam: (H,W) uint16}, "segmentation": {cam: (H,W) int16}}``."""
        r = self.renderer
        if self.keep_qpos:
            self.qpos.append(data.qpos.copy())
        out = {"rgb": {}, "depth_mm": {}, "segmentation": {}}
        for mj_cam, name in self.cameras.items():
            r.update_scene(data, camera=mj_cam, scene_option=self._option)
            out["rgb"][name] = r.render()
            if self.with_depth:
                r.enable_depth_rendering()
                depth = r.render()
                r.disable_depth_rendering()
                out["depth_mm"][name] = depth_to_mm(depth, self.far)
            if self.with_segmentation:
                r.enable_segmentation_rendering()
                seg = r.render()
                r.disable_segmentation_rendering()
                ids = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
                out["segmentation"][name] = ids.astype(np.int16)
        return out

    def close(self) -> None:
        self.renderer.close()

    def __enter__(self) -> FrameRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def depth_to_mm(depth_m: np.ndarray, far: float) -> np.ndarray:
    """Planar z-depth in metres -> uint16 millimetres; far-plane (no hit), non-finite and
    beyond-range (> 65.535 m) pixels become 0 (invalid)."""
    mm = np.rint(np.asarray(depth_m, dtype=np.float64) * 1000.0)
    invalid = ~np.isfinite(mm) | (depth_m >= 0.999 * far) | (mm > 65535) | (mm <= 0)
    mm[invalid] = 0
    return mm.astype(np.uint16)


def segmentation_labels(model: mujoco.MjModel) -> dict[int, tuple[str, str]]:
    """{geom id: (geom name, body name)} of every geom of the model."""
    return {g: (model.geom(g).name, model.body(model.geom_bodyid[g]).name) for g in range(model.ngeom)}


def robot_mask(segmentation: np.ndarray, labels: dict[int, tuple[str, str]]) -> np.ndarray:
    """Boolean mask of the pixels showing the robot: geoms whose body is ``vx300s_left`` /
    ``vx300s_right`` or one of their descendants (gym-aloha names those ``vx300s_left/...``).

    ``segmentation`` is any-shaped int geom ids (-1 = none); ``labels`` {geom id: (geom, body)}.
    """
    seg = np.asarray(segmentation)
    robot_ids = [
        int(g) for g, (_, body) in labels.items()
        if any(body == p or body.startswith(p + "/") for p in ROBOT_PREFIXES)
    ]
    if not robot_ids:
        return np.zeros(seg.shape, dtype=bool)
    lut = np.zeros(max(max(robot_ids), int(seg.max(initial=-1))) + 2, dtype=bool)
    lut[np.array(robot_ids) + 1] = True  # shift by one so -1 (background) indexes lut[0]
    return lut[np.clip(seg.astype(np.int64), -1, None) + 1]


# --------------------------------------------------------------------------- episodes


def initial_object_poses(task: str, seed: int) -> np.ndarray:
    if task in ("transfer_cube", "lift"):
        return sample_box_pose(seed)
    return np.concatenate(sample_insertion_pose(seed))


def reset_scene(model: mujoco.MjModel, data: mujoco.MjData, layout: TaskLayout, task: str, seed: int,
                settle_s: float = 0.0) -> None:
    """gym-aloha's episode start: START_ARM_POSE, ctrl = that pose, objects from its sampler. gym-aloha
    places the box 3 cm above its resting height, so its first frame shows it in the air, falling;
    ``settle_s`` > 0 lets the physics run that long with the arms held first (the clock starts after)."""
    mujoco.mj_resetData(model, data)
    start = np.asarray(START_ARM_POSE, dtype=np.float64)
    data.qpos[:16] = start
    data.ctrl[:16] = start
    poses = initial_object_poses(task, seed).reshape(-1, 7)
    for (name, adr), pose in zip(layout.object_qadr.items(), poses):
        data.qpos[adr: adr + 7] = pose
    mujoco.mj_forward(model, data)
    steps = int(round(float(settle_s) / model.opt.timestep))
    if steps:
        mujoco.mj_step(model, data, nstep=steps)
        data.time = 0.0


class SimEnv:
    """One simulated episode at a time: :meth:`reset` to a seed's start (gym-aloha's
    ``reset(seed)``), :meth:`step` one action, :meth:`render` the cameras (with a ``renderer``),
    :attr:`success` read off the simulator."""

    def __init__(self, task: str, *, frame_stride: int = 2, renderer: FrameRenderer | None = None,
                 model: mujoco.MjModel | None = None, settle_s: float = 0.0):
        if task not in TASKS:
            raise InputError(f"unknown task {task!r}; expected one of {TASKS}")
        if renderer is not None:
            if model is not None and model is not renderer.model:
                raise InputError("SimEnv: pass either model or renderer (which has its own model), not both")
            model = renderer.model
        elif model is None:
            model = load_mujoco_model(task)
        if frame_stride < 1:
            raise InputError(f"frame_stride must be >= 1, got {frame_stride}")
        if not 0.0 <= float(settle_s) <= 10.0:
            raise InputError(f"settle_s (the physics run before the first frame; --settle) must be in [0, 10] seconds, "
                             f"got {settle_s}")
        self.settle_s = float(settle_s)
        self.task, self.frame_stride, self.renderer, self.model = task, int(frame_stride), renderer, model
        self.data = mujoco.MjData(model)
        self.layout = TaskLayout(model, task)
        self.substeps = max(1, int(round(CONTROL_DT / model.opt.timestep)))  # 10, as gym-aloha
        self.max_reward = 0

    @property
    def fps(self) -> float:
        return 1.0 / (self.frame_stride * CONTROL_DT)

    def reset(self, seed: int) -> None:
        reset_scene(self.model, self.data, self.layout, self.task, seed, self.settle_s)
        self.max_reward = 0

    def qpos(self) -> np.ndarray:
        """The 14-D joint vector (normalised grippers)."""
        return self.layout.qpos(self.data)

    def qvel(self) -> np.ndarray:
        return self.layout.qvel(self.data)

    def render(self) -> dict[str, dict[str, np.ndarray]]:
        if self.renderer is None:
            raise InputError("SimEnv: no renderer (pass renderer=FrameRenderer(...))")
        return self.renderer.render(self.data)

    def step(self, action: np.ndarray) -> None:
        """Apply a 14-D action (joint targets, normalised grippers) for ``frame_stride`` control steps."""
        self.layout.apply(self.data, np.asarray(action, dtype=np.float64))
        for _ in range(self.frame_stride):
            mujoco.mj_step(self.model, self.data, nstep=self.substeps)
            self.max_reward = max(self.max_reward, task_reward(self.layout, self.data, self.task))

    @property
    def success(self) -> bool:
        return bool(task_success(self.layout, self.data, self.task))

    def object_position(self, name: str) -> np.ndarray:
        return self.data.xpos[self.layout.object_bodies[name]].copy()

    def move_object(self, name: str, position) -> None:
        """Put object ``name`` (a free body) at ``position`` (world, metres), at rest."""
        body = self.layout.object_bodies[name]
        adr = self.layout.object_qadr[name]
        jnt = self.model.body_jntadr[body]
        dof = self.model.jnt_dofadr[jnt]
        self.data.qpos[adr:adr + 3] = np.asarray(position, dtype=np.float64)
        self.data.qvel[dof:dof + 6] = 0.0
        mujoco.mj_forward(self.model, self.data)

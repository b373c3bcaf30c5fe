"""Recordings with no calibration, and their hidden truth, for ``qa calibrate``
(``benchmarks/calibration_from_nothing.py``, ``tests/test_calibrate_from_nothing.py``).

Every scene is written as plain HDF5 episodes (joint states, RGB, depth in millimetres) in a
directory of its own, with nothing else: no calibration file, no segmentation. The truth
(:class:`~imac_data.core.cameras.Camera` per camera) is returned to the caller only.

* :func:`aloha_episodes`: gym-aloha's scripted transfer-cube episodes (the three ALOHA cameras).
* :func:`aloha_placements`: the same joint states seen by fixed cameras at random poses
  (:func:`random_placements`), rendered by MuJoCo.
* :func:`panda_episodes`: the Franka Panda URDF that pybullet ships, moving between random
  waypoints above a floor, rendered by pybullet's TinyRenderer from random placements.
* :func:`degrade_depth`: depth scaled and with Gaussian noise, as from a monocular estimator.
* :func:`sensor_depth`: the faults of a depth sensor (axial noise growing with the square of the distance,
  holes, flying pixels at depth edges).
* :func:`aloha_out_of_step`: the ALOHA episodes with the cameras out of step with the joint states
  by a known time offset (recorded at 50 fps, subsampled to 25 fps).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from imac_data.core.cameras import Camera, intrinsics_from_fovy, look_at
from imac_data.sources.hdf5 import RawEpisode, episode_paths, read_episode, write_episode

ALOHA_MOUNTS = {"cam_left_wrist": "vx300s_left/gripper_link", "cam_right_wrist": "vx300s_right/gripper_link"}
ALOHA_FOVY = {"cam_high": 78.0, "cam_left_wrist": 20.0, "cam_right_wrist": 20.0}  # gym-aloha's cameras
ALOHA_RECIPE = Path(__file__).resolve().parent.parent / "recipes" / "aloha_sim_transfer_cube.yaml"
ALOHA_NEAR = 0.166  # MuJoCo's near clip of the gym-aloha scene (znear * extent)


def aloha_episodes(out: Path, *, seed: int, episodes: int = 2, height: int = 480, width: int = 640,
                   max_steps: int | None = None) -> dict[str, Camera]:
    """Scripted transfer-cube episodes with depth into ``out`` (only the episodes); returns the truth."""
    from imac_data.core.cameras import load_calibration
    from imac_data.sources.sim.recorder import SimConfig, record_dataset

    raw = out.with_name(out.name + ".recorded")
    record_dataset(SimConfig(num_episodes=episodes, width=width, height=height, seed=seed, noise=0.0,
                             max_steps=max_steps), raw, progress=False, overwrite=True)
    out.mkdir(parents=True, exist_ok=True)
    for p in episode_paths(raw):
        shutil.move(str(p), out / p.name)
    truth = load_calibration(raw / "calibration.json")
    shutil.rmtree(raw)
    return truth


def random_placements(n: int, seed: int, *, centre, front, lo: float = 1.0, hi: float = 2.0,
                      base=(0.0, 0.0, 0.0)) -> list[np.ndarray]:
    """``n`` camera poses (OpenCV camera-to-world) over the upper hemisphere in front of the robot:
    azimuth within 80 degrees of ``front``, elevation 15-75 degrees, ``lo``-``hi`` metres from
    ``base``, looking at ``centre`` (jittered by up to 5 cm)."""
    rng = np.random.default_rng(seed)
    front = np.asarray(front, float) / np.linalg.norm(front)
    az0 = np.arctan2(front[1], front[0])
    poses = []
    for _ in range(n):
        az = az0 + np.radians(rng.uniform(-80, 80))
        el = np.radians(rng.uniform(15, 75))
        r = rng.uniform(lo, hi)
        eye = np.asarray(base) + r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        poses.append(look_at(eye, np.asarray(centre) + rng.uniform(-0.05, 0.05, 3)))
    return poses


def _write(out: Path, name: str, q: np.ndarray, images: dict, depth_mm: dict) -> None:
    write_episode(out / f"{name}.hdf5", RawEpisode(qpos=q, action=q, images=images, depth_mm=depth_mm), sim=False)


def aloha_placements(out: Path, source: Path, poses: list[np.ndarray], *, fovy: float = 60.0, height: int = 480,
                     width: int = 640, stride: int = 4) -> dict[str, Camera]:
    """The joint states of ``source``'s episodes (every ``stride``-th frame) seen by fixed cameras at
    ``poses``, rendered by MuJoCo (RGB, depth); cameras ``cam_rand_00``...; returns the truth."""
    from imac_data.core.mujoco_gl import mujoco
    from imac_data.sources.sim.env import FrameRenderer
    from imac_data.sources.sim.rig import camera_calibration, set_mujoco_qpos

    names = {f"rand{k:02d}": f"cam_rand_{k:02d}" for k in range(len(poses))}
    model = _with_cameras(names, poses, fovy)
    truth = camera_calibration(model, width, height, cameras=names)
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    out.mkdir(parents=True, exist_ok=True)
    with FrameRenderer(model, width, height, cameras=names) as r:
        for p in episode_paths(source):
            q = read_episode(p, load_depth=False).qpos[::stride]
            imgs = {c: [] for c in names.values()}
            dep = {c: [] for c in names.values()}
            for qt in q:
                set_mujoco_qpos(model, data, qt)
                mujoco.mj_forward(model, data)
                frame = r.render(data)
                for c in names.values():
                    imgs[c].append(frame["rgb"][c])
                    dep[c].append(frame["depth_mm"][c])
            _write(out, p.stem, q, {c: np.stack(v) for c, v in imgs.items()}, {c: np.stack(v) for c, v in dep.items()})
    return truth


def _with_cameras(names: dict[str, str], poses, fovy: float):
    """gym-aloha's transfer-cube scene with fixed cameras added on the world body at ``poses``."""
    from imac_data.core.mujoco_gl import mujoco
    from imac_data.core.robot.aloha import mjcf_path

    spec = mujoco.MjSpec.from_file(str(mjcf_path("transfer_cube")))
    for (mj, _), T in zip(names.items(), poses):
        x, y = T[:3, 0], -T[:3, 1]  # MuJoCo cameras: x right, y up, looking down -z
        spec.worldbody.add_camera(name=mj, pos=T[:3, 3], xyaxes=np.r_[x, y], fovy=fovy)
    return spec.compile()


def degrade_depth(src: Path, out: Path, camera: str, *, scale: float, noise: float, seed: int) -> None:
    """Copy ``src``'s episodes to ``out`` with ``camera``'s depth multiplied by ``scale`` and Gaussian
    noise of ``noise`` times the range added (float millimetres; invalid stays 0)."""
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    for p in episode_paths(src):
        ep = read_episode(p)
        d = ep.depth_mm[camera].astype(np.float32)
        valid = d > 0
        d = d * scale * (1.0 + noise * rng.standard_normal(d.shape).astype(np.float32))
        ep.depth_mm[camera] = np.where(valid, np.maximum(d, 1.0), 0.0).astype(np.float32)
        write_episode(out / p.name, ep, sim=False)


def sensor_faults(d: np.ndarray, rng: np.random.Generator, *, axial: float = 0.002, holes: float = 0.05,
                  hole_px: int = 6, edge_mm: float = 50.0, flying: float = 0.5) -> np.ndarray:
    """One depth image ``(H, W)`` in millimetres (0 = invalid) as a stereo or time-of-flight sensor gives it:
    Gaussian axial noise of ``axial`` z^2 (metres), square holes of ``hole_px`` covering about ``holes`` of the
    image, and at depth edges (a neighbour more than ``edge_mm`` away) ``flying`` of the pixels mixed between
    their depth and the neighbour's, at a uniform ratio."""
    z = d.astype(np.float64) / 1000.0
    valid = d > 0
    out = z + axial * z**2 * rng.standard_normal(z.shape)
    far = np.zeros_like(z)  # each pixel's most distant 4-neighbour across an edge, 0 where none
    for axis in (0, 1):
        for shift in (1, -1):
            n = np.roll(z, shift, axis=axis)
            edge = valid & (n > 0) & (np.abs(n - z) * 1000.0 > edge_mm) & ((far == 0) | (np.abs(n - z) > np.abs(far - z)))
            far = np.where(edge, n, far)
    fly = (far > 0) & (rng.random(z.shape) < flying)
    out = np.where(fly, z + rng.random(z.shape) * (far - z), out)
    H, W = z.shape
    blocks = rng.random(((H + hole_px - 1) // hole_px, (W + hole_px - 1) // hole_px)) < holes
    hole = np.kron(blocks, np.ones((hole_px, hole_px), bool))[:H, :W]
    return np.where(valid & ~hole, np.maximum(out, 1e-3) * 1000.0, 0.0).astype(np.float32)


def sensor_depth(src: Path, out: Path, *, seed: int, **faults) -> None:
    """Copy ``src``'s episodes to ``out`` with every camera's depth through :func:`sensor_faults` (float mm)."""
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    for p in episode_paths(src):
        ep = read_episode(p)
        for camera, depth in ep.depth_mm.items():
            ep.depth_mm[camera] = np.stack([sensor_faults(d, rng, **faults) for d in depth])
        write_episode(out / p.name, ep, sim=False)


def aloha_recorded_50fps(out: Path, *, seed: int, episodes: int = 1, height: int = 480, width: int = 640,
                         max_steps: int | None = None) -> dict[str, Camera]:
    """Scripted transfer-cube episodes recorded at every 50 Hz control step (``frame_stride`` 1) into
    ``out``: the raw material of :func:`aloha_out_of_step`; returns the truth."""
    from imac_data.core.cameras import load_calibration
    from imac_data.sources.sim.recorder import SimConfig, record_dataset

    record_dataset(SimConfig(num_episodes=episodes, width=width, height=height, seed=seed, noise=0.0, frame_stride=1,
                             max_steps=max_steps), out, progress=False, overwrite=True)
    truth = load_calibration(out / "calibration.json")
    (out / "calibration.json").unlink()
    return truth


def aloha_out_of_step(source: Path, out: Path, offset_steps: int | dict[str, int], *, stride: int = 2
                      ) -> float | dict[str, float]:
    """``source``'s 50 fps episodes (:func:`aloha_recorded_50fps`) at 50 / ``stride`` fps with the
    cameras out of step: frame k keeps the joint states (and actions) of control step ``stride * k``,
    and its RGB and depth are those of step ``stride * k + offset_steps``, so the images show the robot
    ``offset_steps`` control steps (20 ms each) later than its joint states say; negative: earlier (the
    cameras lag, as USB cameras often do). Frames whose image step falls outside the recording are
    dropped; ``offset_steps`` may be a dict, one per camera (0 for the others). Returns the offset in seconds (the image's time minus the joint states' time), which
    includes the simulator's own: its frames are rendered from MuJoCo's kinematics of the step's last
    physics substep (``mj_step`` computes positions before it integrates), so even in step they show
    the robot one physics step (2 ms) earlier than the recorded joint states (:func:`sim_render_lag`)."""
    out.mkdir(parents=True, exist_ok=True)
    lag = sim_render_lag()
    for p in episode_paths(source):
        ep = read_episode(p)
        n = len(ep.qpos)
        steps = {c: offset_steps.get(c, 0) if isinstance(offset_steps, dict) else offset_steps for c in ep.images}
        k = np.arange(0, n, stride)
        k = k[(k + min(steps.values()) >= 0) & (k + max(steps.values()) < n)]
        write_episode(out / p.name, RawEpisode(qpos=ep.qpos[k], action=ep.action[k],
                                               images={c: v[k + steps[c]] for c, v in ep.images.items()},
                                               depth_mm={c: v[k + steps[c]] for c, v in ep.depth_mm.items()},
                                               fps=50.0 / stride), sim=False)
    if isinstance(offset_steps, dict):
        return {c: s * 0.02 - lag for c, s in steps.items()}
    return offset_steps * 0.02 - lag


def sim_render_lag() -> float:
    """How much earlier than its recorded joint states the simulator's frames show the robot (seconds):
    one physics step of the gym-aloha scene (the recorder renders after ``mj_step`` without ``mj_forward``)."""
    from imac_data.core.mujoco_gl import mujoco
    from imac_data.core.robot.aloha import mjcf_path

    return float(mujoco.MjModel.from_xml_path(str(mjcf_path("transfer_cube"))).opt.timestep)


# ----------------------------------------------------------------------------- Franka Panda (pybullet)

PANDA_CENTRE = (0.35, 0.0, 0.35)


def panda_recipe(out: Path) -> Path:
    """A recipe for the Panda of the ``pybullet`` package (no robot-specific code anywhere else)."""
    from benchmarks.panda_vs_pybullet import ARM, FINGER, panda_paths

    urdf, meshes = panda_paths()
    path = out / "panda.yaml"
    joints = "\n".join(f"    - {j}" for j in (*ARM, FINGER))
    path.write_text(f"name: panda_bench\ntask: move\nrobot:\n  urdf: {urdf}\n  package_dirs:\n    meshes: {meshes}\n"
                    f"  joint_map:\n{joints}\n  gripper_links: [panda_leftfinger, panda_rightfinger]\n"
                    f"source:\n  type: aloha_hdf5\n  path: {out / 'episodes'}\n"
                    "cameras:\n  calibration: calib.json  # what qa calibrate writes\n")
    return path


def panda_trajectory(seed: int, frames: int = 60, waypoints: int = 6) -> np.ndarray:
    """``(frames, 8)`` joint vectors moving linearly between random waypoints in the joint limits
    whose links stay above the floor (z > 5 cm)."""
    import torch

    from benchmarks.panda_vs_pybullet import panda_config, random_configs
    from imac_data.core.robot.model import RobotModel

    robot = RobotModel(panda_config())
    cand = random_configs(200, seed)
    poses = robot.link_poses(torch.as_tensor(cand))
    low = np.min([poses[n].numpy()[:, 2, 3] for n in poses if n not in ("panda_link0", "panda_link1")], axis=0)
    good = cand[low > 0.05][:waypoints]
    t = np.linspace(0, len(good) - 1, frames)
    i = np.minimum(t.astype(int), len(good) - 2)
    return good[i] + (t - i)[:, None] * (good[i + 1] - good[i])


def panda_episodes(out: Path, poses: list[np.ndarray], *, seed: int, fovy: float = 60.0, height: int = 480,
                   width: int = 640, episodes: int = 2, frames: int = 60) -> dict[str, Camera]:
    """The Panda on a floor plane, rendered by pybullet from fixed cameras at ``poses``
    (``cam_rand_00``...), into ``out/episodes``; returns the truth."""
    from benchmarks.panda_vs_pybullet import FAR, NEAR, PyBulletPanda

    K = intrinsics_from_fovy(fovy, width, height)
    names = [f"cam_rand_{k:02d}" for k in range(len(poses))]
    truth = {c: Camera(c, K, width, height, T_world_cam=T) for c, T in zip(names, poses)}
    bullet = PyBulletPanda()
    p, cid = bullet.p, bullet.client
    try:
        import pybullet_data

        p.loadURDF(str(Path(pybullet_data.getDataPath()) / "plane.urdf"), physicsClientId=cid)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        proj = p.computeProjectionMatrix(-cx / fx * NEAR, (width - cx) / fx * NEAR, -(height - 1 - cy) / fy * NEAR,
                                         (cy + 1) / fy * NEAR, NEAR, FAR)
        (out / "episodes").mkdir(parents=True, exist_ok=True)
        for e in range(episodes):
            q = panda_trajectory(seed * 100 + e, frames)
            imgs = {c: [] for c in names}
            dep = {c: [] for c in names}
            for qt in q:
                bullet.set(qt)
                for c, T in zip(names, poses):
                    view = np.linalg.inv(T @ np.diag([1.0, -1.0, -1.0, 1.0]))
                    _, _, rgb, buf, seg = p.getCameraImage(width, height, viewMatrix=view.flatten(order="F").tolist(),
                                                           projectionMatrix=proj, renderer=p.ER_TINY_RENDERER,
                                                           physicsClientId=cid)
                    buf = np.asarray(buf, np.float64).reshape(height, width)
                    z = FAR * NEAR / (FAR - (FAR - NEAR) * buf)
                    hit = np.asarray(seg).reshape(height, width) >= 0
                    imgs[c].append(np.asarray(rgb, np.uint8).reshape(height, width, 4)[..., :3])
                    dep[c].append(np.where(hit, np.rint(z * 1000), 0).astype(np.uint16))
            _write(out / "episodes", f"episode_{e}", q, {c: np.stack(v) for c, v in imgs.items()},
                   {c: np.stack(v) for c, v in dep.items()})
    finally:
        bullet.close()
    return truth

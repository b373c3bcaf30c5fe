"""A second robot, not shipped by the project: the Franka Panda URDF inside the ``pybullet``
package, through our Python API, against PyBullet as an independent oracle.

    python -m benchmarks.panda_vs_pybullet [--configs N] [--height H --width W] [--json PATH]

* **FK**: our :class:`~imac_data.core.robot.model.RobotModel` (pytorch-kinematics, plus our mimic,
  axis and material handling) against PyBullet's own URDF loader and
  ``getLinkState(computeForwardKinematics=1)`` link frames, over random configurations
  in the joint limits (the second finger follows the first through ``<mimic>`` on our
  side, set explicitly on PyBullet's).
* **Render**: our :class:`~imac_data.core.render.RaycastRenderer` against PyBullet's CPU
  software rasteriser (``ER_TINY_RENDERER``): robot mask IoU against its segmentation
  mask, link agreement against its per-link segmentation, |z-depth error| on pixels both
  call robot (its depth buffer converted to z-depth), for a fixed head camera and a wrist
  camera mounted on ``panda_hand``.

PyBullet's camera is an OpenGL view + projection pair. The projection is the frustum of
our K at the near plane. TinyRenderer samples pixel ``(i, j)`` at the integer window
coordinate ``(i, j)`` (OpenGL would sample ``i + 0.5``) and flips rows, so the frustum
that puts its pixel centres where K puts them is ``left = -cx/fx n``, ``right =
(W - cx)/fx n``, ``top = (cy + 1)/fy n``, ``bottom = -(H - 1 - cy)/fy n`` (measured: the
half-pixel variants lose 3-6 points of IoU and bias depth by millimetres). Both sides clip at
the same near plane.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from imac_data.core.cameras import Camera, look_at
from imac_data.core.render import RaycastRenderer
from imac_data.core.robot.model import RobotConfig, RobotModel

ARM = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER, FINGER_MIMIC = "panda_finger_joint1", "panda_finger_joint2"
NEAR, FAR = 0.02, 5.0


def panda_paths() -> tuple[Path, Path]:
    """The Panda URDF shipped in the ``pybullet`` wheel and the directory its ``package://meshes/`` means."""
    import pybullet_data

    d = Path(pybullet_data.getDataPath()) / "franka_panda"
    return d / "panda.urdf", d / "meshes"


def panda_config() -> RobotConfig:
    urdf, meshes = panda_paths()
    return RobotConfig("panda", urdf, joint_map=(*ARM, FINGER),
                       gripper_links=("panda_leftfinger", "panda_rightfinger"), package_dirs={"meshes": meshes})


def panda_cameras(height: int = 240, width: int = 320) -> dict[str, Camera]:
    """A head camera looking at the arm, and a wrist camera on the hand looking at the fingers."""
    f = 0.875 * width
    K = np.array([[f, 0, (width - 1) / 2 + 1.3], [0, f, (height - 1) / 2 - 0.8], [0, 0, 1]])
    K_wrist = np.array([[0.5 * width, 0, (width - 1) / 2], [0, 0.5 * width, (height - 1) / 2], [0, 0, 1]])
    return {
        "cam_high": Camera("cam_high", K, width, height, T_world_cam=look_at([1.4, 0.9, 1.0], [0.0, 0.0, 0.45])),
        # hand frame: z along the fingers (they sit at z ~ 0.06-0.11), y across them
        "cam_wrist": Camera("cam_wrist", K_wrist, width, height, link="panda_hand",
                            T_link_cam=look_at([0.09, 0.0, -0.02], [0.0, 0.0, 0.09], up=(0.0, 0.0, 1.0))),
    }


def random_configs(n: int, seed: int = 0) -> np.ndarray:
    """``(n, 8)`` dataset vectors (7 arm joints, finger opening in metres) uniform in the URDF limits."""
    import yourdfpy

    urdf = yourdfpy.URDF.load(str(panda_paths()[0]), build_scene_graph=False, load_meshes=False)
    lim = {j.name: (j.limit.lower, j.limit.upper) for j in urdf.robot.joints if j.limit is not None}
    lo, hi = np.array([lim[n] for n in (*ARM, FINGER)]).T
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, len(lo)))


class PyBulletPanda:
    """The same URDF in PyBullet (DIRECT, no GUI): FK link frames, TinyRenderer mask/link/depth."""

    def __init__(self):
        import pybullet

        self.p = pybullet
        self.client = pybullet.connect(pybullet.DIRECT)
        self.uid = pybullet.loadURDF(str(panda_paths()[0]), useFixedBase=True, physicsClientId=self.client)
        infos = [pybullet.getJointInfo(self.uid, j, physicsClientId=self.client)
                 for j in range(pybullet.getNumJoints(self.uid, physicsClientId=self.client))]
        self.joint_index = {i[1].decode(): i[0] for i in infos}
        self.link_index = {i[12].decode(): i[0] for i in infos}  # link index = its parent joint's index
        self.link_index[pybullet.getBodyInfo(self.uid, physicsClientId=self.client)[0].decode()] = -1

    def close(self) -> None:
        self.p.disconnect(self.client)

    def set(self, q: np.ndarray) -> None:
        for name, value in zip((*ARM, FINGER), q):
            self.p.resetJointState(self.uid, self.joint_index[name], float(value), physicsClientId=self.client)
        self.p.resetJointState(self.uid, self.joint_index[FINGER_MIMIC], float(q[7]), physicsClientId=self.client)

    def link_poses(self) -> dict[str, np.ndarray]:
        out = {}
        for name, i in self.link_index.items():
            if i < 0:  # the base's pose is its inertial frame's: undo the <inertial> origin
                pos, quat = self.p.getBasePositionAndOrientation(self.uid, physicsClientId=self.client)
                dyn = self.p.getDynamicsInfo(self.uid, -1, physicsClientId=self.client)
                out[name] = self._matrix(pos, quat) @ np.linalg.inv(self._matrix(dyn[3], dyn[4]))
            else:
                state = self.p.getLinkState(self.uid, i, computeForwardKinematics=1, physicsClientId=self.client)
                out[name] = self._matrix(state[4], state[5])  # the URDF link frame (not the inertial frame)
        return out

    def _matrix(self, pos, quat) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = np.array(self.p.getMatrixFromQuaternion(quat)).reshape(3, 3)
        T[:3, 3] = pos
        return T

    def render(self, K: np.ndarray, T_world_cam: np.ndarray, height: int, width: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(mask, link index (-2 = background, -1 = base), z-depth in metres, 0 off the robot)."""
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        proj = self.p.computeProjectionMatrix(-cx / fx * NEAR, (width - cx) / fx * NEAR,
                                              -(height - 1 - cy) / fy * NEAR, (cy + 1) / fy * NEAR, NEAR, FAR)
        view = np.linalg.inv(T_world_cam @ np.diag([1.0, -1.0, -1.0, 1.0]))  # OpenCV -> OpenGL camera, inverted
        _, _, _, depth, seg = self.p.getCameraImage(
            width, height, viewMatrix=view.flatten(order="F").tolist(), projectionMatrix=proj,
            renderer=self.p.ER_TINY_RENDERER, flags=self.p.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
            physicsClientId=self.client)
        seg = np.asarray(seg, dtype=np.int64).reshape(height, width)
        buf = np.asarray(depth, dtype=np.float64).reshape(height, width)
        mask = (seg >= 0) & ((seg & ((1 << 24) - 1)) == self.uid)
        link = np.where(mask, (seg >> 24) - 1, -2)
        z = FAR * NEAR / (FAR - (FAR - NEAR) * buf)  # OpenGL depth buffer -> z-depth
        return mask, link, np.where(mask, z, 0.0)


def compare(configs: np.ndarray, height: int = 240, width: int = 320) -> dict:
    """Every figure of the module docstring, over ``configs`` ``(N, 8)``."""
    robot = RobotModel(panda_config())
    cameras = panda_cameras(height, width)
    renderer = RaycastRenderer(robot, near=NEAR)
    bullet = PyBulletPanda()
    try:
        q = torch.as_tensor(configs, dtype=torch.float64)
        poses = robot.link_poses(q)
        t0, c0 = time.perf_counter(), time.process_time()
        views = renderer.render(q.float(), cameras)
        ours_s, ours_cpu = time.perf_counter() - t0, time.process_time() - c0
        fk_pos = fk_rot = 0.0
        stats = {name: {"iou": [], "link_agree": [], "err": []} for name in cameras}
        pb_s = pb_cpu = 0.0
        link_names = np.array(renderer.link_names)
        for k, qk in enumerate(configs):
            bullet.set(qk)
            for name, T in bullet.link_poses().items():
                ours = poses[name][k].numpy()
                fk_pos = max(fk_pos, float(np.abs(ours[:3, 3] - T[:3, 3]).max()))
                fk_rot = max(fk_rot, float(np.abs(ours[:3, :3] - T[:3, :3]).max()))
            for name, cam in cameras.items():
                T_wc = cam.pose({"panda_hand": poses["panda_hand"][k]}).numpy() if cam.is_mounted else cam.T_world_cam
                t0, c0 = time.perf_counter(), time.process_time()
                mask, link, z = bullet.render(cam.K, T_wc, height, width)
                pb_s, pb_cpu = pb_s + time.perf_counter() - t0, pb_cpu + time.process_time() - c0
                ours = views[name]
                om, oz = ours.mask[k].numpy(), ours.depth[k].numpy()
                both = mask & om
                stats[name]["iou"].append(both.sum() / max((mask | om).sum(), 1))
                bullet_link = np.array([bullet.link_index[n] for n in link_names])[ours.link_id[k].numpy()[both]]
                stats[name]["link_agree"].append(float((bullet_link == link[both]).mean()) if both.any() else 1.0)
                stats[name]["err"].append(np.abs(z[both] - oz[both]))
        out = {"configs": len(configs), "height": height, "width": width, "fk_max_pos_err_m": fk_pos,
               "fk_max_rot_err": fk_rot, "ours_render_ms_per_view": 1e3 * ours_s / (len(configs) * len(cameras)),
               "ours_render_cpu_ms_per_view": 1e3 * ours_cpu / (len(configs) * len(cameras)),
               "pybullet_render_ms_per_view": 1e3 * pb_s / (len(configs) * len(cameras)),
               "pybullet_render_cpu_ms_per_view": 1e3 * pb_cpu / (len(configs) * len(cameras))}
        for name, s in stats.items():
            err = np.concatenate(s["err"])
            out[f"{name}_iou_mean"] = float(np.mean(s["iou"]))
            out[f"{name}_iou_min"] = float(np.min(s["iou"]))
            out[f"{name}_link_agreement"] = float(np.mean(s["link_agree"]))
            out[f"{name}_depth_err_median_mm"] = float(np.median(err) * 1e3)
            out[f"{name}_depth_err_p99_mm"] = float(np.percentile(err, 99) * 1e3)
            out[f"{name}_robot_px_mean"] = float(np.mean([v.sum() for v in views[name].mask.numpy()]))
        return out
    finally:
        bullet.close()


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--configs", type=int, default=50)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    load0 = os.getloadavg()
    res = compare(random_configs(args.configs, args.seed), args.height, args.width)
    res["load_avg"] = [load0, os.getloadavg()]
    width = max(map(len, res))
    for key, value in res.items():
        print(f"{key:<{width}}  {value:.6g}" if isinstance(value, float) and math.isfinite(value)
              else f"{key:<{width}}  {value}")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))
    return res


if __name__ == "__main__":
    main()

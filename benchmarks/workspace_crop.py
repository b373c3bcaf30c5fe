"""The workspace crop on a recorded grasp with far and saturated depth, in one command:

    python -m benchmarks.workspace_crop

The scripted ``transfer_cube`` episode of ``tests/test_contact.py`` (240x320, 25 fps, 60
frames). For the chunks with references 24, 48 and 56 (approach, closing in, squeezing the
cube), the reference depth is poisoned as in the test. The head camera's top quarter and the
left wrist camera's bottom sixth become an 8 m background, and 2 % of the pixels of every view
are set to 65.535 m (uint16 saturation); the cube's pixels are left alone. Printed per chunk:
the caps of the clean and the poisoned depth, without and with the default workspace. Then,
over the frames where MuJoCo's finger-cube distance (``mj_geomDistance``) is under 5 cm: the
largest error of the raw s2g distance and of the distance read back from the stored colour.
Also the reach box and its cost, with the load average.
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch


def main() -> None:
    import mujoco

    from imac_data.core.contact.images import JET_LUT, contact_chunk
    from imac_data.core.contact.workspace import resolve_workspace, saturation_depth
    from imac_data.core.depth import DepthCodec
    from imac_data.core.rig import Rig
    from imac_data.core.robot.aloha import robot_config
    from imac_data.core.robot.model import RobotModel
    from imac_data.sources.sim.env import FrameRenderer
    from imac_data.sources.sim.recorder import simulate_episode
    from imac_data.sources.sim.rig import camera_calibration, load_mujoco_model

    model = load_mujoco_model("transfer_cube")
    cap = FrameRenderer(model, 320, 240, segmentation=True, keep_qpos=True)
    try:
        ep = simulate_episode("transfer_cube", seed=0, frame_stride=2, max_steps=120, renderer=cap)
    finally:
        cap.close()
    robot = RobotModel(robot_config())
    rig = Rig(robot, camera_calibration(model, 320, 240))
    t, c = time.perf_counter(), time.process_time()
    ws = resolve_workspace(None, robot, saturation_depth(DepthCodec.preset("manipulation")))
    print(f"reach box {ws.min} .. {ws.max} (diagonal {ws.diagonal:.3f} m), depth range {ws.depth_range}: "
          f"{time.perf_counter() - t:.2f} s wall, {time.process_time() - c:.2f} s CPU, load {os.getloadavg()}")
    names = rig.names
    depth = torch.stack([torch.as_tensor(ep.depth_mm[n].astype(np.float32) / 1000.0) for n in names], 1)
    seg = np.stack([ep.segmentation[n] for n in names], 1)
    q = torch.as_tensor(ep.qpos, dtype=torch.float32)
    views = rig.robot_views(q)
    K = rig.intrinsics()
    data = mujoco.MjData(model)
    box = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "red_box")
    adr = model.jnt_qposadr[model.body_jntadr[model.geom_bodyid[box]]]
    fingers = [g for g in range(model.ngeom) if "finger" in model.geom(g).name]
    lut = {int(k): i for i, k in enumerate((JET_LUT[:, 0].astype(np.int64) << 16)
                                           | (JET_LUT[:, 1].astype(np.int64) << 8) | JET_LUT[:, 2])}

    def mj_distance(g):
        fromto = np.zeros(6)
        d = mujoco.mj_geomDistance(model, data, g, box, 0.2, fromto)
        return None if d < 0.2 and abs(np.linalg.norm(fromto[3:] - fromto[:3]) - abs(d)) > 1e-4 else d

    rng = np.random.default_rng(0)
    errors = {"cropped": [], "uncropped": []}
    for ref in (24, 48, 56):
        frames = list(range(ref + 1, min(ref + 9, len(q))))
        cube = torch.as_tensor(seg[ref] == box)
        poisoned = depth[ref].clone()
        far = torch.zeros_like(cube)
        far[0, :60], far[1, 200:] = True, True
        poisoned[far & ~cube] = 8.0
        poisoned[torch.as_tensor(rng.random(cube.shape) < 0.02) & ~cube] = 65.535
        caps = {}
        for label, d in (("clean", depth[ref]), ("poisoned", poisoned)):
            for crop in ("uncropped", "cropped"):
                t, c = time.perf_counter(), time.process_time()
                chunk = contact_chunk(d, K, views.T_world_cam[ref], views.mask[ref], views.depth[frames],
                                      views.T_world_cam[frames], views.gripper_points[frames],
                                      workspace=ws if crop == "cropped" else None)
                caps[label, crop] = (chunk.caps.tolist(), time.perf_counter() - t, time.process_time() - c)
                if label != "poisoned":
                    continue
                cap_s = float(chunk.caps[1])
                rgb = chunk.s2g_rgb.to(torch.int64)
                keys = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
                for i, f in enumerate(frames):
                    data.qpos[:] = cap.qpos[f]
                    data.qpos[adr:adr + 7] = cap.qpos[ref][adr:adr + 7]
                    mujoco.mj_kinematics(model, data)
                    dists = [mj_distance(g) for g in fingers]
                    if any(d is None for d in dists):
                        continue  # MuJoCo's answer contradicts its own witness points (as in the test)
                    mj = max(min(dists), 0.0)
                    sel = cube & torch.isfinite(chunk.s2g[i])
                    if mj >= 0.05 or not sel.any():
                        continue
                    levels = np.array([lut.get(int(k), -1) for k in keys[i][sel].tolist()])
                    stored = cap_s * (1 - (levels[levels >= 0] + 0.5) / 256)
                    errors[crop].append((mj, float(chunk.s2g[i][sel].min()), float(stored.min())))
        print(f"chunk {ref}: " + "; ".join(f"{lab} {crop} caps {v[0][0]:.3f}, {v[0][1]:.3f} m "
                                           f"({v[1]:.2f} s wall, {v[2]:.2f} s CPU)"
                                           for (lab, crop), v in caps.items()))
    for crop, rows in errors.items():
        e = np.array(rows)
        print(f"poisoned, {crop}: {len(e)} frames within 5 cm of MuJoCo's contact; largest error of the raw s2g "
              f"{1e3 * np.abs(e[:, 1] - e[:, 0]).max():.2f} mm, of the stored colour "
              f"{1e3 * np.abs(e[:, 2] - e[:, 0]).max():.2f} mm")
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main()

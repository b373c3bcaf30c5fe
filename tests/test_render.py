"""Motion-image renderer and the QA overlay, with MuJoCo as the oracle.

MuJoCo renders the same (frozen-camera) gym-aloha model at the same joint
configurations: its segmentation of the robot geoms and its depth buffer are the
reference for our mask, link ids and z-depth. The MuJoCo oracle hides every
non-robot geom (table, props, floor), so it shows exactly what we render (the
robot alone); our renderer gets MuJoCo's near plane (``znear * extent``, which
clips close geometry in the wrist views) so both clip alike. An analytic scene
(one box at a known distance) checks depth, colour and shading independently of
MuJoCo. The whole-episode comparison and timings are in
``benchmarks/render_vs_mujoco.py``.
"""

from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest
import torch
from gym_aloha.constants import START_ARM_POSE, unnormalize_puppet_gripper_position

from imac_data.cli import main as imac_main
from imac_data.core.cameras import Camera, backproject, save_calibration
from imac_data.core.render import BACKENDS, RasterRenderer, RaycastRenderer, Renderer, RenderOutput, make_renderer
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotConfig, RobotModel
from imac_data.errors import InputError
from imac_data.sources.sim import rig as sim_rig

H, W = 240, 320
N_FRAMES = 6
IOU_MIN = {"cam_high": 0.97, "cam_left_wrist": 0.95, "cam_right_wrist": 0.95}
DEPTH_MEDIAN_MAX = 0.002  # m


# ----------------------------------------------------------------------------- MuJoCo oracle


def robot_geoms(model: mujoco.MjModel) -> np.ndarray:
    """Geoms of the bodies under vx300s_left / vx300s_right."""
    return np.array([g for g in range(model.ngeom)
                     if any(model.body(model.geom_bodyid[g]).name.startswith(a + "/")
                            or model.body(model.geom_bodyid[g]).name == a for a in aloha.ARMS)])


class MujocoOracle:
    """Segmentation + depth (+ RGB) of gym-aloha's frozen-camera model at dataset vectors."""

    def __init__(self, task: str, height: int, width: int, robot_only: bool = True):
        model = sim_rig.load_mujoco_model(task)
        model.vis.quality.shadowsize = 0
        model.vis.quality.offsamples = 0
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        self.robot = robot_geoms(model)
        if robot_only:  # group 5 is hidden by default
            others = np.setdiff1d(np.arange(model.ngeom), self.robot)
            model.geom_group[others] = 5
        self.model, self.data = model, mujoco.MjData(model)
        self.renderer = mujoco.Renderer(model, height=height, width=width)
        self.option = mujoco.MjvOption()
        self.option.sitegroup[:] = 0
        self.near = float(model.vis.map.znear * model.stat.extent)
        self.far = float(model.vis.map.zfar * model.stat.extent)
        self.lut = np.full(model.ngeom + 1, False)
        self.lut[self.robot + 1] = True
        self.body_of_geom = np.r_[-1, model.geom_bodyid]

    def set(self, q14: np.ndarray) -> None:
        m, d = self.model, self.data
        if m.nkey:
            mujoco.mj_resetDataKeyframe(m, d, 0)
        for k, arm in enumerate(aloha.ARMS):
            for i, j in enumerate(aloha.ARM_JOINTS):
                d.qpos[m.joint(f"{arm}/{j}").qposadr[0]] = q14[7 * k + i]
            finger = unnormalize_puppet_gripper_position(q14[7 * k + 6])
            d.qpos[m.joint(f"{arm}/left_finger").qposadr[0]] = finger
            d.qpos[m.joint(f"{arm}/right_finger").qposadr[0]] = -finger
        mujoco.mj_forward(m, d)

    def render(self, q14: np.ndarray, rgb: bool = False) -> dict[str, dict[str, np.ndarray]]:
        """{dataset camera: {"geom": (H,W) geom id or -1, "mask", "depth" (m, 0 = none)[, "rgb"]}}."""
        self.set(q14)
        r, out = self.renderer, {}
        for mj_cam, name in sim_rig.CAMERA_NAMES.items():
            r.update_scene(self.data, camera=mj_cam, scene_option=self.option)
            view = {}
            if rgb:
                view["rgb"] = r.render().copy()
            r.enable_segmentation_rendering()
            seg = r.render().copy()
            r.disable_segmentation_rendering()
            r.enable_depth_rendering()
            depth = r.render().copy()
            r.disable_depth_rendering()
            geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
            view["geom"] = geom
            view["mask"] = self.lut[geom + 1]
            view["depth"] = np.where(depth < 0.999 * self.far, depth, 0.0)
            out[name] = view
        return out

    def close(self) -> None:
        self.renderer.close()


def workspace_configs(n: int, seed: int) -> np.ndarray:
    """A smooth sequence of realistic configurations around gym-aloha's start pose
    (both grippers in the head view, wrist cameras looking over the table)."""
    rng = np.random.default_rng(seed)
    start = np.asarray(START_ARM_POSE, dtype=float)
    base = np.r_[start[0:6], 0.5, start[8:14], 0.5]
    spread = np.array([0.5, 0.35, 0.35, 0.6, 0.5, 0.8, 0.5] * 2)
    key = base + rng.uniform(-1, 1, (2, 14)) * spread
    s = np.linspace(0, 1, n)[:, None]
    q = (1 - s) * key[0] + s * key[1]
    q[:, [6, 13]] = np.clip(q[:, [6, 13]], 0, 1)
    return q


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    return RobotModel(aloha.robot_config(tmp_path_factory.mktemp("imac_cache")))


@pytest.fixture(scope="module", params=aloha.TASKS)
def oracle(request):
    o = MujocoOracle(request.param, H, W)
    yield o
    o.close()


@pytest.fixture(scope="module", params=sorted(BACKENDS))
def renderer(robot, request):
    """Each backend: Open3D's ray casting (the CPU build's) and the torch rasteriser (the GPU build's, run
    here on the CPU) meet the same oracles."""
    model = sim_rig.load_mujoco_model("transfer_cube")
    return make_renderer(robot, request.param, near=float(model.vis.map.znear * model.stat.extent))


def backend(renderer: Renderer) -> str:
    return next(name for name, cls in BACKENDS.items() if isinstance(renderer, cls))


@pytest.fixture(scope="module")
def calib():
    return sim_rig.camera_calibration(sim_rig.load_mujoco_model("transfer_cube"), W, H)


# ----------------------------------------------------------------------------- against MuJoCo


def test_mujoco_depth_is_planar_z(calib):
    """The oracle's depth is z-depth along the optical axis, in metres: back-projected
    as such with our calibration, the table top (z = 0) comes out flat at z = 0; read
    as distance along the ray it would bend by centimetres toward the image corners."""
    o = MujocoOracle("transfer_cube", H, W, robot_only=False)
    try:
        view = o.render(workspace_configs(1, 0)[0])["cam_high"]
        table = mujoco.mj_name2id(o.model, mujoco.mjtObj.mjOBJ_GEOM, "table")
        px = view["geom"] == table
        assert px.sum() > 0.2 * H * W
        cam = calib["cam_high"]
        depth = torch.tensor(view["depth"], dtype=torch.float64)
        pts = backproject(depth, torch.tensor(cam.K), torch.tensor(cam.T_world_cam))[px]
        z = pts[:, 2].numpy()
        assert np.median(np.abs(z)) < 5e-4 and np.abs(z).max() < 3e-3, (np.median(np.abs(z)), np.abs(z).max())
        # the radial reading is clearly different (so the check above can tell them apart)
        rays = backproject(torch.ones(H, W, dtype=torch.float64), torch.tensor(cam.K), torch.eye(4).double())
        radial = view["depth"] / rays.norm(dim=-1).numpy()
        pts_r = backproject(torch.tensor(radial), torch.tensor(cam.K), torch.tensor(cam.T_world_cam))[px]
        assert np.abs(pts_r[:, 2].numpy()).max() > 0.02
    finally:
        o.close()


def test_mask_depth_and_links_match_mujoco(robot, renderer, oracle, calib):
    q = workspace_configs(N_FRAMES, seed=hash(oracle.model.nbody) % 1000)
    views = renderer.render(torch.tensor(q), calib)
    link_index = {name: i for i, name in enumerate(renderer.link_names)}
    body_link = np.array([link_index.get(oracle.model.body(b).name, -2) for b in range(oracle.model.nbody)] + [-1])
    ious = {c: [] for c in calib}
    errors = {c: [] for c in calib}
    link_agree = []
    for t in range(N_FRAMES):
        ref = oracle.render(q[t])
        for c in calib:
            ours, truth = views[c], ref[c]
            mask = ours.mask[t].numpy()
            union = (mask | truth["mask"]).sum()
            assert union > 0, f"{c}: no robot in view at frame {t}"
            ious[c].append((mask & truth["mask"]).sum() / union)
            both = mask & truth["mask"]
            errors[c].append(np.abs(ours.depth[t].numpy()[both] - truth["depth"][both]))
            truth_link = body_link[oracle.body_of_geom[truth["geom"] + 1]]
            link_agree.append((ours.link_id[t].numpy()[both] == truth_link[both]).mean())
    for c in calib:
        mean_iou = float(np.mean(ious[c]))
        med = float(np.median(np.concatenate(errors[c])))
        print(f"{c}: mean IoU {mean_iou:.4f}, median |depth error| {med * 1e3:.3f} mm")
        assert mean_iou >= IOU_MIN[c], (c, ious[c])
        assert med <= DEPTH_MEDIAN_MAX, (c, med)
    assert np.mean(link_agree) > 0.99


def test_resolution_rescales_intrinsics(robot, renderer, calib):
    """resolution=(h, w) renders what MuJoCo renders at that size (K rescaled)."""
    h, w = 120, 160
    o = MujocoOracle("transfer_cube", h, w)
    try:
        q = workspace_configs(2, seed=5)
        views = renderer.render(torch.tensor(q), calib, resolution=(h, w))
        for t in range(2):
            ref = o.render(q[t])
            for c, v in views.items():
                assert v.mask.shape == (2, h, w) and v.rgb.shape == (2, h, w, 3)
                m = v.mask[t].numpy()
                iou = (m & ref[c]["mask"]).sum() / max((m | ref[c]["mask"]).sum(), 1)
                assert iou > IOU_MIN[c], (c, iou)
    finally:
        o.close()


def test_near_plane_only_clips(robot, renderer, calib):
    """The near plane only removes what lies in front of it (for gym-aloha's wrist cameras
    that is nothing of their own gripper, which stays >= 0.19 m away: see the benchmark)."""
    free = make_renderer(robot, backend(renderer))
    q = torch.tensor(workspace_configs(2, seed=3))
    a, b = renderer.render(q, calib), free.render(q, calib)
    for c in calib:
        assert not (a[c].mask & ~b[c].mask).any()
        same = a[c].mask & b[c].mask & (b[c].depth >= renderer.near)
        # same surfaces (float32 rays from another origin: a few grazing edge pixels may differ)
        agree = (a[c].depth[same] - b[c].depth[same]).abs() < 1e-4
        assert agree.float().mean() > 0.999


# ----------------------------------------------------------------------------- outputs and batching


def test_outputs_batching_and_chunking(robot, renderer, calib):
    q = torch.tensor(workspace_configs(6, seed=11))
    flat = renderer.render(q, calib)
    nested = renderer.render(q.reshape(2, 3, 14), calib)
    small = {"open3d": {"max_rays": 50_000}, "opengl": {"max_frames": 4},
             "torch": {"max_candidates": 400_000}}[backend(renderer)]
    chunked = make_renderer(robot, backend(renderer), near=renderer.near, **small).render(q, calib)
    single = renderer.render(q[4], calib)
    poses = renderer.render(link_poses=robot.link_poses(q), cameras=list(calib.values()))
    for c in calib:
        v = flat[c]
        assert isinstance(v, RenderOutput)
        assert v.rgb.shape == (6, H, W, 3) and v.rgb.dtype == torch.uint8
        assert v.mask.dtype == torch.bool and v.depth.dtype == torch.float32 and v.link_id.dtype == torch.int16
        assert torch.equal(v.mask, v.depth > 0) and torch.equal(v.mask, v.link_id >= 0)
        assert (v.rgb[~v.mask] == 0).all()  # black background
        assert (v.rgb[v.mask].amax(-1) > 0).all()  # lit robot (ambient term)
        assert int(v.link_id.max()) < len(renderer.link_names)
        assert nested[c].depth.shape == (2, 3, H, W)
        for other in (nested[c], chunked[c], poses[c]):
            assert torch.equal(other.depth.reshape(6, H, W), v.depth)
            assert torch.equal(other.rgb.reshape(6, H, W, 3), v.rgb)
            assert torch.equal(other.link_id.reshape(6, H, W), v.link_id)
        assert torch.equal(single[c].depth, v.depth[4])
    grip = renderer.links_mask(flat["cam_left_wrist"].link_id, robot.gripper_links)
    assert grip.any() and not (grip & ~flat["cam_left_wrist"].mask).any()


@pytest.mark.parametrize("rasteriser", ["torch", "opengl"])
def test_the_rasterisers_draw_what_the_ray_caster_casts(robot, calib, rasteriser):
    """The torch rasteriser (the GPU build's renderer) and OpenGL's (Mesa's llvmpipe here) against Open3D's
    ray casting, another library's algorithm on the same triangles, within issue 65's tolerances: masks at
    IoU >= 0.9999, RGB within one grey level on 99.9 % of the robot's pixels, depth within 1 mm on 99.9 %.
    Link ids agree on 99 %: where a closed gripper's two finger meshes coincide, which of the two is nearer
    is float rounding (0.3 % of the left wrist's pixels here, at the same depth and colour)."""
    q = torch.tensor(workspace_configs(6, seed=7))
    a, b = RaycastRenderer(robot).render(q, calib), make_renderer(robot, rasteriser).render(q, calib)
    for c in calib:
        ma, mb = a[c].mask, b[c].mask
        both = ma & mb
        iou = float((both.sum() / (ma | mb).sum()))
        grey = (a[c].rgb.int() - b[c].rgb.int()).abs().amax(-1)[both]
        dz = (a[c].depth - b[c].depth).abs()[both]
        same_link = (a[c].link_id == b[c].link_id)[both]
        print(f"{c}: {int(ma.sum())} pixels, IoU {iou:.6f}, grey > 1 on {int((grey > 1).sum())}, "
              f"depth > 1 mm on {int((dz > 1e-3).sum())}, other link on {int((~same_link).sum())}")
        assert iou >= 0.9999, (c, iou)
        assert (grey <= 1).float().mean() >= 0.999 and (dz <= 1e-3).float().mean() >= 0.999
        assert same_link.float().mean() >= 0.99


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device: the rasteriser's algorithm is checked "
                    "on the CPU above; this checks it on a GPU")
def test_the_rasteriser_on_a_gpu_draws_what_it_draws_on_the_cpu(robot, calib):
    q = torch.tensor(workspace_configs(6, seed=7))
    a, b = RasterRenderer(robot).render(q, calib), RasterRenderer(robot, device="cuda").render(q.cuda(), calib)
    for c in calib:
        ma, mb = a[c].mask, b[c].mask.cpu()
        assert float((ma & mb).sum() / (ma | mb).sum()) >= 0.9999
        both = ma & mb
        assert ((a[c].rgb.int() - b[c].rgb.cpu().int()).abs().amax(-1)[both] <= 1).float().mean() >= 0.999
        assert ((a[c].depth - b[c].depth.cpu()).abs()[both] <= 1e-3).float().mean() >= 0.999


def test_renderer_interface():
    assert all(issubclass(cls, Renderer) for cls in BACKENDS.values())
    with pytest.raises(InputError, match="backend"):
        make_renderer(None, backend="nope")


# ----------------------------------------------------------------------------- analytic scene


BOX_URDF = """<?xml version="1.0"?>
<robot name="box">
  <material name="red"><color rgba="0.8 0.2 0.1 1"/></material>
  <link name="world"/>
  <link name="slider">
    <visual><geometry><box size="0.2 0.2 0.2"/></geometry><material name="red"/></visual>
  </link>
  <link name="tip">
    <visual><origin xyz="0 0 0.2"/><geometry><box size="0.05 0.05 0.05"/></geometry>
      <material name="blue"><color rgba="0 0 1 1"/></material></visual>
  </link>
  <joint name="slide" type="prismatic">
    <parent link="world"/><child link="slider"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <joint name="tip_joint" type="fixed"><parent link="slider"/><child link="tip"/></joint>
</robot>
"""


@pytest.fixture(scope="module")
def box_robot(tmp_path_factory):
    path = tmp_path_factory.mktemp("box") / "box.urdf"
    path.write_text(BOX_URDF)
    return RobotModel(RobotConfig(name="box", urdf_path=path, joint_map=("slide",)))


def _look_down_z(height: float) -> np.ndarray:
    """Camera-to-world pose of a camera at (0, 0, height) looking straight down (OpenCV axes)."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[2, 3] = height
    return T


def _shade(rgba, ray_world, normal, ambient=0.3):
    cos = abs(float(np.dot(ray_world, normal))) / np.linalg.norm(ray_world)
    return np.floor(np.asarray(rgba[:3], np.float32) * np.float32(255 * (ambient + (1 - ambient) * cos)) + 0.5)


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_analytic_box(box_robot, name):
    """A 20 cm red cube centred at the origin (and a 5 cm blue cube on top of it) seen
    from 1 m above: z-depths, silhouette columns, link ids, URDF colours and
    Lambertian shading computed by hand; pixel centres on integer coordinates."""
    K = np.array([[200.0, 0, 63.5], [0, 200.0, 47.5], [0, 0, 1]])  # 128 x 96, optical axis between pixels
    cam = Camera("down", K, 128, 96, T_world_cam=_look_down_z(1.0))
    r = make_renderer(box_robot, name, ambient=0.3)
    v = r.render(torch.tensor([[0.0], [0.05]]), [cam])["down"]
    # the top face at 0.9 m spans x in [-0.1, 0.1]: u = 63.5 + 200 x / 0.9 in [41.28, 85.72] -> columns 42..85
    cols = np.flatnonzero(v.mask[0].numpy().any(0))
    assert (cols.min(), cols.max()) == (42, 85)
    d = v.depth[0].numpy()
    assert d[47, 50] == pytest.approx(0.9, abs=1e-6)
    assert d[47, 63] == pytest.approx(1.0 - 0.225, abs=1e-6)  # the blue cube's top, nearer
    ray = np.linalg.inv(K) @ [50, 47, 1]  # camera frame; world = diag(1, -1, -1)
    assert v.rgb[0, 47, 50].tolist() == _shade((0.8, 0.2, 0.1), ray, (0, 0, -1)).tolist()
    assert v.rgb[0, 47, 63].tolist() == _shade((0, 0, 1), np.linalg.inv(K) @ [63, 47, 1], (0, 0, -1)).tolist()
    assert r.link_names[int(v.link_id[0, 47, 50])] == "slider" and r.link_names[int(v.link_id[0, 47, 63])] == "tip"
    # a near plane at 0.95 m clips the blue cube (0.775..0.825 m) and the red cube's top
    # (0.9 m): rays start inside the red cube and hit its bottom face from within (1.1 m)
    clipped = make_renderer(box_robot, name, near=0.95).render(torch.tensor([0.0]), [cam])["down"]
    assert clipped.depth[47, 63].item() == pytest.approx(1.1, abs=1e-5)
    assert clipped.depth[47, 50].item() == pytest.approx(1.1, abs=1e-5)
    # sliding 5 cm along x moves the silhouette to x in [-0.05, 0.15]: columns 53..96
    cols = np.flatnonzero(v.mask[1].numpy().any(0))
    assert (cols.min(), cols.max()) == (53, 96)

    # An oblique view from 1 m away, tilted by 0.5 rad about x: the pixel next to the
    # image centre sees the red top face at a depth and shade computed by hand.
    alpha = 0.5
    p = np.array([0.0, -math.sin(alpha), math.cos(alpha)])
    z = -p
    x = np.array([1.0, 0.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = p
    view = r.render(torch.tensor([0.0]), [Camera("oblique", K, 128, 96, T_world_cam=T)])["oblique"]
    ray_w = T[:3, :3] @ np.linalg.inv(K) @ [63, 47, 1]
    s = (0.1 - p[2]) / ray_w[2]  # hits z = 0.1 (camera z-depth s: the camera-frame ray has z = 1)
    hit = p + s * ray_w
    assert abs(hit[0]) < 0.1 and abs(hit[1]) < 0.1 and abs(hit[1]) > 0.03  # on the cube's top, clear of the tip
    assert view.depth[47, 63].item() == pytest.approx(s, abs=1e-5)
    assert view.rgb[47, 63].tolist() == _shade((0.8, 0.2, 0.1), ray_w, (0, 0, 1)).tolist()


# ----------------------------------------------------------------------------- bad input


def test_bad_input(robot, renderer, calib):
    with pytest.raises(InputError, match="14 entries"):
        renderer.render(torch.zeros(13), calib)
    q = torch.zeros(2, 14)
    q[1, 3] = float("nan")
    with pytest.raises(InputError, match="non-finite"):
        renderer.render(q, calib)
    bad = Camera("cam_x", calib["cam_left_wrist"].K, W, H, link="vx300s_left/no_such_link",
                 T_link_cam=np.eye(4))
    with pytest.raises(InputError, match="no_such_link"):
        renderer.render(torch.zeros(14), {**calib, "cam_x": bad})
    with pytest.raises(InputError, match="no cameras"):
        renderer.render(torch.zeros(14), {})
    with pytest.raises(InputError, match="resolution"):
        renderer.render(torch.zeros(14), calib, resolution=(0, 10))
    with pytest.raises(InputError, match="near"):
        make_renderer(robot, backend(renderer), near=-1.0)
    if backend(renderer) == "open3d":  # its slots bound the range; the rasteriser has no such limit
        with pytest.raises(InputError, match="max_range"):  # the robot in view, 50 m away
            renderer.render(torch.zeros(14), [Camera("far", calib["cam_high"].K, W, H, T_world_cam=_look_down_z(50))])


# ----------------------------------------------------------------------------- QA overlay


@pytest.fixture(scope="module")
def qa_inputs(tmp_path_factory):
    """A 4-frame simulated episode (RGB of the full scene, segmentation, labels) and its calibration."""
    from imac_data.sources.hdf5 import RawEpisode, write_episode

    tmp = tmp_path_factory.mktemp("qa")
    o = MujocoOracle("transfer_cube", H, W, robot_only=False)
    try:
        q = workspace_configs(4, seed=2)
        frames = [o.render(row, rgb=True) for row in q]
        labels = {g: (o.model.geom(g).name, o.model.body(o.model.geom_bodyid[g]).name) for g in range(o.model.ngeom)}
        model = o.model
    finally:
        o.close()
    cams = list(sim_rig.CAMERA_NAMES.values())
    ep = RawEpisode(qpos=q, action=q, images={c: np.stack([f[c]["rgb"] for f in frames]) for c in cams},
                    segmentation={c: np.stack([f[c]["geom"] for f in frames]).astype(np.int16) for c in cams},
                    segmentation_labels=labels, fps=25.0)
    write_episode(tmp / "episode_0.hdf5", ep)
    # calibration at another resolution: the overlay must rescale it to the images
    save_calibration(tmp / "calib.json", sim_rig.camera_calibration(model, 2 * W, 2 * H))
    return tmp


def test_qa_overlay_cli(qa_inputs, capsys):
    import av


    out = qa_inputs / "overlay"
    rc = imac_main(["qa", "overlay", str(qa_inputs / "episode_0.hdf5"), "--calibration", str(qa_inputs / "calib.json"),
                  "--out", str(out)])
    assert rc == 0
    assert "cam_high" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    for c, e in summary["cameras"].items():
        # the full scene occludes a little of the robot (table, props): still close to 1
        assert e["mean_iou"] >= IOU_MIN[c] - 0.02, (c, e)
        with av.open(str(out / f"{c}.mp4")) as f:
            frames = list(f.decode(video=0))
        assert len(frames) == 4 and frames[0].width == W and frames[0].height == H
    rows = (out / "iou.csv").read_text().strip().splitlines()
    assert rows[0] == "frame," + ",".join(summary["cameras"]) and len(rows) == 5
    # png output, one frame
    rc = imac_main(["qa", "overlay", str(qa_inputs / "episode_0.hdf5"), "--calibration", str(qa_inputs / "calib.json"),
                  "--out", str(out), "--format", "png", "--frames", "1:3", "--overwrite", "--cameras", "cam_high"])
    assert rc == 0
    assert sorted(p.name for p in (out / "cam_high").iterdir()) == ["000001.png", "000002.png"]
    assert not (out / "cam_high.mp4").exists()


def test_qa_overlay_fps_is_the_recipes_else_the_episodes_else_50(qa_inputs, tmp_path, capsys):
    """An episode without an 'fps' attribute plays at the recipe's fps (25), not the default 50; a recipe's fps
    wins over the episode's attribute, as in the build; without a recipe the attribute rules; the command says
    which it used."""
    import shutil

    import av
    import h5py
    import yaml

    bare = tmp_path / "episode_0.hdf5"
    shutil.copy(qa_inputs / "episode_0.hdf5", bare)
    with h5py.File(bare, "r+") as f:
        del f.attrs["fps"]
    recipe = {"name": "fps_check", "task": "t", "robot": {"platform": "aloha_sim"}, "fps": 25,
              "source": {"type": "aloha_hdf5", "path": str(tmp_path)},
              "cameras": {"calibration": str(qa_inputs / "calib.json")}}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    (tmp_path / "r30.yaml").write_text(yaml.safe_dump({**recipe, "fps": 30}))
    cases = [(bare, ["--recipe", str(tmp_path / "r.yaml")], 25, "from the recipe's fps"),
             (bare, [], 50, "from the default"),
             (qa_inputs / "episode_0.hdf5", ["--recipe", str(tmp_path / "r30.yaml")], 30, "from the recipe's fps"),
             (qa_inputs / "episode_0.hdf5", [], 25, "from the episode's 'fps' attribute")]
    for i, (episode, extra, rate, said) in enumerate(cases):
        out = tmp_path / f"overlay_{i}"
        assert imac_main(["qa", "overlay", str(episode), "--calibration", str(qa_inputs / "calib.json"),
                          "--out", str(out), "--frames", "0:2", "--cameras", "cam_high", *extra]) == 0
        assert f"fps {rate} {said}" in capsys.readouterr().out
        summary = json.loads((out / "summary.json").read_text())
        assert summary["fps"] == rate
        with av.open(str(out / "cam_high.mp4")) as f:
            assert f.streams.video[0].average_rate == rate


def test_qa_overlay_overwrite_replaces_only_an_overlay(qa_inputs, capsys):
    """--overwrite into a directory of the user's (no summary.json): refused, nothing deleted."""

    out = qa_inputs / "my_notes"
    out.mkdir(exist_ok=True)
    (out / "notes.txt").write_text("mine")
    rc = imac_main(["qa", "overlay", str(qa_inputs / "episode_0.hdf5"), "--calibration", str(qa_inputs / "calib.json"),
                  "--out", str(out), "--overwrite"])
    assert rc == 2
    assert "without summary.json" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_qa_overlay_bad_input_writes_nothing(qa_inputs, capsys):
    from imac_data.core.cameras import load_calibration

    calib = load_calibration(qa_inputs / "calib.json")
    wrist = calib["cam_left_wrist"]
    calib["cam_left_wrist"] = Camera(wrist.name, wrist.K, wrist.width, wrist.height, link="vx300s_left/nope",
                                     T_link_cam=wrist.T_link_cam)
    save_calibration(qa_inputs / "bad_calib.json", calib)
    far = load_calibration(qa_inputs / "calib.json")
    high = far["cam_high"]
    far["cam_high"] = Camera(high.name, high.K, high.width, high.height, T_world_cam=_look_down_z(50.0))
    save_calibration(qa_inputs / "far_calib.json", far)  # fails while rendering, not while validating
    before = sorted(p.name for p in qa_inputs.iterdir())
    cases = [
        (["--calibration", str(qa_inputs / "bad_calib.json")], "vx300s_left/nope"),
        (["--calibration", str(qa_inputs / "far_calib.json")], "max_range"),
        (["--calibration", str(qa_inputs / "calib.json"), "--cameras", "cam_low"], "cam_low"),
        (["--calibration", str(qa_inputs / "missing.json")], "not found"),
        (["--calibration", str(qa_inputs / "calib.json"), "--frames", "10:20"], "selects no frame"),
    ]
    for extra, message in cases:
        rc = imac_main(["qa", "overlay", str(qa_inputs / "episode_0.hdf5"), "--out", str(qa_inputs / "new" / "dir"), *extra])
        assert rc == 2
        assert message in capsys.readouterr().err
        assert sorted(p.name for p in qa_inputs.iterdir()) == before  # nothing written, no temp dirs


def test_the_opengl_renderer_draws_from_any_thread(robot, calib):
    """One EGL context serves every thread in turn (the build's thread pools): it is released after each
    render, and a render on another thread draws what this one drew."""
    import threading

    r = make_renderer(robot, "opengl")
    q = torch.tensor(workspace_configs(2, seed=2))
    here = r.render(q, calib)
    there = {}
    worker = threading.Thread(target=lambda: there.update(r.render(q, calib)))
    worker.start()
    worker.join()
    again = r.render(q, calib)
    for c in calib:
        assert torch.equal(here[c].rgb, there[c].rgb) and torch.equal(here[c].depth, again[c].depth)

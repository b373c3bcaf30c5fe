"""Cameras out of step with the joint states (``qa calibrate``'s time offset, the calibration file's
``time_offset_s``, the build at each camera's own time).

The oracle is the simulator recorded at 50 fps and subsampled to 25 fps with the RGB and depth taken a
known number of 20 ms control steps away from the joint states (``benchmarks.calibration_scenes.
aloha_out_of_step``), so whole and half frames are exact. The simulator's own frames lag its joint states
by one physics step (2 ms, :func:`~benchmarks.calibration_scenes.sim_render_lag`), which the truth includes.
The full grid (1-3 frames and half a frame, every ALOHA camera) is ``benchmarks/calibration_time_offset.py``.
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import h5py
import numpy as np
import pytest

from benchmarks.calibration_scenes import (
    ALOHA_FOVY,
    ALOHA_MOUNTS,
    ALOHA_RECIPE,
    aloha_out_of_step,
    aloha_recorded_50fps,
)
from imac_data.calibrate.from_nothing import calibrate_from_nothing
from imac_data.calibrate.pose import apply_update, pose_change
from imac_data.calibrate.refine import refine_calibration
from imac_data.calibrate.register import Fit
from imac_data.calibrate.scratch import pose_distance
from imac_data.calibrate.time_offset import OffsetSearch, timing_refusal
from imac_data.cli import main as imac_main
from imac_data.core.cameras import Camera, intrinsics_from_fovy, load_calibration, save_calibration
from imac_data.core.motion import joints_at
from imac_data.errors import InputError
from imac_data.sources.hdf5 import RawEpisode, read_episode, write_episode
from imac_data.sources.sim.recorder import SimConfig, record_dataset

HW = (120, 160)
GOALS = {"cam_high": (3.0, 0.3), "cam_right_wrist": (5.0, 0.5)}


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """One scripted transfer-cube episode at 50 fps (300 control steps, 120x160) and the hidden truth."""
    out = tmp_path_factory.mktemp("offset") / "raw50"
    return out, aloha_recorded_50fps(out, seed=3, episodes=1, height=HW[0], width=HW[1], max_steps=300)


def _error(truth: Camera, found: Camera) -> tuple[float, float]:
    a = truth.T_link_cam if truth.is_mounted else truth.T_world_cam
    b = found.T_link_cam if found.is_mounted else found.T_world_cam
    return pose_distance(a, b)


def _calibrate(src, out, cams):
    return calibrate_from_nothing(src, out, recipe=ALOHA_RECIPE, cameras=cams,
                                  mounts={c: ALOHA_MOUNTS[c] for c in cams if c in ALOHA_MOUNTS},
                                  fov={c: ALOHA_FOVY[c] * 1.15 for c in cams}, refine="none", progress=False)


def test_a_wrist_camera_two_frames_late_and_a_head_camera_in_step(recording, tmp_path):
    """The right wrist camera's RGB and depth two frames (80 ms at 25 fps) behind the joint states, the
    head camera in step: each offset is found within 5 ms (the head's is 0 within 5 ms), both cameras
    come back within their goals, and the file carries the offsets. The right arm moves from the first
    frame on, so a candidate frame whose shifted joint states were clamped at the episode's start would
    pull its answer off (it did: -76.7 ms and 0.88 deg before the candidates kept the search's margin)."""
    raw, truth = recording
    true = aloha_out_of_step(raw, tmp_path / "eps", {"cam_right_wrist": -4})  # -80 ms; all: the simulator's -2 ms
    out = tmp_path / "calib.json"
    summary = _calibrate(tmp_path / "eps", out, ["cam_high", "cam_right_wrist"])
    found = load_calibration(out)
    assert summary["refused"] == {}
    assert abs(found["cam_high"].time_offset_s) <= 0.005
    for c, (mm, deg) in GOALS.items():
        t, r = _error(truth[c], found[c])
        assert t <= mm and r <= deg, (c, t, r)
        assert abs(found[c].time_offset_s - true[c]) <= 0.005, (c, found[c].time_offset_s, true[c])
        e = summary["cameras"][c]
        assert e["time_offset_observable"] and e["time_offset_rise"] > 0.5  # a sharp minimum
    wrist = summary["cameras"]["cam_right_wrist"]
    assert wrist["inlier_ratio_at_best_offset"] > wrist["inlier_ratio_at_zero_offset"] + 0.02
    assert wrist["time_offset_cost"] < 0.6 * wrist["time_offset_cost_at_zero"]
    saved = json.loads(out.read_text())["cameras"]
    assert saved["cam_right_wrist"]["time_offset_s"] == found["cam_right_wrist"].time_offset_s
    # no candidate frame within the search's +-200 ms (5 frames) of the episode's ends
    frames = [t for _, t in summary["cameras"]["cam_right_wrist"]["frames"]]
    assert min(frames) >= 5 and max(frames) <= len(read_episode(next((tmp_path / "eps").glob("*.hdf5"))).qpos) - 6


def test_joints_between_frames_are_interpolated_and_clamped():
    """Catmull-Rom: quadratics come back exactly between interior frames (an arm accelerating steadily), which a
    straight line between samples misses by a quarter of a frame squared times the acceleration; clamped at
    the ends; whole frames are the recorded vectors."""
    t = np.arange(8.0)
    q = np.stack([3.0 - 2.0 * t + 0.7 * t**2, 10.0 + 5.0 * t], axis=1)
    at = np.array([1.5, 2.25, 3.9, 5.5])
    want = np.stack([3.0 - 2.0 * at + 0.7 * at**2, 10.0 + 5.0 * at], axis=1)
    np.testing.assert_allclose(joints_at(q, at), want, rtol=0, atol=1e-12)
    linear = q[1:2] * 0.5 + q[2:3] * 0.5  # at 1.5: off by 0.7 / 4
    assert abs(linear[0, 0] - want[0, 0]) == pytest.approx(0.7 / 4)
    np.testing.assert_allclose(joints_at(q, [-2.0, 7.0, 99.0]), q[[0, 7, 7]])
    assert joints_at(q, [1.0, 6.0]).tobytes() == q[[1, 6]].tobytes()  # whole frames: the recorded vectors themselves


def test_the_calibration_file_carries_the_offset_and_old_files_load(tmp_path):
    K = intrinsics_from_fovy(60.0, 160, 120)
    cams = {"a": Camera("a", K, 160, 120, T_world_cam=np.eye(4), time_offset_s=-0.04),
            "b": Camera("b", K, 160, 120, link="l", T_link_cam=np.eye(4))}
    save_calibration(tmp_path / "c.json", cams)
    raw = json.loads((tmp_path / "c.json").read_text())
    assert raw["cameras"]["a"]["time_offset_s"] == -0.04 and "time_offset_s" not in raw["cameras"]["b"]
    back = load_calibration(tmp_path / "c.json")
    assert back["a"].time_offset_s == -0.04 and back["b"].time_offset_s == 0.0
    assert back["a"].rescaled(320, 240).time_offset_s == -0.04
    raw["cameras"]["a"]["time_offset_s"] = "soon"
    (tmp_path / "bad.json").write_text(json.dumps(raw))
    with pytest.raises(InputError, match="cameras.a.*time_offset_s"):
        load_calibration(tmp_path / "bad.json")


def test_a_refusal_that_an_offset_explains_names_timing_first():
    fit = Fit(np.eye(4), 100.0, 1.0, 0.75, 4.0, 10)
    search = OffsetSearch(offset_s=-0.2, cost=0.05, inlier_ratio=0.78, cost_at_zero=0.2, inlier_ratio_at_zero=0.55,
                          rise=0.8, fit=fit, window_s=0.2)
    assert search.clearly_better and search.at_window_edge
    msg = timing_refusal("cam_x", search, "camera 'cam_x': no pose explains the depth (best: 78% ...)")
    assert msg.startswith("camera 'cam_x': the camera looks out of step with the joint states by about 200 ms")
    assert "lags" in msg and "edge of the searched" in msg and "no pose explains" in msg
    flat = OffsetSearch(offset_s=-0.04, cost=0.2, inlier_ratio=0.56, cost_at_zero=0.2, inlier_ratio_at_zero=0.55,
                        rise=0.001, fit=fit, window_s=0.2)
    assert not flat.observable and not flat.clearly_better


# ----------------------------------------------------------------------------- the build


def _chunks(path, cameras, settings, fps=50.0, depth=True):
    from imac_data.augment.pipeline import EpisodePipeline
    from imac_data.core.rig import Rig
    from imac_data.recipes import load_recipe
    from imac_data.sources.depth import NoDepth, RecordedDepth
    from imac_data.sources.hdf5 import EpisodeReader

    rig = Rig.from_recipe(load_recipe(ALOHA_RECIPE), calibration=cameras)
    pipe = EpisodePipeline(rig, settings, RecordedDepth() if depth else NoDepth(), threads=1, fps=fps)
    with EpisodeReader(path) as reader:
        outs = list(pipe.chunks(reader))
    streams = {k: np.concatenate([o.streams[k] for o in outs]) for k in outs[0].streams}
    poses = {c: np.concatenate([o.poses[c] for o in outs]) for c in outs[0].poses}
    return streams, poses


def test_the_build_draws_each_camera_at_its_own_time(recording, tmp_path):
    """A camera one frame (20 ms at 50 fps) ahead is drawn and posed at the next frame's joint states
    (motion images, camera poses), clamped at the episode's end; a camera in step is drawn as before,
    bit for bit; an offset of 0 everywhere is the build as it always was."""
    import dataclasses

    from imac_data.recipes import AugmentSettings
    from imac_data.sources.hdf5 import read_episode, write_episode

    raw, truth = recording
    ep = read_episode(sorted(raw.glob("*.hdf5"))[0])
    n = 12
    ep = dataclasses.replace(ep, qpos=ep.qpos[100:100 + n], action=ep.action[100:100 + n], qvel=None,
                             images={c: v[100:100 + n] for c, v in ep.images.items()},
                             depth_mm={c: v[100:100 + n] for c, v in ep.depth_mm.items()}, segmentation={},
                             segmentation_labels={})
    path = tmp_path / "episode_0.hdf5"
    write_episode(path, ep, sim=False)
    settings = AugmentSettings(height=60, width=80, contact_chunk=4)
    base, base_poses = _chunks(path, truth, settings)
    shifted = {c: dataclasses.replace(cam, time_offset_s=0.02) if c == "cam_left_wrist" else cam
               for c, cam in truth.items()}
    out, poses = _chunks(path, shifted, settings)
    for c in truth:
        m0, m1 = base[f"control.motion.{c}"], out[f"control.motion.{c}"]
        if c == "cam_left_wrist":
            np.testing.assert_array_equal(m1[:-1], m0[1:])
            np.testing.assert_array_equal(m1[-1], m0[-1])
            np.testing.assert_allclose(poses[c][:-1], base_poses[c][1:], atol=1e-12)
            assert not np.array_equal(m1, m0)
        else:
            np.testing.assert_array_equal(m1, m0)
            np.testing.assert_array_equal(poses[c], base_poses[c])
        np.testing.assert_array_equal(out[f"observation.depth.{c}"], base[f"observation.depth.{c}"])
    assert not np.array_equal(out["control.contact_r2s.cam_left_wrist"], base["control.contact_r2s.cam_left_wrist"])
    # every camera half a frame late: between the frames; no depth (motion only) works alike
    late = {c: dataclasses.replace(cam, time_offset_s=-0.01) for c, cam in truth.items()}
    half, _ = _chunks(path, late, settings, depth=False)
    assert set(half) == {f"control.motion.{c}" for c in truth}
    (tmp_path / "no_fps").mkdir()
    write_episode(tmp_path / "no_fps" / "episode_0.hdf5", dataclasses.replace(ep, fps=None), sim=False)
    with pytest.raises(InputError, match="frame rate"):
        _chunks(tmp_path / "no_fps" / "episode_0.hdf5", late, settings, fps=None, depth=False)


# ----------------------------------------------------------------------------- qa overlay and qa refine

LAG = {"cam_high": 2, "cam_left_wrist": 1, "cam_right_wrist": 0}  # frames each camera's images are ahead


@pytest.fixture(scope="module")
def shifted(tmp_path_factory):
    """A recording in step (40 frames at 25 fps, 120x160, MuJoCo's segmentation) and the same recording with each
    camera's images (and segmentation) :data:`LAG` frames ahead of the joint states: its frame t shows the robot at
    the joint states of t + LAG, so its true offset is LAG / 25 s (the simulator's own 2 ms aside)."""
    tmp = tmp_path_factory.mktemp("shifted")
    record_dataset(SimConfig(num_episodes=1, width=HW[1], height=HW[0], with_segmentation=True, noise=0.0,
                             max_steps=80), tmp / "in_step", progress=False)
    ep = read_episode(tmp / "in_step" / "episode_0.hdf5", load_segmentation=True)
    n = len(ep.qpos) - max(LAG.values())
    (tmp / "shifted").mkdir()
    write_episode(tmp / "shifted" / "episode_0.hdf5", RawEpisode(
        qpos=ep.qpos[:n], action=ep.action[:n], images={c: v[LAG[c]:LAG[c] + n] for c, v in ep.images.items()},
        segmentation={c: v[LAG[c]:LAG[c] + n] for c, v in ep.segmentation.items()},
        segmentation_labels=ep.segmentation_labels, fps=25.0))
    truth = load_calibration(tmp / "in_step" / "calibration.json")
    save_calibration(tmp / "offsets.json", {c: dataclasses.replace(cam, time_offset_s=LAG[c] / 25.0)
                                            for c, cam in truth.items()})
    return tmp, truth


def _ious(out) -> dict[str, np.ndarray]:
    rows = (out / "iou.csv").read_text().split()
    cams = rows[0].split(",")[1:]
    values = np.array([[float(x) for x in r.split(",")] for r in rows[1:]])
    return {c: dict(zip(values[:, 0].astype(int), values[:, 1 + i])) for i, c in enumerate(cams)}


def test_qa_overlay_draws_each_camera_at_its_images_own_time(shifted, tmp_path, capsys):
    """``imac qa overlay`` of the shifted recording with the offsets in the calibration is the overlay of the same
    images in step: each camera's IoU with MuJoCo's segmentation at frame t equals the in-step recording's at
    frame t + LAG (the same image, the same joint vector). Without the offsets the cameras ahead are drawn a frame
    or two early, and their IoU drops; the camera in step is drawn as before. An episode without an 'fps' attribute
    cannot say how many frames an offset is, and is refused unless a recipe gives its fps."""
    tmp, truth = shifted
    save_calibration(tmp_path / "no_offsets.json", truth)

    def run(episode, calibration, out, frames="4:36"):
        assert imac_main(["qa", "overlay", str(episode), "--calibration", str(calibration), "--out", str(out),
                          "--frames", frames, "--format", "png"]) == 0, capsys.readouterr().err
        return _ious(out), json.loads((out / "summary.json").read_text())

    in_step, _ = run(tmp / "in_step" / "episode_0.hdf5", tmp_path / "no_offsets.json", tmp_path / "in_step", "4:38")
    drawn, summary = run(tmp / "shifted" / "episode_0.hdf5", tmp / "offsets.json", tmp_path / "with")
    blind, _ = run(tmp / "shifted" / "episode_0.hdf5", tmp_path / "no_offsets.json", tmp_path / "without")
    for c, lag in LAG.items():
        assert summary["cameras"][c]["time_offset_s"] == lag / 25.0
        for t, iou in drawn[c].items():
            assert iou == pytest.approx(in_step[c][t + lag], abs=1e-9), (c, t)
        mean, mean_blind = np.mean(list(drawn[c].values())), np.mean(list(blind[c].values()))
        assert mean > 0.97, (c, mean)
        if lag:
            assert mean_blind < mean - 0.05, (c, mean, mean_blind)  # 0.93 and 0.88 here
        else:
            assert blind[c] == drawn[c]
    bare = tmp_path / "bare.hdf5"
    shutil.copy(tmp / "shifted" / "episode_0.hdf5", bare)
    with h5py.File(bare, "r+") as f:
        del f.attrs["fps"]
    assert imac_main(["qa", "overlay", str(bare), "--calibration", str(tmp / "offsets.json"), "--out",
                      str(tmp_path / "bare")]) == 2
    err = capsys.readouterr().err
    assert "offsets.json: camera time offsets" in err and "no 'fps' attribute: pass --recipe" in err
    assert not (tmp_path / "bare").exists()


def test_qa_refine_fits_each_camera_at_its_images_own_time(shifted, tmp_path):
    """``qa refine`` of the left wrist camera of the shifted recording (a frame ahead), from a start 1 cm and 3 deg
    off with the offset in the calibration, comes back within 2 mm and 0.5 deg of the truth and keeps the offset;
    the robot is fitted at the joint vectors of each image's own time. Fitted at the recorded frames' joints
    instead (the offset ignored) the same start came back 6.5 mm and 0.85 deg off."""
    tmp, truth = shifted
    cam = "cam_left_wrist"
    start = load_calibration(tmp / "offsets.json")
    rng = np.random.default_rng(1)
    dt, dr = rng.normal(size=3), rng.normal(size=3)
    start[cam] = apply_update(start[cam], np.r_[dt / np.linalg.norm(dt), dr / np.linalg.norm(dr) * 3.0])  # cm, deg
    save_calibration(tmp_path / "start.json", start)
    report = refine_calibration(tmp / "shifted", tmp_path / "refined.json", recipe=ALOHA_RECIPE,
                                calibration=tmp_path / "start.json", robot_pixels="sim", cameras=[cam], frames=6)
    refined = load_calibration(tmp_path / "refined.json")
    assert pose_change(truth[cam], start[cam])["t_mm"] >= 9.9
    err = pose_change(truth[cam], refined[cam])
    assert err["t_mm"] <= 2.0 and err["r_deg"] <= 0.5, err
    assert refined[cam].time_offset_s == report["cameras"][cam]["time_offset_s"] == LAG[cam] / 25.0
    assert report["cameras"][cam]["iou_after"] > 0.97

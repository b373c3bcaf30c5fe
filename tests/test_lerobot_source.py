"""LeRobot datasets as the build's source (``source.type: lerobot``), and the depth sources.

The sources are made the way a user's dataset is: episodes recorded by our simulator,
written by LeRobot's own writer (``LeRobotDataset.create``, ``add_frame``,
``save_episode``: its PNG path and encoder), with camera keys of another naming. No
DA3 weights can be downloaded here: the ``da3`` build loads a randomly initialised
``da3-small`` saved to a local directory, as real weights would be.
"""

import hashlib
import json
import os
import re
import shutil

import huggingface_hub
import numpy as np
import pytest
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.build.flow import build_dataset as build
from imac_data.build.staging import BuildRequest
from imac_data.core.cameras import load_calibration, save_calibration
from imac_data.core.robot import aloha
from imac_data.errors import InputError
from imac_data.metadata import dataset_info, imac_block
from imac_data.recipes import load_recipe
from imac_data.sources.hdf5 import read_episode
from imac_data.sources.sim.recorder import SimConfig, record_dataset

H, W = 48, 64
KEYS = {"cam_high": "observation.images.top", "cam_left_wrist": "observation.images.left_wrist",
        "cam_right_wrist": "observation.images.right_wrist"}


def write_lerobot(sim, root, cameras, *, depth_key=None, state_unit=1.0):
    """A LeRobot v3.0 dataset of the recorded episodes, by LeRobot's own writer (``state_unit``:
    the observation.state of the arm joints is written as ``qpos * state_unit``)."""
    features = {"observation.state": {"dtype": "float32", "shape": (14,), "names": list(aloha.STATE_NAMES)},
                "action": {"dtype": "float32", "shape": (14,), "names": list(aloha.STATE_NAMES)}}
    for cam in cameras:
        features[KEYS[cam]] = {"dtype": "video", "shape": (H, W, 3), "names": ["height", "width", "channels"]}
        if depth_key:
            features[depth_key.format(cam=cam)] = {"dtype": "float32", "shape": (H, W), "names": None}
    ds = LeRobotDataset.create("local/source", fps=25, features=features, root=root, use_videos=True)
    for path in sorted(sim.glob("episode_*.hdf5")):
        ep = read_episode(path)
        for t in range(ep.num_frames):
            state = ep.qpos[t] * np.where(np.isin(np.arange(14), (6, 13)), 1.0, state_unit)
            frame = {"observation.state": state.astype(np.float32), "action": ep.action[t].astype(np.float32),
                     "task": "transfer the cube"}
            for cam in cameras:
                frame[KEYS[cam]] = ep.images[cam][t]
                if depth_key:
                    frame[depth_key.format(cam=cam)] = ep.depth_mm[cam][t].astype(np.float32) / 1000.0
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return root


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("lerobot_source")
    record_dataset(SimConfig(num_episodes=2, width=W, height=H, max_steps=22), out / "sim", progress=False)
    return out


@pytest.fixture(scope="module")
def source(sim):
    """Three cameras, no depth: the acceptance case."""
    return write_lerobot(sim / "sim", sim / "source", list(KEYS))


def tree_digest(root):
    return {p.relative_to(root): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(root.rglob("*"))
            if p.is_file()}


def recipe_file(tmp_path, source_root, calibration, **sections):
    data = {"name": "from_lerobot", "task": "transfer the cube", "robot": {"platform": "aloha_sim"},
            "cameras": {"calibration": str(calibration)},
            "source": {"type": "lerobot", "path": str(source_root), "cameras": {v: k for k, v in KEYS.items()}},
            "augment": {"height": H, "width": W, "contact_chunk": 4}}
    for key, value in sections.items():
        data[key] = {**data.get(key, {}), **value} if isinstance(value, dict) else value
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_recipe(path)


@pytest.fixture(scope="module")
def da3_weights(sim):
    from imac_data.sources.da3 import DepthAnything3

    pytest.importorskip("depth_anything_3")
    weights = sim / "da3-small-random"
    DepthAnything3.random_init("da3-small", device="cpu")._api_model.save_pretrained(str(weights))
    return weights


def test_lerobot_v30_source_built_with_da3(source, sim, da3_weights, tmp_path):
    before = tree_digest(source)
    meta = tmp_path / "episodes.csv"
    meta.write_text("episode_index,success,policy_name\n0,true,act\n1,0,act\n")
    recipe = recipe_file(tmp_path, source, sim / "sim" / "calibration.json",
                         source={"metadata": str(meta), "episode_defaults": {"source": "policy"}},
                         depth={"source": "da3", "model": str(da3_weights), "process_res": 28, "device": "cpu"},
                         # random weights give depth of no particular scale: crop nothing away
                         augment={"contact_workspace": {"min": [-1e3] * 3, "max": [1e3] * 3,
                                                        "depth_range": [0.0, 1e6]}})
    root = tmp_path / "out"
    ds = build(BuildRequest("local/out", recipe, root, progress=False))

    assert tree_digest(source) == before  # the source is only read
    for key, cam in ((v, k) for k, v in KEYS.items()):  # original videos: byte-identical, under our names
        for f in (source / "videos" / key).rglob("*.mp4"):
            out = root / "videos" / f"observation.images.{cam}" / f.relative_to(source / "videos" / key)
            assert out.read_bytes() == f.read_bytes(), out

    ds = LeRobotDataset("local/out", root=root)  # LeRobot's own loader
    src = LeRobotDataset("local/source", root=source)
    assert ds.meta.total_frames == src.meta.total_frames and ds.meta.total_episodes == 2
    for cam in KEYS:
        for key in (f"observation.images.{cam}", f"observation.depth.{cam}", f"control.motion.{cam}",
                    f"control.contact_r2s.{cam}", f"control.contact_s2g.{cam}"):
            assert key in ds.meta.video_keys, key
        assert f"camera_pose.{cam}" in ds.meta.features
    assert "control.contact_cap" in ds.meta.features
    item, ref = ds[13], src[13]
    np.testing.assert_array_equal(item["observation.state"], ref["observation.state"])
    np.testing.assert_array_equal(item["observation.images.cam_left_wrist"], ref["observation.images.left_wrist"])
    assert item["control.motion.cam_high"].shape == (3, H, W) and item["control.motion.cam_high"].max() > 0
    assert list(ds.meta.episodes["imac/success"]) == [True, False]
    assert list(ds.meta.episodes["imac/source"]) == ["policy", "policy"]
    assert list(ds.meta.episodes["imac/policy_name"]) == ["act", "act"]
    imac = imac_block(ds.meta)
    assert imac["depth"]["source"]["kind"] == "depth_anything_3"
    assert imac["depth"]["source"]["model"] == str(da3_weights)
    assert imac["build"]["source"]["cameras"]["observation.images.top"] == "cam_high"


def test_reader_frames_equal_lerobots_decoding(source):
    """The streamed reader against LeRobot's own loader (its video decoder) as the oracle,
    read in the pipeline's ranges: frame 0..4, then 5..8, ..."""
    from imac_data.sources.lerobot_dataset import SourceDataset, episode_states
    from imac_data.sources.lerobot_episodes import LeRobotEpisodeReader

    src = SourceDataset.open(source)
    ds = LeRobotDataset("local/source", root=source)
    states = episode_states(source, src.episodes, "observation.state")
    row = src.episodes[1]
    with LeRobotEpisodeReader(src, row, {"cam_left_wrist": KEYS["cam_left_wrist"]}, states[1], states[1]) as ep:
        frames = np.concatenate([ep.images("cam_left_wrist", lo, min(lo + 4, ep.num_frames))
                                 for lo in range(0, ep.num_frames, 4)])
    start = row["dataset_from_index"]
    truth = np.stack([(ds[start + t][KEYS["cam_left_wrist"]].numpy().transpose(1, 2, 0) * 255).round()
                      for t in range(row["length"])]).astype(np.uint8)
    assert frames.shape == truth.shape
    assert np.abs(frames.astype(int) - truth).max() <= 1  # same frames; colour conversion rounding only


@pytest.mark.parametrize("depth", ["recorded", "none"])
def test_one_camera_source_recorded_depth_or_none(sim, tmp_path, depth):
    """One camera; depth recorded as float metres in the source, or no depth (motion only)."""
    from imac_data.core.depth import depth_codec_of

    source = tmp_path / "one_cam"
    write_lerobot(sim / "sim", source, ["cam_high"], depth_key="observation.depth_m.{cam}")
    calibration = tmp_path / "calibration.json"
    save_calibration(calibration, {"cam_high": load_calibration(sim / "sim" / "calibration.json")["cam_high"]})
    section = ({"source": "recorded", "feature": "observation.depth_m.{cam}", "format": "metres"}
               if depth == "recorded" else {"source": "none"})
    recipe = recipe_file(tmp_path, source, calibration, depth=section,
                         source={"cameras": {"observation.images.top": "cam_high"}})
    ds = build(BuildRequest("local/one", recipe, tmp_path / "out", progress=False))
    if depth == "none":
        assert [k for k in ds.meta.video_keys if k.startswith(("control.", "observation.depth."))] == \
            ["control.motion.cam_high"]
        assert imac_block(ds.meta)["depth"]["source"]["kind"] == "none"
        return
    truth = read_episode(sorted((sim / "sim").glob("episode_*.hdf5"))[1]).depth_mm["cam_high"][3] / 1000.0
    item = ds[ds.meta.episodes["dataset_from_index"][1] + 3]
    metres = np.asarray(depth_codec_of(ds.meta).decode(item["observation.depth.cam_high"], channel_axis=-3))
    valid = (truth > 0.1) & (truth < 1.2)
    assert np.median(np.abs(metres[valid] - truth[valid])) < 3e-3
    assert "control.contact_s2g.cam_high" in ds.meta.video_keys


def test_a_state_recorded_in_degrees_is_named(sim, tmp_path, capsys):
    """The arm joints of observation.state in degrees, the recipe's joint map in radians: the
    build warns before it starts, naming the dataset, key, joint and the scale that fixes it."""
    source = tmp_path / "degrees"
    write_lerobot(sim / "sim", source, ["cam_high"], state_unit=180 / np.pi)
    calibration = tmp_path / "calibration.json"
    save_calibration(calibration, {"cam_high": load_calibration(sim / "sim" / "calibration.json")["cam_high"]})
    recipe = recipe_file(tmp_path, source, calibration, depth={"source": "none"},
                         source={"cameras": {"observation.images.top": "cam_high"}})
    build(BuildRequest("local/deg", recipe, tmp_path / "out", progress=False))
    err = capsys.readouterr().err
    assert f"warning: {source} (observation.state): recorded joint values lie outside the URDF limits" in err
    assert "index 8 ('vx300s_right/shoulder')" in err and "scale: 0.01745329" in err and "left_finger" not in err
    assert "[build] stage" in err  # progress=False hides the bars, not the stage timings


# ------------------------------------------------------------------------ bad input


def expect_error(recipe, tmp_path, match):
    root = tmp_path / "never"
    with pytest.raises(InputError, match=match):
        build(BuildRequest("local/never", recipe, root, progress=False))
    assert not root.exists() and not (tmp_path / ".never.staging").exists()


def test_camera_mapping_naming_a_missing_key(source, sim, tmp_path):
    recipe = recipe_file(tmp_path, source, sim / "sim" / "calibration.json", depth={"source": "none"},
                         source={"cameras": {"observation.images.head": "cam_high",
                                             KEYS["cam_left_wrist"]: "cam_left_wrist",
                                             KEYS["cam_right_wrist"]: "cam_right_wrist"}})
    expect_error(recipe, tmp_path, r"source.cameras: dataset .*source has no feature 'observation.images.head'")


def test_joint_layout_wider_than_the_state(source, sim, tmp_path):
    from imac_data.sources.lerobot_dataset import SourceDataset, check_joint_layout

    with pytest.raises(InputError, match=r"robot.joint_map has 16 entries, wider than 'observation.state' of "
                                         r"dataset .*source \(14 entries"):
        check_joint_layout(SourceDataset.open(source), "observation.state", "action", "joint", 16, "r.yaml")
    with pytest.raises(InputError, match=r"no feature 'observation.qpos' \(source.state_key\)"):
        check_joint_layout(SourceDataset.open(source), "observation.qpos", "action", "joint", 14, "r.yaml")


def test_damaged_source_video_is_named_before_any_work(source, sim, tmp_path):
    """A camera video cut at 60 % of its bytes (the second episode's frames are gone): one error
    naming the file, the frame where decoding stops and the episode that needs the rest, before
    any work; without the check the build copied the video and only a later load failed."""
    copy = tmp_path / "src"
    shutil.copytree(source, copy)
    video = sorted((copy / "videos" / KEYS["cam_left_wrist"]).rglob("*.mp4"))[0]
    os.truncate(video, int(video.stat().st_size * 0.6))
    before = tree_digest(copy)
    recipe = recipe_file(tmp_path, copy, sim / "sim" / "calibration.json", depth={"source": "none"})
    expect_error(recipe, tmp_path, rf"{re.escape(str(video))} \({KEYS['cam_left_wrist']}\) (does not decode after frame "
                                   r"\d+|holds \d+ frames).*but episode \d uses its frames \d+\.\.\d+: the video is "
                                   "damaged or cut short")
    assert tree_digest(copy) == before


def test_missing_source_files_are_named_before_any_work(source, sim, tmp_path):
    """A deleted camera video or tasks table: one error naming the file, before the copy
    (LeRobot would otherwise try to download it from the hub), and nothing written."""
    copy = tmp_path / "src"
    shutil.copytree(source, copy)
    video = sorted((copy / "videos" / KEYS["cam_high"]).rglob("*.mp4"))[0]
    video.unlink()
    recipe = recipe_file(tmp_path, copy, sim / "sim" / "calibration.json", depth={"source": "none"})
    expect_error(recipe, tmp_path, f"episode 0 needs {video}, which is missing")
    shutil.copytree(source / "videos", copy / "videos", dirs_exist_ok=True)
    (copy / "meta" / "tasks.parquet").unlink()
    expect_error(recipe, tmp_path, r"meta/tasks.parquet is missing")


@pytest.mark.parametrize("damage, match", [
    (lambda info: info.pop("fps"), r"'fps' must be a number; it is missing"),
    (lambda info: info.update(fps=12.5), r"'fps' must be a positive whole number, got 12.5"),
    (lambda info: info.pop("total_episodes"), r"'total_episodes' must be an integer; it is missing"),
    (lambda info: info.update(features=[]), r"'features' must be an object; got \[\]"),
    (None, r"info.json: not valid JSON"),
])
def test_damaged_info_json_is_named(source, tmp_path, damage, match):
    from imac_data.sources.lerobot_dataset import SourceDataset

    copy = tmp_path / "src"
    shutil.copytree(source / "meta", copy / "meta")
    path = copy / "meta" / "info.json"
    info = json.loads(path.read_text())
    if damage is not None:
        damage(info)
    path.write_text("{not json" if damage is None else json.dumps(info))
    with pytest.raises(InputError, match=match):
        SourceDataset.open(copy)


def test_da3_model_directory_that_does_not_exist(source, sim, tmp_path):
    recipe = recipe_file(tmp_path, source, sim / "sim" / "calibration.json",
                         depth={"source": "da3", "model": str(tmp_path / "weights" / "da3-base")})
    expect_error(recipe, tmp_path, r"depth.model: the Depth Anything 3 model directory .*weights/da3-base does not "
                                   "exist")


def test_end_effector_actions_are_refused(source, sim, tmp_path):
    from imac_data.sources.lerobot_dataset import cartesian_names

    recipe = recipe_file(tmp_path, source, sim / "sim" / "calibration.json", depth={"source": "none"},
                         source={"action_space": "ee"})
    expect_error(recipe, tmp_path, "joint-space actions are required.*declares an end-effector action space")
    assert cartesian_names(["x", "y", "z", "roll", "pitch", "yaw", "gripper"])[:3] == ["x", "y", "z"]
    assert cartesian_names(["eef_pos_0", "eef_pos_1"]) == ["eef_pos_0", "eef_pos_1"]
    assert cartesian_names(list(aloha.STATE_NAMES)) == []  # forearm_roll, wrist_rotate: joints


def test_hub_source_offline_is_a_clear_error(tmp_path, monkeypatch):
    from imac_data.sources.lerobot_dataset import locate_source

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    with pytest.raises(InputError, match="source.repo_id 'lerobot/pusht': LeRobot cannot download it.*source.path"):
        locate_source(None, "lerobot/pusht", tmp_path / "staging")


def test_episode_metadata_errors_name_the_file_and_entry(tmp_path):
    from imac_data.recipes import EpisodeDefaults
    from imac_data.sources.lerobot_dataset import episode_metadata

    bad = tmp_path / "meta.json"
    bad.write_text(json.dumps({"0": {"success": True}, "5": {"success": False}}))
    with pytest.raises(InputError, match=r"meta.json entry 1: episode_index 5 is not an episode"):
        episode_metadata(bad, 2, EpisodeDefaults())
    bad.write_text(json.dumps([{"episode_index": 0, "sucess": True}]))
    with pytest.raises(InputError, match=r"unknown field\(s\) \['sucess'\]"):
        episode_metadata(bad, 2, EpisodeDefaults())
    good = tmp_path / "meta.csv"
    good.write_text("episode_index,success,checkpoint\n1,false,step_1000\n")
    rows = episode_metadata(good, 2, EpisodeDefaults(policy_name="act"))
    assert rows[1] == {"imac/source": "teleop", "imac/policy_name": "act", "imac/checkpoint": "step_1000",
                       "imac/success": False}
    assert rows[0]["imac/success"] is None


def write_v21(v30, out):
    """The LeRobot v2.1 layout of the v3.0 dataset ``v30`` (per-episode data and video files,
    jsonl metadata), as LeRobot 0.3 wrote it; the videos re-encoded per episode."""
    import pandas as pd

    from imac_data.dataset.videos import encode_video, read_video_frames

    info = json.loads((v30 / "meta" / "info.json").read_text())
    episodes = pd.concat([pd.read_parquet(f) for f in sorted((v30 / "meta" / "episodes").rglob("*.parquet"))])
    data = pd.concat([pd.read_parquet(f) for f in sorted((v30 / "data").rglob("*.parquet"))])
    tasks = pd.read_parquet(v30 / "meta" / "tasks.parquet")
    videos = [k for k, f in info["features"].items() if f["dtype"] == "video"]
    info.update(codebase_version="v2.1", total_chunks=1, total_videos=len(videos) * len(episodes),
                data_path="data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
                video_path="videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4")
    for key in ("data_files_size_in_mb", "video_files_size_in_mb"):
        info.pop(key, None)
    (out / "meta").mkdir(parents=True)
    (out / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    with open(out / "meta" / "tasks.jsonl", "w") as f:
        for task, row in tasks.iterrows():
            f.write(json.dumps({"task_index": int(row["task_index"]), "task": task}) + "\n")
    with open(out / "meta" / "episodes.jsonl", "w") as f, open(out / "meta" / "episodes_stats.jsonl", "w") as g:
        for _, row in episodes.iterrows():
            ep = int(row["episode_index"])
            f.write(json.dumps({"episode_index": ep, "tasks": list(row["tasks"]), "length": int(row["length"])}) + "\n")
            stats = {}
            for col in (c for c in episodes.columns if c.startswith("stats/")):
                _, key, stat = col.split("/")
                stats.setdefault(key, {})[stat] = np.asarray(row[col].tolist() if hasattr(row[col], "tolist")
                                                             else row[col], dtype=object).tolist()
            g.write(json.dumps({"episode_index": ep, "stats": stats}, default=lambda a: np.asarray(a).tolist()) + "\n")
            part = out / "data" / "chunk-000" / f"episode_{ep:06d}.parquet"
            part.parent.mkdir(parents=True, exist_ok=True)
            data[data["episode_index"] == ep].to_parquet(part, index=False)
            for key in videos:
                src = v30 / "videos" / key / "chunk-000" / "file-000.mp4"
                frames = read_video_frames(src)[int(row["dataset_from_index"]):int(row["dataset_to_index"])]
                encode_video(out / "videos" / "chunk-000" / key / f"episode_{ep:06d}.mp4", frames, fps=info["fps"])
    return out


def test_v21_source_is_converted_by_lerobot_on_a_staged_copy(source, sim, tmp_path):
    from imac_data.dataset.videos import read_video_frames

    v21 = write_v21(source, tmp_path / "v21")
    before = tree_digest(v21)
    recipe = recipe_file(tmp_path, v21, sim / "sim" / "calibration.json", depth={"source": "none"})
    ds = build(BuildRequest("local/from_v21", recipe, tmp_path / "out", progress=False))
    assert tree_digest(v21) == before and not (tmp_path / "v21_old").exists()  # converted elsewhere
    assert dataset_info(ds.meta)["codebase_version"] == "v3.0" and ds.meta.total_episodes == 2
    assert imac_block(ds.meta)["build"]["source"]["codebase_version"] == "v2.1"
    out = read_video_frames(tmp_path / "out" / "videos" / "observation.images.cam_high" / "chunk-000" / "file-000.mp4")
    episodes = v21 / "videos" / "chunk-000" / KEYS["cam_high"]
    recorded = np.concatenate([read_video_frames(episodes / f"episode_{e:06d}.mp4") for e in range(2)])
    np.testing.assert_array_equal(out, recorded)  # concatenated by the converter, not re-encoded


def test_output_inside_the_source_dataset_is_refused(source, sim, tmp_path):
    before = tree_digest(source)
    recipe = recipe_file(tmp_path, source, sim / "sim" / "calibration.json", depth={"source": "none"})
    with pytest.raises(InputError, match=r"lies inside the source dataset directory .*source"):
        build(BuildRequest("local/x", recipe, source / "out", progress=False))
    with pytest.raises(InputError, match=r"would contain the source dataset .*source"):
        build(BuildRequest("local/x", recipe, source.parent, overwrite=True, progress=False))
    assert tree_digest(source) == before


def test_hdf5_build_with_depth_none_has_motion_streams_only(sim, tmp_path):
    """The depth section reaches the HDF5 build's shard workers too."""
    recipe = recipe_file(tmp_path, sim / "sim", sim / "sim" / "calibration.json", depth={"source": "none"},
                         source={"type": "aloha_hdf5", "cameras": {}})
    ds = build(BuildRequest("local/h5", recipe, tmp_path / "out", progress=False), workers=1)
    added = sorted(k for k in ds.meta.video_keys if not k.startswith("observation.images."))
    assert added == sorted(f"control.motion.{c}" for c in KEYS)
    assert "control.contact_cap" not in ds.meta.features and imac_block(ds.meta)["contact"] is None


READER = """
import json, sys
from pathlib import Path
from imac_data.sources.lerobot_episodes import _VideoFrames
from imac_data.build.workers import peak_rss_mb
path, length, step = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
frames = _VideoFrames(path, 0.0, 25.0, length, "memory test")
total = 0
for lo in range(0, length, step):
    total += int(frames.read(lo, min(lo + step, length))[:, 0, 0, 0].astype(int).sum() >= 0)
frames.close()
print(json.dumps({"peak_mb": peak_rss_mb(), "chunks": total}))
"""


def test_reader_memory_does_not_grow_with_episode_length(tmp_path):
    """Peak memory of reading a camera video chunk by chunk (9 frames, as the pipeline does),
    for a 24-frame and a 400-frame episode at 240x320: a reader that held the episode would
    grow by 90 MB between them."""
    import subprocess
    import sys
    from pathlib import Path

    from imac_data.dataset.videos import VideoEncoding, encode_video

    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, (8, 240, 320, 3), dtype=np.uint8)
    peaks = {}
    for n in (24, 400):
        path = encode_video(tmp_path / f"{n}.mp4", np.resize(base, (n, 240, 320, 3)), fps=25,
                            encoding=VideoEncoding.lerobot_default())
        out = subprocess.run([sys.executable, "-c", READER, str(path), str(n), "9"], capture_output=True, text=True,
                             timeout=300, cwd=Path(__file__).resolve().parent.parent)
        assert out.returncode == 0, out.stderr[-3000:]
        result = json.loads(out.stdout.strip().splitlines()[-1])
        assert result["chunks"] == -(-n // 9)
        peaks[n] = result["peak_mb"]
    print(f"reader peak RSS: {peaks} MB")
    assert peaks[400] - peaks[24] < 30.0, peaks


def test_unmapped_cameras_are_left_out(source, sim, tmp_path):
    calibration = tmp_path / "calibration.json"
    save_calibration(calibration, {"cam_high": load_calibration(sim / "sim" / "calibration.json")["cam_high"]})
    recipe = recipe_file(tmp_path, source, calibration, depth={"source": "none"},
                         source={"cameras": {"observation.images.top": "cam_high"}})
    ds = build(BuildRequest("local/top", recipe, tmp_path / "out", progress=False))
    assert ds.meta.video_keys == ["observation.images.cam_high", "control.motion.cam_high"]
    assert not any("wrist" in c for c in ds.meta.episodes.column_names)
    assert sorted(p.name for p in (tmp_path / "out" / "videos").iterdir()) == sorted(ds.meta.video_keys)
    top = source / "videos" / "observation.images.top" / "chunk-000" / "file-000.mp4"
    assert (tmp_path / "out" / "videos" / "observation.images.cam_high" / "chunk-000" / "file-000.mp4").read_bytes() \
        == top.read_bytes()


def test_lerobot_source_build_takes_the_output_lock(source, sim, tmp_path):
    """A LeRobot-source build stages next to its output like any build, so it takes the
    output's lock: with another build holding it, refused before anything is staged."""
    import subprocess
    import sys

    from imac_data.errors import EnvironmentFault

    recipe = recipe_file(tmp_path, source, sim / "sim" / "calibration.json", depth={"source": "none"})
    root = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom pathlib import Path\n"
                               "from imac_data.dataset.output import output_lock\nwith output_lock(Path(sys.argv[1])):\n"
                               "    print('locked', flush=True)\n    time.sleep(600)", str(root)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(EnvironmentFault, match=f"another build \\(PID {holder.pid}\\)"):
            build(BuildRequest("local/locked", recipe, root, progress=False))
        assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [".out.lock"]
    finally:
        holder.kill()
        holder.wait()

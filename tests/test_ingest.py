"""HDF5 episodes -> base LeRobot dataset: content, both HDF5 variants, and bad input."""

import shutil

import h5py
import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.build.from_episodes import ingest_episodes
from imac_data.core.cameras import load_calibration, save_calibration
from imac_data.core.rig import Rig
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.dataset.ingest import IngestOptions
from imac_data.dataset.output import staging_dir
from imac_data.errors import InputError
from imac_data.metadata import dataset_info
from imac_data.sources.hdf5 import read_episode, write_episode
from imac_data.sources.sim.recorder import SimConfig, record_dataset


@pytest.fixture(scope="module")
def robot():
    return RobotModel(aloha.robot_config())


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    record_dataset(SimConfig(num_episodes=2, width=80, height=64, max_steps=24), out, progress=False)
    return out


@pytest.fixture
def source(sim_dir, tmp_path):
    """A private copy of the recorded episodes that a test may corrupt."""
    dst = tmp_path / "src"
    shutil.copytree(sim_dir, dst)
    return dst


def options(**kw):
    return IngestOptions(**{"fps": 25, "task": "transfer", "state_names": aloha.STATE_NAMES, **kw})


def ingest(src, robot, root, **kw):
    paths = sorted(src.glob("episode_*.hdf5"))
    calib = load_calibration(src / "calibration.json")
    return ingest_episodes(paths, rig=Rig(robot, calib), repo_id="local/test", root=root,
                           options=kw.pop("opts", options()), progress=False, **kw)


def assert_nothing_written(root):
    assert not root.exists()
    assert not staging_dir(root).exists()


def test_ingest_round_trip(source, robot, tmp_path):
    root = tmp_path / "ds"
    before = {p.name: p.read_bytes() for p in source.iterdir()}
    ds = ingest(source, robot, root)
    # the source is only read
    assert {p.name: p.read_bytes() for p in source.iterdir()} == before
    ds = LeRobotDataset("local/test", root=root)
    ep = [read_episode(p) for p in sorted(source.glob("episode_*.hdf5"))]
    assert ds.meta.total_episodes == 2
    assert ds.meta.total_frames == sum(e.num_frames for e in ep)
    calib = load_calibration(source / "calibration.json")
    last = ep[1].num_frames - 1
    item = ds[ep[0].num_frames + last]  # last frame of episode 1
    np.testing.assert_allclose(item["observation.state"].numpy(), ep[1].qpos[last], atol=1e-6)
    np.testing.assert_allclose(item["action"].numpy(), ep[1].action[last], atol=1e-6)
    np.testing.assert_allclose(item["camera_pose.cam_high"].numpy().reshape(4, 4), calib["cam_high"].T_world_cam,
                               atol=1e-6)
    # wrist camera pose = FK(measured state) @ mount
    links = robot.link_poses(torch.as_tensor(ep[1].qpos[last], dtype=torch.float64))
    T = calib["cam_left_wrist"].pose(links, dtype=torch.float64).numpy()
    np.testing.assert_allclose(item["camera_pose.cam_left_wrist"].numpy().reshape(4, 4), T, atol=1e-5)
    # video is lossy, but the frame is the same frame
    rgb = (item["observation.images.cam_high"].permute(1, 2, 0).numpy() * 255).astype(np.float32)
    assert np.abs(rgb - ep[1].images["cam_high"][last]).mean() < 6.0
    # every video holds every frame (LeRobot 0.4.4's streaming encoder drops episodes' last frames)
    import av

    for mp4 in (root / "videos").rglob("*.mp4"):
        with av.open(str(mp4)) as container:
            assert sum(1 for _ in container.decode(video=0)) == ds.meta.total_frames, mp4
    for end in np.cumsum([e.num_frames for e in ep]) - 1:
        assert ds[int(end)]["observation.images.cam_right_wrist"].shape == (3, 64, 80)
    # episode metadata and the imac block
    info = dataset_info(root)
    assert info["imac"]["robot"]["name"] == "aloha"
    assert set(info["imac"]["cameras"]) == {"cam_high", "cam_left_wrist", "cam_right_wrist"}
    episodes = ds.meta.episodes
    assert list(episodes["imac/source"]) == ["policy", "policy"]
    assert list(episodes["imac/policy_name"]) == ["scripted_transfer_cube"] * 2


def test_ingest_jpeg_compressed_variant(source, robot, tmp_path):
    for p in source.glob("episode_*.hdf5"):
        write_episode(p, read_episode(p), compress=True)
    with h5py.File(next(source.glob("episode_*.hdf5"))) as f:
        assert f.attrs["compress"] and "compress_len" in f
    ds = ingest(source, robot, tmp_path / "ds")
    assert ds.meta.total_episodes == 2
    assert ds[0]["observation.images.cam_high"].shape == (3, 64, 80)


def rewrite(path, fn):
    with h5py.File(path, "a") as f:
        fn(f)


@pytest.mark.parametrize("corrupt, message", [
    (lambda f: f.__delitem__("action"), r"missing HDF5 dataset 'action'"),
    (lambda f: f.move("observations/qpos", "observations/q_pos"), r"missing HDF5 dataset 'observations/qpos'.*q_pos"),
    (lambda f: (f.__delitem__("action"), f.create_dataset("action", data=np.zeros((3, 14)))),
     r"length/width mismatch.*'action' is \(3, 14\)"),
    (lambda f: f["observations/qpos"].__setitem__((2, 4), np.nan), r"'observations/qpos' has NaN.*frame 2, joint index 4"),
    (lambda f: (f.__delitem__("observations/images/cam_high"),
                f.create_dataset("observations/images/cam_high", data=np.zeros((2, 64, 80, 3), np.uint8))),
     r"'observations/images/cam_high' has 2 frames"),
])
def test_bad_episode_names_file_and_key(source, robot, tmp_path, corrupt, message):
    bad = sorted(source.glob("episode_*.hdf5"))[1]
    rewrite(bad, corrupt)
    root = tmp_path / "ds"
    with pytest.raises(InputError, match=message) as e:
        ingest(source, robot, root)
    assert str(bad) in str(e.value)
    assert_nothing_written(root)


def test_calibration_for_cameras_the_episode_lacks(source, robot, tmp_path):
    calib = load_calibration(source / "calibration.json")
    calib["cam_low"] = calib["cam_high"]
    save_calibration(source / "calibration.json", calib)
    with pytest.raises(InputError, match=r"calibration has camera\(s\) \['cam_low'\]"):
        ingest(source, robot, tmp_path / "ds")
    assert_nothing_written(tmp_path / "ds")


def test_mixed_camera_sets(source, robot, tmp_path):
    def drop_camera(f):
        del f["observations/images/cam_right_wrist"]
        del f["observations/images_depth/cam_right_wrist"]

    rewrite(sorted(source.glob("episode_*.hdf5"))[1], drop_camera)
    with pytest.raises(InputError, match="different camera sets"):
        ingest(source, robot, tmp_path / "ds")
    assert_nothing_written(tmp_path / "ds")


def test_existing_output_is_not_replaced_without_overwrite(source, robot, tmp_path):
    root = tmp_path / "ds"
    root.mkdir()
    (root / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="already exists"):
        ingest(source, robot, root)
    assert (root / "keep.txt").read_text() == "mine"


def test_failure_midway_leaves_nothing(source, robot, tmp_path, monkeypatch):
    """An error after LeRobot has started writing (here: while reading episode 2's frames)
    removes the staging dir."""
    from imac_data.sources.hdf5 import EpisodeReader

    real = EpisodeReader.images

    def failing(self, cam, start, stop):
        if self.path.name == "episode_1.hdf5":
            raise InputError(f"{self.path}: simulated read failure")
        return real(self, cam, start, stop)

    monkeypatch.setattr(EpisodeReader, "images", failing)
    with pytest.raises(InputError, match="simulated read failure"):
        ingest(source, robot, tmp_path / "ds")
    assert_nothing_written(tmp_path / "ds")


def test_options_are_validated():
    with pytest.raises(InputError, match="source"):
        IngestOptions(fps=25, task="t", source="scripted")
    with pytest.raises(InputError, match="fps"):
        IngestOptions(fps=0, task="t")

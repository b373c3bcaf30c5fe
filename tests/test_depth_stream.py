"""The stored depth stream ``observation.depth.{cam}``: simulated ground-truth depth ->
codec -> our encoder -> LeRobotDataset (default decoder) -> decoded metres.

Oracle: MuJoCo's depth recorded in the episodes. With the lossless settings the
decoded depth must equal the codec's own 8-bit round trip exactly (no error added by
the video), which is a stronger statement than the error bounds checked as well.
Figures over whole episodes (and LeRobot's default encoder for comparison):
``benchmarks/depth_fidelity.py``.
"""

import hashlib
import json
import shutil

import numpy as np
import pytest
from lerobot.datasets.aggregate import aggregate_datasets
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.build.from_episodes import ingest_episodes
from imac_data.core.cameras import load_calibration, rescale_intrinsics
from imac_data.core.depth import DepthCodec, depth_codec_of
from imac_data.core.metric_depth import resize_depth
from imac_data.core.rig import Rig
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.dataset.depth_streams import add_depth_streams
from imac_data.dataset.ingest import IngestOptions
from imac_data.dataset.videos import VideoEncoding
from imac_data.errors import InputError
from imac_data.layout import depth_key
from imac_data.metadata import dataset_info
from imac_data.sources.depth import RecordedDepth, episode_views
from imac_data.sources.hdf5 import episode_paths, read_episode
from imac_data.sources.sim.recorder import SimConfig, record_dataset

CAMS = ["cam_high", "cam_left_wrist", "cam_right_wrist"]
CODEC = DepthCodec.preset("manipulation")


@pytest.fixture(scope="module")
def robot():
    return RobotModel(aloha.robot_config())


@pytest.fixture(scope="module")
def sim(tmp_path_factory, robot):
    """Two short simulated episodes (12 frames, 64x80) and their base LeRobot dataset."""
    out = tmp_path_factory.mktemp("depth_sim")
    src = out / "src"
    record_dataset(SimConfig(num_episodes=2, width=80, height=64, max_steps=24), src, progress=False)
    root = out / "base"
    ingest_episodes(episode_paths(src), rig=Rig(robot, load_calibration(src / "calibration.json")),
                    repo_id="local/depth", root=root,
                    options=IngestOptions(fps=25, task="t", state_names=aloha.STATE_NAMES), progress=False)
    raws = [read_episode(p) for p in episode_paths(src)]
    return {"src": src, "root": root, "raws": raws, "calib": load_calibration(src / "calibration.json")}


def recorded(sim, robot):
    for i, raw in enumerate(sim["raws"]):
        yield RecordedDepth().depth(episode_views(raw, Rig(robot, sim["calib"]), name=f"episode {i}"))


@pytest.fixture(scope="module")
def with_depth(sim, robot, tmp_path_factory):
    """The base dataset with depth streams added (read-only for the tests)."""
    root = tmp_path_factory.mktemp("with_depth") / "ds"
    shutil.copytree(sim["root"], root)
    before = video_digest(root)
    add_depth_streams(root, recorded(sim, robot), source=RecordedDepth().describe())
    return root, before


@pytest.fixture
def copy(sim, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(sim["root"], dst)
    return dst


def video_digest(root):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted((root / "videos").rglob("*.mp4"))}


def tree_digest(root):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def gt_metres(raw, cam):
    return raw.depth_mm[cam].astype(np.float32) / 1000.0


def colours(frames):
    """LeRobot's float (..., 3, H, W) frames in [0, 1] -> the uint8 (..., H, W, 3) colours decoded."""
    return (frames * 255).round().byte().movedim(-3, -1).numpy()


def test_depth_round_trip_is_bit_exact_through_lerobot(with_depth, sim):
    root, before = with_depth
    after = video_digest(root)
    assert {k: after[k] for k in before} == before  # the RGB streams are byte-identical

    ds = LeRobotDataset("local/depth", root=root)  # default decoder: torchcodec
    codec = depth_codec_of(ds.meta)
    assert codec == CODEC
    errs, n = [], 0
    for raw in sim["raws"]:
        for t in range(raw.num_frames):
            item = ds[n]
            n += 1
            for cam in CAMS:
                gt = gt_metres(raw, cam)[t]
                frame = item[depth_key(cam)]
                # lossless: the very colours the codec wrote
                np.testing.assert_array_equal(colours(frame), CODEC.encode_uint8(gt))
                got = codec.decode(frame, channel_axis=-3).numpy()  # what a user does
                np.testing.assert_allclose(got, CODEC.decode(CODEC.encode_uint8(gt)), rtol=1e-6, atol=0)
                assert np.array_equal(got == 0, gt == 0)  # invalid stays invalid, nothing else becomes it
                m = (gt >= 0.1) & (gt <= 1.2)
                errs.append(np.abs(got[m] - gt[m]))
    err_mm = np.concatenate(errs) * 1000
    assert err_mm.size > 10_000
    assert np.median(err_mm) <= 3.0 and np.percentile(err_mm, 99) <= 10.0
    assert err_mm.max() <= 1.5  # half the 8-bit step at 1.2 m (2.8 mm)


def test_metadata_records_codec_encoder_and_intrinsics(with_depth, sim):
    root, _ = with_depth
    info = dataset_info(root)
    block = info["imac"]["depth"]
    assert DepthCodec.from_dict(block["codec"]) == CODEC
    assert VideoEncoding.from_dict(block["encoding"]) == VideoEncoding.lossless_rgb()
    assert block["source"]["kind"] == "recorded"
    for cam in CAMS:
        key = depth_key(cam)
        feature = info["features"][key]
        assert feature["shape"] == [64, 80, 3]
        assert feature["info"]["imac.depth_codec"] == CODEC.to_dict()
        assert feature["info"]["video.pix_fmt"] == "gbrp"
        stream = block["streams"][cam]
        assert stream["key"] == key and (stream["height"], stream["width"]) == (64, 80)
        np.testing.assert_allclose(stream["K"], info["imac"]["cameras"][cam]["K"])
    stats = json.loads((root / "meta" / "stats.json").read_text())
    assert np.array(stats[depth_key("cam_high")]["mean"]).shape == (3, 1, 1)


def test_delta_timestamps_on_the_depth_key(with_depth, sim):
    root, _ = with_depth
    key = depth_key("cam_left_wrist")
    ds = LeRobotDataset("local/depth", root=root, delta_timestamps={key: [-0.08, -0.04, 0.0]})
    raw = sim["raws"][1]
    item = ds[sim["raws"][0].num_frames + 1]  # episode 1, frame 1
    assert item[key].shape == (3, 3, 64, 80)
    assert item[f"{key}_is_pad"].tolist() == [True, False, False]
    np.testing.assert_array_equal(colours(item[key][1:]), CODEC.encode_uint8(gt_metres(raw, "cam_left_wrist")[0:2]))


def test_resized_streams_rescale_the_intrinsics(copy, sim, robot):
    add_depth_streams(copy, recorded(sim, robot), size={"cam_high": (32, 40)}, codec=CODEC)
    info = dataset_info(copy)
    assert info["features"][depth_key("cam_high")]["shape"] == [32, 40, 3]
    assert info["features"][depth_key("cam_left_wrist")]["shape"] == [64, 80, 3]
    K = np.array(info["imac"]["cameras"]["cam_high"]["K"])
    np.testing.assert_allclose(info["imac"]["depth"]["streams"]["cam_high"]["K"],
                               rescale_intrinsics(K, (64, 80), (32, 40)))
    ds = LeRobotDataset("local/depth", root=copy)
    want = resize_depth(gt_metres(sim["raws"][0], "cam_high")[3], (32, 40))
    np.testing.assert_array_equal(colours(ds[3][depth_key("cam_high")]), CODEC.encode_uint8(want))


def test_resize_depth_is_nearest_and_never_mixes_invalid():
    d = np.array([[1.0, 0.0, 3.0, 4.0], [5.0, 6.0, np.nan, 8.0]], np.float32)
    np.testing.assert_array_equal(resize_depth(d, (1, 2)), [[6.0, 8.0]])  # pixel containing each centre
    up = resize_depth(d, (4, 8))
    assert set(np.unique(up[np.isfinite(up)])) <= set(np.unique(d[np.isfinite(d)]))
    assert np.isnan(up).sum() == 4 and (up == 0).sum() == 4


def test_aggregate_datasets_with_depth_streams(with_depth, sim, tmp_path):
    root, _ = with_depth
    roots = [tmp_path / "a", tmp_path / "b"]
    for r in roots:
        shutil.copytree(root, r)
    aggregate_datasets(["local/a", "local/b"], "local/ab", roots=roots, aggr_root=tmp_path / "ab")
    ds = LeRobotDataset("local/ab", root=tmp_path / "ab")
    assert ds.meta.total_episodes == 4
    key = depth_key("cam_right_wrist")
    assert ds.meta.features[key]["info"]["imac.depth_codec"] == CODEC.to_dict()  # survives; info["imac"] does not
    n0 = sum(r.num_frames for r in sim["raws"])
    raw = sim["raws"][1]
    for offset in (0, n0):  # the same frame in the first and in the second source dataset
        item = ds[offset + sim["raws"][0].num_frames + 5]
        np.testing.assert_array_equal(colours(item[key]), CODEC.encode_uint8(gt_metres(raw, "cam_right_wrist")[5]))


@pytest.mark.parametrize("case", ["extra_axis", "integer_mm", "negative", "missing_camera", "short_episode",
                                  "other_aspect"])
def test_bad_depth_leaves_the_dataset_as_it_was(copy, sim, robot, case):
    episodes = list(recorded(sim, robot))
    ep = episodes[1]
    if case == "extra_axis":
        ep["cam_high"] = ep["cam_high"][..., None]
    elif case == "integer_mm":
        ep["cam_high"] = sim["raws"][1].depth_mm["cam_high"]
    elif case == "negative":
        ep["cam_high"] = ep["cam_high"].copy()
        ep["cam_high"][3, 10, 10] = -0.5
    elif case == "missing_camera":
        del ep["cam_high"]
    elif case == "short_episode":
        ep["cam_high"] = ep["cam_high"][:-1]
    elif case == "other_aspect":
        ep["cam_high"] = ep["cam_high"][:, :, :64]
    before = tree_digest(copy)
    with pytest.raises(InputError, match="episode 1"):
        add_depth_streams(copy, episodes)
    assert tree_digest(copy) == before


def test_nan_and_inf_depth_are_stored_as_invalid(copy, sim, robot):
    episodes = list(recorded(sim, robot))
    d = episodes[0]["cam_left_wrist"].copy()
    d[0, :5, :5] = np.nan
    d[0, 5:10, :5] = np.inf
    episodes[0]["cam_left_wrist"] = d
    add_depth_streams(copy, episodes)
    ds = LeRobotDataset("local/depth", root=copy)
    got = CODEC.decode(ds[0][depth_key("cam_left_wrist")], channel_axis=-3).numpy()
    assert (got[:10, :5] == 0).all()
    assert (got[10:][d[0, 10:] > 0] > 0).all()


def test_recorded_depth_source(sim, robot):
    raw = sim["raws"][0]
    views = episode_views(raw, Rig(robot, sim["calib"]))
    depth = RecordedDepth().depth(views)
    assert sorted(depth) == CAMS
    for cam in CAMS:
        assert depth[cam].dtype == np.float32 and depth[cam].shape == (raw.num_frames, 64, 80)
        np.testing.assert_allclose(depth[cam], raw.depth_mm[cam] / 1000.0, rtol=1e-6)
    views.depth_mm = {}
    with pytest.raises(InputError, match="no recorded depth"):
        RecordedDepth().depth(views)

"""Adding a video stream to an existing LeRobot v3.0 dataset (imac_data.dataset.streams).

The oracle is the frames themselves: the lossless settings must come back bit-exact
through LeRobot's own loader (torchcodec) and through PyAV, and LeRobot's own files
must not change.
"""

import hashlib
import json
import os
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
from lerobot.datasets.compute_stats import sample_indices
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.build.staging import staged_output
from imac_data.dataset import streams as video_streams
from imac_data.dataset.streams import add_video_stream, add_video_streams
from imac_data.dataset.videos import VideoEncoding, read_video_frames
from imac_data.errors import InputError

LENGTHS = (5, 7, 4)
FPS = 10
KEY = "control.test.cam"


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A small LeRobot dataset written by LeRobot itself: one camera, three episodes."""
    root = tmp_path_factory.mktemp("base") / "ds"
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": None},
        "observation.images.cam": {"dtype": "video", "shape": (64, 80, 3), "names": ["height", "width", "channels"]},
    }
    ds = LeRobotDataset.create(repo_id="local/base", fps=FPS, features=features, root=root, use_videos=True)
    rng = np.random.default_rng(0)
    for ep, n in enumerate(LENGTHS):
        for t in range(n):
            ds.add_frame({"observation.state": np.array([ep, t], np.float32),
                          "observation.images.cam": rng.integers(0, 255, (64, 80, 3), dtype=np.uint8), "task": "t"})
        ds.save_episode()
    ds.finalize()
    return root


@pytest.fixture
def root(base, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(base, dst)
    return dst


def stream_frames(hw=(24, 40), seed=1):
    """Frames with sharp edges and every colour corner: hard for a lossy codec."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (n, *hw, 3), dtype=np.uint8) for n in LENGTHS]


def tree_digest(root):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def video_digest(root):
    return {k: v for k, v in tree_digest(root).items() if k.startswith("videos/")}


def as_uint8(x):
    return (x * 255).round().byte().permute(*range(x.dim() - 3), -2, -1, -3).numpy()


def test_round_trip_bit_exact_through_lerobot(root):
    frames = stream_frames()
    before = video_digest(root)
    # three ways of giving frames: one array, frame by frame, chunks
    episodes = [frames[0], (f for f in frames[1]), [frames[2][:1], frames[2][1:]]]
    feature = add_video_stream(root, KEY, episodes)

    after = video_digest(root)
    assert {k: after[k] for k in before} == before  # LeRobot's files untouched
    assert feature["shape"] == [24, 40, 3] and feature["dtype"] == "video"
    info = feature["info"]
    assert info["video.codec"] == "h264" and info["video.pix_fmt"] == "gbrp" and info["video.fps"] == FPS
    assert info["imac.encoding"] == VideoEncoding.lossless_rgb().to_dict()

    ds = LeRobotDataset("local/base", root=root)  # default decoder (torchcodec)
    assert ds.meta.video_keys == ["observation.images.cam", KEY]
    i = 0
    for ep, n in enumerate(LENGTHS):
        for t in range(n):
            np.testing.assert_array_equal(as_uint8(ds[i][KEY]), frames[ep][t])
            i += 1
    files = sorted((root / "videos" / KEY).rglob("*.mp4"))
    assert len(files) == 1  # episodes share a file, like LeRobot's
    np.testing.assert_array_equal(read_video_frames(files[0]), np.concatenate(frames))  # PyAV


def test_episode_metadata_and_stats_mirror_lerobot(root):
    frames = stream_frames()
    add_video_stream(root, KEY, frames)
    table = pq.read_table(next((root / "meta" / "episodes").rglob("*.parquet")))
    names = table.column_names
    cam = "observation.images.cam"
    # same column set and types as LeRobot's own video feature
    for suffix in ("chunk_index", "file_index", "from_timestamp", "to_timestamp"):
        assert table.schema.field(f"videos/{KEY}/{suffix}").type == table.schema.field(f"videos/{cam}/{suffix}").type
    ours = sorted(n.split("/")[-1] for n in names if n.startswith(f"stats/{KEY}/"))
    theirs = sorted(n.split("/")[-1] for n in names if n.startswith(f"stats/{cam}/"))
    assert ours == theirs
    for stat in ours:
        assert table.schema.field(f"stats/{KEY}/{stat}").type == table.schema.field(f"stats/{cam}/{stat}").type
    # video columns sit with the other video columns, stats with the other stats
    assert names.index(f"videos/{KEY}/to_timestamp") < min(i for i, n in enumerate(names) if n.startswith("stats/"))
    rows = table.to_pylist()
    start = 0
    for ep, n in enumerate(LENGTHS):
        row = rows[ep]
        assert row[f"videos/{KEY}/from_timestamp"] == pytest.approx(start / FPS)
        assert row[f"videos/{KEY}/to_timestamp"] == pytest.approx((start + n) / FPS)
        start += n
        # stats: LeRobot's sampling (all frames of a short episode), per channel, in [0, 1]
        sampled = frames[ep][sample_indices(n)].astype(np.float64) / 255.0
        for stat, ref in (("mean", sampled.mean(axis=(0, 1, 2))), ("std", sampled.std(axis=(0, 1, 2))),
                          ("min", sampled.min(axis=(0, 1, 2))), ("max", sampled.max(axis=(0, 1, 2)))):
            got = np.array(row[f"stats/{KEY}/{stat}"])
            assert got.shape == (3, 1, 1)
            np.testing.assert_allclose(got.ravel(), ref, atol=1e-9)
        assert row[f"stats/{KEY}/count"] == [len(sample_indices(n))]
    stats = json.loads((root / "meta" / "stats.json").read_text())
    all_frames = np.concatenate(frames).astype(np.float64) / 255.0
    np.testing.assert_allclose(np.array(stats[KEY]["mean"]).ravel(), all_frames.mean(axis=(0, 1, 2)), atol=1e-9)
    np.testing.assert_allclose(np.array(stats[KEY]["std"]).ravel(), all_frames.std(axis=(0, 1, 2)), atol=1e-9)
    assert np.array(stats[KEY]["q50"]).shape == (3, 1, 1)


def test_delta_timestamps_on_the_new_key(root):
    frames = stream_frames()
    add_video_stream(root, KEY, frames)
    ds = LeRobotDataset("local/base", root=root, delta_timestamps={KEY: [-0.2, -0.1, 0.0, 0.1]})
    item = ds[LENGTHS[0] + 1]  # episode 1, frame 1
    assert item[KEY].shape == (4, 3, 24, 40)
    assert item[f"{KEY}_is_pad"].tolist() == [True, False, False, False]
    np.testing.assert_array_equal(as_uint8(item[KEY][1:]), frames[1][0:3])


def test_files_roll_over_like_lerobot(root):
    """A tiny file-size limit and two files per chunk: episodes spread over files and chunks."""
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["video_files_size_in_mb"] = 0.001  # about 1 KB: every episode gets its own file
    info["chunks_size"] = 2
    info_path.write_text(json.dumps(info, indent=4))
    frames = stream_frames()
    add_video_stream(root, KEY, frames)
    files = sorted(str(p.relative_to(root / "videos" / KEY)) for p in (root / "videos" / KEY).rglob("*.mp4"))
    assert files == ["chunk-000/file-000.mp4", "chunk-000/file-001.mp4", "chunk-001/file-000.mp4"]
    ds = LeRobotDataset("local/base", root=root)
    for ep in range(3):
        first = ds.meta.episodes[ep]["dataset_from_index"]
        assert ds.meta.episodes[ep][f"videos/{KEY}/from_timestamp"] == 0.0
        np.testing.assert_array_equal(as_uint8(ds[first + 1][KEY]), frames[ep][1])


def test_several_streams_in_one_pass_with_their_own_settings(root):
    frames = stream_frames()
    other = stream_frames(hw=(32, 48), seed=2)
    add_video_streams(root, ({"a.x": f, "b.y": g} for f, g in zip(frames, other)), keys=["a.x", "b.y"],
                      encodings={"a.x": VideoEncoding.lossless_rgb(), "b.y": VideoEncoding.lerobot_default()})
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["features"]["b.y"]["info"]["video.codec"] == "av1"
    assert info["features"]["b.y"]["info"]["imac.encoding"]["crf"] == 30
    ds = LeRobotDataset("local/base", root=root)
    item = ds[3]
    np.testing.assert_array_equal(as_uint8(item["a.x"]), frames[0][3])
    assert item["b.y"].shape == (3, 32, 48)


@pytest.mark.parametrize("case", [
    "too_few_frames", "too_many_frames", "float_frames", "grey_frames", "size_changes", "too_few_episodes",
    "too_many_episodes", "existing_key", "bad_key", "not_frames",
])
def test_bad_input_leaves_the_dataset_as_it_was(root, case):
    frames = stream_frames()
    key = KEY
    if case == "too_few_frames":
        frames[1] = frames[1][:-1]
    elif case == "too_many_frames":
        frames[2] = np.concatenate([frames[2], frames[2][:1]])
    elif case == "float_frames":
        frames[1] = frames[1].astype(np.float32) / 255
    elif case == "grey_frames":
        frames[1] = frames[1][..., 0]
    elif case == "size_changes":
        frames[2] = np.zeros((LENGTHS[2], 24, 42, 3), np.uint8)
    elif case == "too_few_episodes":
        frames = frames[:2]
    elif case == "too_many_episodes":
        frames = frames + frames[:1]
    elif case == "existing_key":
        key = "observation.images.cam"
    elif case == "bad_key":
        key = "control/test"
    elif case == "not_frames":
        frames[0] = "frames.mp4"
    before = tree_digest(root)
    with pytest.raises(InputError):
        add_video_stream(root, key, frames)
    assert tree_digest(root) == before
    assert not list(root.glob(".imac-tmp-*"))


def test_failure_while_committing_restores_the_metadata(root, monkeypatch):
    before = tree_digest(root)
    real_replace = os.replace

    def failing_replace(src, dst):
        if str(dst).endswith("info.json"):
            raise OSError("disk full")
        return real_replace(src, dst)

    monkeypatch.setattr(video_streams.os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        add_video_stream(root, KEY, stream_frames())
    monkeypatch.undo()
    assert tree_digest(root) == before
    assert not (root / "videos" / KEY).exists()


def test_an_edit_is_staged_swapped_in_on_success_and_discarded_on_error(root):
    frames = stream_frames()
    videos_before = video_digest(root)
    with pytest.raises(RuntimeError):
        with staged_output(root, edit=True, validate=False) as stage:
            add_video_stream(stage.dataset, KEY, frames)
            raise RuntimeError("later step failed")
    assert KEY not in json.loads((root / "meta" / "info.json").read_text())["features"]
    assert not list(root.parent.glob(f".{root.name}.*"))

    with staged_output(root, edit=True, validate=False) as stage:
        assert stage.dataset != root
        add_video_stream(stage.dataset, KEY, frames)
        add_video_stream(stage.dataset, "control.other.cam", frames)
    assert not list(root.parent.glob(f".{root.name}.*"))
    assert {k: v for k, v in video_digest(root).items() if k in videos_before} == videos_before
    ds = LeRobotDataset("local/base", root=root)
    np.testing.assert_array_equal(as_uint8(ds[0]["control.other.cam"]), frames[0][0])


def test_encoding_settings_are_validated_and_round_trip():
    enc = VideoEncoding.lossless_rgb()
    assert enc.encoder_options() == {"g": "10", "qp": "0", "preset": "ultrafast", "threads": "1"}
    assert VideoEncoding.from_dict(json.loads(json.dumps(enc.to_dict()))) == enc
    lr = VideoEncoding.lerobot_default()
    assert lr.encoder_options() == {"g": "2", "crf": "30", "preset": "12"}
    for bad in (dict(codec="no_such_encoder"), dict(codec="libx264", pix_fmt="rgb48"), dict(qp=0, crf=0),
                dict(gop=0), dict(crf=-1, qp=None), dict(options={"g": "5"}), dict(codec="aac")):
        with pytest.raises(InputError):
            VideoEncoding(**bad)

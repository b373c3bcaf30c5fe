"""The dataset package: exact image stats (oracle: LeRobot's own functions), LeRobot's
encoder reproduced byte for byte, merging keeps the imac block and refuses two rigs, and
validation (``imac validate``) finds each kind of damage and names it."""

import copy
import functools
import hashlib
import json
import os
import shutil
import subprocess
import sys

import datasets.config
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
import yaml
from lerobot.datasets.compute_stats import auto_downsample_height_width, get_feature_stats, sample_indices
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data import lerobot_compat
from imac_data.build import from_episodes
from imac_data.build.staging import staged_output
from imac_data.build.workers import run_local
from imac_data.cli import main as imac_main
from imac_data.core.robot.description import DESCRIPTION_DIR
from imac_data.dataset import merge
from imac_data.dataset.info import SCHEMA_VERSION, write_info
from imac_data.dataset.merge import merge_datasets
from imac_data.dataset.validate import validate_dataset
from imac_data.dataset.videos import ImageStats, VideoEncoding, VideoWriter
from imac_data.errors import InputError
from imac_data.lerobot_compat import encode_image_dir
from imac_data.metadata import dataset_info
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset


@pytest.mark.parametrize("T, H, W", [(37, 48, 64), (130, 120, 160), (5, 300, 400)])
def test_image_stats_equal_lerobots_in_constant_memory(T, H, W):
    rng = np.random.default_rng(T)
    frames = rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8)
    frames[..., 1] //= 3  # channels with different ranges
    stats = ImageStats(T)
    for start in range(0, T, 8):
        stats.update(frames[start:start + 8])
    samples = np.stack([auto_downsample_height_width(frames[i].transpose(2, 0, 1)) for i in sample_indices(T)])
    ref = get_feature_stats(samples.astype(np.float64), axis=(0, 2, 3), keepdims=True)
    ours = stats.stats()
    assert list(ours) == list(ref)
    for k in ref:
        np.testing.assert_array_equal(ours[k], ref[k], err_msg=k)
    with pytest.raises(InputError, match="frames seen"):
        ImageStats(T + 1).stats()


def test_lerobot_style_writer_is_lerobots_encoder(tmp_path):
    """Our streaming writer with LeRobot's settings writes the bytes LeRobot's own PNG path
    (encode_video_frames) writes, with no PNGs."""
    from PIL import Image

    rng = np.random.default_rng(0)
    frames = np.clip(rng.normal(128, 40, (9, 48, 64, 3)), 0, 255).astype(np.uint8)
    (tmp_path / "png").mkdir()
    for i, f in enumerate(frames):
        Image.fromarray(f).save(tmp_path / "png" / f"frame-{i:06d}.png")
    encode_image_dir(tmp_path / "png", tmp_path / "lerobot.mp4", 10, vcodec="libsvtav1", overwrite=True)
    writer = VideoWriter(tmp_path / "ours.mp4", VideoEncoding.lerobot_default().with_threads(1), 10, 48, 64,
                         style="lerobot")
    writer.write(frames[:4])
    writer.write(frames[4:])
    writer.close()
    digest = [hashlib.sha256((tmp_path / n).read_bytes()).hexdigest() for n in ("lerobot.mp4", "ours.mp4")]
    assert digest[0] == digest[1]


# Run in a program of its own: the test process may not become real-time (tests/conftest.py), a program it runs may.
_ENCODE_BARE_AND_KEPT = """
import json, os, sys
import av, numpy as np
from imac_data.console import scheduling, scheduling_kept

def realtime_threads():
    return {t for t in os.listdir("/proc/self/task") if os.sched_getscheduler(int(t)) != os.SCHED_OTHER}

def encode(path):
    with av.open(path, "w") as container:
        stream = container.add_stream("libsvtav1", rate=10)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        frame = av.VideoFrame.from_ndarray(np.zeros((48, 64, 3), np.uint8), format="rgb24")
        packets = list(stream.encode(frame))  # the encoder and its threads are open from here
        realtime = len(realtime_threads())
        for packet in [*packets, *stream.encode(None)]:
            container.mux(packet)
    return realtime, scheduling()

before = scheduling()
with scheduling_kept():
    kept = encode(sys.argv[1] + "/kept.mp4")
after = scheduling()
bare = encode(sys.argv[1] + "/bare.mp4")
print(json.dumps({"before": before, "kept": kept, "after_kept": after, "bare": bare}))
"""


def test_the_av1_encoder_makes_a_root_caller_and_its_threads_real_time_unless_refused(tmp_path):
    """Why the encoders run inside ``scheduling_kept``: PyAV's SVT-AV1 encoder, opened by root, makes the calling
    thread and every encoder thread SCHED_FIFO at priority 99, and leaves the caller so (every process started from
    it inherits that). Measured here on the bare encoder, while it encodes. Inside the block no thread becomes
    real-time, and the bytes are the same; as another user the encoder has no right to, and nothing changes."""
    done = subprocess.run([sys.executable, "-c", _ENCODE_BARE_AND_KEPT, str(tmp_path)], capture_output=True,
                          text=True, env={**os.environ, "SVT_LOG": "1"})
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout)
    usual = seen["before"]
    assert seen["kept"] == [0, usual] and seen["after_kept"] == usual
    if os.geteuid() == 0:
        assert seen["bare"][1] == [os.SCHED_FIFO, 99] and seen["bare"][0] > 1
    else:
        assert seen["bare"] == [0, usual]
    assert (tmp_path / "kept.mp4").read_bytes() == (tmp_path / "bare.mp4").read_bytes()


# ----------------------------------------------------------------------------- built datasets


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A one-episode dataset (tiny), built by the build CLI, and a copy of it."""
    tmp = tmp_path_factory.mktemp("dataset_pkg")
    src = tmp / "src"
    record_dataset(SimConfig(num_episodes=1, width=80, height=64, max_steps=14), src, progress=False)
    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["augment"] = {"height": 32, "width": 40, "contact_chunk": 4}
    recipe = tmp / "recipe.yaml"
    recipe.write_text(yaml.safe_dump(data))
    root = tmp / "ds0"
    assert imac_main(["build", "--repo", "local/pkg", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
                       "--no-progress", "--workers", "1", "--episodes", "1"]) == 0
    shutil.copytree(root, tmp / "ds1")
    return [root, tmp / "ds1"]


def test_built_dataset_is_valid_every_frame(built, capsys):
    report = validate_dataset(built[0], full=True)
    assert report.ok, report.format()
    assert set(report.results) == {"metadata", "frame_counts", "imac_block", "rig", "joint_units", "calibration", "caps",
                                   "decode", "depth"}
    assert imac_main(["validate", str(built[0])]) == 0
    assert "OK" in capsys.readouterr().out


def test_merge_keeps_the_imac_block_and_refuses_two_rigs(built, tmp_path):
    out = tmp_path / "merged"
    merge_datasets(built, out, "local/pkg", imac_extra={"build": {"episodes": 2}})
    info = dataset_info(out)
    first = dataset_info(built[0])["imac"]
    assert info["total_episodes"] == 2 and info["imac"]["schema_version"] == SCHEMA_VERSION
    assert {k: v for k, v in info["imac"].items() if k != "build"} == {k: v for k, v in first.items() if k != "build"}
    assert info["imac"]["build"] == {"episodes": 2}
    assert list(json.loads((out / "meta" / "stats.json").read_text())) == \
        [k for k in info["features"] if k in json.loads((out / "meta" / "stats.json").read_text())]
    assert validate_dataset(out).ok
    other = tmp_path / "other"
    shutil.copytree(built[1], other)
    changed = dataset_info(other)
    changed["imac"]["cameras"]["cam_high"]["K"][0][0] += 1.0
    write_info(other, changed)
    with pytest.raises(InputError, match=r"imac\.cameras differ"):
        merge_datasets([built[0], other], tmp_path / "never", "local/pkg")
    assert not (tmp_path / "never").exists()


def test_a_merge_and_a_staged_write_leave_no_arrow_copies_in_the_users_cache(built, tmp_path, monkeypatch):
    """LeRobot loads parquet through `datasets`, which keeps an Arrow copy of each file in its cache folder. The
    merge's copies (of shards about to be deleted) and those of a staged dataset's validation go to the staging's own
    folder and leave with it; an ordinary load of the result still caches, so the count below sees copies."""
    user_cache = tmp_path / "user_cache"  # this process's own: the other test process shares the suite's folder
    monkeypatch.setattr(datasets.config, "HF_DATASETS_CACHE", user_cache)

    def copies():
        return sorted(p.name for p in user_cache.glob("parquet/*"))

    merge_datasets(built, tmp_path / "out" / "merged", "local/pkg")
    assert copies() == [] and os.listdir(tmp_path / "out") == ["merged"]  # the levels and their copies are gone
    with staged_output(tmp_path / "staged") as stage:
        shutil.copytree(built[0], stage.dataset)
    assert (tmp_path / "staged" / "meta" / "info.json").is_file()  # validated and swapped in
    assert copies() == [] and sorted(os.listdir(tmp_path)) == ["out", "staged"]
    LeRobotDataset("local/pkg", root=tmp_path / "out" / "merged")
    assert copies(), "an ordinary load keeps its copies in the user's cache"


def _damage(root, what):
    info = dataset_info(root)
    if what == "schema":
        info["imac"]["schema_version"] = 99
    elif what == "calibration":
        info["imac"]["cameras"]["cam_high"]["T_world_cam"][0] = [-x for x in info["imac"]["cameras"]["cam_high"]
                                                                  ["T_world_cam"][0][:3]] + [0.0]
    elif what == "mesh":
        mesh = sorted((root / DESCRIPTION_DIR / "meshes").iterdir())[0]
        mesh.write_bytes(mesh.read_bytes()[:-4])
    elif what == "caps":
        f = next((root / "data").rglob("*.parquet"))
        t = pq.read_table(f)
        caps = t.column("control.contact_cap").to_pylist()
        caps[3] = [float("nan"), 0.1]
        i = t.column_names.index("control.contact_cap")
        pq.write_table(t.set_column(i, "control.contact_cap", pa.array(caps, type=pa.list_(pa.float32()))), f)
    elif what == "video":
        mp4 = next((root / "videos" / "control.motion.cam_left_wrist").rglob("*.mp4"))
        mp4.write_bytes(mp4.read_bytes()[: len(mp4.read_bytes()) // 2])
    elif what == "depth":  # an RGB video where the depth should be
        shutil.copy(next((root / "videos" / "control.motion.cam_high").rglob("*.mp4")),
                    next((root / "videos" / "observation.depth.cam_high").rglob("*.mp4")))
    write_info(root, info)


@pytest.mark.parametrize("what, check", [("schema", "imac_block"), ("calibration", "calibration"), ("mesh", "rig"),
                                         ("caps", "caps"), ("video", "frame_counts"), ("depth", "depth")])
def test_validation_names_the_damage(built, tmp_path, what, check, capsys):
    root = tmp_path / "ds"
    shutil.copytree(built[0], root)
    _damage(root, what)
    report = validate_dataset(root, full=True)
    assert not report.ok and report.results.get(check), report.format()
    assert imac_main(["validate", str(root), "--full"]) == 2
    assert "INVALID" in capsys.readouterr().out


def test_linear_features_constructor_equals_datasets_own(built):
    """lerobot_compat.use_linear_features() (installed by the first LeRobot name used): the same Features
    (values and decoding flags) as datasets' own quadratic constructor, on every parquet schema of a built
    dataset and on old-style lists."""
    import datasets
    from datasets.features.features import Features, List, Value

    if not str(datasets.__version__).startswith("4."):
        pytest.skip(f"datasets {datasets.__version__}: the patch is not installed there")
    lerobot_compat.LeRobotDataset  # noqa: B018 (the first name resolved installs it)
    assert Features.__init__ is lerobot_compat._linear_features_init and lerobot_compat.use_linear_features()
    original = lerobot_compat.original_features_init()

    def both(*args, **kwargs):
        ours = Features(*args, **kwargs)
        theirs = Features.__new__(Features)
        original(theirs, *args, **kwargs)
        return ours, theirs

    schemas = [pq.read_schema(f) for f in sorted(built[0].rglob("*.parquet"))]
    assert max(len(s.names) for s in schemas) > 300  # the wide episodes table
    for schema in schemas:
        given = [dict(Features.from_arrow_schema(schema))]
        if schema.metadata and b"huggingface" in schema.metadata:
            given.append(dict(Features.from_dict(json.loads(schema.metadata[b"huggingface"])["info"]["features"])))
        for features in given:
            ours, theirs = both(features)
            assert dict(ours) == dict(theirs) and ours._column_requires_decoding == theirs._column_requires_decoding
    ours, theirs = both({"a": [Value("int64")], "b": {"c": [[Value("float32")]]}}, d=Value("string"))
    assert dict(ours) == dict(theirs) and ours._column_requires_decoding == theirs._column_requires_decoding
    assert ours["a"] == List(Value("int64"))


def _mutables(x, seen=None) -> list:
    """Every dict, list and feature object inside ``x`` (what a deep copy must not share)."""
    seen = [] if seen is None else seen
    if isinstance(x, (dict, list)) or hasattr(x, "__dataclass_fields__"):
        seen.append(x)
    for v in (dict.values(x) if isinstance(x, dict) else x if isinstance(x, list) else ()):
        _mutables(v, seen)
    for v in getattr(x, "__dict__", {}).values():
        _mutables(v, seen)
    return seen


def test_features_copy_equals_a_deep_copy_and_shares_nothing_mutable(built):
    """The structural ``Features.copy`` that lerobot_compat installs beside the linear constructor: on every
    parquet schema of a built dataset (the 400-column episodes table among them) and on nested lists, dicts and
    class labels, the copy equals ``copy.deepcopy`` (values, types, decoding flags, a label's lookup tables) and
    shares no dict, list or feature object with the original."""
    import datasets
    from datasets.features.features import ClassLabel, Features, List, Value

    if not str(datasets.__version__).startswith("4."):
        pytest.skip(f"datasets {datasets.__version__}: the patch is not installed there")
    lerobot_compat.LeRobotDataset  # noqa: B018 (the first name resolved installs it)
    assert Features.copy is lerobot_compat._structural_features_copy
    given = [Features.from_arrow_schema(pq.read_schema(f)) for f in sorted(built[0].rglob("*.parquet"))]
    given.append(Features({"a": List(Value("int64"), length=3), "b": {"c": [[Value("float32")]]},
                           "label": ClassLabel(names=["neg", "pos"])}))
    assert max(len(f) for f in given) > 300
    for features in given:
        ours, theirs = features.copy(), copy.deepcopy(features)
        assert type(ours) is Features and ours == theirs and list(ours) == list(features)
        assert ours._column_requires_decoding == theirs._column_requires_decoding
        assert [type(x) for x in _mutables(ours)] == [type(x) for x in _mutables(theirs)]
        assert not {id(x) for x in _mutables(ours)} & {id(x) for x in _mutables(features)}
    label = given[-1].copy()["label"]
    assert label.str2int("pos") == 1 and label.int2str(0) == "neg" and vars(label) == vars(given[-1]["label"])


def test_a_build_merged_as_a_tree_equals_one_merged_at_once(tmp_path, monkeypatch):
    """Three shards merged two at a time (two levels of LeRobot aggregates, one group of one) give what one
    aggregate of all three gives (the oracle: LeRobot's merge as it was always called): the same episodes and timestamps, data rows and
    decoded frames of every stream, and ``validate --full`` passes. A tree whose level runs on two processes
    writes the same bytes as one made in this process."""
    src = tmp_path / "src"
    record_dataset(SimConfig(num_episodes=3, width=80, height=64, max_steps=8), src, progress=False)
    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["augment"] = {"height": 32, "width": 40, "contact_chunk": 4}
    (tmp_path / "recipe.yaml").write_text(yaml.safe_dump(data))

    def build(root):
        assert imac_main(["build", "--repo", "local/tree", "--recipe", str(tmp_path / "recipe.yaml"), "--source",
                          str(src), "--root", str(root), "--no-progress", "--workers", "1", "--episodes", "3"]) == 0

    build(tmp_path / "flat")
    monkeypatch.setattr(from_episodes, "merge_datasets", functools.partial(merge_datasets, fan_in=2))
    build(tmp_path / "tree")
    flat, tree = (LeRobotDataset("local/tree", root=tmp_path / r) for r in ("flat", "tree"))
    assert flat.meta.total_episodes == tree.meta.total_episodes == 3 and len(flat) == len(tree)
    for key in ("length", "dataset_from_index", "dataset_to_index", "data/chunk_index", "data/file_index"):
        assert list(flat.meta.episodes[key]) == list(tree.meta.episodes[key]), key
    for key in flat.meta.video_keys:
        np.testing.assert_allclose(flat.meta.episodes[f"videos/{key}/from_timestamp"],
                                   tree.meta.episodes[f"videos/{key}/from_timestamp"], rtol=0, atol=1e-9)
    for i in range(len(flat)):
        a, b = flat[i], tree[i]
        assert a.keys() == b.keys()
        for k in a:
            assert (torch.equal(a[k], b[k]) if isinstance(a[k], torch.Tensor) else a[k] == b[k]), (i, k)
    assert not list(tmp_path.glob("**/*.levels"))
    assert validate_dataset(tmp_path / "tree", full=True).ok
    # a merge killed mid-tree leaves its levels in staging: the rerun starts them afresh
    stale = tmp_path / ".again.merging.levels" / "1" / "000000"
    stale.mkdir(parents=True)
    (stale / "junk").write_text("a killed merge's half-made group")
    merge_datasets([tmp_path / "flat", tmp_path / "tree", tmp_path / "flat"], tmp_path / "again", "local/tree", fan_in=2)
    assert LeRobotDataset("local/tree", root=tmp_path / "again").meta.total_episodes == 9
    assert not (tmp_path / ".again.merging.levels").exists()
    # a level's groups on two processes, as the build runs them: the same bytes, file by file
    monkeypatch.setattr(merge, "PARALLEL_MIN_GROUPS", 2)
    levels = []

    def run_groups(fn, tasks):
        levels.append(len(tasks))
        run_local(fn, tasks, workers=2, threads=1)

    merge_datasets([tmp_path / "flat", tmp_path / "tree", tmp_path / "flat"], tmp_path / "parallel", "local/tree",
                   fan_in=2, run_groups=run_groups)
    assert levels == [2]

    def files(root):
        return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    assert files(tmp_path / "parallel") == files(tmp_path / "again")
    with pytest.raises(InputError, match="fan_in"):
        merge_datasets([tmp_path / "flat"], tmp_path / "never", "local/tree", fan_in=1)

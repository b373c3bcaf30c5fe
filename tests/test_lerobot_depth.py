"""LeRobot 0.6's native depth maps, in and out (``docs/lerobot.md``), against LeRobot 0.6.1's
own code and the simulator.

* in: videos made by 0.6.1's quantiser and encoder (``tests/fixtures/lerobot061/depth``, from
  ``make_fixture.py``), placed in a dataset written by LeRobot 0.4.4, read through our source;
* out: our depth maps decoded by 0.6.1's own ``dequantize_depth``, run from the vendored files
  in a fresh process (``tests/fixtures/lerobot061/lerobot061.py``);
* end to end: a LeRobot dataset whose only depth is a depth map, built, its contact streams
  against MuJoCo's finger-cube distances;
* refusals: a depth map's quantiser missing or inconsistent, named before any work.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import av
import mujoco
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from packaging.version import Version

from imac_data.build.flow import build_dataset
from imac_data.build.staging import BuildRequest
from imac_data.core.cameras import save_calibration
from imac_data.core.contact.images import JET_LUT, chunk_plan
from imac_data.core.depth_map import DepthMapParams
from imac_data.dataset.streams import StreamWriter
from imac_data.dataset.videos import VideoEncoding
from imac_data.errors import InputError
from imac_data.lerobot_compat import version as lerobot_version
from imac_data.metadata import imac_block
from imac_data.recipes import load_recipe, parse_recipe
from imac_data.sources.depth import EpisodeViews, RecordedDepth
from imac_data.sources.lerobot_dataset import SourceDataset
from imac_data.sources.lerobot_episodes import DepthFeature, LeRobotEpisodeReader
from imac_data.sources.sim.recorder import FrameRenderer, simulate_episode
from imac_data.sources.sim.rig import camera_calibration, load_mujoco_model

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "lerobot061"
FIXTURE = FIXTURES / "depth"
REFERENCE_STEPS_MM = {True: {0.3: 1.25, 1.0: 1.48, 5.0: 2.80}, False: {0.3: 2.44, 1.0: 2.44, 5.0: 2.44}}
# LeRobot 0.6.0 added depth maps: its LeRobotDataset decodes one to (1, H, W) float millimetres. LeRobot
# 0.4.4 has none and decodes the same video as a grey (3, H, W) image in [0, 1].
LEROBOT_DEPTH_MAPS = Version(lerobot_version()) >= Version("0.6.0")
NO_DEPTH_MAPS = "LeRobot 0.4.4 has no depth maps (0.6.0 added them): its LeRobotDataset decodes one as grey RGB"


def run_lerobot061(request: dict, tmp_path: Path) -> dict:
    """LeRobot 0.6.1's own code on ``request`` (see lerobot061.py), in a fresh process."""
    (tmp_path / "request.json").write_text(json.dumps(request))
    out = subprocess.run([sys.executable, str(FIXTURES / "lerobot061.py"), str(tmp_path / "request.json"),
                          str(tmp_path / "result.json")], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads((tmp_path / "result.json").read_text())


def write_lerobot(root: Path, frames: dict[str, np.ndarray], state: np.ndarray, action: np.ndarray, fps: int):
    """A LeRobot v3.0 dataset of one episode, by LeRobot 0.4.4's own writer (its PNG path)."""
    h, w = next(iter(frames.values())).shape[1:3]
    features = {"observation.state": {"dtype": "float32", "shape": (state.shape[1],), "names": None},
                "action": {"dtype": "float32", "shape": (action.shape[1],), "names": None}}
    features.update({f"observation.images.{c}": {"dtype": "video", "shape": (h, w, 3),
                                                 "names": ["height", "width", "channels"]} for c in frames})
    ds = LeRobotDataset.create("local/source", fps=fps, features=features, root=root, use_videos=True)
    for t in range(len(state)):
        frame = {f"observation.images.{c}": v[t] for c, v in frames.items()}
        ds.add_frame({**frame, "observation.state": state[t].astype(np.float32),
                      "action": action[t].astype(np.float32), "task": "transfer the cube"})
    ds.save_episode()
    ds.finalize()
    return root


def place_video_feature(root: Path, key: str, feature: dict, video: Path) -> None:
    """Put a video made elsewhere into the dataset at ``root`` as feature ``key`` (one episode,
    one file), as LeRobot lays a camera out: the file, its ``meta/episodes`` columns, the feature."""
    dst = root / "videos" / key / "chunk-000" / "file-000.mp4"
    dst.parent.mkdir(parents=True)
    shutil.copyfile(video, dst)
    with av.open(str(dst)) as c:
        n = c.streams.video[0].frames
    info = json.loads((root / "meta" / "info.json").read_text())
    info["features"][key] = feature
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    f = next((root / "meta" / "episodes").rglob("*.parquet"))
    t = pq.read_table(f)
    for col, value, typ in (("chunk_index", 0, pa.int64()), ("file_index", 0, pa.int64()),
                            ("from_timestamp", 0.0, pa.float64()), ("to_timestamp", n / info["fps"], pa.float64())):
        t = t.append_column(f"videos/{key}/{col}", pa.array([value], type=typ))
    pq.write_table(t, f)


def rename_feature(root: Path, old: str, new: str) -> None:
    """Feature ``old`` of the dataset at ``root`` renamed to ``new`` everywhere LeRobot names it."""
    (root / "videos" / old).rename(root / "videos" / new)
    for name in ("info.json", "stats.json"):
        path = root / "meta" / name
        data = json.loads(path.read_text())
        block = data["features"] if name == "info.json" else data
        renamed = {new if k == old else k: v for k, v in block.items()}  # in place, order kept
        block.clear()
        block.update(renamed)
        path.write_text(json.dumps(data, indent=4))
    for f in (root / "meta" / "episodes").rglob("*.parquet"):
        t = pq.read_table(f)
        pq.write_table(t.rename_columns([n.replace(f"/{old}/", f"/{new}/") for n in t.column_names]), f)


# ----------------------------------------------------------------------------- the fixture


def test_vendored_files_are_lerobot_061s():
    """The five vendored files are the wheel's (sha256 as make_fixture.py recorded them from it)."""
    manifest = json.loads((FIXTURE / "manifest.json").read_text())
    assert manifest["wheel"] == {"file": "lerobot-0.6.1-py3-none-any.whl", "version": "0.6.1",
                                 "sha256": "1894516040c65f80a45bd9741f8174aae90ed5d93da0627ab4f1a85fd8d75e90"}
    recorded = {v["file"]: v["sha256"] for v in manifest["loaded_modules"].values() if v.get("file")}
    vendored = sorted(p.relative_to(FIXTURES).as_posix() for p in (FIXTURES / "lerobot").rglob("*.py"))
    assert len(vendored) == 5
    for rel in vendored:
        assert hashlib.sha256((FIXTURES / rel).read_bytes()).hexdigest() == recorded[rel], rel


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    """A dataset written by LeRobot 0.4.4: one episode of 3 frames of a 24x32 camera, 10 fps."""
    T, H, W = np.load(FIXTURE / "depth.npz")["depth_m"].shape
    rgb = np.zeros((T, H, W, 3), np.uint8)
    return write_lerobot(tmp_path_factory.mktemp("tiny") / "ds", {"cam": rgb}, np.zeros((T, 2)), np.zeros((T, 2)),
                         fps=10)


@pytest.fixture(scope="module")
def fixture_dataset(tiny_dataset, tmp_path_factory):
    """The tiny dataset holding the three depth maps LeRobot 0.6.1 made (log in metres, linear,
    log from uint16 millimetres)."""
    features = json.loads((FIXTURE / "features.json").read_text())
    depth = np.load(FIXTURE / "depth.npz")
    root = tmp_path_factory.mktemp("fixture") / "ds"
    shutil.copytree(tiny_dataset, root)
    for key, feature in features.items():
        place_video_feature(root, key, feature, FIXTURE / (key.rsplit(".", 1)[1] + ".mp4"))
    return root, features, depth


def test_lerobot_061_depth_maps_decode_through_our_source_within_the_step(fixture_dataset):
    """Every valid pixel within half the quantiser's step (plus float32 rounding in LeRobot's
    quantiser) of the metres it was made from, log and linear; the step between neighbouring
    codes as LeRobot's reference says; zero depth (code 0) reads as invalid."""
    root, features, depth = fixture_dataset
    src = SourceDataset.open(root)
    cams = [k.rsplit(".", 1)[1] for k in features]  # depth_log, depth_linear, depth_log_mm
    feature = DepthFeature("observation.images.{cam}", None)
    feature.check(src, cams, "recipe.yaml")
    assert feature.format == "lerobot"
    feature.check_streams(src, cams, "recipe.yaml")
    T = depth["depth_m"].shape[0]
    with LeRobotEpisodeReader(src, src.episodes[0], {}, np.zeros((T, 2)), np.zeros((T, 2)), feature) as ep:
        views = EpisodeViews(images={}, cameras={}, poses={}, depth_mm={c: ep.depth_mm(c, 0, T) for c in cams})
    metres = RecordedDepth(cams).depth(views)
    truth = depth["depth_m"].astype(np.float64)
    for cam in cams:
        p = feature.params[cam]
        given = depth["depth_mm"] / 1000.0 if cam.endswith("_mm") else truth
        valid = given > 0
        step = np.vectorize(p.step)(given[valid])
        err = np.abs(metres[cam][valid] - given[valid])
        assert (err <= step / 2 + 1e-6).all(), (cam, (err / step).max())
        assert (metres[cam][~valid] == 0).all()
        codes = depth[f"codes_{cam}"]
        for d, ref in REFERENCE_STEPS_MM[p.use_log].items():  # pixels (t, 0, 0..2) hold 0.3, 1 and 5 m
            t_px = np.argwhere(np.isclose(given[:, 0, :3], d))[0]
            c = int(codes[t_px[0], 0, t_px[1]])
            table = p.code_values()
            assert (table[c + 1] - table[c]) * 1000 == pytest.approx(ref, abs=0.01)
            assert abs(metres[cam][t_px[0], 0, t_px[1]] - d) <= p.step(d) / 2 + 1e-6
        print(f"{cam}: max error {err.max() * 1000:.3f} mm, max error / step {(err / step).max():.4f}")


def test_our_quantiser_gives_lerobots_codes():
    """Our quantiser against the codes LeRobot 0.6.1's quantize_depth gave (the fixture)."""
    depth = np.load(FIXTURE / "depth.npz")
    for name, params, given in (("depth_log", DepthMapParams(), depth["depth_m"]),
                                ("depth_linear", DepthMapParams(use_log=False), depth["depth_m"]),
                                ("depth_log_mm", DepthMapParams(), depth["depth_mm"] / 1000.0)):
        np.testing.assert_array_equal(params.quantize(given), depth[f"codes_{name}"])
    assert DepthMapParams().quantize(np.array([np.nan, np.inf, -np.inf, -1.0, 0.0])).tolist() == [0] * 5
    # valid depth below the range (LeRobot's code 0) is code 1: code 0 stays "invalid"
    assert DepthMapParams().quantize(np.array([1e-4, 0.01, 0.0105, 0.011])).tolist() == [1, 1, 1, 1]


# ----------------------------------------------------------------------------- the output


def add_depth_maps(src: Path, root: Path, cases: dict[str, DepthMapParams], metres: np.ndarray) -> dict:
    """A copy of ``src`` at ``root`` with a depth-map stream per case, by our StreamWriter."""
    shutil.copytree(src, root)
    with StreamWriter(root, list(cases), {k: VideoEncoding.depth_map() for k in cases}, depth_maps=cases) as w:
        w.begin_episode(0)
        w.write({k: p.quantize(metres) for k, p in cases.items()})
        w.end_episode()
        return w.commit()


def random_metres(seed: int) -> np.ndarray:
    """(3, 24, 32) float32 metres, log-uniform over 0.05-8 m; the top 4 rows invalid (0)."""
    metres = np.exp(np.random.default_rng(seed).uniform(np.log(0.05), np.log(8.0), (3, 24, 32))).astype(np.float32)
    metres[:, :4] = 0.0
    return metres


def test_our_depth_maps_decode_with_lerobot_061s_own_code(tiny_dataset, tmp_path):
    """A depth-map stream written by our StreamWriter: LeRobot 0.6.1's dequantize_depth of its
    decoded codes gives our metres within half a step; its quantize_depth of our metres gives
    the codes in the file; its DepthEncoderConfig.from_video_info reads the feature's info."""
    root = tmp_path / "ds"
    H, W = 24, 32
    metres = random_metres(0)
    cases = {"observation.depth_map.log": DepthMapParams(), "observation.depth_map.linear":
             DepthMapParams(0.1, 4.0, 0.0, False)}
    features = add_depth_maps(tiny_dataset, root, cases, metres)
    jobs = {"quantize": [], "dequantize": [], "encoder_from_video_info": []}
    np.save(tmp_path / "metres.npy", metres)
    for i, (key, p) in enumerate(cases.items()):
        with av.open(str(root / "videos" / key / "chunk-000" / "file-000.mp4")) as c:
            codes = np.stack([f.to_ndarray(format="gray12le") for f in c.decode(video=0)])
        np.save(tmp_path / f"codes{i}.npy", codes)
        args = {k.removeprefix("video."): v for k, v in p.info().items()}
        jobs["quantize"].append({"depth": str(tmp_path / "metres.npy"), "params": args,
                                 "out": str(tmp_path / f"q{i}.npy")})
        jobs["dequantize"].append({"codes": str(tmp_path / f"codes{i}.npy"), "params": args,
                                   "out": str(tmp_path / f"m{i}.npy")})
        jobs["encoder_from_video_info"].append(features[key]["info"])
    result = run_lerobot061(jobs, tmp_path)
    assert sorted(v["file"] for v in result["loaded"].values()) == sorted(
        ["lerobot/configs/video.py", "lerobot/datasets/depth_utils.py", "lerobot/datasets/image_writer.py",
         "lerobot/datasets/pyav_utils.py", "lerobot/utils/import_utils.py"])
    for i, (key, p) in enumerate(cases.items()):
        codes = np.load(tmp_path / f"codes{i}.npy")
        theirs = np.load(tmp_path / f"m{i}.npy")
        # LeRobot clips to its range; below half a step above depth_min we write code 1 (quantize)
        inside = (metres >= p.depth_min + p.step(p.depth_min) / 2) & (metres <= p.depth_max)
        step = np.vectorize(p.step)(metres[inside])
        err = np.abs(theirs[inside] - metres[inside])
        assert (err <= step / 2 + 1e-6).all(), (key, (err / step).max())
        theirs_q = np.load(tmp_path / f"q{i}.npy")
        # the same codes, except that valid depth LeRobot writes as 0 (below the range) is our code 1
        near = (metres > 0) & (theirs_q == 0)
        assert near.sum() > 0 or p.depth_min <= 0.05
        np.testing.assert_array_equal(theirs_q[(metres > 0) & ~near], codes[(metres > 0) & ~near])
        assert (codes[near] == 1).all() and (codes[metres == 0] == 0).all()
        enc = result["encoders"][i]
        assert (enc["vcodec"], enc["pix_fmt"], enc["depth_min"], enc["depth_max"], enc["shift"], enc["use_log"]) == \
            ("hevc", "gray12le", p.depth_min, p.depth_max, p.shift, p.use_log)
        info = features[key]["info"]
        assert info["is_depth_map"] is True and info["depth_unit"] == "m" and features[key]["shape"] == [H, W, 1]
        print(f"{key}: LeRobot 0.6.1 reads our metres within {(err / step).max():.4f} of a step "
              f"(max {err.max() * 1000:.3f} mm)")
    stats = json.loads((root / "meta" / "stats.json").read_text())["observation.depth_map.log"]
    assert np.shape(stats["mean"]) == (1, 1, 1) and 0.01 <= stats["min"][0][0][0] < stats["max"][0][0][0] <= 8.0


def test_lerobots_merge_keeps_our_depth_maps(tiny_dataset, tmp_path):
    """LeRobot's aggregate_datasets (what merges a build's shards) on two datasets with our
    depth maps: the codes concatenated unchanged, the stats still (1, 1, 1) metres, every frame
    loadable by LeRobot (0.6 on: as the metres written, within half a step; the closed GOPs let
    its PyAV reader seek across the join). (Under a key holding "image", 0.4.4's aggregate_stats
    refuses (1, 1, 1).)"""
    from imac_data import lerobot_compat as lr

    key, params = "observation.depth_map.cam", DepthMapParams()
    roots = [tmp_path / f"part{i}" for i in range(2)]
    for i, root in enumerate(roots):
        add_depth_maps(tiny_dataset, root, {key: params}, random_metres(i))
    out = tmp_path / "merged"
    lr.aggregate_datasets(["local/part"] * 2, "local/merged", roots=roots, aggr_root=out)
    merged = _decode(out / "videos" / key / "chunk-000" / "file-000.mp4", "gray12le")
    np.testing.assert_array_equal(merged, np.concatenate([params.quantize(random_metres(i)) for i in range(2)]))
    stats = json.loads((out / "meta" / "stats.json").read_text())[key]
    assert np.shape(stats["q50"]) == (1, 1, 1) and stats["count"] == [6]
    assert json.loads((out / "meta" / "info.json").read_text())["features"][key]["info"]["is_depth_map"] is True
    merged_ds = LeRobotDataset("local/merged", root=out, **({"depth_output_unit": "m"} if LEROBOT_DEPTH_MAPS else {}))
    for i in range(6):  # every frame, the first of the second part included (a seek across the join)
        item = merged_ds[i][key]
        if LEROBOT_DEPTH_MAPS:  # read as a depth map: within half a step where valid
            metres = random_metres(i // 3)[i % 3]
            valid = metres > 0
            assert item.shape == (1, 24, 32), i
            err = np.abs(item[0].numpy()[valid] - metres[valid])
            assert (err <= np.vectorize(params.step)(metres[valid]) / 2 + 1e-6).all(), i
        else:
            assert item.shape == (3, 24, 32), i  # grey RGB


@pytest.mark.skipif(not LEROBOT_DEPTH_MAPS, reason=NO_DEPTH_MAPS)
@pytest.mark.parametrize("unit", ["mm", "m"])
def test_lerobots_own_dataset_reads_our_depth_maps_within_half_a_step(tiny_dataset, tmp_path, unit):
    """LeRobot's own ``LeRobotDataset`` (0.6.0 on) on a dataset with our depth maps (log and
    linear): every valid pixel of every frame inside the quantiser's range within half a step of
    the metres written (plus 0.5 mm in millimetres, which LeRobot rounds to whole ones); valid
    depth below the range reads as code 1, beyond it as ``depth_max``.
    An invalid pixel (0 in the source: code 0) comes back as ``depth_min`` (10 mm by default),
    every valid one a step above it or more: ``depth > depth_min`` gives the validity mask back
    exactly, so nothing is lost and no mask is stored."""
    cases = {"observation.depth_map.log": DepthMapParams(),
             "observation.depth_map.linear": DepthMapParams(0.2, 4.0, 0.0, False)}
    metres = random_metres(2)
    metres[0, 4, :4] = [0.0105, 0.1, 0.2005, 3.99]  # near either end of both ranges
    root = tmp_path / "ds"
    add_depth_maps(tiny_dataset, root, cases, metres)
    ds = LeRobotDataset("local/source", root=root, depth_output_unit=unit)
    scale = 1000.0 if unit == "mm" else 1.0
    # In millimetres (its default) LeRobot 0.6.1 rounds to whole millimetres: up to 0.5 mm more.
    rounding = 0.0005 if unit == "mm" else 0.0

    def as_read(m: float) -> float:
        return round(m * 1000) / 1000 if unit == "mm" else m

    valid = metres > 0
    assert len(ds) == len(metres) and (~valid).sum() > 0
    for key, p in cases.items():
        got = np.stack([ds[t][key].numpy() for t in range(len(ds))])
        assert got.shape == (len(metres), 1, 24, 32) and got.dtype == np.float32, (key, got.shape, got.dtype)
        got = got[:, 0].astype(np.float64) / scale
        table = p.code_values()
        inside = valid & (metres >= p.depth_min + p.step(p.depth_min) / 2) & (metres <= p.depth_max)
        near, far = valid & (metres < p.depth_min + p.step(p.depth_min) / 2), valid & (metres > p.depth_max)
        assert inside.sum() > 1000 and near.sum() >= 1 and (far.sum() >= 1 or p.depth_max >= 8.0), key
        step = np.vectorize(p.step)(metres[inside])
        err = np.abs(got[inside] - metres[inside])
        assert (err <= step / 2 + rounding + 1e-6).all(), (key, (err / step).max())
        # a code's value, up to LeRobot's float32 arithmetic (1 um)
        np.testing.assert_allclose(got[near], as_read(table[1]), rtol=0, atol=1e-6)
        np.testing.assert_allclose(got[far], as_read(p.depth_max), rtol=0, atol=1e-6)
        np.testing.assert_allclose(got[~valid], as_read(p.depth_min), rtol=0, atol=1e-6)
        assert as_read(table[1]) > as_read(table[0])
        assert ((got > as_read(table[0]) + 1e-6) == valid).all(), key
        print(f"{key} ({unit}): LeRobot {lerobot_version()}'s LeRobotDataset within {(err / step).max():.4f} of a "
              f"step; invalid pixels read {got[~valid].max() * 1000:.4f} mm, the lowest valid "
              f"{got[valid].min() * 1000:.3f} mm")


# ----------------------------------------------------------------------------- refusals


def _feature(**edit) -> dict:
    f = json.loads((FIXTURE / "features.json").read_text())["observation.images.depth_log"]
    for k, v in edit.items():
        if k == "shape":
            f["shape"] = v
        elif v is None:
            f["info"].pop(k)
        else:
            f["info"][k] = v
    return f


@pytest.mark.parametrize("edit, match", [
    ({"video.depth_max": None}, r"info lacks \['video.depth_max'\]"),
    ({"video.use_log": None, "video.shift": None}, r"info lacks \['video.shift', 'video.use_log'\]"),
    ({"video.depth_min": 10.0}, r"needs 0 <= video.depth_min < video.depth_max, got 10.0 and 10.0"),
    ({"video.depth_min": -0.5}, r"needs 0 <= video.depth_min"),
    ({"video.shift": -0.01}, r"video.depth_min \+ video.shift > 0, got 0.01 \+ -0.01"),
    ({"video.depth_max": math.inf}, r"video.depth_max must be a finite number, got inf"),
    ({"video.shift": "3.5"}, r"video.shift must be a finite number, got '3.5'"),
    ({"video.use_log": 1}, r"video.use_log must be true or false, got 1"),
    ({"video.is_depth_map": False}, r"conflicting depth-map markers"),
    ({"video.pix_fmt": "yuv420p"}, r"video.pix_fmt 'yuv420p'; a depth map is gray12le"),
    ({"depth_unit": "cm"}, r"depth_unit 'cm'"),
    ({"shape": [24, 32, 3]}, r"shape \[24, 32, 3\]; a depth map is \(height, width, 1\)"),
])
def test_a_bad_quantiser_is_named_with_the_dataset_and_key(edit, match):
    src = SourceDataset(Path("/data/src"), {"features": {"observation.images.cam_depth": _feature(**edit)}}, [])
    with pytest.raises(InputError, match=r"r.yaml: depth.feature: dataset /data/src: feature "
                                         r"'observation.images.cam_depth'.*" + match):
        DepthFeature("observation.images.{cam}_depth", None).check(src, ["cam"], "r.yaml")


def test_formats_that_do_not_fit_the_feature_are_refused():
    flagged = {"observation.images.cam_depth": _feature()}
    unflagged = {"observation.images.cam_depth": _feature(is_depth_map=False)}
    with pytest.raises(InputError, match=r"depth.format 'millimetres', but .* is a LeRobot depth map"):
        DepthFeature("observation.images.{cam}_depth", "millimetres").check(
            SourceDataset(Path("/d"), {"features": flagged}, []), ["cam"], "r.yaml")
    with pytest.raises(InputError, match=r"'observation.images.cam_depth' is not flagged as a depth map"):
        DepthFeature("observation.images.{cam}_depth", "lerobot").check(
            SourceDataset(Path("/d"), {"features": unflagged}, []), ["cam"], "r.yaml")
    with pytest.raises(InputError, match=r"is a video that is not flagged as a LeRobot depth map; if it holds our "
                                         r"colour codec, set depth.format: codec"):
        DepthFeature("observation.images.{cam}_depth", None).check(
            SourceDataset(Path("/d"), {"features": unflagged}, []), ["cam"], "r.yaml")
    feature = DepthFeature("observation.images.{cam}_depth", "lerobot")
    feature.check(SourceDataset(Path("/d"), {"features": flagged}, []), ["cam"], "r.yaml")
    assert feature.params["cam"] == DepthMapParams()


def test_recipe_depth_map_output_is_checked():
    base = {"name": "x", "task": "t", "robot": {"platform": "aloha_sim"}, "source": {"type": "aloha_sim"}}
    recipe = parse_recipe({**base, "augment": {"lerobot_depth_map": {"enabled": True, "use_log": False}}}, "r.yaml")
    assert recipe.augment.lerobot_depth_map.params() == DepthMapParams(use_log=False)
    assert parse_recipe(base, "r.yaml").augment.lerobot_depth_map.enabled is False  # off by default
    with pytest.raises(InputError, match=r"r.yaml: augment.lerobot_depth_map: needs 0 <= depth_min < depth_max, "
                                         r"got 2.0 and 1.0"):
        parse_recipe({**base, "augment": {"lerobot_depth_map": {"depth_min": 2.0, "depth_max": 1.0}}}, "r.yaml")
    with pytest.raises(InputError, match=r"depth.format: must be one of .*'lerobot'"):
        parse_recipe({**base, "depth": {"format": "native"}}, "r.yaml")


# ----------------------------------------------------------------------------- end to end

H_SIM, W_SIM, CHUNK = 120, 160, 8



@pytest.fixture(scope="module")
def depth_map_source(tmp_path_factory):
    """The transfer_cube grasp (the first 2.4 s) as a LeRobot dataset whose only depth is a
    LeRobot depth map per camera, ``observation.images.<cam>_depth`` as LeRobot 0.6 names
    them: cameras and joints by LeRobot 0.4.4's writer, depth maps by ours."""
    out = tmp_path_factory.mktemp("depth_map_source")
    model = load_mujoco_model("transfer_cube")
    cap = FrameRenderer(model, W_SIM, H_SIM, segmentation=True, keep_qpos=True)
    try:
        ep = simulate_episode("transfer_cube", seed=0, frame_stride=2, max_steps=120, renderer=cap)
    finally:
        cap.close()
    save_calibration(out / "calibration.json", camera_calibration(model, W_SIM, H_SIM))
    root = write_lerobot(out / "source", ep.images, ep.qpos, ep.action, fps=25)
    params = DepthMapParams()
    with StreamWriter(root, [f"depth.{c}" for c in ep.images], VideoEncoding.depth_map(),
                      depth_maps={f"depth.{c}": params for c in ep.images}) as w:
        w.begin_episode(0)
        w.write({f"depth.{c}": params.quantize(ep.depth_mm[c] / 1000.0) for c in ep.images})
        w.end_episode()
        w.commit()
    # LeRobot 0.6's name (its robots call a depth camera "<cam>_depth"); written under another, as
    # LeRobot 0.4.4's aggregate_stats refuses (1, 1, 1) stats for keys that contain "image"
    keys = {c: f"observation.images.{c}_depth" for c in ep.images}
    for c, key in keys.items():
        rename_feature(root, f"depth.{c}", key)
    return dict(root=root, calibration=out / "calibration.json", model=model, qfull=np.array(cap.qpos),
                seg=ep.segmentation, depth_mm=ep.depth_mm, keys=keys)


def _colour_distance(rgb: np.ndarray, cap: float) -> np.ndarray:
    """Stored s2g colours (..., 3) back to metres (the middle of the colour level's interval;
    NaN for black; of jet's 3 repeated colours the nearer level)."""
    level_of = {tuple(c): i for i, c in enumerate(np.asarray(JET_LUT).tolist())}
    flat = rgb.reshape(-1, 3)
    levels = np.array([level_of.get(tuple(c), -1) for c in flat.tolist()])
    d = cap * (1 - (levels + 0.5) / 256)
    return np.where(levels >= 0, d, np.nan).reshape(rgb.shape[:-1])


def _mj_distance(model, data, g1, g2):
    """mj_geomDistance, or None when its answer disagrees with its own witness points (its
    convex solver occasionally returns 0 with far-apart witnesses; tests/test_contact.py)."""
    fromto = np.zeros(6)
    d = mujoco.mj_geomDistance(model, data, g1, g2, 0.2, fromto)
    return None if d < 0.2 and abs(np.linalg.norm(fromto[3:] - fromto[:3]) - abs(d)) > 1e-4 else d


def _decode(path: Path, fmt: str) -> np.ndarray:
    with av.open(str(path)) as c:
        return np.stack([f.to_ndarray(format=fmt) for f in c.decode(video=0)])


def test_build_from_a_depth_map_source_matches_mujoco(depth_map_source, tmp_path):
    """``depth: recorded`` on the depth maps (no depth.format: read from the feature), every
    stream built: the smallest stored s2g distance over the cube's reference pixels is MuJoCo's
    finger-cube distance (cube at its reference pose, fingers at the future frame) within 5 mm
    plus half a colour level, whenever MuJoCo's distance is under 5 cm; the output's own depth
    maps hold the source's codes exactly."""
    s = depth_map_source
    data = {"name": "depth_maps", "task": "transfer the cube", "robot": {"platform": "aloha_sim"},
            "cameras": {"calibration": str(s["calibration"])},
            "source": {"type": "lerobot", "path": str(s["root"])},
            "depth": {"source": "recorded", "feature": "observation.images.{cam}_depth"},
            # the measured state drawn: the commanded fingers lead MuJoCo's by up to 13 mm while closing
            "augment": {"height": H_SIM, "width": W_SIM, "contact_chunk": CHUNK, "motion_source": "state",
                        "lerobot_depth_map": {"enabled": True}}}
    (tmp_path / "recipe.yaml").write_text(yaml.safe_dump(data))
    root = tmp_path / "out"
    ds = build_dataset(BuildRequest("local/out", load_recipe(tmp_path / "recipe.yaml"), root, progress=False))
    names = list(imac_block(ds.meta)["cameras"])
    assert [k for k in ds.meta.video_keys if "_depth" in k] == []  # the source's depth maps are read, not copied
    for cam in names:
        ours = _decode(root / "videos" / f"observation.depth_map.{cam}" / "chunk-000" / "file-000.mp4", "gray12le")
        source = _decode(s["root"] / "videos" / s["keys"][cam] / "chunk-000" / "file-000.mp4", "gray12le")
        np.testing.assert_array_equal(ours, source)

    model, qfull = s["model"], s["qfull"]
    mj = mujoco.MjData(model)
    box = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "red_box")
    adr = model.jnt_qposadr[model.body_jntadr[model.geom_bodyid[box]]]
    fingers = [g for g in range(model.ngeom) if "finger" in model.geom(g).name]
    s2g = np.stack([_decode(root / "videos" / f"control.contact_s2g.{c}" / "chunk-000" / "file-000.mp4", "rgb24")
                    for c in names], axis=1)  # (T, V, H, W, 3)
    caps = pq.read_table(next((root / "data").rglob("*.parquet")), columns=["control.contact_cap"])
    caps = np.asarray(caps.column(0).to_pylist())[:, 1]
    errors = []
    for ref, frames in chunk_plan(len(qfull), CHUNK):
        cube = np.stack([s["seg"][c][ref] == box for c in names]) & np.stack(
            [s["depth_mm"][c][ref] > 0 for c in names])
        for f in frames:
            mj.qpos[:] = qfull[f]
            mj.qpos[adr:adr + 7] = qfull[ref][adr:adr + 7]
            mujoco.mj_kinematics(model, mj)
            dists = [_mj_distance(model, mj, g, box) for g in fingers]
            if any(d is None for d in dists):
                continue
            truth = max(min(dists), 0.0)  # penetration (squeezing) counts as contact
            if truth < 0.05 and cube.any():
                stored = np.nanmin(_colour_distance(s2g[f][cube], caps[f]))
                errors.append((f, truth, stored, caps[f] / 512))
    errors = np.array(errors)
    assert len(errors) >= 10 and errors[:, 1].min() < 0.002, errors
    err = np.abs(errors[:, 2] - errors[:, 1])
    print(f"{len(errors)} frames under 5 cm: |stored s2g - MuJoCo| max {err.max() * 1000:.2f} mm, "
          f"median {np.median(err) * 1000:.2f} mm")
    assert (err <= 0.005 + errors[:, 3]).all(), errors[err.argmax()]


def test_a_depth_map_without_its_quantiser_stops_the_build_before_any_work(depth_map_source, tmp_path):
    s = depth_map_source
    copy = tmp_path / "src"
    shutil.copytree(s["root"], copy)
    info = json.loads((copy / "meta" / "info.json").read_text())
    key = s["keys"]["cam_left_wrist"]
    del info["features"][key]["info"]["video.shift"]
    (copy / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    data = {"name": "x", "task": "t", "robot": {"platform": "aloha_sim"}, "cameras": {"calibration": str(
        s["calibration"])}, "source": {"type": "lerobot", "path": str(copy)},
            "depth": {"feature": "observation.images.{cam}_depth"}}
    (tmp_path / "recipe.yaml").write_text(yaml.safe_dump(data))
    root = tmp_path / "never"
    with pytest.raises(InputError, match=rf"recipe.yaml: depth.feature: dataset .*src: feature '{key}': info lacks "
                                         r"\['video.shift'\]"):
        build_dataset(BuildRequest("local/never", load_recipe(tmp_path / "recipe.yaml"), root, progress=False))
    assert not root.exists() and not (tmp_path / ".never.staging").exists()

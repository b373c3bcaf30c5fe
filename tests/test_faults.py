"""Faults a user can make, tried as a user would: each gets a clear error, the source is
never modified, and nothing half-written is left behind."""

import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.cli import main as imac_main
from imac_data.metadata import imac_block
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset


@pytest.fixture(scope="module")
def sim_src(tmp_path_factory):
    """Tiny simulated episodes: 2 episodes, 120x160, a few frames."""
    out = tmp_path_factory.mktemp("faults_sim")
    record_dataset(SimConfig(num_episodes=2, width=160, height=120, max_steps=12), out, progress=False)
    return out


def tree_digest(path: Path) -> dict[str, str]:
    """sha256 of every file under ``path`` (relative name -> digest)."""
    return {str(p.relative_to(path)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(path.rglob("*")) if p.is_file()}


def recipe_file(where: Path, **augment) -> Path:
    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["augment"] = {"height": 60, "width": 80, "contact_chunk": 4, **augment}
    path = where / "recipe.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def copy_source(sim_src: Path, dst: Path) -> Path:
    shutil.copytree(sim_src, dst)
    return dst


@pytest.mark.parametrize("layout", ["root_is_source", "root_inside_source", "root_contains_source"])
def test_overwrite_never_deletes_the_source(sim_src, tmp_path, capsys, layout):
    """--overwrite with --root equal to, inside or containing the source directory is refused
    before any work, and the raw episodes and calibration stay byte-identical."""
    if layout == "root_contains_source":
        root = tmp_path / "out"
        src = copy_source(sim_src, root / "episodes")
    else:
        src = copy_source(sim_src, tmp_path / "episodes")
        root = src if layout == "root_is_source" else src / "built"
    recipe = recipe_file(tmp_path)
    before = tree_digest(src)
    listing = sorted(p.name for p in tmp_path.iterdir())
    rc = imac_main(["build", "--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
               "--overwrite", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(src) in err and "source episodes" in err
    assert tree_digest(src) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == listing  # nothing new next to the output


def test_overwrite_never_deletes_the_calibration(sim_src, tmp_path, capsys):
    """A calibration file kept inside the output directory is an input too."""
    src = copy_source(sim_src, tmp_path / "episodes")
    root = tmp_path / "out"
    root.mkdir()
    calib = root / "calibration.json"
    shutil.copy(src / "calibration.json", calib)
    data = yaml.safe_load(recipe_file(tmp_path).read_text())
    data["cameras"] = {"calibration": str(calib)}
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text(yaml.safe_dump(data))
    digest = hashlib.sha256(calib.read_bytes()).hexdigest()
    rc = imac_main(["build", "--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
               "--overwrite", "--no-progress"])
    assert rc == 2
    assert "calibration" in capsys.readouterr().err
    assert hashlib.sha256(calib.read_bytes()).hexdigest() == digest


def test_augment_refuses_a_dataset_inside_its_raw_episodes(sim_src, tmp_path, capsys):

    src = copy_source(sim_src, tmp_path / "episodes")
    before = tree_digest(src)
    rc = imac_main(["augment", "--repo", "local/x", "--root", str(src), "--recipe", str(recipe_file(tmp_path)),
                       "--source", str(src), "--no-progress"])
    assert rc == 2
    assert "raw episodes" in capsys.readouterr().err
    assert tree_digest(src) == before


# --------------------------------------------------------------------------- bad input: exit 2, nothing written


def build_main(recipe: Path, src: Path, root: Path, *extra) -> int:
    """The build CLI in this process (one worker: no pool), quiet."""
    return imac_main(["build", "--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
                 "--no-progress", "--workers", "1", *extra])


def edit_calibration(src: Path, cam: str, edit) -> None:
    path = src / "calibration.json"
    data = json.loads(path.read_text())
    edit(data["cameras"][cam])
    path.write_text(json.dumps(data))


def edit_datasets(path: Path, edit, keys: list[str] | None = None) -> None:
    """Replace HDF5 datasets ``keys`` (default: every one) of episode ``path`` by ``edit(array)``."""
    with h5py.File(path, "r+") as f:
        if keys is None:
            keys = []
            f.visititems(lambda name, obj: keys.append(name) if isinstance(obj, h5py.Dataset) else None)
        for key in keys:
            value = edit(f[key][()])
            del f[key]
            f.create_dataset(key, data=value)


def _scale_rotation(c):
    c["T_world_cam"] = (np.asarray(c["T_world_cam"]) @ np.diag([1.1, 1.1, 1.1, 1.0])).tolist()


def _reflect(c):
    c["T_world_cam"][0][:3] = [-x for x in c["T_world_cam"][0][:3]]


def _negative_focal(c):
    c["K"][0][0] = -c["K"][0][0]


def _last_row(c):
    c["T_world_cam"][3] = [0.0, 0.0, 0.1, 1.0]


def _principal_point(c):
    c["K"][0][2] = 400.0


def _unknown_link(c):
    c["link"] = "vx300s_left/no_such_link"


def _twice_the_resolution(c):
    """The same camera calibrated at 240x320: pixel edges scale by 2, centres c -> 2c + 0.5."""
    K = np.asarray(c["K"])
    K[:2, :2] *= 2
    K[:2, 2] = 2 * K[:2, 2] + 0.5
    c["K"], c["width"], c["height"] = K.tolist(), 2 * c["width"], 2 * c["height"]


def _other_aspect(c):
    c["width"] = 200


def edit_file(path: Path, edit) -> None:
    """``edit(h5py.File)`` on episode ``path``, opened for writing."""
    with h5py.File(path, "r+") as f:
        edit(f)


def _set_attr(name, value):
    def edit(f):
        f.attrs[name] = value
    return edit


DEPTH_HIGH, IMAGES_HIGH = "observations/images_depth/cam_high", "observations/images/cam_high"
BAD_INPUT = {  # case -> (damage the source directory, what the message must name)
    # calibration (item 2): the calibration file, the camera, the field
    "rotation_scaled": (lambda s: edit_calibration(s, "cam_high", _scale_rotation),
                        ["calibration.json", "cam_high", "T_world_cam", "not orthonormal"]),
    "rotation_reflection": (lambda s: edit_calibration(s, "cam_high", _reflect),
                            ["calibration.json", "cam_high", "T_world_cam", "det -1"]),
    "negative_focal_length": (lambda s: edit_calibration(s, "cam_high", _negative_focal),
                              ["calibration.json", "cam_high", "fx=-"]),
    "pose_last_row": (lambda s: edit_calibration(s, "cam_high", _last_row),
                      ["calibration.json", "cam_high", "last row", "[0, 0, 0, 1]"]),
    "principal_point_outside": (lambda s: edit_calibration(s, "cam_high", _principal_point),
                                ["calibration.json", "cam_high", "principal point"]),
    "unknown_link": (lambda s: edit_calibration(s, "cam_left_wrist", _unknown_link),
                     ["cam_left_wrist", "vx300s_left/no_such_link"]),
    "calibration_other_aspect": (lambda s: edit_calibration(s, "cam_high", _other_aspect),
                                 ["cam_high", "120x160", "aspect ratio"]),
    "calibration_fractional_width": (lambda s: edit_calibration(s, "cam_high", lambda c: c.update(width=160.5)),
                                     ["calibration.json", "cam_high", "width", "160.5", "whole number"]),
    # recorded depth (item 3) and the up-front checks (item 4): the file and the key
    "depth_other_aspect": (lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d[:, :, :120], [DEPTH_HIGH]),
                           ["episode_1.hdf5", DEPTH_HIGH, "aspect ratio"]),
    "depth_dtype": (lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d.astype(np.int32), [DEPTH_HIGH]),
                    ["episode_1.hdf5", DEPTH_HIGH, "int32", "uint16 or float"]),
    "resolution_differs_between_episodes": (
        lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d[:, ::2, ::2], [IMAGES_HIGH, DEPTH_HIGH]),
        ["episode_1.hdf5", IMAGES_HIGH, "(60, 80)", "episode_0.hdf5"]),
    "empty_episode": (lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d[:0]), ["episode_1.hdf5", "no frames"]),
    # one dataset, one feature set and one rate: what differs between episodes is named
    "depth_missing_in_one_episode": (lambda s: edit_file(s / "episode_1.hdf5", lambda f: f.__delitem__(DEPTH_HIGH)),
                                     ["episode_1.hdf5", "images_depth", "episode_0.hdf5"]),
    "qvel_missing_in_one_episode": (
        lambda s: edit_file(s / "episode_1.hdf5", lambda f: f.__delitem__("observations/qvel")),
        ["episode_1.hdf5", "observations/qvel", "episode_0.hdf5"]),
    "qvel_width": (lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d[:, :7], ["observations/qvel"]),
                   ["episode_1.hdf5", "observations/qvel", ", 7)"]),
    "fps_differs_between_episodes": (lambda s: edit_file(s / "episode_1.hdf5", _set_attr("fps", 50.0)),
                                     ["episode_1.hdf5", "'fps'", "50.0", "episode_0.hdf5"]),
    "fps_not_whole": (lambda s: [edit_file(s / f"episode_{i}.hdf5", _set_attr("fps", 12.5)) for i in (0, 1)],
                      ["episode_0.hdf5", "'fps'", "12.5", "whole number"]),
    # episode attributes are read up front, not in the worker
    "success_not_a_boolean": (lambda s: edit_file(s / "episode_1.hdf5", _set_attr("success", "maybe")),
                              ["episode_1.hdf5", "'success'", "maybe"]),
    "source_unknown": (lambda s: edit_file(s / "episode_1.hdf5", _set_attr("source", "human")),
                       ["episode_1.hdf5", "'source'", "human"]),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUT))
def test_bad_input_is_refused_before_any_work(sim_src, tmp_path, capsys, case):
    """Exit 2 with one message naming the file, key or field; nothing new next to the
    output; the source byte-identical."""
    damage, names = BAD_INPUT[case]
    src = copy_source(sim_src, tmp_path / "episodes")
    damage(src)
    recipe = recipe_file(tmp_path)
    before, listing = tree_digest(src), sorted(p.name for p in tmp_path.iterdir())
    rc = build_main(recipe, src, tmp_path / "out")
    err = capsys.readouterr().err
    assert rc == 2, err
    for name in names:
        assert name in err, f"{name!r} not in {err!r}"
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert tree_digest(src) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == listing


def test_success_text_is_parsed_not_truthy(sim_src, tmp_path):
    """Oracle: the words themselves (bool("no") is True)."""
    from imac_data.sources.hdf5 import EpisodeReader

    src = copy_source(sim_src, tmp_path / "episodes")
    for value, expected in (("no", False), (b"Yes", True), ("failure", False), (np.int64(1), True), ("", None)):
        edit_file(src / "episode_0.hdf5", _set_attr("success", value))
        with EpisodeReader(src / "episode_0.hdf5") as ep:
            assert ep.info.success is expected, value


def test_root_that_holds_the_working_directory_is_refused(sim_src, tmp_path, capsys, monkeypatch):
    """--root . --overwrite from inside an existing dataset: refused before any work (it
    would delete the directory the command runs in), and the dataset stays as it was."""
    recipe = recipe_file(tmp_path)
    root = tmp_path / "out"
    assert build_main(recipe, sim_src, root) == 0
    before, listing = tree_digest(tmp_path), sorted(p.name for p in tmp_path.iterdir())
    monkeypatch.chdir(root / "meta")
    assert build_main(recipe, sim_src, Path(".."), "--overwrite") == 2
    err = capsys.readouterr().err
    assert str(root) in err and "current directory" in err
    assert tree_digest(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == listing


def test_reference_frame_without_scene_is_named_or_built_without_contact(sim_src, tmp_path, capsys):
    """Depth 0 in every camera at frame 0 of episode 1 (a sensor warming up): by default one
    error naming the file and the frame; with empty_reference_scene: no_contact the build
    completes, and that chunk (frames 0..4) has the documented empty caps, the others not."""
    from imac_data.core.contact.images import EMPTY_CAP

    src = copy_source(sim_src, tmp_path / "episodes")
    depth_keys = [f"observations/images_depth/{c}" for c in ("cam_high", "cam_left_wrist", "cam_right_wrist")]

    def zero_first(d):
        d = d.copy()
        d[0] = 0
        return d

    edit_datasets(src / "episode_1.hdf5", zero_first, depth_keys)
    before = tree_digest(src)
    assert build_main(recipe_file(tmp_path), src, tmp_path / "out") == 2
    err = capsys.readouterr().err
    for name in ("episode_1.hdf5", "reference frame 0", "augment.empty_reference_scene: no_contact"):
        assert name in err, err
    assert build_main(recipe_file(tmp_path, empty_reference_scene="no_contact"), src, tmp_path / "out") == 0
    data = LeRobotDataset("local/x", root=tmp_path / "out").hf_dataset.with_format("numpy")
    episode = np.asarray(data["episode_index"]) == 1
    frame = np.asarray(data["frame_index"])[episode]
    cap = np.stack(list(data["control.contact_cap"]))[episode]
    assert (frame > 4).any() and np.all(cap[frame <= 4] == EMPTY_CAP) and np.all(cap[frame > 4] != EMPTY_CAP)
    assert tree_digest(src) == before


@pytest.mark.parametrize("kind", ["file", "other_directory"])
def test_overwrite_replaces_only_a_dataset(sim_src, tmp_path, capsys, kind):
    """--overwrite with --root an existing file, or a directory that is not a LeRobot dataset:
    refused (exit 2), and it stays as it was."""
    root = tmp_path / "out"
    if kind == "file":
        root.write_text("my notes")
    else:
        root.mkdir()
        (root / "notes.txt").write_text("my notes")
    recipe = recipe_file(tmp_path)
    before, listing = tree_digest(tmp_path), sorted(p.name for p in tmp_path.iterdir())
    assert build_main(recipe, sim_src, root, "--overwrite") == 2
    err = capsys.readouterr().err
    assert str(root) in err and ("is a file" if kind == "file" else "not a LeRobot dataset") in err
    assert tree_digest(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == listing


def test_joints_recorded_in_degrees_are_named_before_the_build(sim_src, tmp_path, capsys):
    """The arm joints of one episode recorded in degrees (the grippers left as they are): the
    build warns up front, naming the index, the joint and the scale that fixes it, and goes on.
    The episodes as recorded (radians) give no warning."""
    recipe = recipe_file(tmp_path)
    assert build_main(recipe, sim_src, tmp_path / "ok") == 0
    assert "URDF limits" not in capsys.readouterr().err
    src = copy_source(sim_src, tmp_path / "episodes")
    arms = [i for i in range(14) if i not in (6, 13)]

    def to_degrees(q):
        q = q.copy()
        q[:, arms] = np.degrees(q[:, arms])
        return q
    edit_datasets(src / "episode_1.hdf5", to_degrees, ["observations/qpos"])
    assert build_main(recipe, src, tmp_path / "out") == 0
    err = capsys.readouterr().err
    assert err.startswith("warning: the episodes in") and "outside the URDF limits of robot" in err
    assert "joint vector index 1 ('vx300s_left/shoulder')" in err and "scale: 0.01745329" in err
    assert "'vx300s_left/left_finger'" not in err and str(recipe) in err


@pytest.mark.parametrize("suffix", ["staging", "old"])
def test_a_users_directory_where_the_build_stages_is_never_deleted(sim_src, tmp_path, capsys, suffix):
    """A directory of the user's named like the build's staging or kept-output path (``.out.staging``,
    ``.out.old``): refused before any work, with the path named; a leftover of ours there (marker,
    or a dataset) is cleared and the build goes on."""
    root, recipe = tmp_path / "out", recipe_file(tmp_path)
    theirs = tmp_path / f".out.{suffix}"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    before = tree_digest(tmp_path)
    assert build_main(recipe, sim_src, root, "--overwrite") == 2
    err = capsys.readouterr().err
    assert str(theirs) in err and "not made by imac_data" in err
    assert tree_digest(tmp_path) == before and not root.exists()

    from imac_data.dataset.output import SIBLING_MARKER

    (theirs / SIBLING_MARKER).write_text("")  # now it is a leftover of ours
    assert build_main(recipe, sim_src, root, "--overwrite") == 0
    assert not theirs.exists() and (root / "meta" / "info.json").is_file()


# --------------------------------------------------------------------------- environment: exit 3, resumable


def staging_entries(staging: Path) -> list[str]:
    """The directories a build left in staging, apart from the robot description and the timings."""
    return sorted(str(p.relative_to(staging)) for p in staging.rglob("*")
                  if p.is_dir() and p.parent in (staging, staging / "shards") and p.name not in ("robot", "timings"))


def fail_with(code: int, after: int = 0):
    """A stand-in writer that works ``after`` times (calling ``real``), then raises OSError(code)."""
    calls = []

    def wrap(real):
        def writer(*args, **kwargs):
            calls.append(args)
            if len(calls) > after:
                raise OSError(code, os.strerror(code), str(args[0]))
            return real(*args, **kwargs)
        return writer
    return wrap


def test_environment_faults_exit_3_keep_finished_shards_and_resume(sim_src, tmp_path, capsys, monkeypatch):
    """Disk full while episode 1 is written, then a read-only file system at the merge: each
    exits 3 with one line, leaves only the finished shards in staging (no partial shard, no
    half-merged dataset, no lock), and the rerun completes, without any progress bar.

    The source also holds what is accepted and rescaled (items 2, 3): a calibration made at
    twice the images' resolution, and float depth at half of it in one episode."""
    from imac_data.build import from_episodes, streams

    src = copy_source(sim_src, tmp_path / "episodes")
    K = np.asarray(json.loads((src / "calibration.json").read_text())["cameras"]["cam_high"]["K"])
    edit_calibration(src, "cam_high", _twice_the_resolution)
    edit_datasets(src / "episode_1.hdf5", lambda d: d[:, ::2, ::2].astype(np.float32), [DEPTH_HIGH])
    recipe, root = recipe_file(tmp_path), tmp_path / "local" / "out"  # like $HF_LEROBOT_HOME/local/<name>
    staging, source = root.parent / ".out.staging", tree_digest(src)

    monkeypatch.setattr(streams, "add_frame_column", fail_with(errno.ENOSPC, after=1)(streams.add_frame_column))
    assert build_main(recipe, src, root) == 3
    err = capsys.readouterr().err
    assert "No space left on device (ENOSPC)" in err and len(err.strip().splitlines()) == 1, err
    assert staging_entries(staging) == ["shards", "shards/episode_000000"]  # episode 1's partial shard removed
    assert sorted(p.name for p in root.parent.iterdir()) == [".out.staging"]  # no lock left behind
    monkeypatch.undo()

    monkeypatch.setattr(from_episodes, "write_card", fail_with(errno.EROFS)(from_episodes.write_card))
    assert build_main(recipe, src, root) == 3
    err = capsys.readouterr().err
    assert "Read-only file system (EROFS)" in err and len(err.strip().splitlines()) == 1, err
    assert staging_entries(staging) == ["shards", "shards/episode_000000", "shards/episode_000001"]  # no dataset/
    monkeypatch.undo()

    assert build_main(recipe, src, root) == 0
    err = capsys.readouterr().err
    assert "%|" not in err and "it/s" not in err, err  # --no-progress: LeRobot's bars too
    ds = LeRobotDataset("local/x", root=root)
    assert ds.meta.total_episodes == 2
    camera = imac_block(ds.meta)["cameras"]["cam_high"]  # the simulator's own K at 120x160 again
    assert (camera["height"], camera["width"]) == (120, 160) and np.allclose(camera["K"], K, atol=1e-9)
    assert sorted(p.name for p in root.parent.iterdir()) == ["out"]
    assert tree_digest(src) == source
    # the free-space estimate is a lower bound of the staging peak (about twice the output)
    from imac_data.dataset.output import estimate_build_bytes

    robot = sum(p.stat().st_size for p in (root / "meta" / "imac" / "robot").rglob("*") if p.is_file())
    need = estimate_build_bytes(12, {c: (120, 160) for c in ("cam_high", "cam_left_wrist", "cam_right_wrist")},
                                (60, 80), robot)
    assert need <= 2 * sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def test_ctrl_c_is_one_line_and_exit_130(capsys):
    from imac_data.console import EXIT_INTERRUPTED, run_command

    def body():
        raise KeyboardInterrupt

    assert run_command(body) == EXIT_INTERRUPTED == 130
    err = capsys.readouterr().err
    assert err.startswith("interrupted") and len(err.strip().splitlines()) == 1

    def import_cut_short():  # what open3d's native import raises when Ctrl-C lands inside it
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise ImportError("initialization failed") from e

    assert run_command(import_cut_short) == 130
    err = capsys.readouterr().err
    assert err.startswith("interrupted") and len(err.strip().splitlines()) == 1


def test_a_ctrl_c_that_a_library_swallowed_still_stops_the_command():
    """trimesh wraps its optional imports in ``except BaseException``: a real SIGINT there is
    swallowed, yet recorded, and the pipeline's next check raises it."""
    import signal

    from imac_data.console import interrupt_pending, note_interrupts, raise_if_interrupted

    note_interrupts()
    try:
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # the handler runs here
        except BaseException:  # noqa: BLE001 - what the library does
            pass
        assert interrupt_pending()
        with pytest.raises(KeyboardInterrupt):
            raise_if_interrupted()
    finally:
        note_interrupts()  # clears the record
        signal.signal(signal.SIGINT, signal.default_int_handler)


def test_ctrl_c_while_the_command_loads_is_one_line(tmp_path):
    """Ctrl-C half a second after ``python -m imac_data.build`` starts (torch is still loading):
    the one line and 130, not a traceback from inside an import."""
    import signal

    proc = subprocess.Popen([sys.executable, "-m", "imac_data.build", "--repo", "local/x", "--root",
                             str(tmp_path / "out"), "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and err.strip().splitlines() == [
        "interrupted (a build keeps its finished episodes: rerun the same command to resume)"], err
    assert not (tmp_path / "out").exists()


ENCODING_WORKER = """
import os, signal, sys, time
import av, numpy as np
from imac_data.console import quiet_worker_interrupts, run_as_job

def job(path):
    container = av.open(path, "w")
    stream = container.add_stream("libsvtav1", rate=10)
    stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
    for i in range(3):
        for packet in stream.encode(av.VideoFrame.from_ndarray(np.full((48, 64, 3), 40 * i, np.uint8), "rgb24")):
            container.mux(packet)
    os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C mid-stream: the encoder is freed unflushed as the job unwinds
    time.sleep(10)

if sys.argv[2] == "worker":
    quiet_worker_interrupts()
try:
    run_as_job(job, sys.argv[1])
except KeyboardInterrupt:
    sys.exit(130)
"""


@pytest.mark.parametrize("process", ["worker", "plain"])
def test_a_pool_worker_interrupted_while_encoding_stays_quiet(tmp_path, process):
    """Ctrl-C in a pool worker whose SVT-AV1 encoder is mid-stream: SVT-AV1 writes "deinit called
    without sending EOS!" to fd 2 as the encoder is freed; a pool worker's stderr stays empty (the
    command prints the one line). ``plain``: the same job without the worker's handler, where the
    library's line shows, so the quiet is the handler's doing."""
    env = {**os.environ, "SVT_LOG": "1"}  # errors only, as the commands set it
    done = subprocess.run([sys.executable, "-c", ENCODING_WORKER, str(tmp_path / "x.mp4"), process], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 130, done.stderr
    if process == "worker":
        assert done.stderr == ""
    else:
        assert "deinit called without sending EOS" in done.stderr


WRITER_AFTER_LEROBOT = """
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets.video_utils import get_video_info

from imac_data.console import quiet_libraries
from imac_data.dataset.videos import VideoEncoding, VideoWriter, encode_video

quiet_libraries()
tmp = Path(sys.argv[1])
camera = encode_video(tmp / "a.mp4", np.zeros((4, 64, 64, 3), np.uint8), fps=10, encoding=VideoEncoding.lerobot_default())
for how in ("abort", "close", "unguarded"):
    writer = VideoWriter(tmp / f"{how}.mp4", VideoEncoding.lossless_rgb(), 10, 16, 16)
    writer.write(np.zeros((3, 16, 16, 3), np.uint8))
    get_video_info(camera)  # as LeRobot reads a camera video mid-build: it puts FFmpeg's own callback back
    print(f"--{how}--", file=sys.stderr, flush=True)
    if how == "abort":
        writer.abort()  # an interrupted build's clean-up
    elif how == "close":
        writer.close()
    else:  # the writer's container closed without its guard
        writer.container.close()
"""


def test_a_video_writer_stays_quiet_after_lerobot_restores_ffmpegs_logging(tmp_path):
    """LeRobot's ``get_video_info`` puts FFmpeg's own log callback back, which prints x264's
    statistics (INFO) to fd 2 as an encoder closes; an interrupted build printed them above its
    one line. A VideoWriter's abort and close stay quiet; ``unguarded``, the same close without
    the writer's guard, shows the statistics, so the quiet is the guard's doing."""
    done = subprocess.run([sys.executable, "-c", WRITER_AFTER_LEROBOT, str(tmp_path)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    parts = dict(zip(("abort", "close", "unguarded"), done.stderr.split("--")[2::2]))
    assert parts["abort"].strip() == "" and parts["close"].strip() == "", done.stderr
    assert "libx264rgb" in parts["unguarded"]


ABORTED_SVT_WRITER = """
import sys
from pathlib import Path

import numpy as np

from imac_data.dataset.videos import VideoEncoding, VideoWriter

for how in ("abort", "unguarded"):
    writer = VideoWriter(Path(sys.argv[1]) / f"{how}.mp4", VideoEncoding.lerobot_default(), 10, 48, 64)
    writer.write(np.zeros((5, 48, 64, 3), np.uint8))
    print(f"--{how}--", file=sys.stderr, flush=True)
    if how == "abort":
        writer.abort()
    else:  # the same close without the writer's guard, the encoder freed as its reference goes
        writer.container.close()
        writer.stream = None
    writer = None  # as a build unwinds: the writer goes too
    print(f"--{how} done--", file=sys.stderr, flush=True)
"""


def test_an_aborted_svt_av1_writer_stays_quiet_in_the_commands_own_process(tmp_path):
    """The command's own process builds episodes too (the pool's first worker), without a pool
    worker's silenced fd 2: an SVT-AV1 encoder it aborts after Ctrl-C printed "deinit called
    without sending EOS!" above the one line (CI, the pool Ctrl-C test). ``abort`` frees the
    encoder quietly; ``unguarded`` shows the library's line, so the quiet is abort's doing."""
    env = {**os.environ, "SVT_LOG": "1"}  # errors only, as the commands set it
    done = subprocess.run([sys.executable, "-c", ABORTED_SVT_WRITER, str(tmp_path)], env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    parts = done.stderr.split("--")
    assert parts[1:4] == ["abort", "\n", "abort done"], done.stderr
    assert "deinit called without sending EOS" in parts[6], done.stderr


def test_environment_errors_are_recognised_however_they_arrive():
    """From a pool worker (pickled), wrapped by a library (chained), or with only the text kept
    (pyarrow, PyAV): still an environment fault; anything else is a bug."""
    import pickle

    from imac_data.console import environment_problem

    full = pickle.loads(pickle.dumps(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/data/x.mp4")))
    assert environment_problem(full).startswith("No space left on device (ENOSPC): /data/x.mp4 - free some space")
    try:
        try:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        except OSError as e:
            raise RuntimeError("could not write the video") from e
    except RuntimeError as wrapped:
        assert "(EROFS)" in environment_problem(wrapped)
    assert "(ENOSPC)" in environment_problem(OSError("IOError: [Errno 28] No space left on device"))
    assert environment_problem(OSError(errno.ENOENT, "No such file or directory")) is None
    assert environment_problem(ValueError("a bug")) is None


def test_output_parent_that_is_a_file(sim_src, tmp_path, capsys):
    recipe = recipe_file(tmp_path)
    (tmp_path / "afile").write_text("x")
    assert build_main(recipe, sim_src, tmp_path / "afile" / "out") == 3
    err = capsys.readouterr().err
    assert "afile is a file, not a directory" in err and len(err.strip().splitlines()) == 1
    assert (tmp_path / "afile").read_text() == "x"


@pytest.fixture
def small_tmpfs(tmp_path):
    """A real 2 MB file system (tmpfs), or a skip where mounting is not permitted."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"mounting a tmpfs is not permitted here: {r.stderr.strip()}")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], check=False)


def test_a_really_full_disk_warns_fails_cleanly_and_resumes(sim_src, tmp_path, small_tmpfs, capsys):
    """The build into a 2 MB tmpfs: a warning before it starts, exit 3 when the disk fills,
    only finished shards left; after the file system grows the rerun completes."""
    recipe, root = recipe_file(tmp_path), small_tmpfs / "out"
    assert build_main(recipe, sim_src, root) == 3
    err = capsys.readouterr().err
    assert "warning:" in err and "MB free" in err, err
    assert "No space left on device (ENOSPC)" in err and "Traceback" not in err, err
    staging = small_tmpfs / ".out.staging"
    assert all(e == "shards" or e.startswith("shards/episode_0") for e in staging_entries(staging))
    assert not list(staging.rglob("*.tmp")) and not list(staging.rglob("*.merging"))
    subprocess.run(["mount", "-o", "remount,size=32m", str(small_tmpfs)], check=True)
    assert build_main(recipe, sim_src, root) == 0
    assert LeRobotDataset("local/x", root=root).meta.total_episodes == 2
    assert sorted(p.name for p in small_tmpfs.iterdir()) == ["out"]


# --------------------------------------------------------------------------- concurrency and killed builds


HOLD_LOCK = """
import os, sys, time
from pathlib import Path
from imac_data.dataset.output import lock_path, output_lock
root = Path(sys.argv[1])
with output_lock(root):
    print("locked", flush=True)
    if len(sys.argv) < 3:
        time.sleep(600)
    else:  # "a build" that finishes once another one waits for its lock (a "->" line in /proc/locks)
        inode = f":{os.stat(lock_path(root)).st_ino} "
        while not any(line.split()[1] == "->" and inode in line for line in open("/proc/locks")):
            time.sleep(0.05)
        (root / "meta").mkdir(parents=True)
        (root / "meta" / "info.json").write_text("{}")
"""


def hold_lock(root: Path, *args) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, str(root), *args], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_a_second_build_of_the_same_output_is_locked_out(sim_src, tmp_path, capsys):
    """Another build holds the output's lock: refused with exit 3 naming its PID, nothing
    written; the lock file lies next to the staging directory."""
    from imac_data.dataset.output import lock_path

    recipe, root = recipe_file(tmp_path), tmp_path / "out"
    assert lock_path(root).parent == root.parent
    other = hold_lock(root)
    try:
        assert build_main(recipe, sim_src, root) == 3
        err = capsys.readouterr().err
        assert f"another build (PID {other.pid}) is writing {root}" in err and "--wait" in err, err
        assert sorted(p.name for p in tmp_path.iterdir()) == [".out.lock", "recipe.yaml"]  # the other's lock only
    finally:
        other.kill()
        other.wait()


def test_wait_waits_for_the_other_build(sim_src, tmp_path, capsys):
    """--wait: the build waits for the lock's holder, then sees the output it made (exit 2,
    already exists) instead of replacing it."""
    recipe, root = recipe_file(tmp_path), tmp_path / "out"
    other = hold_lock(root, "finish when waited for")
    assert build_main(recipe, sim_src, root, "--wait") == 2
    err = capsys.readouterr().err
    assert f"waiting for the build with PID {other.pid}" in err and "already exists" in err, err
    assert other.wait() == 0 and (root / "meta" / "info.json").read_text() == "{}"


def _alive_children(pid: int) -> set[int]:
    """PIDs of the processes whose parent is ``pid`` (from /proc/*/stat)."""
    out = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                out.add(int(stat.parent.name))
        except (OSError, ValueError, IndexError):
            pass  # gone meanwhile
    return out


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"  # zombies are dead
    except OSError:
        return False


def test_pool_workers_die_with_a_killed_build(sim_src, tmp_path):
    """SIGKILL the build while a pool worker writes its episode: the worker dies with it and
    finishes no shard afterwards."""
    recipe, root = recipe_file(tmp_path), tmp_path / "out"
    shards = tmp_path / ".out.staging" / "shards"
    proc = subprocess.Popen([sys.executable, "-m", "imac_data.build", "--repo", "local/x", "--recipe", str(recipe),
                             "--source", str(sim_src), "--root", str(root), "--no-progress", "--workers", "2"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 600  # a spawned worker imports torch, Open3D, ... first: slow on a loaded machine
    while time.time() < deadline:  # both episodes started, one still being written (by the pool worker)
        writing, done = list(shards.glob(".episode_*.tmp")), list(shards.glob("episode_*"))
        if writing and len(writing) + len(done) == 2:
            break
        time.sleep(0.05)
    children = _alive_children(proc.pid)
    proc.kill()
    proc.wait()
    assert children and writing, "the build started no pool worker"
    deadline = time.time() + 10
    while time.time() < deadline and any(_running(c) for c in children):
        time.sleep(0.1)
    assert not any(_running(c) for c in children), "a pool worker outlived the build"
    time.sleep(1.0)
    assert list(shards.glob("episode_*")) == done, "an orphan finished a shard after the build was killed"


def _pool_workers(pid: int) -> list[int]:
    """The spawned pool workers among ``pid``'s children (not multiprocessing's resource tracker)."""
    out = []
    for child in _alive_children(pid):
        try:
            if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes():
                out.append(child)
        except OSError:
            pass
    return out


@pytest.mark.parametrize("when", ["worker_starting", "worker_writing"])
def test_ctrl_c_of_a_pool_build_is_one_line(sim_src, tmp_path, when):
    """A terminal's Ctrl-C (SIGINT to the whole process group) while a pool worker imports its
    libraries or writes its episode: exit 130 with the one 'interrupted' line and no worker
    traceback, no process left, and the rerun completes."""
    import signal

    recipe, root = recipe_file(tmp_path), tmp_path / "out"
    shards = tmp_path / ".out.staging" / "shards"
    cmd = [sys.executable, "-m", "imac_data.build", "--repo", "local/x", "--recipe", str(recipe),
           "--source", str(sim_src), "--root", str(root), "--no-progress", "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.time() + 600
    while time.time() < deadline and proc.poll() is None:
        if when == "worker_starting" and _pool_workers(proc.pid):
            time.sleep(0.5)  # into its imports (seconds long)
            break
        writing, done = list(shards.glob(".episode_*.tmp")), list(shards.glob("episode_*"))
        if when == "worker_writing" and writing and len(writing) + len(done) == 2:
            break
        time.sleep(0.02)
    workers = _pool_workers(proc.pid)
    assert proc.poll() is None and workers, "the build ended before the moment to interrupt it"
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["interrupted (a build keeps its finished episodes: rerun the same command "
                                        "to resume)"], err
    deadline = time.time() + 10
    while time.time() < deadline and any(_running(w) for w in workers):
        time.sleep(0.1)
    assert not any(_running(w) for w in workers), "a pool worker outlived the interrupted build"
    assert subprocess.run(cmd, capture_output=True).returncode == 0 and (root / "meta" / "info.json").is_file()

"""Faults a user can make, tried as a user would: each gets a clear error, the source is
never modified, and nothing half-written is left behind."""

import hashlib
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from imac_data.build import main
from imac_data.recipes import RECIPES_DIR
from imac_data.simulate import SimConfig, record_dataset


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
    rc = main(["--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
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
    rc = main(["--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
               "--overwrite", "--no-progress"])
    assert rc == 2
    assert "calibration" in capsys.readouterr().err
    assert hashlib.sha256(calib.read_bytes()).hexdigest() == digest


def test_augment_refuses_a_dataset_inside_its_raw_episodes(sim_src, tmp_path, capsys):
    from imac_data.augment import main as augment_main

    src = copy_source(sim_src, tmp_path / "episodes")
    before = tree_digest(src)
    rc = augment_main(["--repo", "local/x", "--root", str(src), "--recipe", str(recipe_file(tmp_path)),
                       "--source", str(src), "--no-progress"])
    assert rc == 2
    assert "raw episodes" in capsys.readouterr().err
    assert tree_digest(src) == before


# --------------------------------------------------------------------------- bad input: exit 2, nothing written


def build_main(recipe: Path, src: Path, root: Path, *extra) -> int:
    """The build CLI in this process (one worker: no pool), quiet."""
    return main(["--repo", "local/x", "--recipe", str(recipe), "--source", str(src), "--root", str(root),
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


def _other_aspect(c):
    c["width"] = 200


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
    # recorded depth (item 3) and the up-front checks (item 4): the file and the key
    "depth_other_aspect": (lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d[:, :, :120], [DEPTH_HIGH]),
                           ["episode_1.hdf5", DEPTH_HIGH, "aspect ratio"]),
    "depth_dtype": (lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d.astype(np.int32), [DEPTH_HIGH]),
                    ["episode_1.hdf5", DEPTH_HIGH, "int32", "uint16 or float"]),
    "resolution_differs_between_episodes": (
        lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d[:, ::2, ::2], [IMAGES_HIGH, DEPTH_HIGH]),
        ["episode_1.hdf5", IMAGES_HIGH, "(60, 80)", "episode_0.hdf5"]),
    "empty_episode": (lambda s: edit_datasets(s / "episode_1.hdf5", lambda d: d[:0]), ["episode_1.hdf5", "no frames"]),
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

"""Augmenting an existing LeRobot dataset in place: new streams, original videos untouched."""

import json

import numpy as np
import pytest
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.build.from_episodes import ingest_episodes
from imac_data.cli import main as imac_main
from imac_data.core.cameras import load_calibration
from imac_data.core.depth import depth_codec_of
from imac_data.core.rig import Rig
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.dataset.ingest import IngestOptions
from imac_data.metadata import dataset_info
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset


@pytest.fixture(scope="module")
def sim_src(tmp_path_factory):
    src = tmp_path_factory.mktemp("aug") / "src"
    record_dataset(SimConfig(num_episodes=2, width=80, height=64, max_steps=16), src, progress=False)
    return src


@pytest.fixture
def base(sim_src, tmp_path):
    """A fresh base dataset (ingest only) of the recorded episodes."""
    src, tmp = sim_src, tmp_path
    root = tmp / "base"
    ingest_episodes(sorted(src.glob("episode_*.hdf5")),
                    rig=Rig(RobotModel(aloha.robot_config()), load_calibration(src / "calibration.json")), repo_id="local/base", root=root,
                    options=IngestOptions(fps=25, task="t", state_names=aloha.STATE_NAMES), progress=False)
    recipe = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    recipe["augment"] = {"height": 64, "width": 80, "contact_chunk": 4}
    recipe_path = tmp / "recipe.yaml"
    recipe_path.write_text(yaml.safe_dump(recipe))
    return src, root, recipe_path


def test_augment_existing_dataset_keeps_original_videos(base):
    src, root, recipe = base
    originals = {p: p.read_bytes() for p in (root / "videos").rglob("*.mp4")}
    assert imac_main(["augment", "--repo", "local/base", "--root", str(root), "--recipe", str(recipe), "--source", str(src),
                 "--no-progress"]) == 0
    for path, content in originals.items():
        assert path.read_bytes() == content, f"{path} changed"
    ds = LeRobotDataset("local/base", root=root)
    assert "control.motion.cam_high" in ds.meta.video_keys
    assert "observation.depth.cam_left_wrist" in ds.meta.video_keys
    # depth decodes back to the recorded depth (bit-exact stream, 8-bit codec steps)
    item = ds[3]
    metres = depth_codec_of(ds.meta).decode(item["observation.depth.cam_high"], channel_axis=-3)
    from imac_data.sources.hdf5 import read_episode

    truth = read_episode(sorted(src.glob("episode_*.hdf5"))[0]).depth_mm["cam_high"][3] / 1000.0
    valid = (truth > 0.1) & (truth < 1.2)
    assert np.median(np.abs(np.asarray(metres)[valid] - truth[valid])) < 3e-3
    assert dataset_info(root)["imac"]["contact"]["chunk_size"] == 4


def test_augment_refuses_mismatched_source(base, tmp_path, capsys):
    src, root, recipe = base
    other = tmp_path / "other"
    record_dataset(SimConfig(num_episodes=2, width=80, height=64, max_steps=16, seed=7), other, progress=False)
    assert imac_main(["augment", "--repo", "local/base", "--root", str(root), "--recipe", str(recipe), "--source", str(other),
                 "--no-progress"]) == 2
    assert "does not match" in capsys.readouterr().err
    assert "control.motion.cam_high" not in json.loads((root / "meta" / "info.json").read_text())["features"]
    assert not (root.parent / f".{root.name}.staging").exists()


@pytest.mark.parametrize("suffix", ["staging", "old"])
def test_augment_never_deletes_a_users_directory_next_to_the_dataset(base, capsys, suffix):
    """A directory of the user's named like augment's staged copy or kept original: refused
    before any work, with the path named, and left as it was; the dataset is untouched."""
    src, root, recipe = base
    theirs = root.parent / f".{root.name}.{suffix}"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    info = (root / "meta" / "info.json").read_text()
    assert imac_main(["augment", "--repo", "local/base", "--root", str(root), "--recipe", str(recipe), "--source", str(src),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert str(theirs) in err and "not made by imac_data" in err
    assert [p.name for p in theirs.iterdir()] == ["notes.txt"] and (root / "meta" / "info.json").read_text() == info
    assert not (root.parent / f".{root.name}.{'old' if suffix == 'staging' else 'staging'}").exists()

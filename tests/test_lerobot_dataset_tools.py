"""LeRobot's own dataset tools (``lerobot.datasets.dataset_tools``) on a dataset built by imac
(docs/lerobot.md, "LeRobot's dataset tools"): which keep the control streams, which drop the
``imac`` block, that ``imac validate`` names the loss, and that ``--restore-imac-from`` puts the
block back from the dataset it was made from."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from lerobot.datasets import dataset_tools
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from packaging.version import Version

from imac_data.cli import main as imac_main
from imac_data.dataset.info import write_info
from imac_data.dataset.merge import restore_imac_block
from imac_data.dataset.streams import video_info
from imac_data.dataset.validate import validate_dataset
from imac_data.errors import InputError
from imac_data.layout import IMAC_INFO, INFO, is_added_stream
from imac_data.lerobot_compat import version as lerobot_version
from imac_data.metadata import dataset_info, imac_block
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset

REPO = "local/tools"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """Two episodes of 7 frames, every stream, built by the build CLI."""
    tmp = tmp_path_factory.mktemp("lerobot_tools")
    record_dataset(SimConfig(num_episodes=2, width=80, height=64, max_steps=14), tmp / "src", progress=False)
    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["augment"] = {"height": 32, "width": 40, "contact_chunk": 4}
    (tmp / "recipe.yaml").write_text(yaml.safe_dump(data))
    root = tmp / "ds"
    assert imac_main(["build", "--repo", REPO, "--recipe", str(tmp / "recipe.yaml"), "--source", str(tmp / "src"),
                      "--root", str(root), "--no-progress", "--workers", "1"]) == 0
    return root


def _streams(root: Path) -> dict:
    info = json.loads((root / "meta" / "info.json").read_text())
    return {k: v for k, v in info["features"].items() if is_added_stream(k)}


TOOLS = {
    "merge_datasets": lambda ds, out: dataset_tools.merge_datasets(
        [ds, LeRobotDataset(REPO, root=ds.root)], "local/merged", output_dir=out),
    "add_features": lambda ds, out: dataset_tools.add_features(
        ds, {"extra": (np.zeros(ds.meta.total_frames, np.float32),
                       {"dtype": "float32", "shape": [1], "names": None})}, output_dir=out, repo_id="local/added"),
    "remove_feature": lambda ds, out: dataset_tools.remove_feature(
        ds, "control.contact_cap", output_dir=out, repo_id="local/removed"),
}


# LeRobot 0.4.4's add_features cannot add a column of shape [1] with the datasets it installs (4.x: a TypeError in
# datasets' encode_nested_example, on any dataset); 0.6.1's can
ADD_FEATURES_BROKEN = pytest.mark.skipif(Version(lerobot_version()) < Version("0.6.0"), reason=(
    "LeRobot 0.4.4's add_features fails on any dataset (TypeError: object of type 'float' has no len(), from "
    "datasets 4's encoder); 0.6.1's works and is tested under it"))


@pytest.mark.parametrize("tool", [pytest.param(t, marks=ADD_FEATURES_BROKEN) if t == "add_features" else t
                                  for t in TOOLS])
def test_tools_keep_the_streams_drop_the_block_and_validate_restores_it(built, tmp_path, tool, capsys):
    out = tmp_path / "out"
    TOOLS[tool](LeRobotDataset(REPO, root=built), out)
    before, after = _streams(built), _streams(out)
    # every video stream kept, with its definition; remove_feature took the one column it was asked to
    assert set(after) == set(before) - ({"control.contact_cap"} if tool == "remove_feature" else set())
    for key, feature in after.items():
        assert (feature["dtype"], feature["shape"]) == (before[key]["dtype"], before[key]["shape"]), key
    assert "imac" not in json.loads((out / INFO).read_text()) and "imac" not in dataset_info(out)
    assert not (out / "meta" / "imac").exists()  # neither the block (meta/imac/info.json) nor the robot description
    report = validate_dataset(out)
    assert not report.ok and report.results["imac_block"], report.format()
    assert f"imac validate {out} --restore-imac-from ORIGINAL" in report.results["imac_block"][0]
    assert report.results["frame_counts"] == [] and report.results["decode"] == [], report.format()
    capsys.readouterr()
    assert imac_main(["validate", str(out), "--restore-imac-from", str(built)]) == 0, capsys.readouterr().out
    assert f"restored the imac block of {out} from {built}" in capsys.readouterr().out
    restored, original = imac_block(out), imac_block(built)
    assert restored["build"].pop("imac_block_restored_from") == str(built.resolve())
    assert restored == original
    assert validate_dataset(out, full=True).ok


def test_restore_refuses_a_dataset_with_a_block_or_other_streams(built, tmp_path):
    with pytest.raises(InputError, match="already has an imac block"):
        restore_imac_block(built, built)
    other = tmp_path / "other"
    shutil.copytree(built, other)
    info = dataset_info(other)
    del info["imac"]
    info["features"]["control.motion.cam_high"]["shape"] = [16, 20, 3]
    write_info(other, info)  # without the block: meta/imac/info.json goes
    assert not (other / IMAC_INFO).exists()
    with pytest.raises(InputError, match=r"control.motion.cam_high.shape differs \(\[16, 20, 3\] against \[32, 40, 3\]\)"):
        restore_imac_block(other, built)
    assert "imac" not in dataset_info(other) and not (other / IMAC_INFO).exists()


# LeRobot 0.6.0 validates the encoder settings it re-encodes with; 0.4.4 re-encodes with its camera encoder
REENCODE_REFUSED = Version(lerobot_version()) >= Version("0.6.0")


@pytest.mark.parametrize("tool", ["delete_episodes", "split_dataset"])
def test_tools_that_reencode_refuse_or_spoil_our_control_streams(built, tmp_path, tool):
    """LeRobot's delete and split re-encode each video file that mixes kept and dropped episodes
    (every imac build's). 0.6 re-encodes with the settings in info.json: our control streams are
    libx264rgb (gbrp), which its encoder configuration refuses (codec h264 has no gbrp), before
    writing a video. 0.4.4 re-encodes them with its camera encoder (AV1, yuv420p: lossy) under the
    old labels; restoring the block onto that is refused, naming the file."""
    ds = LeRobotDataset(REPO, root=built)
    out = tmp_path / "out"

    def run():
        if tool == "delete_episodes":
            return [dataset_tools.delete_episodes(ds, [0], output_dir=out, repo_id="local/deleted").root]
        return [d.root for d in dataset_tools.split_dataset(ds, {"a": [0], "b": [1]}, output_dir=out).values()]

    if REENCODE_REFUSED:
        with pytest.raises(ValueError, match="pix_fmt='gbrp' is not supported by codec 'h264'"):
            run()
        return
    for root in run():
        assert "imac" not in dataset_info(root) and not (root / "meta" / "imac").exists()
        path = next((root / "videos" / "control.motion.cam_high").rglob("*.mp4"))
        got = video_info(path)
        assert (got["video.codec"], got["video.pix_fmt"]) == ("av1", "yuv420p")
        assert _streams(root)["control.motion.cam_high"]["info"]["video.codec"] == "h264"  # the label kept
        with pytest.raises(InputError, match=r"videos/[^ ]+\.mp4 is av1 yuv420p, not the h264 gbrp "
                                             r"imac wrote \(re-encoded by the tool\)"):
            restore_imac_block(root, built)

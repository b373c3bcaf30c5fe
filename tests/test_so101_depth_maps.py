"""The SO-101 round trip on the Python 3.12 line: a LeRobot dataset written by LeRobot 0.6's own writer with its own
depth maps, calibrated from that depth alone and built (``benchmarks/so101_round_trip.py``, leg ``lerobot_depth``;
``.ci/run`` runs this file under LeRobot 0.6.1). LeRobot 0.4.4 has no depth maps: skipped there (the 3.11 line's
LeRobot leg, without depth, is in ``tests/test_so101.py``)."""

from __future__ import annotations

import json

import pytest
import yaml
from packaging.version import Version

from benchmarks import so101_round_trip, so101_sim
from imac_data.cli import main as imac_main
from imac_data.core.cameras import load_calibration
from imac_data.lerobot_compat import version as lerobot_version

pytestmark = pytest.mark.skipif(Version(lerobot_version()) < Version(so101_sim.DEPTH_MAPS_SINCE),
                                reason=f"LeRobot {lerobot_version()} has no depth maps (0.6.0 added them)")


def test_a_lerobot_061_dataset_with_its_depth_maps_is_calibrated_from_them_and_built(tmp_path):
    """At 96x128 (2 episodes of 20 frames, the body in degrees): LeRobot's writer stores each camera's MuJoCo depth
    (uint16 millimetres) as its depth map (``info.is_depth_map``, ``gray12le``, ``depth_unit: mm``, its log
    quantiser); through ``recipes/so101_lerobot.yaml`` as shipped (its ``depth:`` section names
    ``observation.images.{cam}_depth``), ``imac qa calibrate`` on the dataset alone finds both cameras within 3 mm
    and 0.3 degrees (nominal fields of view 15 % off), and the dataset's build (``imac build``, in this process)
    draws the arm where MuJoCo's segmentation has it: IoU >= 0.97 per camera (the benchmark, both conventions:
    >= 0.99 at 480x640; at 96x128 the outline's pixels weigh more)."""
    paths = so101_sim.record(tmp_path / "recorded", episodes=2, frames=20, height=96, width=128, lerobot=False,
                             depth_maps=True, conventions=("degrees",))
    dataset = paths["lerobot_depth"]["degrees"]
    features = json.loads((dataset / "meta" / "info.json").read_text())["features"]
    for c in so101_sim.CAMERAS:
        info = features[f"observation.images.{c}_depth"]["info"]
        assert info["is_depth_map"] is True and info["video.pix_fmt"] == "gray12le" and info["depth_unit"] == "mm"
    recipe = so101_round_trip.lerobot_recipe(tmp_path, paths, "degrees", (96, 128), depth=True)
    shipped = yaml.safe_load(so101_round_trip.RECIPE.read_text())
    assert yaml.safe_load(recipe.read_text())["depth"] == shipped["depth"]
    truth = load_calibration(paths["truth"])
    calib = tmp_path / "lerobot_depth_degrees.calibration.json"
    report = so101_round_trip.calibrate(dataset, recipe, calib, truth)
    assert report["source"] == str(dataset) and report["depth"] == "recorded"
    errors = so101_round_trip.pose_errors(calib, truth)
    assert all(mm < 3.0 and deg < 0.3 for mm, deg in errors.values()), errors
    assert imac_main(["build", "--repo", "local/so101_depth_maps", "--recipe", str(recipe), "--root",
                      str(tmp_path / "built"), "--workers", "1", "--no-progress"]) == 0
    states, ious = so101_round_trip.built_iou(tmp_path / "built", truth, so101_sim.masks_of(paths["masks"]))
    assert [len(q) for q in states] == [20, 20]
    assert min(ious.values()) >= 0.97, ious

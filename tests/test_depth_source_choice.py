"""The recipe's depth section and DA3's monocular metric model (random weights: no
download is possible here, so the plumbing is checked against DA3's own ``inference()``
and its metric rule, not the accuracy of the depth)."""

import numpy as np
import pytest

from imac_data.errors import InputError
from imac_data.recipes import DepthSection, parse_recipe
from imac_data.sources.depth import NoDepth, RecordedDepth, check_depth_inputs, make_depth_source, uses_monocular


def test_depth_sections_choose_the_source_and_fail_early(tmp_path):
    assert isinstance(make_depth_source(DepthSection(source="none"), "", 3), NoDepth)
    assert isinstance(make_depth_source(DepthSection(), "", 3), RecordedDepth)
    assert uses_monocular(2) and not uses_monocular(3)
    with pytest.raises(InputError, match=r"r.yaml: depth.monocular_model: the Depth Anything 3 model directory "
                                         r".*/nowhere does not exist"):
        check_depth_inputs(DepthSection(source="da3", monocular_model=str(tmp_path / "nowhere")), "r.yaml", 2)
    assert check_depth_inputs(DepthSection(source="da3"), "r.yaml", 3) == "depth-anything/DA3-BASE"
    (tmp_path / "w").mkdir()
    assert check_depth_inputs(DepthSection(source="da3", model="w"), str(tmp_path / "r.yaml"), 3) == \
        str(tmp_path / "w")  # relative to the recipe


def test_recipe_depth_section_errors_name_the_field():
    base = {"name": "x", "task": "t", "robot": {"platform": "aloha_sim"}, "source": {"type": "aloha_sim"}}
    with pytest.raises(InputError, match=r"r.yaml: depth.source: must be one of \['recorded', 'da3', 'none'\]"):
        check_depth_inputs(parse_recipe({**base, "depth": {"source": "lidar"}}, "r.yaml").depth, "r.yaml", 3)
    with pytest.raises(InputError, match=r"depth.feature: a LeRobot source has no HDF5 depth"):
        parse_recipe({**base, "cameras": {"calibration": "c.json"},
                      "source": {"type": "lerobot", "path": "/data/ds"}}, "r.yaml")
    with pytest.raises(InputError, match=r"source: type lerobot needs 'path'"):
        parse_recipe({**base, "cameras": {"calibration": "c.json"}, "source": {"type": "lerobot"},
                      "depth": {"source": "none"}}, "r.yaml")
    with pytest.raises(InputError, match=r"\['cameras'\] only apply to source.type lerobot"):
        parse_recipe({**base, "source": {"type": "aloha_sim", "cameras": {"a": "b"}}}, "r.yaml")


def test_da3_monocular_metric_model_follows_das_own_inference_and_metric_rule():
    pytest.importorskip("depth_anything_3")
    from imac_data.sources.da3 import DepthAnything3Metric

    model = DepthAnything3Metric.random_init("da3metric-large", device="cpu", process_res=42, batch_size=2)
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (3, 28, 42, 3), dtype=np.uint8)  # 28x42: the processing size itself
    K = np.array([[40.0, 0.0, 20.5], [0.0, 40.0, 13.5], [0.0, 0.0, 1.0]])
    depth = model.predict([images], [K])[0]
    assert depth.shape == (3, 28, 42) and depth.dtype == np.float32 and (depth > 0).all()
    raw = model._api_model.inference([images[2]], process_res=42).depth[0]  # DA3's own pipeline, unscaled
    np.testing.assert_allclose(depth[2], raw * 40.0 / 300.0, rtol=1e-4)  # metres = focal * output / 300
    K2 = K.copy()
    K2[:2, :2] *= 2  # twice the focal length: twice as far
    np.testing.assert_allclose(model.predict([images[:1]], [K2])[0], 2 * depth[:1], rtol=1e-5)
    assert model.describe()["kind"] == "depth_anything_3_metric"

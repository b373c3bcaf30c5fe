"""The depth-sensor faults of the calibration benchmark's ``sensor`` case (benchmarks/calibration_scenes.py), checked
against their definition on a synthetic step: noise that grows with the square of the distance, holes, and flying
pixels only at the edge and only between its two sides."""

from __future__ import annotations

import numpy as np

from benchmarks.calibration_scenes import sensor_faults


def test_sensor_faults_follow_their_definition_on_a_step():
    H, W = 120, 160
    d = np.full((H, W), 1000.0)  # 1 m on the left half, 2 m on the right, a hole of no depth in a corner
    d[:, W // 2:] = 2000.0
    d[:10, :10] = 0.0
    out = sensor_faults(d, np.random.default_rng(0), axial=0.002, holes=0.05, hole_px=6, flying=0.5)
    assert (out[:10, :10] == 0).all()  # invalid stays invalid
    holes = (out == 0) & (d > 0)
    assert 0.03 < holes.mean() < 0.07
    inner = np.zeros((H, W), bool)
    inner[:, 2:W // 2 - 2] = inner[:, W // 2 + 2:-2] = True  # away from the edge
    for z, side in ((1.0, slice(2, W // 2 - 2)), (2.0, slice(W // 2 + 2, W - 2))):
        got = out[:, side][out[:, side] > 0] / 1000.0 - z
        assert abs(got.std() / (0.002 * z**2) - 1) < 0.05 and abs(got.mean()) < 1e-4  # sigma = 0.002 z^2 m
    edge = out[:, W // 2 - 1:W // 2 + 1]
    flew = (edge > 1000 + 10) & (edge < 2000 - 10)
    assert 0.3 < flew[edge > 0].mean() < 0.7  # about half the edge pixels fly, between their two sides
    assert not ((out[inner] > 1050) & (out[inner] < 1950)).any()  # and nothing away from the edge

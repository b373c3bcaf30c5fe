"""The small world-model workload that ``model_rollout`` and ``evaluate_closed_loop`` share:
the experiment's model config at a tiny size, and recorded frames as model mosaics."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
CHUNK = 8  # H: frames per chunk
DATASET_HW = (96, 128)  # the recorded episode (and control streams) per view
MODEL_HW = (48, 64)  # the model's frames per view


def one_thread() -> None:
    """Timings on one core, with no spinning OpenMP pool."""
    import torch

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    torch.set_num_threads(1)


def experiment_spec():
    """``imac_model/configs/experiment.yaml``'s backbone, conditioning and flow at MODEL_HW."""
    from imac_model.config import ModelSpec, load_run_config

    run_cfg = load_run_config(REPO / "imac_model" / "configs" / "experiment.yaml")
    return ModelSpec(backbone=run_cfg.backbone, conditioning=run_cfg.conditioning, flow=run_cfg.flow, views=VIEWS,
                     view_height=MODEL_HW[0], view_width=MODEL_HW[1], chunk=CHUNK, action_dim=14, fps=25.0)


def recorded_mosaics(ep, codec, frames, size=MODEL_HW):
    """Mosaics ``(n, 3, 2h, 3w)`` of the recorded RGB and colour-coded depth at ``frames``."""
    import torch

    from imac_data.core.metric_depth import depth_from_millimetres
    from imac_model.data import mosaic

    rgb = torch.stack([torch.as_tensor(ep.images[v][frames]).permute(0, 3, 1, 2).float() / 255 for v in VIEWS], 1)
    depth = torch.stack([codec.encode(torch.as_tensor(depth_from_millimetres(ep.depth_mm[v][frames])), channel_axis=-3)
                         for v in VIEWS], 1)
    return mosaic.assemble(mosaic.resize_frames(rgb, size), mosaic.resize_frames(depth, size, kind="depth"))

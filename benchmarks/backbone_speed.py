"""CPU cost of the ranking benchmark's backbone candidates: seconds of one training step and
samples per CPU-hour, one thread, at the benchmark's mosaic (two 48x64 views, chunks of 1 + 8
frames, motion+contact). Run it on an idle machine::

    python -m benchmarks.backbone_speed --json benchmarks/results/backbone_speed.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from imac_model.config import BackboneConfig, ConditioningConfig, FlowConfig, ModelSpec, SmallDiTConfig, UNetConfig
from imac_model.data.batch import ChunkBatch
from imac_model.models.world_model import WorldModel

CANDIDATES = {
    # the previous CPU preset: 16x16-pixel tokens (unshuffle 4 x patch 4), 3x4 tokens per view
    "small_dit_p16": BackboneConfig(kind="small", small=SmallDiTConfig(unshuffle=4, patch=4, dim=128, depth=4, heads=4)),
    # finer DiT tokens: 8x8 pixels (unshuffle 4 x patch 2), 6x8 tokens per view
    "small_dit_p8": BackboneConfig(kind="small", small=SmallDiTConfig(unshuffle=4, patch=2, dim=128, depth=4, heads=4)),
    # the U-Net of imac_model/configs/ranking.yaml: full resolution
    "unet": BackboneConfig(kind="unet", unet=UNetConfig(channels=(32, 64, 96, 128), blocks=2, frame_dim=16)),
}


def batch(B: int, g: torch.Generator) -> ChunkBatch:
    H, h, w = 8, 96, 128
    return ChunkBatch(reference=torch.rand(B, 3, h, w, generator=g), actions=torch.randn(B, H, 14, generator=g),
                      controls={s: torch.rand(B, H, 3, h, w, generator=g) for s in ("motion", "contact_s2g",
                                                                                   "contact_r2s")},
                      future=torch.rand(B, H, 3, h, w, generator=g))


def measure(name: str, backbone: BackboneConfig, batch_size: int, steps: int) -> dict:
    spec = ModelSpec(backbone=backbone, conditioning=ConditioningConfig(mode="motion+contact"),
                     flow=FlowConfig(prediction="data"), views=("cam_workspace", "cam_right_wrist"), view_height=48,
                     view_width=64, chunk=8, action_dim=14, fps=10.0)
    torch.manual_seed(0)
    model = WorldModel(spec)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    g = torch.Generator().manual_seed(0)
    data = batch(batch_size, g)
    for _ in range(2):  # warm-up
        model(data, generator=g).loss.backward()
        opt.step()
        opt.zero_grad()
    t0 = time.process_time()
    for _ in range(steps):
        loss = model(data, generator=g).loss
        loss.backward()
        opt.step()
        opt.zero_grad()
    per_step = (time.process_time() - t0) / steps
    return {"backbone": name, "parameters": sum(p.numel() for p in model.parameters()), "batch_size": batch_size,
            "cpu_s_per_step": round(per_step, 3), "samples_per_cpu_hour": round(3600 * batch_size / per_step)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--json")
    args = p.parse_args()
    torch.set_num_threads(1)
    rows = [measure(n, c, args.batch_size, args.steps) for n, c in CANDIDATES.items()]
    for r in rows:
        print(json.dumps(r))
    if args.json:
        Path(args.json).write_text(json.dumps({"threads": 1, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()

"""Write a PNG mosaic of every stream of one frame of a built dataset (README picture).

    .venv/bin/python scripts/stream_mosaic.py --repo local/aloha_sim_transfer_cube --frame 60 --out docs/streams.png
"""

import argparse

import cv2
import numpy as np

from imac_data import lerobot_compat as lr

ROWS = ("observation.images", "observation.depth", "control.motion", "control.contact_r2s", "control.contact_s2g")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--repo", default="local/aloha_sim_transfer_cube")
    p.add_argument("--root", default=None)
    p.add_argument("--frame", type=int, default=60)
    p.add_argument("--out", default="docs/streams.png")
    args = p.parse_args()
    ds = lr.LeRobotDataset(args.repo, root=args.root)
    item = ds[args.frame]
    cams = [k.split(".", 2)[2] for k in ds.meta.video_keys if k.startswith("observation.images.")]
    rows = []
    for prefix in ROWS:
        tiles = []
        for cam in cams:
            img = (item[f"{prefix}.{cam}"].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
            img = cv2.resize(img, (320, 240), interpolation=cv2.INTER_NEAREST)
            cv2.putText(img, f"{prefix}.{cam}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
            tiles.append(img)
        rows.append(np.concatenate(tiles, axis=1))
    cv2.imwrite(args.out, cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

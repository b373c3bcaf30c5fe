"""What rebuilding contact images from a pack costs a training step (``CONTACT=rebuild``,
:class:`imac_model.pipelines.packed_contact.PackedContact`): milliseconds a chunk on one device
for a batch of the pack's chunks from their recorded references, brute force (the GPU's search)
against KD-trees (the CPU's), the searches' sizes, and how far the two methods' images differ
(an oracle check where the GPU runs it: the KD-trees are exact)::

    python -m benchmarks.packed_contact --pack runs/side_settled/gpu/pack.npz --chunks 8
    python -m benchmarks.packed_contact --pack ... --chunks 256 --device cuda --json contact.json   # on a GPU
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from imac_model.pipelines.packed_contact import PackedContact
from imac_model.training.pack import Pack


def _timed(fn, device: torch.device, repeats: int):
    fn()  # warm-up: CUDA's set-up, the first allocations
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(repeats):
        out = fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return out, (time.perf_counter() - t0) / repeats


def measure(pack: Pack, chunks: int, methods: tuple[str, ...], repeats: int = 1) -> dict:
    """Per method: seconds for ``chunks`` of the pack's training chunks, ms a chunk; the first method's
    images against each other's (largest difference, share of differing pixels)."""
    packed = PackedContact.from_pack(pack)
    index = pack.train[:chunks]
    reference = pack.tensors["reference"][index].float() / 255.0
    device = reference.device
    rows, images = {}, {}
    for method in methods:
        packed.method = method
        (controls, _), seconds = _timed(lambda: packed.controls(reference, index), device, repeats)
        images[method] = controls
        rows[method] = {"seconds": round(seconds, 4), "ms_per_chunk": round(1000 * seconds / len(index), 2)}
        print(json.dumps({method: rows[method]}), flush=True)
    first = methods[0]
    for method in methods[1:]:
        diff = torch.stack([(images[method][s] - images[first][s]).abs() for s in images[first]])
        rows[method]["max_difference_to_" + first] = round(float(diff.max()) * 255, 2)  # colour levels
        rows[method]["share_differing"] = float((diff > 0).float().mean())
    t = packed.t
    robot = (t["robot_depth"][index] > 0).flatten(1).sum(1).float().mean()
    sizes = {"chunks": len(index), "views": list(packed.views), "steps": int(t["robot_depth"].shape[1]),
             "gripper_points": int(t["gripper_samples"].shape[0]), "robot_pixels_a_chunk": round(float(robot)),
             "scene_pixels_a_view": int(t["ref_mask"].shape[-1] * t["ref_mask"].shape[-2])}
    return {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu", "torch": torch.__version__,
            **sizes, "methods": rows}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.packed_contact", description=__doc__.split("\n\n")[0])
    p.add_argument("--pack", required=True)
    p.add_argument("--chunks", type=int, default=8)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--methods", nargs="+", default=["kdtree", "brute"], choices=["kdtree", "brute"])
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--json", help="also write the figures here")
    args = p.parse_args(argv)
    if args.device == "cpu":
        torch.set_num_threads(1)
    result = measure(Pack(args.pack, args.device), args.chunks, tuple(args.methods), args.repeats)
    print(json.dumps(result, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

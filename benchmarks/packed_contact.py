"""What rebuilding contact images from a pack costs a training step (``ABLATION=contact``,
:class:`imac_model.pipelines.packed_contact.PackedContact`): milliseconds a chunk on one device
for a batch of the pack's chunks from their recorded references, brute force (the GPU's search)
against KD-trees (the CPU's; where pykdtree is installed, which the GPU machine lacks), the
searches' sizes, how far the methods' images differ, and on a GPU how far its images are from the
CPU's on the first ``--check`` chunks (the oracle there)::

    python -m benchmarks.packed_contact --pack runs/side_settled/gpu/pack.npz --chunks 8
    python -m benchmarks.packed_contact --pack ... --chunks 256 --device cuda --json contact.json   # on a GPU
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import time

import torch

from imac_model.data.pack import Pack
from imac_model.pipelines.packed_contact import PackedContact
from imac_model.training.runtime import fast_kernels


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


def _difference(a: dict, b: dict) -> dict:
    diff = torch.stack([(a[s].cpu() - b[s].cpu()).abs() for s in a])
    return {"max_difference_levels": round(float(diff.max()) * 255, 2), "share_differing": float((diff > 0).float().mean())}


def measure(pack: Pack, chunks: int, methods: tuple[str, ...], repeats: int = 1, check: int = 4) -> dict:
    """Per method: seconds for ``chunks`` of the pack's training chunks, ms a chunk; each method's images
    against the first's (largest difference in colour levels, share of differing values); on a GPU, its
    first ``check`` chunks against the CPU's."""
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
    for method in methods[1:]:
        rows[method]["against_" + methods[0]] = _difference(images[method], images[methods[0]])
    cpu_check = None
    if device.type == "cuda" and check > 0:
        cpu = PackedContact({k: v.cpu() for k, v in pack.tensors.items() if k.startswith("geometry.")},
                            pack.geometry, method="kdtree" if _has_kdtree() else "brute")
        few = {s: v[:check] for s, v in images[methods[0]].items()}
        cpu_check = {"chunks": min(check, len(index)), "cpu_method": cpu.method,
                     **_difference(few, cpu.controls(reference[:check].cpu(), index[:check].cpu())[0])}
        print(json.dumps({"cpu_check": cpu_check}), flush=True)
    t = packed.t
    robot = (t["robot_depth"][index] > 0).flatten(1).sum(1).float().mean()
    sizes = {"chunks": len(index), "views": list(packed.views), "steps": int(t["robot_depth"].shape[1]),
             "gripper_points": int(t["gripper_samples"].shape[0]), "robot_pixels_a_chunk": round(float(robot)),
             "scene_pixels_a_view": int(t["ref_mask"].shape[-1] * t["ref_mask"].shape[-2])}
    return {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu", "torch": torch.__version__,
            **sizes, "methods": rows, "cpu_check": cpu_check}


def _has_kdtree() -> bool:
    return importlib.util.find_spec("pykdtree") is not None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.packed_contact", description=__doc__.split("\n\n")[0])
    p.add_argument("--pack", required=True)
    p.add_argument("--chunks", type=int, default=8)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--methods", nargs="+", choices=["kdtree", "brute"],
                   help="default: brute, and kdtree where pykdtree is installed")
    p.add_argument("--check", type=int, default=4, help="on a GPU: chunks also painted on the CPU, compared")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--json", help="also write the figures here")
    args = p.parse_args(argv)
    if args.device == "cpu":
        torch.set_num_threads(1)
    fast_kernels()  # what the trainer sets (contact_batch keeps full float32 for itself)
    methods = tuple(args.methods or (["brute"] + (["kdtree"] if _has_kdtree() else [])))
    result = measure(Pack(args.pack, args.device), args.chunks, methods, args.repeats, args.check)
    print(json.dumps(result, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The plan (``imac-model plan``) against memory measured on the CPU.

    python -m benchmarks.model_plan [--part states sharded activations] [--json PATH]

Workload: a Wan world model whose transformer is 1024 wide (8 heads of 128), FFN 4096, 5 blocks
(94.5 M trainable parameters with the three control layers: 1.89 GB of predicted training
states), a tiny VAE, ``motion+contact``, fp32:

* ``states``: one process builds the model, the trainer's EMA, the gradients (one backward on
  a one-token-per-frame batch) and AdamW's moments (first step); each phase's growth of the
  resident set against the plan's bytes for the unsharded trainer;
* ``sharded``: the same on 2 gloo processes with the trainer's FSDP2 wrapping: per-rank growth
  against the plan's bytes over 2 GPUs;
* ``activations``: a forward of the denoiser with 2 blocks at the paper's 882 tokens with the
  graph held, against the plan's count of what autograd saves (meta device).

Measured = growth of VmRSS in a process started with ``MALLOC_MMAP_THRESHOLD_=65536`` (glibc then
returns every freed large block, so transients leave the resident set; the script re-executes
itself with it). Prints JSON; exits 1 when a total is more than 15 % off the prediction.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

PARTS = ("states", "sharded", "activations")
TOLERANCE = 0.15
TRANSFORMER = dict(num_attention_heads=8, attention_head_dim=128, ffn_dim=4096, num_layers=5, text_dim=1024,
                   freq_dim=256)
TINY_VAE = dict(base_dim=8, decoder_base_dim=8, dim_mult=[1, 1, 1, 1], num_res_blocks=1)


def rss() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS")


def spec(views: int = 32, layers: int | None = None, chunk: int = 4):
    from imac_model.config import BackboneConfig, ConditioningConfig, FlowConfig, ModelSpec, WanConfig

    tr = {**TRANSFORMER, **({"num_layers": layers} if layers else {})}
    wan = WanConfig(transformer=tr, vae=TINY_VAE, context_tokens=16)
    return ModelSpec(backbone=BackboneConfig(kind="wan", wan=wan), conditioning=ConditioningConfig(),
                     flow=FlowConfig(), views=("a", "b", "c"), view_height=views, view_width=views, chunk=chunk,
                     action_dim=14, fps=30.0)


def predicted_states(world: int) -> dict[str, float]:
    """The plan's bytes for the states of :func:`spec`, unsharded or over ``world`` ranks."""
    from imac_model.training import plan

    counts = plan.parameter_counts(plan.meta_model(spec()))
    zero = {"checkpointing": 0, "no_checkpointing": 0, "encode_chunk_peak": 0}
    setting = plan.Setting("measured", world, strategy="fsdp2" if world > 1 else "none")
    m = plan.memory(counts, zero, zero, setting, micro_batch=1, bf16=False, checkpointing=False)
    return {"weights": m["weights"] + m["vae"], "ema": m["ema"], "gradients": m["gradients"], "adamw": m["adamw"],
            "trainable": counts["trainable"]}


def _states(world: int = 1, rank: int = 0) -> dict:
    import torch

    from imac_model.data.batch import ChunkBatch
    from imac_model.models.world_model import WorldModel
    from imac_model.training.train import EMA

    torch.set_num_threads(1)
    # before the baseline: the libraries' first-use allocations (diffusers' modules, autograd's engine)
    pred = predicted_states(world)
    torch.randn(256, 256) @ torch.randn(256, 256)
    torch.ones(2, requires_grad=True).sum().backward()
    got: dict[str, int] = {}
    keep = []

    def phase(name, fn):
        before = rss()
        keep.append(fn())
        got[name] = rss() - before

    s = spec()

    def build():
        torch.manual_seed(0)
        model = WorldModel(s)
        if world > 1:
            from imac_model.training.sharding import shard_world_model

            mesh = torch.distributed.device_mesh.init_device_mesh("cpu", (world,))
            shard_world_model(model, mesh, bf16=False)
        return model

    phase("weights", build)
    model = keep[-1]
    phase("ema", lambda: EMA(model, 0.999))
    g = torch.Generator().manual_seed(rank)
    Hm, Wm = s.mosaic_hw
    batch = ChunkBatch(reference=torch.rand(1, 3, Hm, Wm, generator=g), actions=torch.zeros(1, s.chunk, 14),
                       controls={k: torch.rand(1, s.chunk, 3, Hm, Wm, generator=g) for k in s.conditioning.streams},
                       future=torch.rand(1, s.chunk, 3, Hm, Wm, generator=g))
    phase("gradients", lambda: model(batch, generator=g).loss.backward())
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    phase("adamw", optimizer.step)
    rows = {k: {"predicted_mb": round(pred[k] / 1e6, 1), "measured_mb": round(got[k] / 1e6, 1),
                "ratio": round(got[k] / pred[k], 4)} for k in got}
    total_p, total_m = sum(pred[k] for k in got), sum(got.values())
    rows["total"] = {"predicted_mb": round(total_p / 1e6, 1), "measured_mb": round(total_m / 1e6, 1),
                     "ratio": round(total_m / total_p, 4)}
    return {"world": world, "rank": rank, "trainable": pred["trainable"], "rows": rows}


def _sharded_rank(rank: int, world: int, port: int, out: str) -> None:
    import torch.distributed as dist

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    try:
        with open(f"{out}.{rank}.json", "w") as f:
            json.dump(_states(world, rank), f)
    finally:
        dist.destroy_process_group()


def _sharded(world: int = 2) -> list[dict]:
    import socket

    import torch.multiprocessing as mp

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    out = os.path.join(tempfile.mkdtemp(prefix="model_plan_"), "rank")
    mp.spawn(_sharded_rank, args=(world, port, out), nprocs=world)
    return [json.load(open(f"{out}.{r}.json")) for r in range(world)]


def _activations(layers: int = 2) -> dict:
    """Predicted: the plan's count on the meta device (fp32, flash-style attention; the CPU's
    SDPA keeps the same tensors). Measured: RSS growth of the real forward with its graph."""
    import torch

    from imac_model.models.world_model import WorldModel
    from imac_model.training import plan

    torch.set_num_threads(2)
    s = spec(views=224, layers=layers, chunk=8)
    meta = plan.meta_model(s)
    tok = plan.token_counts(s, meta)
    predicted = plan.saved_bytes(meta, tok, dtype=torch.float32)
    torch.manual_seed(0)
    model = WorldModel(s)
    ref, future, _, controls = plan._denoiser_inputs(model, tok, 1, torch.float32)
    ref, future = torch.randn(ref.shape), torch.randn(future.shape)
    controls = {k: torch.randn(v.shape) for k, v in controls.items()}
    tau = torch.full((1,), 0.5)
    with torch.no_grad():  # kernels and their workspaces before the baseline
        model.velocity(future, tau, reference_latent=ref, control_latents=controls)
    before = rss()
    out = model.velocity(future, tau, reference_latent=ref, control_latents=controls)
    grown = rss() - before
    del out
    return {"layers": layers, "tokens": tok["per_chunk"], "predicted_mb": round(predicted / 1e6, 1),
            "measured_mb": round(grown / 1e6, 1), "ratio": round(grown / predicted, 4)}


def run(parts=PARTS) -> dict:
    report: dict = {"tolerance": TOLERANCE}
    for part in parts:
        t0 = time.time()
        report[part] = {"states": _states, "sharded": _sharded, "activations": _activations}[part]()
        report[f"{part}_seconds"] = round(time.time() - t0, 1)
    ratios = []
    if "states" in report:
        ratios.append(report["states"]["rows"]["total"]["ratio"])
    ratios += [r["rows"]["total"]["ratio"] for r in report.get("sharded", [])]
    if "activations" in report:
        ratios.append(report["activations"]["ratio"])
    report["within_tolerance"] = all(abs(r - 1) <= TOLERANCE for r in ratios)
    report["load_avg"] = list(os.getloadavg())
    return report


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--part", nargs="+", choices=PARTS, default=list(PARTS))
    p.add_argument("--json", help="also write the report here")
    args = p.parse_args(argv)
    report = run(tuple(args.part))
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")
    return 0 if report["within_tolerance"] else 1


if __name__ == "__main__":
    if os.environ.get("MALLOC_MMAP_THRESHOLD_") != "65536":  # freed transients must leave the resident set
        os.environ["MALLOC_MMAP_THRESHOLD_"] = "65536"
        os.execv(sys.executable, [sys.executable, "-m", "benchmarks.model_plan", *sys.argv[1:]])
    sys.exit(main())

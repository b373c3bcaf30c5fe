"""Wan2.2-TI2V-5B with fewer blocks, measured on a GPU and extrapolated to 30, against the plan.

    python -m benchmarks.model_scale [--blocks 2 4] [--micro-batch 1] [--steps 4] [--json PATH]
    python -m benchmarks.model_scale --quick      # a narrow model on the CPU: checks the script, measures nothing

Workload: the real config (``imac_model/configs/wan2.2_ti2v_5b.yaml``) with ``backbone.wan.num_layers`` N,
random weights of the real shapes (VAE included), 224x224 views, 1 + 8 frames, ``motion+contact``, the
trainer's own FSDP2 wrapping on one process (bf16 policy, gradient checkpointing, VAE slicing), AdamW and the
EMA. Each N runs in its own process. After two warm-up steps: the step time (forward with the VAE encodes,
backward, clipping, AdamW, EMA; ``torch.cuda.synchronize`` around it), the peak of
``torch.cuda.max_memory_allocated``, and the time of sampling one chunk (20 Euler steps, after a one-step
warm-up sample). The plan's bytes for
the same N are printed beside the peak.

Extrapolation to 30 blocks: per block = (x(N2) - x(N1)) / (N2 - N1), then x(30) = x(N2) + (30 - N2) x per
block, for the step time, the sampling time and the peak. The plan's terms are linear in the blocks too
(states with the parameters, checkpointed activations with the block inputs), so its 30-block figure is the
one to compare with. On one GPU the 30-block states (100 GB) do not fit: the extrapolated peak is what an
80 GB card would need, the 8-GPU figure divides the states by 8 (``docs/scale.md``).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import tempfile
import time
from pathlib import Path
from queue import Empty

REAL = Path(__file__).resolve().parent.parent / "imac_model" / "configs" / "wan2.2_ti2v_5b.yaml"
QUICK = {"backbone.wan.transformer.num_attention_heads": 2, "backbone.wan.transformer.attention_head_dim": 32,
         "backbone.wan.transformer.ffn_dim": 128, "backbone.wan.transformer.text_dim": 64,
         "backbone.wan.vae.base_dim": 8, "backbone.wan.vae.decoder_base_dim": 8,
         "backbone.wan.vae.dim_mult": [1, 1, 1, 1], "backbone.wan.vae.num_res_blocks": 1,
         "data.view_height": 32, "data.view_width": 32, "train.mixed_precision": "no"}


def _overrides(blocks: int, micro_batch: int, quick: bool) -> dict:
    over = {"backbone.wan.pretrained": None, "backbone.wan.num_layers": blocks, "train.batch_size": micro_batch,
            "train.output_dir": tempfile.mkdtemp(prefix="model_scale_")}
    return {**over, **(QUICK if quick else {})}


def _load(overrides: dict):
    from imac_model.config import load_run_config

    run = load_run_config(REAL)
    data = run.to_dict()
    for key, value in overrides.items():  # nested keys (backbone.wan.transformer.x) that replace() cannot reach
        node = data
        *parents, leaf = key.split(".")
        for part in parents:
            node = node[part]
        node[leaf] = value
    from imac_model.config import RunConfig, parse

    return parse(RunConfig, data, "")


def _measure(blocks: int, micro_batch: int, steps: int, quick: bool, queue) -> None:
    import resource

    import torch

    from imac_model.data.batch import ChunkBatch
    from imac_model.models.world_model import WorldModel
    from imac_model.training import plan
    from imac_model.training.sharding import ShardedRuntime
    from imac_model.training.train import EMA, balanced_loss

    run = _load(_overrides(blocks, micro_batch, quick))
    spec = plan.plan_spec(run)
    predicted = plan.make_plan(run, gpus=(1,), micro_batch=micro_batch, flops=False)
    predicted = next(r for r in predicted["settings"] if r["setting"]["name"] == "fsdp2, 1 GPU")["bytes"]
    runtime = ShardedRuntime(run, Path(run.train.output_dir))
    cuda = runtime.device.type == "cuda"
    try:
        torch.manual_seed(0)
        model = runtime.wrap(WorldModel(spec))
        params = [p for p in model.parameters() if p.requires_grad]
        optimizer = torch.optim.AdamW(params, lr=1e-5)
        ema = EMA(model, 0.9999)
        g = torch.Generator().manual_seed(0)
        Hm, Wm = spec.mosaic_hw
        b, H = micro_batch, spec.chunk

        def rand(*shape):
            return torch.rand(*shape, generator=g).to(runtime.device)

        batch = ChunkBatch(reference=rand(b, 3, Hm, Wm), actions=rand(b, H, spec.action_dim),
                           controls={s: rand(b, H, 3, Hm, Wm) for s in spec.conditioning.streams},
                           future=rand(b, H, 3, Hm, Wm))

        def sync():
            if cuda:
                torch.cuda.synchronize()

        def step(i: int) -> None:
            out = model(batch, generator=torch.Generator().manual_seed(i))
            balanced_loss(out, runtime).backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0)
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
            ema.update(model, i + 1)

        for i in range(2):
            step(i)
        if cuda:
            torch.cuda.reset_peak_memory_stats()
        sync()
        t0 = time.perf_counter()
        for i in range(steps):
            step(2 + i)
        sync()
        step_s = (time.perf_counter() - t0) / steps
        peak = torch.cuda.max_memory_allocated() if cuda else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        model.eval()
        model.sample(batch, steps=1, generator=torch.Generator().manual_seed(0))  # the decoder's first-call costs
        sync()
        t0 = time.perf_counter()
        model.sample(batch, steps=spec.flow.sample_steps, generator=torch.Generator().manual_seed(0))
        sync()
        sample_s = time.perf_counter() - t0
        queue.put({"blocks": blocks, "micro_batch": micro_batch, "device": str(runtime.device),
                   "gpu": torch.cuda.get_device_name() if cuda else None, "step_s": step_s, "sample_chunk_s": sample_s,
                   "peak_bytes": peak, "peak_kind": "cuda max_memory_allocated" if cuda else "process max RSS",
                   "predicted_bytes": predicted["total"]})
    finally:
        runtime.close()


def run(blocks=(2, 4), micro_batch: int = 1, steps: int = 4, quick: bool = False) -> dict:
    ctx = mp.get_context("spawn")
    rows = []
    for n in blocks:
        queue = ctx.Queue()
        proc = ctx.Process(target=_measure, args=(n, micro_batch, steps, quick, queue))
        proc.start()
        while True:  # a measurement that dies (an import, out of memory) must not leave us waiting
            try:
                rows.append(queue.get(timeout=5))
                break
            except Empty:
                if not proc.is_alive():
                    raise RuntimeError(f"the {n}-block measurement died (exit code {proc.exitcode}); see above")
        proc.join()
    report = {"rows": rows, "quick": quick, "load_avg": list(os.getloadavg())}
    if len(rows) >= 2:
        a, b = rows[-2], rows[-1]
        span = b["blocks"] - a["blocks"]
        report["extrapolated_30_blocks"] = {
            key: b[key] + (30 - b["blocks"]) * (b[key] - a[key]) / span
            for key in ("step_s", "sample_chunk_s", "peak_bytes", "predicted_bytes")}
    return report


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--blocks", type=int, nargs="+", default=[2, 4])
    p.add_argument("--micro-batch", type=int, default=1)
    p.add_argument("--steps", type=int, default=4)
    p.add_argument("--quick", action="store_true", help="a narrow model on the CPU (checks the script only)")
    p.add_argument("--json")
    args = p.parse_args(argv)
    report = run(tuple(args.blocks), args.micro_batch, args.steps, args.quick)
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

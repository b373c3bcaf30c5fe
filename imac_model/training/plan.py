"""The memory and compute plan of a run (``imac-model plan``): the world model built on the meta
device (no weights, no GPU, no dataset), its parameters per component, the bytes per GPU for
weights, gradients, optimizer states and EMA without sharding and sharded over N GPUs, the
activations per transformer block with and without gradient checkpointing, the tokens per
chunk, the FLOPs of training and of sampling a chunk, and whether it fits a GPU's memory.

Activations are what autograd saves for backward in one forward of the denoiser, counted on
the meta device (deduplicated by storage, parameters excluded), with attention counted as
flash / memory-efficient attention keeps it. ``docs/scale.md`` has the formulas and the checks
against measured memory."""

from __future__ import annotations

import dataclasses
import json
import math
import weakref

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten
from torch.utils.flop_counter import FlopCounterMode

from imac_data.errors import InputError
from imac_model.config import ModelSpec, RunConfig
from imac_model.models.backbones.wan import wan_configs
from imac_model.models.world_model import WorldModel

GB = 1e9
GiB = 2 ** 30
DEFAULT_VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")


# --------------------------------------------------------------------------- the model on the meta device


def plan_spec(run: RunConfig, *, views: int | None = None, action_dim: int = 14) -> ModelSpec:
    """The model a run would train, from its config alone (a dataset fixes these facts in
    training: the plan needs ``data.view_width`` and ``data.chunk`` set)."""
    if run.backbone.kind != "wan":
        raise InputError(f"backbone.kind: the plan covers the Wan backbone (got {run.backbone.kind!r})")
    d = run.data
    for name in ("view_width", "chunk"):
        if getattr(d, name) is None:
            raise InputError(f"data.{name}: the plan reads no dataset; set it in the config")
    names = d.views or DEFAULT_VIEWS[:views or 3]
    if views is not None and len(names) != views:
        names = tuple(f"view{i}" for i in range(views))
    tr, vae = wan_configs(run.backbone.wan)
    wan = dataclasses.replace(run.backbone.wan, pretrained=None, transformer=tr, vae=vae)
    return ModelSpec(backbone=dataclasses.replace(run.backbone, wan=wan), conditioning=run.conditioning,
                     flow=run.flow, views=tuple(names), view_height=d.view_height, view_width=d.view_width,
                     chunk=d.chunk, action_dim=action_dim, fps=30.0)


def meta_model(spec: ModelSpec, num_layers: int | None = None) -> WorldModel:
    if num_layers is not None:
        wan = dataclasses.replace(spec.backbone.wan, num_layers=None,
                                  transformer={**spec.backbone.wan.transformer, "num_layers": num_layers})
        spec = dataclasses.replace(spec, backbone=dataclasses.replace(spec.backbone, wan=wan))
    with torch.device("meta"):
        return WorldModel(spec)


def _numel(params) -> int:
    return sum(p.numel() for p in params)


def parameter_counts(model: WorldModel) -> dict[str, int]:
    bb = model.backbone
    tr = bb.transformer
    out = {"transformer": _numel(tr.parameters()), "block": _numel(tr.blocks[0].parameters()), "blocks": len(tr.blocks)}
    out["transformer_outside_blocks"] = out["transformer"] - _numel(tr.blocks.parameters())
    out["control_layers"] = _numel(model.controls.parameters()) if model.controls is not None else 0
    out["null_context"] = bb.null_context.numel()
    out["action_encoder"] = _numel(model.action_encoder.parameters()) if model.action_encoder is not None else 0
    out["vae"] = _numel(bb.vae.parameters())
    out["trainable"] = _numel(p for p in model.parameters() if p.requires_grad)
    out["frozen"] = _numel(p for p in model.parameters() if not p.requires_grad)
    out["root"] = out["control_layers"] + out["null_context"] + out["action_encoder"]  # FSDP2's root group
    return out


def token_counts(spec: ModelSpec, model: WorldModel) -> dict[str, int]:
    bb = model.backbone
    Hm, Wm = spec.mosaic_hw
    patch = bb.transformer.config.patch_size
    comp = bb.spatial_multiple // patch[1]  # the VAE's spatial compression
    frames = bb.latent_frames(spec.chunk + 1)
    h, w = Hm // comp, Wm // comp
    per_frame = (h // patch[1]) * (w // patch[2])
    return {"mosaic_h": Hm, "mosaic_w": Wm, "frames": spec.chunk + 1, "latent_frames": frames, "latent_h": h,
            "latent_w": w, "per_latent_frame": per_frame, "per_chunk": frames * per_frame,
            "future": (frames - 1) * per_frame, "context": spec.backbone.wan.context_tokens}


# --------------------------------------------------------------------------- activations (meta)


class _FlashAttention(torch.autograd.Function):
    """Stands in for attention while counting: saves what flash / memory-efficient attention
    saves (q, k, v, the output and a float32 log-sum-exp), not the L x L matrix of the math path."""

    @staticmethod
    def forward(ctx, q, k, v):
        out = torch.empty_like(q)
        ctx.save_for_backward(q, k, v, out, torch.empty(q.shape[:-1], device=q.device, dtype=torch.float32))
        return out

    @staticmethod
    def backward(ctx, grad):  # never run: the count needs the forward only
        raise RuntimeError("counting only")


class _CountAttentionAsFlash(TorchFunctionMode):
    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func is torch.nn.functional.scaled_dot_product_attention:
            named = dict(zip(("query", "key", "value"), args[:3]), **(kwargs or {}))
            return _FlashAttention.apply(named["query"], named["key"], named["value"])
        return func(*args, **(kwargs or {}))


def _denoiser_inputs(model: WorldModel, tok: dict, batch: int, dtype):
    C = model.backbone.latent_channels
    kw = dict(device="meta", dtype=dtype)
    ref = torch.empty(batch, C, 1, tok["latent_h"], tok["latent_w"], **kw)
    future = torch.empty(batch, C, tok["latent_frames"] - 1, tok["latent_h"], tok["latent_w"], **kw)
    controls = {s: torch.empty(batch, C, tok["latent_frames"], tok["latent_h"], tok["latent_w"], **kw)
                for s in model.streams}
    return ref, future, torch.full((batch,), 0.5, device="meta"), controls


def saved_bytes(model: WorldModel, tok: dict, *, dtype=torch.bfloat16, flash: bool = True) -> int:
    """Bytes autograd keeps for backward in one forward of the denoiser (one sample)."""
    model = model.to(dtype)
    model.backbone.compute_dtype = dtype
    model.backbone.transformer.disable_gradient_checkpointing()  # the count is of everything a block keeps
    params = {p.untyped_storage()._cdata for p in model.parameters()}
    seen: dict[int, int] = {}

    def pack(t):
        s = t.untyped_storage()
        if s._cdata not in params:
            seen[s._cdata] = s.nbytes()
        return t

    ref, future, tau, controls = _denoiser_inputs(model, tok, 1, dtype)
    context = model.context(torch.empty(1, model.spec.chunk, model.spec.action_dim, device="meta"))
    mode = _CountAttentionAsFlash() if flash else None
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        if mode is not None:
            with mode:
                model.velocity(future, tau, reference_latent=ref, control_latents=controls or None, context=context)
        else:
            model.velocity(future, tau, reference_latent=ref, control_latents=controls or None, context=context)
    return sum(seen.values())


def activations(spec: ModelSpec, tok: dict, layers: int, *, dtype=torch.bfloat16, flash: bool = True) -> dict:
    """Per sample: bytes per block (two blocks minus one), outside the blocks, and the totals
    without and with gradient checkpointing (then every block keeps its input, and one block
    is recomputed at a time)."""
    one = saved_bytes(meta_model(spec, 1), tok, dtype=dtype, flash=flash)
    two = saved_bytes(meta_model(spec, 2), tok, dtype=dtype, flash=flash)
    block, rest = two - one, 2 * one - two
    tc = spec.backbone.wan.transformer
    block_input = tok["per_chunk"] * tc["num_attention_heads"] * tc["attention_head_dim"] * dtype.itemsize
    return {"per_block": block, "outside_blocks": rest, "block_input": block_input, "layers": layers,
            "no_checkpointing": layers * block + rest, "checkpointing": layers * block_input + block + rest}


# --------------------------------------------------------------------------- FLOPs and the VAE's peak (meta)


class _PeakBytes(TorchDispatchMode):
    """Peak bytes of live tensors during a no-grad computation (on meta: storages tracked
    from creation to the last reference), excluding ``exclude`` (the weights)."""

    def __init__(self, exclude=()):
        super().__init__()
        self.live: dict[int, list[int]] = {}
        self.now = self.peak = 0
        self.exclude = {t.untyped_storage()._cdata for t in exclude}

    def _drop(self, key: int) -> None:
        entry = self.live.get(key)
        if entry is not None:
            entry[1] -= 1
            if entry[1] == 0:
                self.now -= entry[0]
                del self.live[key]

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor):
                key = t.untyped_storage()._cdata
                if key in self.exclude:
                    continue
                entry = self.live.get(key)
                if entry is None:
                    self.live[key] = entry = [t.untyped_storage().nbytes(), 0]
                    self.now += entry[0]
                    self.peak = max(self.peak, self.now)
                entry[1] += 1
                weakref.finalize(t, self._drop, key)
        return out


def vae_costs(model: WorldModel, spec: ModelSpec, dtype) -> dict[str, int]:
    """FLOPs and peak bytes of the frozen VAE for one sample: encoding a chunk (1 + H frames:
    the recorded video, or a control video with its black reference slot), the reference
    alone (sampling), decoding a chunk."""
    vae = model.backbone.vae.to(dtype)
    Hm, Wm = spec.mosaic_hw
    out: dict[str, int] = {}
    with torch.no_grad():
        for name, frames in (("encode_chunk", spec.chunk + 1), ("encode_reference", 1)):
            x = torch.empty(1, 3, frames, Hm, Wm, device="meta", dtype=dtype)
            with FlopCounterMode(display=False) as flops, _PeakBytes(exclude=list(vae.parameters())) as peak:
                z = vae.encode(x).latent_dist.mode()
            out[f"{name}_flops"], out[f"{name}_peak"] = flops.get_total_flops(), peak.peak
            if name == "encode_chunk":
                latents = z
        with FlopCounterMode(display=False) as flops, _PeakBytes(exclude=list(vae.parameters())) as peak:
            vae.decode(latents)
        out["decode_chunk_flops"], out["decode_chunk_peak"] = flops.get_total_flops(), peak.peak
    return out


def denoiser_flops(model: WorldModel, tok: dict, dtype) -> int:
    """FLOPs of one call of the denoiser (transformer + control layers) for one sample (freezes
    the meta model: a view of a trainable weight made under no_grad still requires grad, which
    the FLOP counter's module tracker refuses)."""
    model = model.to(dtype).requires_grad_(False)
    model.backbone.compute_dtype = dtype
    ref, future, tau, controls = _denoiser_inputs(model, tok, 1, dtype)
    context = model.context(torch.empty(1, model.spec.chunk, model.spec.action_dim, device="meta"))
    with torch.no_grad(), FlopCounterMode(display=False) as flops:
        model.velocity(future, tau, reference_latent=ref, control_latents=controls or None, context=context)
    return flops.get_total_flops()


# --------------------------------------------------------------------------- bytes per GPU


@dataclasses.dataclass(frozen=True)
class Setting:
    """One way to run: ``strategy`` none (the plain trainer, one GPU) or fsdp2 over ``gpus``."""

    name: str
    gpus: int
    strategy: str = "fsdp2"
    reshard_after_forward: bool = True
    cpu_offload: bool = False


def memory(counts: dict, act: dict, vae: dict, setting: Setting, *, micro_batch: int, bf16: bool,
           checkpointing: bool, ema: bool = True, vae_slicing: bool = False) -> dict[str, float]:
    """Bytes per GPU (and in host memory) of one setting; ``docs/scale.md`` ("The plan") derives
    each term. States: fp32 weights 4, gradients 4, AdamW's two moments 8 and the EMA 4 bytes per
    trainable parameter, divided by the GPUs under fsdp2 (or moved to the host with
    ``cpu_offload``). Transients: the parameter groups gathered in compute precision, one
    block's unsharded gradient and the activations; the VAE's own peak (it encodes before the
    transformer runs); AdamW's temporary: the step's peak is the largest of the three phases."""
    P, N, b = counts["trainable"], setting.gpus, micro_batch
    c = 2 if bf16 else 4  # bytes per parameter in compute precision
    n = N if setting.strategy == "fsdp2" else 1
    states = {"weights": 4 * P / n, "gradients": 4 * P / n, "adamw": 8 * P / n, "ema": 4 * P / n if ema else 0.0}
    host = sum(states.values()) if setting.cpu_offload else 0.0
    if setting.cpu_offload:
        states = {k: 0.0 for k in states}
    out: dict[str, float] = dict(states)
    if setting.strategy == "fsdp2":
        out["vae"] = c * counts["vae"]  # cast to the compute dtype, replicated
        out["gathered"] = (c * (2 * counts["block"] + counts["transformer_outside_blocks"] + counts["root"])
                           if setting.reshard_after_forward else c * P)  # the current and the prefetched block
        out["block_gradients"] = (c + (4 if bf16 else 0)) * counts["block"]  # unsharded + its fp32 reduce copy
    else:
        out["vae"] = 4 * counts["vae"]  # fp32, as built
        out["gathered"] = 2 * P if bf16 else 0.0  # the autocast cache: a bf16 copy of every weight used
        out["block_gradients"] = c * counts["block"]
    out["activations"] = b * (act["checkpointing"] if checkpointing else act["no_checkpointing"])
    out["vae_peak"] = (1 if vae_slicing else b) * vae["encode_chunk_peak"]
    # torch's AdamW on GPU tensors is multi-tensor: one fp32 temporary per parameter (the denominator)
    out["adamw_step"] = 0.0 if setting.cpu_offload else 4 * P / n
    fixed = sum(states.values()) + out["vae"]
    out["total"] = fixed + max(out["gathered"] + out["block_gradients"] + out["activations"], out["vae_peak"],
                               out["adamw_step"])
    out["host"] = host
    return out


def max_micro_batch(counts, act, vae, setting: Setting, *, gpu_bytes: float, reserve: float, **kw) -> int:
    """The largest micro-batch per GPU that fits (0: not even one sample)."""
    fits = lambda b: memory(counts, act, vae, setting, micro_batch=b, **kw)["total"] + reserve <= gpu_bytes  # noqa: E731
    lo, hi = 0, 1
    while fits(hi) and hi < 1 << 16:
        lo, hi = hi, hi * 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


# --------------------------------------------------------------------------- the plan


def make_plan(run: RunConfig, *, gpus: tuple[int, ...] = (1, 8), gpu_gb: float = 80.0, reserve_gb: float = 4.0,
              micro_batch: int | None = None, views: int | None = None, action_dim: int = 14,
              flops: bool = True) -> dict:
    """Everything ``imac-model plan`` prints, as plain data (JSON-ready)."""
    if any(g < 1 for g in gpus) or gpu_gb <= 0 or reserve_gb < 0 or (micro_batch is not None and micro_batch < 1):
        raise InputError("--gpus / --gpu-gb / --reserve-gb / --micro-batch: must be positive")
    spec = plan_spec(run, views=views, action_dim=action_dim)
    model = meta_model(spec)
    counts = parameter_counts(model)
    tok = token_counts(spec, model)
    bf16 = run.train.mixed_precision in ("auto", "bf16")  # auto: bf16 on a GPU that has it
    dtype = torch.bfloat16 if bf16 else torch.float32
    act = activations(spec, tok, counts["blocks"], dtype=dtype)
    act_math = activations(spec, tok, counts["blocks"], dtype=dtype, flash=False)
    vae = vae_costs(model, spec, dtype)
    sh, tc = run.train.sharding, run.train
    checkpointing = spec.backbone.wan.gradient_checkpointing
    kw = dict(bf16=bf16, checkpointing=checkpointing, ema=tc.ema_decay > 0, vae_slicing=spec.backbone.wan.vae_slicing)
    settings = [Setting("no sharding, 1 GPU", 1, strategy="none")]
    for n in gpus:
        settings.append(Setting(f"fsdp2, {n} GPU{'s' if n > 1 else ''}", n,
                                reshard_after_forward=sh.reshard_after_forward))
        if n > 1 and sh.reshard_after_forward:
            settings.append(Setting(f"fsdp2, {n} GPUs, reshard_after_forward false", n, reshard_after_forward=False))
    if 1 in gpus:
        settings.append(Setting("fsdp2, 1 GPU, CPU offload", 1, cpu_offload=True))
    rows = []
    for s in settings:
        b = micro_batch or max(1, math.ceil(tc.batch_size / s.gpus))
        m = memory(counts, act, vae, s, micro_batch=b, **kw)
        mx = max_micro_batch(counts, act, vae, s, gpu_bytes=gpu_gb * GB, reserve=reserve_gb * GB, **kw)
        rows.append({"setting": dataclasses.asdict(s), "micro_batch": b, "bytes": m,
                     "fits": m["total"] + reserve_gb * GB <= gpu_gb * GB, "max_micro_batch": mx})
    plan = {"spec": {"views": list(spec.views), "view_hw": [spec.view_height, spec.view_width], "chunk": spec.chunk,
                     "mode": spec.conditioning.mode},
            "parameters": counts, "tokens": tok, "compute_dtype": str(dtype).removeprefix("torch."),
            "gradient_checkpointing": checkpointing, "activations": act, "activations_math_attention": act_math,
            "vae": vae, "gpu_gb": gpu_gb, "reserve_gb": reserve_gb, "batch_size": tc.batch_size, "settings": rows}
    if flops:
        call = denoiser_flops(model, tok, dtype)
        steps, streams = spec.flow.sample_steps, len(spec.conditioning.streams)
        plan["flops"] = {
            "denoiser_call": call, "sample_steps": steps, "sampler_calls": steps,
            "sample_chunk": steps * call + vae["encode_reference_flops"] + streams * vae["encode_chunk_flops"]
            + vae["decode_chunk_flops"],
            "train_sample": (4 if checkpointing else 3) * call + (1 + streams) * vae["encode_chunk_flops"]}
    return plan


def _gb(x: float) -> str:
    return f"{x / GB:.2f}"


def format_plan(plan: dict, config: str = "") -> str:
    c, t, a, v = plan["parameters"], plan["tokens"], plan["activations"], plan["vae"]
    lines = [f"plan of {config or 'the run'} (meta device: nothing allocated, no weights read)", "parameters:"]
    for key, label in (("transformer", "transformer"), ("control_layers", "control layers"),
                       ("null_context", "null prompt"), ("action_encoder", "action encoder"), ("vae", "VAE (frozen)"),
                       ("trainable", "trainable")):
        n = c[key]
        lines.append(f"  {label:<16}{n:>16,d}  ({f'{n / 1e9:.1f} B' if n >= 1e8 else f'{n / 1e6:.2f} M'})")
    lines.append(f"  one transformer block {c['block']:,d} x {c['blocks']} blocks; outside the blocks "
                 f"{c['transformer_outside_blocks']:,d}")
    lines.append(f"tokens per chunk: {t['per_chunk']} ({t['frames']} frames of {t['mosaic_h']}x{t['mosaic_w']} -> "
                 f"latent {t['latent_frames']} x {t['latent_h']} x {t['latent_w']} -> {t['per_latent_frame']} per latent "
                 f"frame; {t['future']} future), + {t['context']} cross-attention context tokens")
    lines.append(f"activations per sample ({plan['compute_dtype']}, flash attention): {a['per_block'] / 2**20:.1f} MiB "
                 f"per block, {a['outside_blocks'] / 2**20:.1f} MiB outside the blocks; {a['layers']} blocks: "
                 f"{a['no_checkpointing'] / GiB:.2f} GiB without gradient checkpointing, "
                 f"{a['checkpointing'] / GiB:.2f} GiB with it (math attention: "
                 f"{plan['activations_math_attention']['per_block'] / 2**20:.1f} MiB per block); checkpointing is "
                 f"{'on' if plan['gradient_checkpointing'] else 'off'}")
    lines.append(f"VAE, one sample, no grad: encoding a {t['frames']}-frame chunk peaks at "
                 f"{v['encode_chunk_peak'] / GiB:.2f} GiB, decoding at {v['decode_chunk_peak'] / GiB:.2f} GiB")
    if "flops" in plan:
        f = plan["flops"]
        lines.append(f"FLOPs: one denoiser call {f['denoiser_call'] / 1e12:.2f} TFLOP; VAE encode of a chunk "
                     f"{v['encode_chunk_flops'] / 1e12:.2f}, of the reference {v['encode_reference_flops'] / 1e12:.2f}, "
                     f"decode {v['decode_chunk_flops'] / 1e12:.2f} TFLOP")
        lines.append(f"  sampling one chunk: {f['sample_steps']} Euler steps x 1 call = "
                     f"{f['sample_steps'] * f['denoiser_call'] / 1e12:.1f} TFLOP in the transformer, "
                     f"{f['sample_chunk'] / 1e12:.1f} TFLOP with the encodes and the decode")
        lines.append(f"  training one sample: {f['train_sample'] / 1e12:.1f} TFLOP (forward, backward"
                     f"{', recompute' if plan['gradient_checkpointing'] else ''} and the VAE encodes)")
    lines.append(f"memory per GPU in GB (1e9 bytes), global batch {plan['batch_size']}; fits = total + "
                 f"{plan['reserve_gb']:g} GB reserve <= {plan['gpu_gb']:g} GB:")
    cols = ("weights", "gradients", "adamw", "ema", "vae", "gathered", "block_gradients", "activations", "vae_peak",
            "adamw_step")
    lines.append(f"  {'setting':<44}{'b':>4} " + " ".join(f"{k[:10]:>10}" for k in cols) + f" {'total':>8}  fits")
    for r in plan["settings"]:
        m = r["bytes"]
        host = f" (host {_gb(m['host'])})" if m["host"] else ""
        lines.append(f"  {r['setting']['name']:<44}{r['micro_batch']:>4} " + " ".join(f"{_gb(m[k]):>10}" for k in cols)
                     + f" {_gb(m['total']):>8}  {'yes' if r['fits'] else 'NO'} (max micro-batch "
                       f"{r['max_micro_batch']}){host}")
    return "\n".join(lines)


def plan_json(plan: dict) -> str:
    return json.dumps(plan, indent=1)

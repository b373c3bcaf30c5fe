"""The paper's model at the paper's scale: the Wan2.2-TI2V-5B config and its plan (meta device,
against diffusers' own parameter count), real-layout weights saved by diffusers, sharded
training on 2 gloo processes through the training entry point (against one process on the same
global batch, and resumed from its sharded checkpoint), and the plan against measured memory."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from imac_data.cli import main as imac_main
from imac_data.errors import InputError
from imac_data.recipes import RECIPES_DIR
from imac_data.sources.sim.recorder import SimConfig, record_dataset
from imac_model.cli import main as model_main
from imac_model.config import BackboneConfig, ConditioningConfig, FlowConfig, ModelSpec, WanConfig, load_run_config
from imac_model.models.checkpoint import load_world_model
from imac_model.models.world_model import WorldModel

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "imac_model" / "configs" / "wan2.2_ti2v_5b.yaml"

# diffusers v0.35.2 scripts/convert_wan_to_diffusers.py (commit b71269675ec1b85193107a691dd35c308e46f0a5),
# get_transformer_config("Wan2.2-TI2V-5B") and vae22_diffusers_config without latents_mean/std and the stale
# clip_output: the values the Hub's Wan-AI/Wan2.2-TI2V-5B-Diffusers was written with. The independent oracle.
CONVERSION_TRANSFORMER = {
    "added_kv_proj_dim": None, "attention_head_dim": 128, "cross_attn_norm": True, "eps": 1e-06, "ffn_dim": 14336,
    "freq_dim": 256, "in_channels": 48, "num_attention_heads": 24, "num_layers": 30, "out_channels": 48,
    "patch_size": [1, 2, 2], "qk_norm": "rms_norm_across_heads", "text_dim": 4096}
CONVERSION_VAE = {"base_dim": 160, "z_dim": 48, "is_residual": True, "in_channels": 12, "out_channels": 12,
                  "decoder_base_dim": 256, "scale_factor_temporal": 4, "scale_factor_spatial": 16, "patch_size": 2}

TINY_TRANSFORMER = dict(num_attention_heads=2, attention_head_dim=8, ffn_dim=32, num_layers=2, text_dim=16,
                        freq_dim=16)
TINY_VAE = dict(base_dim=8, decoder_base_dim=8, dim_mult=[1, 1, 1, 1], num_res_blocks=1)


# --------------------------------------------------------------------------- the real config and its plan


def test_the_plan_of_the_real_config_prints_diffusers_own_5b_count(tmp_path, capsys):
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    with torch.device("meta"):  # diffusers' classes on the conversion script's values
        transformer = sum(p.numel() for p in WanTransformer3DModel(**CONVERSION_TRANSFORMER).parameters())
        vae = sum(p.numel() for p in AutoencoderKLWan(**CONVERSION_VAE).parameters())
    assert transformer == 4_999_787_712 and vae == 704_688_668
    run = load_run_config(REAL)  # the real config parses and sets every value of the conversion script
    assert {k: run.backbone.wan.transformer[k] for k in CONVERSION_TRANSFORMER} == CONVERSION_TRANSFORMER
    assert {k: run.backbone.wan.vae[k] for k in CONVERSION_VAE} == CONVERSION_VAE
    assert (run.data.view_height, run.data.view_width, run.data.chunk) == (224, 224, 8)

    out = tmp_path / "plan.json"
    assert model_main(["plan", "--config", str(REAL), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"transformer     {transformer:>16,d}  (5.0 B)" in text
    assert f"VAE (frozen)    {vae:>16,d}  (0.7 B)" in text
    assert "tokens per chunk: 882 " in text  # 448 x 672 mosaic, 9 frames -> 3 x 28 x 42 latents, 2 x 2 patches
    plan = json.loads(out.read_text())
    counts = plan["parameters"]
    assert counts["transformer"] == transformer and counts["vae"] == vae
    assert counts["control_layers"] == 3 * (3072 * 48 * 4 + 3072)  # three patch embeddings, zero-initialised
    rows = {r["setting"]["name"]: r for r in plan["settings"]}
    # the training states alone (20 bytes per trainable parameter) exceed one 80 GB GPU; sharded over 8 they fit
    assert rows["no sharding, 1 GPU"]["bytes"]["weights"] == 4 * counts["trainable"]
    assert not rows["no sharding, 1 GPU"]["fits"] and not rows["fsdp2, 1 GPU"]["fits"]
    assert rows["fsdp2, 8 GPUs"]["fits"] and rows["fsdp2, 1 GPU, CPU offload"]["fits"]
    assert rows["fsdp2, 8 GPUs"]["bytes"]["adamw"] == 8 * counts["trainable"] / 8
    assert plan["flops"]["sample_chunk"] > 20 * plan["flops"]["denoiser_call"] > 0


def test_the_plan_needs_what_no_dataset_gives(tmp_path, capsys):
    config = tmp_path / "c.yaml"
    config.write_text(yaml.safe_dump({"data": {"view_height": 224}, "backbone": {"kind": "wan"}}))
    assert model_main(["plan", "--config", str(config)]) == 2
    assert "data.view_width: the plan reads no dataset" in capsys.readouterr().err


# --------------------------------------------------------------------------- weights in the diffusers layout


def test_weights_saved_by_diffusers_load_through_backbone_wan_pretrained(tmp_path):
    """A tiny transformer and VAE saved by diffusers' own ``save_pretrained`` in the Hub's layout
    (``transformer/``, ``vae/``) load through ``backbone.wan.pretrained``: every weight, the VAE's
    latent statistics, and the shapes the plan reads from the directory."""
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    from imac_model.training.plan import parameter_counts, plan_spec

    torch.manual_seed(1)
    transformer = WanTransformer3DModel(**{"in_channels": 48, "out_channels": 48, "patch_size": (1, 2, 2),
                                           **TINY_TRANSFORMER})
    mean, std = torch.randn(48).tolist(), (torch.rand(48) + 0.5).tolist()
    vae = AutoencoderKLWan(**{**CONVERSION_VAE, **TINY_VAE, "latents_mean": mean, "latents_std": std})
    with torch.no_grad():
        for p in [*transformer.parameters(), *vae.parameters()]:
            p.add_(torch.randn_like(p) * 0.1)
    transformer.save_pretrained(tmp_path / "wan" / "transformer")
    vae.save_pretrained(tmp_path / "wan" / "vae")
    assert (tmp_path / "wan" / "transformer" / "diffusion_pytorch_model.safetensors").is_file()

    backbone = BackboneConfig(kind="wan", wan=WanConfig(pretrained=str(tmp_path / "wan"), context_tokens=3))
    spec = ModelSpec(backbone=backbone, conditioning=ConditioningConfig(), flow=FlowConfig(), views=("a", "b", "c"),
                     view_height=32, view_width=32, chunk=4, action_dim=5, fps=25.0)
    model = WorldModel(spec)
    for own, saved in ((model.backbone.transformer, transformer), (model.backbone.vae, vae)):
        loaded = own.state_dict()
        assert loaded.keys() == saved.state_dict().keys()
        assert all(torch.equal(loaded[k], v) for k, v in saved.state_dict().items())
    torch.testing.assert_close(model.backbone.latents_mean.flatten(), torch.tensor(mean))
    torch.testing.assert_close(model.backbone.latents_std.flatten(), torch.tensor(std))
    assert all(float(p.detach().abs().sum()) == 0 for p in model.controls.parameters())  # the controls start at 0
    # the plan reads the same shapes from the directory's config.json files, without the weights
    run = load_run_config(None, {"backbone.kind": "wan", "backbone.wan.pretrained": str(tmp_path / "wan"),
                                 "backbone.wan.context_tokens": 3, "data.view_height": 32, "data.view_width": 32,
                                 "data.chunk": 4})
    with torch.device("meta"):
        counts = parameter_counts(WorldModel(plan_spec(run)))
    assert counts["transformer"] == sum(p.numel() for p in transformer.parameters())
    assert counts["vae"] == sum(p.numel() for p in vae.parameters())
    with pytest.raises(InputError, match="backbone.wan.pretrained: cannot load Wan weights"):
        WorldModel(dataclasses.replace(spec, backbone=BackboneConfig(kind="wan", wan=WanConfig(
            pretrained=str(tmp_path / "missing")))))


# --------------------------------------------------------------------------- sharded training, 2 gloo processes


@pytest.fixture(scope="module")
def square_dataset(tmp_path_factory):
    """Two short simulated episodes with square 64x64 cameras (Wan patchifies 32x32 views), contact chunk 4."""
    tmp = tmp_path_factory.mktemp("scale_ds")
    record_dataset(SimConfig(num_episodes=2, width=64, height=64, max_steps=44), tmp / "sim", progress=False)
    recipe = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    recipe["augment"] = {"height": 64, "width": 64, "contact_chunk": 4}
    (tmp / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    root = tmp / "ds"
    assert imac_main(["build", "--repo", "local/scale_tiny", "--recipe", str(tmp / "recipe.yaml"), "--source",
                      str(tmp / "sim"), "--root", str(root), "--no-progress", "--workers", "1"]) == 0
    return root


TINY_RUN = {
    "data": {"view_height": 32, "held_out_episodes": [1]},
    "backbone": {"kind": "wan", "wan": {"transformer": TINY_TRANSFORMER, "vae": TINY_VAE, "context_tokens": 3}},
    "train": {"batch_size": 4, "lr": 1e-3, "weight_decay": 0.01, "warmup_steps": 2, "max_steps": 4, "ema_decay": 0.9,
              "log_every": 1, "eval_every": 2, "eval_batches": 1, "checkpoint_every": 2, "cpu_threads": 1},
}
# float64 weights: sharded and single-process gradients are summed in different orders; in float32 AdamW turns
# that rounding in gradients that are zero in exact arithmetic (attention key biases) into lr-sized steps
FLOAT64_ENTRY = "import sys, torch\ntorch.set_default_dtype(torch.float64)\nfrom imac_model.cli import main\n" \
                "sys.exit(main(sys.argv[1:]))\n"


@contextlib.contextmanager
def float64():
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        yield
    finally:
        torch.set_default_dtype(before)


def _torchrun(tmp_path: Path, args: list[str]) -> None:
    entry = tmp_path / "float64_entry.py"
    entry.write_text(FLOAT64_ENTRY)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           str(entry), *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]


def _weights(path: Path, weights: str) -> dict[str, torch.Tensor]:
    with float64():  # the model is rebuilt in float64, so nothing is rounded on loading
        model, _ = load_world_model(path, weights=weights)
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _log(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]


def test_sharded_training_on_two_processes_equals_one_process_and_resumes_exactly(square_dataset, tmp_path):
    config = tmp_path / "tiny_wan.yaml"
    config.write_text(yaml.safe_dump(TINY_RUN))
    common = ["train", "--dataset", "local/scale_tiny", "--root", str(square_dataset), "--config", str(config),
              "--no-progress", "--set", f"data.cache_dir={tmp_path / 'cache'}"]
    single, sharded, resumed = tmp_path / "single", tmp_path / "sharded", tmp_path / "resumed"
    with float64():  # one process, the unsharded trainer: the oracle, on the same global batch of 4
        assert model_main([*common, "--output-dir", str(single)]) == 0
    _torchrun(tmp_path, [*common, "--output-dir", str(sharded), "--set", "train.sharding.strategy=fsdp2"])

    # each rank holds half of every block (and of the rest); the frozen VAE is replicated
    report = json.loads((sharded / "sharding.json").read_text())
    assert report["world"] == 2
    for name, group in report["groups"].items():
        if name.startswith("vae"):
            assert group["per_rank"] == [group["parameters"]] * 2
        else:
            assert group["per_rank"] == [group["parameters"] // 2] * 2 and group["parameters"] % 2 == 0, name
    assert sum(name.startswith("transformer.blocks.") for name in report["groups"]) == 2
    files = sorted((sharded / "checkpoints" / "step_000004" / "state").glob("*.distcp"))
    assert len(files) == 2 and not (sharded / "checkpoints" / "step_000004" / "model.safetensors").exists()

    # losses, held-out losses, weights and EMA equal those of one process
    a, b = _log(single), _log(sharded)
    assert [r["step"] for r in a] == [r["step"] for r in b] == [0, 1, 2, 3, 4]
    for key in ("loss", "heldout_loss"):
        pairs = [(x[key], y[key]) for x, y in zip(a, b) if key in x]
        assert len(pairs) >= 3 and all(abs(x - y) <= 1e-6 * abs(x) for x, y in pairs), (key, pairs)
    for weights, tol in (("raw", 1e-7), ("ema", 1e-6)):  # the EMA is kept in float32 by design
        one, two = _weights(single, weights), _weights(sharded, weights)
        assert one.keys() == two.keys()
        worst = max(float((one[k] - two[k]).abs().max()) for k in one)
        assert worst <= tol, (weights, worst)
    trained = _weights(sharded, "raw")
    assert all(float(trained[k].abs().sum()) > 0 for k in trained if k.startswith("controls."))  # zero at step 0
    at2 = _weights(sharded / "checkpoints" / "step_000002", "raw")  # not vacuous: 2 steps move the weights more
    assert max(float((at2[k] - trained[k]).abs().max()) for k in at2) > 1e-4

    # a fresh pair of processes resumes from the step-2 sharded checkpoint and ends bit-identical
    shutil.copytree(sharded, resumed, ignore=shutil.ignore_patterns("step_000004"))
    _torchrun(tmp_path, [*common, "--output-dir", str(resumed), "--set", "train.sharding.strategy=fsdp2"])
    for weights in ("raw", "ema"):
        x, y = _weights(sharded, weights), _weights(resumed, weights)
        assert all(torch.equal(x[k], y[k]) for k in x), weights
    assert [r.get("loss") for r in _log(resumed)] == [r.get("loss") for r in b]


def test_sharding_is_refused_where_it_cannot_work(square_dataset, tmp_path, capsys):
    out = tmp_path / "run"
    base = ["train", "--dataset", "local/scale_tiny", "--root", str(square_dataset), "--output-dir", str(out),
            "--no-progress", "--set", "train.sharding.strategy=fsdp2"]
    cases = [
        ([], "train.sharding.strategy: fsdp2 shards the Wan transformer's blocks; backbone.kind is 'small'"),
        (["--set", "backbone.kind=wan", "--set", "backbone.wan.train_vae=true"],
         "backbone.wan.train_vae: the VAE is replicated, not sharded"),
        (["--set", "backbone.kind=wan", "--set", "data.view_height=32", "--set", "train.sharding.cpu_offload=true"],
         "train.sharding.cpu_offload: offloads from a CUDA device to host memory; there is no CUDA device here"),
    ]
    for extra, message in cases:
        assert model_main([*base, *extra]) == 2
        assert message in capsys.readouterr().err
        assert not out.exists()
    with pytest.raises(InputError, match="train.sharding.cpu_offload / reshard_after_forward: need"):
        load_run_config(None, {"train.sharding.cpu_offload": True})
    with pytest.raises(InputError, match="train.adam_betas: two numbers"):
        load_run_config(None, {"train.adam_betas": [0.9]})
    run = load_run_config(REAL)  # the sharding section round-trips
    assert load_run_config(None, run.to_dict()) == run


# --------------------------------------------------------------------------- the plan against measured memory


def test_the_plans_prediction_is_within_15_percent_of_measured_cpu_memory(tmp_path):
    """The training states of a model whose plan predicts 1.9 GB (weights, EMA, gradients, AdamW)
    and the activations of two blocks at the paper's 882 tokens, measured as the growth of the
    resident set (``benchmarks/model_plan.py``; docs/scale.md has the figures)."""
    out = tmp_path / "plan_vs_rss.json"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.model_plan", "--part", "states", "activations",
                           "--json", str(out)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.is_file(), proc.stderr[-4000:]
    report = json.loads(out.read_text())
    states = report["states"]["rows"]["total"]
    assert states["predicted_mb"] >= 1500
    assert abs(states["ratio"] - 1) <= 0.15, report["states"]
    assert abs(report["activations"]["ratio"] - 1) <= 0.15, report["activations"]
    assert report["activations"]["tokens"] == 882
    assert proc.returncode == 0

"""The world model on both backbones (the small DiT, and Wan2.2-TI2V through diffusers with a
tiny random config): control injection as paper eq. 2, the loss mask, sampling."""

import dataclasses

import pytest
import torch
from torch import nn

from imac_model.config import BackboneConfig, ConditioningConfig, FlowConfig, ModelSpec, SmallDiTConfig, WanConfig
from imac_model.data.batch import ChunkBatch
from imac_model.models.world_model import WorldModel

TINY_WAN = WanConfig(
    transformer=dict(num_attention_heads=2, attention_head_dim=8, ffn_dim=32, num_layers=2, text_dim=16, freq_dim=16),
    vae=dict(base_dim=8, decoder_base_dim=8, dim_mult=[1, 1, 1, 1], num_res_blocks=1),
    context_tokens=3,
)
BACKBONES = {
    "small": (BackboneConfig(kind="small", small=SmallDiTConfig(dim=32, depth=2, heads=2, context_dim=16)), 16),
    "wan": (BackboneConfig(kind="wan", wan=TINY_WAN), 32),  # Wan2.2: mosaic sides multiples of 32
}
H_FUTURE, ACTION_DIM = 4, 5


def make_spec(kind: str, mode: str = "motion+contact", **conditioning) -> ModelSpec:
    backbone, view = BACKBONES[kind]
    return ModelSpec(backbone=backbone, conditioning=ConditioningConfig(mode=mode, **conditioning), flow=FlowConfig(
        sample_steps=2), views=("head", "left", "right"), view_height=view, view_width=view, chunk=H_FUTURE,
        action_dim=ACTION_DIM, fps=25.0)


def make_batch(spec: ModelSpec, seed: int = 0, B: int = 2) -> ChunkBatch:
    g = torch.Generator().manual_seed(seed)
    Hm, Wm = spec.mosaic_hw
    T = spec.chunk
    return ChunkBatch(reference=torch.rand(B, 3, Hm, Wm, generator=g), actions=torch.randn(B, T, ACTION_DIM, generator=g),
                      controls={s: torch.rand(B, T, 3, Hm, Wm, generator=g) for s in
                                ("motion", "contact_s2g", "contact_r2s")},
                      future=torch.rand(B, T, 3, Hm, Wm, generator=g))


def randomise(module: nn.Module, seed: int = 0) -> None:
    """Give every parameter a non-zero random value (DiT's zero-initialised output and
    adaLN gates would otherwise make every output, and every gradient, zero)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.1)


def build(kind, mode="motion+contact", **conditioning) -> WorldModel:
    torch.manual_seed(0)
    model = WorldModel(make_spec(kind, mode, **conditioning))
    if kind == "small":
        randomise(model.backbone)
    return model


def inputs(model, batch, tau=0.4):
    z_ref, x1 = model.encode_chunk(batch.reference, batch.future)
    x_tau = 0.5 * x1 + torch.randn_like(x1) * 0.5
    return z_ref, x_tau, torch.full((len(batch),), tau), model.encode_controls(batch.controls)


@pytest.mark.parametrize("kind", BACKBONES)
def test_zero_initialised_controls_leave_the_backbone_output_unchanged(kind):
    model = build(kind)
    batch = make_batch(model.spec)
    z_ref, x_tau, tau, controls = inputs(model, batch)
    with torch.no_grad():
        with_controls = model.velocity(x_tau, tau, reference_latent=z_ref, control_latents=controls)
        latents = torch.cat([z_ref, x_tau], dim=2)
        t = torch.full(latents.shape[:1] + latents.shape[2:3], 600.0)
        t[:, 0] = 0.0
        plain = model.backbone.denoise(latents, t)[:, :, 1:]
    assert torch.equal(with_controls, plain)
    # the comparison is not vacuous: non-zero control layers change the output
    randomise(model.controls, seed=1)
    with torch.no_grad():
        changed = model.velocity(x_tau, tau, reference_latent=z_ref, control_latents=controls)
    assert (changed - plain).abs().max() > 1e-4


@pytest.mark.parametrize("kind", BACKBONES)
def test_gradients_reach_every_control_layer(kind):
    model = build(kind)
    out = model(make_batch(model.spec), generator=torch.Generator().manual_seed(0))
    out.loss.backward()
    assert set(model.controls.layers) == {"motion", "contact_s2g", "contact_r2s"}
    for name, layer in model.controls.layers.items():
        assert layer.weight.grad is not None and layer.weight.grad.abs().sum() > 0, name
        assert layer.bias.grad.abs().sum() > 0, name


def _patch_tokens(model, batch):
    """The tokens after patch embedding + controls (h_tau of eq. 2), captured by a hook."""
    seen = {}
    handle = model.backbone.patch_embedding.register_forward_hook(lambda m, i, o: seen.setdefault("h", o.detach()))
    z_ref, x_tau, tau, controls = inputs(model, batch)
    with torch.no_grad():
        model.velocity(x_tau, tau, reference_latent=z_ref, control_latents=controls)
    handle.remove()
    return seen["h"]


@pytest.mark.parametrize("kind", BACKBONES)
def test_reference_tokens_are_unaffected_by_the_controls(kind):
    model = build(kind)
    randomise(model.controls, seed=1)
    batch = make_batch(model.spec)
    other = make_batch(model.spec, seed=5)
    torch.manual_seed(3)
    h1 = _patch_tokens(model, batch)
    batch.controls = other.controls  # same reference and future, other controls
    torch.manual_seed(3)
    h2 = _patch_tokens(model, batch)
    assert torch.equal(h1[:, :, 0], h2[:, :, 0])  # latent frame 0 = the reference
    assert (h1[:, :, 1:] - h2[:, :, 1:]).abs().max() > 1e-4  # the future tokens carry the controls
    # the public release's option adds them to the reference too: then frame 0 changes
    model.controls.on_reference = True
    torch.manual_seed(3)
    h3 = _patch_tokens(model, batch)
    assert (h3[:, :, 0] - h2[:, :, 0]).abs().max() > 1e-4


@pytest.mark.parametrize("kind", BACKBONES)
def test_loss_ignores_reference_and_padded_frames(kind):
    model = build(kind)
    batch = make_batch(model.spec)
    batch.future_valid = torch.tensor([[True] * H_FUTURE, [True] * (H_FUTURE - 3) + [False] * 3])
    gen = lambda: torch.Generator().manual_seed(7)  # noqa: E731
    out = model(batch, generator=gen())
    # the loss is the MSE of the velocity over the valid future latent frames only (brute force)
    tf = model.backbone.temporal_factor
    valid_latents = [[f for f in range(H_FUTURE // tf) if batch.future_valid[b, f * tf:(f + 1) * tf].all()]
                     for b in range(2)]
    err = torch.cat([((out.velocity[b, :, f] - out.target[b, :, f]) ** 2).flatten()
                     for b in range(2) for f in valid_latents[b]])
    torch.testing.assert_close(out.loss, err.mean())
    assert out.velocity.shape[2] == H_FUTURE // tf  # no reference frame in the prediction
    # no gradient from padded frames: d loss / d velocity is zero exactly there, non-zero elsewhere
    grad = torch.autograd.grad(out.loss, out.velocity)[0]
    for b in range(2):
        for f in range(H_FUTURE // tf):
            assert (grad[b, :, f].abs().sum() > 0) == (f in valid_latents[b]), (b, f)
    # a target in a padded frame can be anything
    target = out.target.clone()
    target[1, :, -1] += 100.0
    from imac_model.schedulers.flow import masked_mse
    torch.testing.assert_close(masked_mse(out.velocity, target, out.frame_mask), out.loss)


@pytest.mark.parametrize("kind", BACKBONES)
def test_forward_loss_and_sampling_run_in_every_mode(kind):
    for mode in ("none", "motion", "motion+contact", "action-vector"):
        model = build(kind, mode)
        batch = make_batch(model.spec)
        out = model(batch, generator=torch.Generator().manual_seed(0))
        assert torch.isfinite(out.loss)
        out.loss.backward()
        sample = model.sample(batch, steps=2, generator=torch.Generator().manual_seed(0))
        Hm, Wm = model.spec.mosaic_hw
        assert sample.frames.shape == (2, H_FUTURE, 3, Hm, Wm)
        assert 0 <= sample.frames.min() and sample.frames.max() <= 1
        # the one-step estimate decodes to frames too (the rollout's next reference)
        frames = model.decode_future(out.reference_latent, out.clean_estimate.detach())
        assert frames.shape == (2, H_FUTURE, 3, Hm, Wm)
        if mode == "action-vector":
            grads = [p.grad for p in model.action_encoder.parameters()]
            assert all(g is not None and g.abs().sum() > 0 for g in grads)


def test_wan_adapter_is_diffusers_forward_with_tokens_timesteps_and_the_paper_velocity():
    """Against diffusers called directly: per-token timesteps (0 on the reference frame),
    the learned null context, and the velocity sign (Wan predicts noise - data)."""
    model = build("wan", "none")
    batch = make_batch(model.spec)
    z_ref, x_tau, tau, _ = inputs(model, batch, tau=0.25)
    seen = {}
    handle = model.backbone.transformer.register_forward_pre_hook(
        lambda m, args, kwargs: seen.update(kwargs), with_kwargs=True)
    with torch.no_grad():
        v = model.velocity(x_tau, tau, reference_latent=z_ref)
    handle.remove()
    t = seen["timestep"]
    per_frame = z_ref.shape[3] * z_ref.shape[4] // 4  # patch (1, 2, 2)
    assert t.shape == (2, per_frame * (1 + x_tau.shape[2]))
    assert torch.all(t[:, :per_frame] == 0) and torch.allclose(t[:, per_frame:], torch.tensor(750.0))
    with torch.no_grad():
        direct = model.backbone.transformer(torch.cat([z_ref, x_tau], 2), timestep=t,
                                            encoder_hidden_states=model.backbone.null_context.expand(2, -1, -1),
                                            return_dict=False)[0]
    torch.testing.assert_close(v, -direct[:, :, 1:])


def test_wan_vae_reference_latent_is_the_reference_alone():
    """The causal VAE: encoding reference + future gives the same first latent as the
    reference alone, so sampling (reference only) and training see the same z_ref."""
    model = build("wan", "none")
    batch = make_batch(model.spec)
    with torch.no_grad():
        together, _ = model.encode_chunk(batch.reference, batch.future)
        alone, _ = model.encode_chunk(batch.reference)
    torch.testing.assert_close(together, alone, rtol=0, atol=1e-6)


def test_controls_with_a_resolution_the_backbone_cannot_patchify_are_refused():
    from imac_data.errors import InputError

    spec = make_spec("wan")
    bad = ModelSpec(**{**spec.__dict__, "view_height": 40})
    with pytest.raises(InputError, match="cannot be patchified"):
        WorldModel(bad)
    bad = ModelSpec(**{**spec.__dict__, "chunk": 6})
    with pytest.raises(InputError, match="data.chunk"):
        WorldModel(bad)
    bad = ModelSpec(**{**spec.__dict__, "conditioning": dataclasses.replace(spec.conditioning, first_frame=True)})
    with pytest.raises(InputError, match="conditioning.first_frame: .* wan compresses time by 4"):
        WorldModel(bad)

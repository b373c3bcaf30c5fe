"""The pixel-space U-Net backbone (imac_model/models/backbones/unet.py).

* Its latent is exact: RGB and depth come back from ``decode(encode(x))``, and every generated
  depth value lands on the codec's colour walk (valid metres), whatever the network outputs.
* A behaviour test with an analytic oracle: a small square that a control image moves. The
  reference shows it at one place, the motion control at another; after a fixed budget the
  generated square's centroid lies near the control's, and the same model without controls
  (``none``) misses it.
* Classifier-free guidance: trained with a share of the samples without controls, the model
  samples the controlled square at guidance 1, and at guidance 0 it is exactly the model without
  its controls, which misses it.
* The same for the episode's first frame (``conditioning.first_frame``): a square only that frame
  shows is painted where it shows it, and another first frame moves it; a checkpoint widened for it
  computes what it did."""

from dataclasses import replace

import pytest
import torch
import torch._dynamo

from benchmarks.cpu_ablation import add_first_frame, add_scene_warp
from imac_data.core.depth import DepthCodec
from imac_data.errors import InputError
from imac_model.config import BackboneConfig, ConditioningConfig, FlowConfig, ModelSpec, RolloutConfig, UNetConfig
from imac_model.data.batch import ChunkBatch
from imac_model.data.depth import decode_depth
from imac_model.models.backbones.build import build_backbone
from imac_model.models.checkpoint import load_world_model, read_spec, read_trainer_state, save_checkpoint
from imac_model.models.world_model import WorldModel
from imac_model.pipelines.rollout import rollout_loss
from imac_model.training.train import _eager, compile_trunk

H, SIDE, SQUARE = 2, 16, 3
CODEC = DepthCodec.preset("manipulation")


def test_unet_latent_round_trips_rgb_and_depth():
    backbone = build_backbone(BackboneConfig(kind="unet", unet=UNetConfig(channels=(8, 16), blocks=1, frame_dim=4)),
                              num_frames=3)
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(2, 3, 3, 8, 16, generator=g)
    metres = 0.2 + 1.5 * torch.rand(2, 3, 8, 16, generator=g)
    colour = CODEC.encode(metres, channel_axis=-3).float()  # (2, 3, 3, 8, 16)
    back = backbone.decode(backbone.encode(torch.cat([rgb, colour], dim=-2)))
    assert torch.allclose(back[..., :8, :], rgb, atol=1e-6)
    assert (CODEC.decode(back[..., 8:, :], channel_axis=-3) - metres).abs().max() < 1e-4
    # any output of the network is painted on the colour walk: it decodes to valid metres unless the
    # depth channel itself says black (walk position within 2 codes of 0, the codec's "invalid")
    latent = torch.randn(2, 4, 3, 8, 16, generator=g) * 0.6
    _, invalid = decode_depth(backbone.decode(latent)[..., 8:, :], CODEC)
    black = (latent[:, 3] + 1) / 2 * 7 < 3 / 255
    assert not (invalid & ~black).any()
    assert (~invalid).float().mean() > 0.9


def _square(centres: torch.Tensor) -> torch.Tensor:
    """``(B, 2)`` pixel centres -> ``(B, 3, SIDE, SIDE)`` a white square on black."""
    ys, xs = torch.meshgrid(torch.arange(SIDE), torch.arange(SIDE), indexing="ij")
    inside = ((ys[None] - centres[:, :1, None]).abs() <= SQUARE // 2) & ((xs[None] - centres[:, 1:, None]).abs()
                                                                          <= SQUARE // 2)
    return inside[:, None].float().expand(-1, 3, -1, -1)


def _depth_row(B: int) -> torch.Tensor:
    return CODEC.encode(torch.full((B, SIDE, SIDE), 0.8), channel_axis=-3).float()


def batch_of(g: torch.Generator, B: int) -> tuple[ChunkBatch, torch.Tensor]:
    start = torch.randint(2, SIDE - 2, (B, 2), generator=g)
    target = torch.randint(2, SIDE - 2, (B, 2), generator=g)
    depth = _depth_row(B)
    reference = torch.cat([_square(start), depth], dim=-2)
    frame = torch.cat([_square(target), depth], dim=-2)
    future = frame[:, None].expand(B, H, -1, -1, -1).clone()
    control = torch.cat([_square(target)] * 2, dim=-2)[:, None].expand(B, H, -1, -1, -1).clone()
    batch = ChunkBatch(reference=reference, actions=torch.zeros(B, H, 1), controls={"motion": control}, future=future)
    return batch, target.float()


def train(mode: str, steps: int = 150, dropout: float = 0.0) -> WorldModel:
    torch.manual_seed(0)
    spec = ModelSpec(backbone=BackboneConfig(kind="unet", unet=UNetConfig(channels=(16, 32), blocks=1, frame_dim=8)),
                     conditioning=ConditioningConfig(mode=mode, dropout=dropout), flow=FlowConfig(prediction="data", sample_steps=8),
                     views=("cam",), view_height=SIDE, view_width=SIDE, chunk=H, action_dim=1, fps=10.0)
    model = WorldModel(spec)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    g = torch.Generator().manual_seed(1)
    for _ in range(steps):
        batch, _ = batch_of(g, 16)
        if mode == "none":
            batch.controls = {}
        loss = model(batch, generator=g).loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model.eval()


def centroid_error(model: WorldModel) -> float:
    """Mean distance (px) between the generated square's centroid and the controlled one's."""
    batch, target = batch_of(torch.Generator().manual_seed(2), 12)
    if not model.streams:
        batch.controls = {}
    return square_error(model.sample(batch, generator=torch.Generator().manual_seed(3)).frames, target)


def test_unet_paints_a_small_square_where_the_control_puts_it():
    torch.set_num_threads(1)
    seen, blind = centroid_error(train("motion")), centroid_error(train("none"))
    assert seen < 1.5, seen  # within a pixel or so of the controlled place
    assert blind > 3.0, blind  # without the control the model can only guess (random places: about 5 px off)


def test_guidance_scales_what_the_controls_do_and_at_zero_is_the_model_without_them():
    torch.set_num_threads(1)
    model = train("motion", dropout=0.2)

    def guided(w):
        model.spec = replace(model.spec, conditioning=replace(model.spec.conditioning, guidance=w))
        return model

    assert centroid_error(guided(1.0)) < 1.5
    assert centroid_error(guided(2.0)) < 1.5
    # at guidance 0 the sample is the unconditional model's: the same weights with the control injector removed
    batch, target = batch_of(torch.Generator().manual_seed(2), 12)
    unguided = guided(0.0).sample(batch, generator=torch.Generator().manual_seed(3)).frames
    (injector, streams), (model.controls, model.streams) = (model.controls, model.streams), (None, ())
    without = guided(1.0).sample(replace(batch, controls={}), generator=torch.Generator().manual_seed(3)).frames
    model.controls, model.streams = injector, streams
    assert torch.equal(unguided, without)
    assert square_error(unguided, target) > 3.0  # and it misses the controlled place
    with pytest.raises(InputError, match="conditioning.guidance: 2.0 needs a model trained with conditioning.dropout"):
        ConditioningConfig(guidance=2.0)
    with pytest.raises(InputError, match="conditioning.dropout"):
        ConditioningConfig(dropout=1.0)


# --------------------------------------------------------------------------- the episode's first frame as memory


def first_frame_batch(g: torch.Generator, B: int) -> tuple[ChunkBatch, torch.Tensor]:
    """The square is in the episode's first frame only: the reference has lost it (black), and the
    future shows it where the first frame had it."""
    place = torch.randint(2, SIDE - 2, (B, 2), generator=g)
    depth = _depth_row(B)
    first = torch.cat([_square(place), depth], dim=-2)
    reference = torch.cat([torch.zeros(B, 3, SIDE, SIDE), depth], dim=-2)
    future = first[:, None].expand(B, H, -1, -1, -1).clone()
    return ChunkBatch(reference=reference, actions=torch.zeros(B, H, 1), future=future, first_frame=first), \
        place.float()


def unet_spec(**conditioning) -> ModelSpec:
    return ModelSpec(backbone=BackboneConfig(kind="unet", unet=UNetConfig(channels=(16, 32), blocks=1, frame_dim=8)),
                     conditioning=ConditioningConfig(mode="none", **conditioning),
                     flow=FlowConfig(prediction="data", sample_steps=8),
                     views=("cam",), view_height=SIDE, view_width=SIDE, chunk=H, action_dim=1, fps=10.0)


def square_error(frames: torch.Tensor, place: torch.Tensor) -> float:
    """Mean distance (px) between the centroid of the last generated frame's square and ``place``."""
    weight = frames[:, -1, :, :SIDE].mean(dim=1).clamp_min(0) ** 2
    ys, xs = torch.meshgrid(torch.arange(SIDE).float(), torch.arange(SIDE).float(), indexing="ij")
    total = weight.sum(dim=(-1, -2)).clamp_min(1e-6)
    centre = torch.stack([(weight * ys).sum(dim=(-1, -2)) / total, (weight * xs).sum(dim=(-1, -2)) / total], dim=-1)
    return float((centre - place).norm(dim=-1).mean())


def test_a_model_conditioned_on_the_first_frame_paints_what_only_that_frame_shows():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    model = WorldModel(unet_spec(first_frame=True))
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    g = torch.Generator().manual_seed(1)
    for _ in range(150):
        loss = model(first_frame_batch(g, 16)[0], generator=g).loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    batch, place = first_frame_batch(torch.Generator().manual_seed(2), 12)
    sample = lambda b: model.sample(b, generator=torch.Generator().manual_seed(3)).frames  # noqa: E731
    assert square_error(sample(batch), place) < 1.5  # within a pixel or so of the first frame's square
    # the first frame, not a guess, decides: another sample's first frame moves the square to its place
    swapped = sample(ChunkBatch(reference=batch.reference, actions=batch.actions, first_frame=batch.first_frame.roll(1, 0)))
    assert square_error(swapped, place.roll(1, 0)) < 1.5
    assert square_error(swapped, place) > 3.0
    with pytest.raises(ValueError, match="ChunkBatch.first_frame"):
        model.sample(ChunkBatch(reference=batch.reference, actions=batch.actions))


def trained_one_step() -> tuple[WorldModel, torch.optim.AdamW, ChunkBatch, torch.Generator]:
    """A motion-mode U-Net after one AdamW step (what a branch starts from)."""
    torch.manual_seed(0)
    spec = unet_spec()
    model = WorldModel(ModelSpec(**{**spec.__dict__, "conditioning": ConditioningConfig(mode="motion")}))
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(1)
    batch, _ = batch_of(g, 4)
    model(batch, generator=g).loss.backward()
    opt.step()
    return model, opt, batch, g


def test_a_checkpoint_widened_for_the_first_frame_computes_what_it_did(tmp_path):
    """``add_first_frame`` (an ablation's branch): the widened checkpoint's model gives the original's
    loss and samples whatever first frame it is shown, and its trainer state resumes an AdamW."""
    model, opt, batch, g = trained_one_step()
    spec = model.spec
    ema = {k: v.detach() * 0.5 for k, v in model.named_parameters()}
    path = save_checkpoint(tmp_path / "step_000001", model=model, spec=spec, ema=ema,
                           trainer_state={"optimizer": opt.state_dict(), "step": 1})
    add_first_frame(path)
    assert read_spec(path).conditioning.first_frame
    wide, _ = load_world_model(path, weights="raw")
    assert wide.clean_frames == 2 and wide.backbone.conv_in.in_channels == model.backbone.conv_in.in_channels + 8
    model.eval()
    batch.first_frame = torch.rand(batch.reference.shape, generator=g)
    tau, noise = torch.full((4,), 0.4), torch.randn(4, 4, H, SIDE, SIDE, generator=g)
    with torch.no_grad():
        assert torch.allclose(wide(batch, tau=tau, noise=noise).loss, model(batch, tau=tau, noise=noise).loss)
    a = model.sample(batch, noise=noise).frames
    b = wide.sample(batch, noise=noise).frames
    assert torch.allclose(a, b, atol=1e-6)
    ema_model, _ = load_world_model(path, weights="ema")
    assert torch.equal(ema_model.backbone.conv_in.weight[:, 8:], ema["backbone.conv_in.weight"])
    assert not ema_model.backbone.conv_in.weight[:, :8].any()
    resumed = torch.optim.AdamW(wide.parameters(), lr=1e-3)
    resumed.load_state_dict(read_trainer_state(path)["optimizer"])
    wide.train()
    wide(batch, generator=g).loss.backward()
    resumed.step()
    assert wide.backbone.conv_in.weight[:, :8].abs().sum() > 0  # training reaches the first frame's slice


def test_a_checkpoint_given_the_scene_warp_computes_what_it_did(tmp_path):
    """``add_scene_warp`` (an ablation's branch): the new stream's projection is zero, so the model gives
    the original's loss and samples whatever warp it is shown; every parameter's AdamW moments stay
    with it though the new layer sits between them; training reaches the new layer."""
    model, opt, batch, g = trained_one_step()
    spec = model.spec
    path = save_checkpoint(tmp_path / "step_000001", model=model, spec=spec,
                           trainer_state={"optimizer": opt.state_dict(), "step": 1})
    add_scene_warp(path)
    assert read_spec(path).conditioning.streams == ("motion", "scene_warp")
    wide, _ = load_world_model(path, weights="raw")
    assert not wide.controls.layers["scene_warp"].weight.any()
    batch.controls["scene_warp"] = torch.rand(batch.controls["motion"].shape, generator=g)
    model.eval()
    wide.eval()
    tau, noise = torch.full((4,), 0.4), torch.randn(4, 4, H, SIDE, SIDE, generator=g)
    with torch.no_grad():
        assert torch.allclose(wide(batch, tau=tau, noise=noise).loss, model(batch, tau=tau, noise=noise).loss)
    assert torch.allclose(model.sample(batch, noise=noise).frames, wide.sample(batch, noise=noise).frames, atol=1e-6)
    resumed = torch.optim.AdamW(wide.parameters(), lr=1e-3)
    resumed.load_state_dict(read_trainer_state(path)["optimizer"])
    before = dict(zip([k for k, _ in model.named_parameters()], opt.state_dict()["state"].values()))
    after = {k: resumed.state_dict()["state"].get(i) for i, (k, _) in enumerate(wide.named_parameters())}
    assert set(before) == {k for k, v in after.items() if v is not None}
    for k, moments in before.items():
        assert torch.equal(after[k]["exp_avg"], moments["exp_avg"]), k
    wide.train()
    wide(batch, generator=g).loss.backward()
    resumed.step()
    assert wide.controls.layers["scene_warp"].weight.abs().sum() > 0



def test_a_compiled_trunk_computes_what_the_eager_one_does_in_one_graph():
    """The GPU preset's ``--compile``: dynamo captures the U-Net's trunk whole (one graph, no break),
    the loss and every gradient are the eager ones, the weights keep their names, and the eager trunk
    comes back. ``aot_eager`` traces forward and backward as the GPU's inductor does, without code
    generation (a CPU compile takes minutes)."""
    model, _, batch, _ = trained_one_step()
    keys = list(model.state_dict())

    def loss_and_grads():
        model.zero_grad()
        loss = model(batch, tau=torch.full((4,), 0.4), noise=torch.randn(4, 4, H, SIDE, SIDE,
                                                                         generator=torch.Generator().manual_seed(5))).loss
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in model.parameters() if p.grad is not None]

    eager_loss, eager_grads = loss_and_grads()
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    compiled = compile_trunk(model, backend="aot_eager")
    for _ in range(2):  # the second call reuses the graph
        loss, grads = loss_and_grads()
        assert torch.allclose(loss, eager_loss, rtol=1e-5)
        assert len(grads) == len(eager_grads)
        assert all(torch.allclose(a, b, rtol=1e-4, atol=1e-6) for a, b in zip(grads, eager_grads))
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1
    assert not torch._dynamo.utils.counters["graph_break"]
    assert list(model.state_dict()) == keys
    assert _eager(model) is compiled and model.backbone.trunk.__func__ is type(model.backbone).trunk
    torch._dynamo.reset()


def test_a_rollout_from_sampled_frames_starts_the_next_chunk_where_the_sampler_ends():
    """``rollout.reference_steps`` k: chunk 2 starts from the last frame of k sampler steps on chunk 1
    (the frame a replay goes on from), not from chunk 1's one-step estimate, whose noised input holds a
    share tau of the true future."""
    model = train("motion", steps=40)
    g = torch.Generator().manual_seed(1)
    batch, _ = batch_of(g, 4)
    clip = [batch, batch]
    taus = [torch.full((4,), 0.5)] * 2
    noises = [torch.randn(4, 4, H, SIDE, SIDE, generator=torch.Generator().manual_seed(k)) for k in (1, 2)]
    sampled = rollout_loss(model, clip, None, generator=torch.Generator().manual_seed(3), taus=taus, noises=noises,
                           reference_steps=2)
    noise = torch.randn(4, 4, H, SIDE, SIDE, generator=torch.Generator().manual_seed(3))
    expected = model.sample(batch, steps=2, noise=noise).frames[:, -1].clamp(0, 1)
    assert torch.allclose(sampled.references[1], expected, atol=1e-6)
    estimate = rollout_loss(model, clip, None, taus=taus, noises=noises)
    assert (estimate.references[1] - sampled.references[1]).abs().mean() > 1e-3
    assert torch.equal(sampled.references[0], estimate.references[0])  # chunk 1 starts from its recording either way
    with pytest.raises(InputError, match="rollout.reference_steps"):
        RolloutConfig(reference_steps=-1)

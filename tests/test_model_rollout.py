"""Training-time rollout and the online control rebuild, on a dataset built by imac_data.build.hdf5.

Oracles: the dataset's own stored control streams (the offline build) against the online
rebuild, with the certified contact tolerance and the codec's quantisation as the bounds;
analytic colour geometry for corrupt depth (grey is sqrt(1/2) from the codec's walk); the
exact one-step estimate at tau = 1 (it recovers the recorded future, so chunk 2's reference is
its recorded reference); the paper's formulas x1_hat = x_tau + (1 - tau) v and L = (1/R) sum L_r
computed by hand.
"""

import json
import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
import yaml
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from imac_data.augment.pipeline import EpisodePipeline
from imac_data.cli import main as imac_main
from imac_data.core.contact.clouds import dilate_mask
from imac_data.core.contact.images import JET_LUT, chunk_plan
from imac_data.core.contact.nearest import DEFAULT_TOLERANCE
from imac_data.core.depth import DepthCodec, depth_codec_of, walk_distance
from imac_data.core.metric_depth import depth_from_millimetres
from imac_data.core.rig import Rig
from imac_data.errors import InputError
from imac_data.metadata import dataset_info
from imac_data.recipes import RECIPES_DIR, AugmentSettings
from imac_data.sources.depth import RecordedDepth
from imac_data.sources.hdf5 import EpisodeReader, read_episode
from imac_data.sources.sim import rig as sim_rig
from imac_data.sources.sim.recorder import SimConfig, record_dataset
from imac_model.cli import main as model_main
from imac_model.config import RolloutConfig, RunConfig, load_run_config, parse, save_config, to_dict
from imac_model.data import mosaic
from imac_model.data.chunks import ChunkDataset, open_metadata
from imac_model.data.depth import decode_depth
from imac_model.models.world_model import WorldModel
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.rollout import rollout_loss
from imac_model.training.dataset_source import model_spec

CHUNK = 4
VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
HW = (64, 80)  # the dataset's stream resolution
TINY = {"backbone.small.dim": 32, "backbone.small.depth": 1, "backbone.small.heads": 2, "data.view_height": 32,
        "train.batch_size": 2, "train.eval_batches": 1, "train.log_every": 1, "train.warmup_steps": 1,
        "data.held_out_episodes": [1]}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Two short simulated episodes (22 and 21 frames), built with the real builder (contact chunk 4)."""
    tmp = tmp_path_factory.mktemp("rollout_ds")
    sim = tmp / "sim"
    record_dataset(SimConfig(num_episodes=2, width=HW[1], height=HW[0], max_steps=44), sim, progress=False)
    recipe = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    recipe["augment"] = {"height": HW[0], "width": HW[1], "contact_chunk": CHUNK}
    (tmp / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    root = tmp / "ds"
    assert imac_main(["build", "--repo", "local/rollout_tiny", "--recipe", str(tmp / "recipe.yaml"), "--source", str(sim),
                       "--root", str(root), "--no-progress", "--workers", "1"]) == 0
    return root, sim


@pytest.fixture(scope="module")
def stored(built):
    """LeRobot's own frames of episode 0 (every stream), and the raw episode."""
    root, sim = built
    ds = LeRobotDataset("local/rollout_tiny", root=root)
    n = int(ds.meta.episodes["length"][0])
    return ds, [ds[i] for i in range(n)], read_episode(sorted(sim.glob("episode_*.hdf5"))[0])


def _spec(root, **overrides):
    run = RunConfig().replace(**{"data.dataset": "local/rollout_tiny", "data.root": str(root), **TINY, **overrides})
    spec, layout = model_spec(run, open_metadata(run.data))
    return run, spec, layout


# --------------------------------------------------------------------------- decoding stored contact colours


def _levels(rgb: torch.Tensor):
    """JET colours (..., 3) uint8 -> (lowest, highest) level of each colour, -1 for black.
    (matplotlib's jet has three repeated colours among its 256.)"""
    lut = torch.as_tensor(JET_LUT, dtype=torch.int64)
    flat = rgb.reshape(-1, 3).to(torch.int64)
    match = (flat[:, None, :] == lut[None]).all(-1)  # (N, 256)
    black = (flat == 0).all(-1)
    assert bool((match.any(-1) | black).all()), "a painted contact colour is not a jet colour"
    idx = torch.arange(256)
    lo = torch.where(match, idx, 999).min(-1).values
    hi = torch.where(match, idx, -1).max(-1).values
    lo[black], hi[black] = -1, -1
    return lo.reshape(rgb.shape[:-1]), hi.reshape(rgb.shape[:-1])


def _interval(lo_level, hi_level, cap):
    """Distances a level range stands for: level l <=> d in (cap (1 - (l+1)/256), cap (1 - l/256)];
    level 0 also holds everything beyond the cap."""
    lo_d = cap * (1 - (hi_level.double() + 1) / 256)
    hi_d = torch.where(lo_level == 0, torch.full_like(lo_d, math.inf), cap * (1 - lo_level.double() / 256))
    return lo_d.clamp_min(0), hi_d


def _gap(a, b):
    """Distance between intervals a = (lo, hi) and b (0 where they overlap)."""
    return torch.maximum(torch.zeros_like(a[0]), torch.maximum(a[0] - b[1], b[0] - a[1]))


def _compare_chunk(online_rgb, stored_rgb, cap_on, cap_st):
    """Per painted pixel, the gap between the distance intervals of the two colours."""
    on, st = _levels(online_rgb), _levels(stored_rgb)
    painted = on[0] >= 0
    assert torch.equal(painted, st[0] >= 0), "online and stored contact images paint different pixels"
    gap = _gap(_interval(*on, cap_on), _interval(*st, cap_st))[painted]
    upper = torch.minimum(_interval(*on, cap_on)[1], _interval(*st, cap_st)[1])[painted]
    same = (online_rgb == stored_rgb).all(-1)[painted]
    return gap, upper, same


def _rebuild_episode(online, frames_of_episode, ep, depth_of):
    """Every chunk of an episode rebuilt online (reference depth from ``depth_of(frame)``), against
    its stored streams: the distance gaps, identical-pixel counts and cap differences."""
    T = len(ep.qpos)
    assert len(frames_of_episode) == T
    gaps, uppers, same, caps, motion_equal = [], [], [], [], []
    for ref, frames in chunk_plan(T, CHUNK):
        future = [f for f in frames if f > 0]
        q_ref = torch.as_tensor(ep.qpos[ref], dtype=torch.float32)[None]
        actions = torch.as_tensor(ep.action[[f - 1 for f in future]], dtype=torch.float32)[None]
        q_future = online.configurations(q_ref, actions)
        c = online.contact(depth_of(ref)[None], q_ref, q_future, include_reference_step=ref == 0)
        motion = online.motion(q_future)
        rows = [frames_of_episode[f] for f in future]
        cap_st = rows[0]["control.contact_cap"].double()
        caps.append((c.caps[0].double(), cap_st))
        for k, row in enumerate(rows):
            for v, cam in enumerate(VIEWS):
                for name, got, cap_i in (("r2s", c.r2s, 0), ("s2g", c.s2g, 1)):
                    stored = (row[f"control.contact_{name}.{cam}"] * 255).round().byte().permute(1, 2, 0)
                    mine = (got[0, k, v] * 255).round().byte().permute(1, 2, 0)
                    g, u, s = _compare_chunk(mine, stored, c.caps[0, cap_i].double(), cap_st[cap_i])
                    gaps.append(g), uppers.append(u), same.append(s)
                stored_motion = (row[f"control.motion.{cam}"] * 255).round().byte()
                motion_equal.append(torch.equal((motion[0, k, v] * 255).round().byte(), stored_motion))
    return torch.cat(gaps), torch.cat(uppers), torch.cat(same), caps, motion_equal


def _tolerance(d):
    metres, relative = DEFAULT_TOLERANCE
    return torch.maximum(torch.full_like(d, metres), relative * d)


# --------------------------------------------------------------------------- the online rebuild vs the build


def test_online_rebuild_matches_the_build(built, stored):
    """Fed the float depth the build used, at the dataset's resolution, the online rebuild paints
    the stored contact images within the certified tolerance (and the same caps); the motion
    images from the actions and FK alone are the stored ones."""
    root, _ = built
    _, rows, ep = stored
    _, spec, _ = _spec(root, **{"data.view_height": HW[0]})
    assert (spec.view_height, spec.view_width) == HW
    online = OnlineControls.from_dataset(root, spec)

    def float_depth(frame):  # what imac_data.sources.depth.RecordedDepth gave the build
        return torch.stack([torch.as_tensor(depth_from_millimetres(ep.depth_mm[v][frame])) for v in VIEWS])

    gap, upper, same, caps, motion_equal = _rebuild_episode(online, rows, ep, float_depth)
    assert all(motion_equal)
    bound = _tolerance(upper.clamp(max=10.0).float()).double() + 1e-6
    print(f"\nonline vs build, float depth: {int(same.sum())}/{len(same)} painted pixels identical "
          f"({100 * float(same.float().mean()):.2f} %), largest distance gap {1e3 * float(gap.max()):.3f} mm, "
          f"caps differ by at most {max(float((a - b).abs().max()) for a, b in caps) * 1e3:.4f} mm")
    assert bool((gap <= bound).all())
    for on, st in caps:
        assert bool(((on - st).abs() <= _tolerance(st.float()).double() + 1e-6).all())
    assert float(same.float().mean()) > 0.99  # the same functions on the same inputs


def test_online_controls_are_the_builds_bit_for_bit(built):
    """One episode, at the dataset's stream resolution (``rollout.resolution: dataset``, the size the
    build drew at) and fed the depth in metres the build used: the rollout's controls for the
    recorded actions are bit-identical to the build's control images before encoding, and its caps
    to the build's. Both sides call ``Rig.contact_images`` with the settings the dataset records."""
    root, sim = built
    _, spec, _ = _spec(root, **{"data.view_height": HW[0]})
    online = OnlineControls.from_dataset(root, spec, resolution="dataset")
    assert online.compute_hw == online.view_hw == HW
    path = sorted(sim.glob("episode_*.hdf5"))[0]
    # the build's images before encoding: its own pipeline, with the rig and settings the dataset records
    pipe = EpisodePipeline(Rig.from_dataset(root), AugmentSettings.from_info(root), RecordedDepth(), threads=1)
    with EpisodeReader(path) as reader:
        built_chunks = list(pipe.chunks(reader))
    ep = read_episode(path)
    plan = list(chunk_plan(len(ep.qpos), CHUNK))
    assert len(built_chunks) == len(plan)
    compared = 0
    for (ref, frames), out in zip(plan, built_chunks):
        future = [f for f in frames if f > 0]
        q_ref = torch.as_tensor(ep.qpos[ref], dtype=torch.float32)[None]
        actions = torch.as_tensor(ep.action[[f - 1 for f in future]], dtype=torch.float32)[None]
        depth = torch.stack([torch.as_tensor(depth_from_millimetres(ep.depth_mm[v][ref])) for v in VIEWS])[None]
        q_future = online.configurations(q_ref, actions)
        contact = online.contact(depth, q_ref, q_future, include_reference_step=ref == 0)
        motion = online.motion(q_future)
        assert torch.equal(contact.caps[0], torch.as_tensor(out.caps[0]))
        rows = [f - out.start for f in future]
        for v, cam in enumerate(VIEWS):
            for key, mine in ((f"control.motion.{cam}", motion), (f"control.contact_r2s.{cam}", contact.r2s),
                              (f"control.contact_s2g.{cam}", contact.s2g)):
                got = (mine[0, :, v] * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
                np.testing.assert_array_equal(got, out.streams[key][rows], err_msg=f"{key}, chunk at frame {ref}")
                compared += got.size
    assert compared > 0


def test_decoded_depth_stream_difference_is_bounded_by_the_codec(built, stored):
    """Fed the dataset's decoded depth stream instead, every scene point moves by at most the
    codec's quantisation (half a step at its depth, along its pixel ray), so every contact distance
    moves by at most that times the longest ray, plus the certified tolerance."""
    root, _ = built
    ds, rows, ep = stored
    _, spec, _ = _spec(root, **{"data.view_height": HW[0]})
    online = OnlineControls.from_dataset(root, spec)
    codec = depth_codec_of(ds.meta)
    errors = []

    def stream_depth(frame):
        row = rows[frame]
        decoded = torch.stack([codec.decode(row[f"observation.depth.{v}"], channel_axis=-3) for v in VIEWS])
        exact = torch.stack([torch.as_tensor(depth_from_millimetres(ep.depth_mm[v][frame])) for v in VIEWS])
        assert torch.equal(decoded > 0, exact > 0)  # validity survives the stream
        err = (decoded - exact).abs()[exact > 0].double()
        half_step = torch.as_tensor(codec.quantisation_step(exact[exact > 0].double().numpy() + err.numpy())) / 2
        assert bool((err <= half_step + 1e-6).all())  # the codec's rounding, and nothing else
        errors.append(err)
        return decoded

    gap, upper, same, caps, _ = _rebuild_episode(online, rows, ep, stream_depth)
    eps = float(torch.cat(errors).max())
    K = online.rig.intrinsics(HW).double()
    corners = torch.tensor([[0, 0, 1], [HW[1] - 1, 0, 1], [0, HW[0] - 1, 1], [HW[1] - 1, HW[0] - 1, 1]],
                           dtype=torch.float64)
    rays = corners @ torch.linalg.inv(K).transpose(-1, -2)
    rho = float((rays / rays[..., 2:]).norm(dim=-1).max())  # longest pixel ray per metre of z-depth
    bound = eps * rho + _tolerance(upper.clamp(max=10.0).float()).double() + 1e-6  # both saturated: gap 0
    finite = torch.isfinite(upper)
    print(f"\nonline (decoded depth stream) vs build (float depth): depth error max {1e3 * eps:.3f} mm "
          f"(longest ray x{rho:.2f}); {100 * float(same.float().mean()):.2f} % of painted pixels identical; "
          f"distance gap mean {1e3 * float(gap.mean()):.4f} mm, max {1e3 * float(gap.max()):.3f} mm "
          f"(bound there {1e3 * float(bound[finite][gap[finite].argmax()]):.3f} mm); caps differ by at most "
          f"{max(float((a - b).abs().max()) for a, b in caps) * 1e3:.4f} mm")
    assert eps > 0  # the stream is quantised: this is not the float-depth test again
    assert bool((gap <= bound).all())
    for on, st in caps:
        assert bool(((on - st).abs() <= eps * rho + _tolerance(st.float()).double() + 1e-6).all())


# --------------------------------------------------------------------------- corrupt depth


def test_corrupt_depth_becomes_invalid_never_nan(built):
    root, _ = built
    run, spec, layout = _spec(root)
    online = OnlineControls.from_dataset(root, spec)
    chunks = ChunkDataset("local/rollout_tiny", layout, root=root, episodes=[0], cache="none")
    batch = chunks.batch([1])
    ref = batch.reference.clone()  # (1, 3, 2h, V w), recorded
    rgb, colour = mosaic.split(ref, len(VIEWS))
    clean, clean_invalid = decode_depth(colour, online.codec)
    assert torch.equal(clean_invalid, (colour == 0).all(dim=-3))  # recorded colours: only black is invalid

    # view 1: grey (sqrt(1/2) from every segment of the walk), NaN and inf blocks; a colour pushed
    # 0.05 off its segment along a fixed channel keeps its projection, hence its depth
    bad = colour.clone()
    bad[0, 1, :, :8, :] = 0.5
    bad[0, 1, :, 8:16, :] = float("nan")
    bad[0, 1, :, 16:20, :] = float("inf")
    k, t = _segment(bad[0, 2, :, 20:24, :])
    nudged = bad[0, 2, :, 20:24, :].clone()
    fixed = _fixed_channel(k)
    for ch in range(3):
        sel = fixed == ch
        nudged[ch][sel] = (nudged[ch][sel] + torch.where(nudged[ch][sel] < 0.5, 0.05, -0.05))
    bad[0, 2, :, 20:24, :] = nudged
    assert float(walk_distance(torch.full((3,), 0.5))) == pytest.approx(math.sqrt(0.5))
    metres, invalid = decode_depth(bad, online.codec)
    assert bool(invalid[0, 1, :20].all()) and bool((metres[0, 1, :20] == 0).all())
    assert torch.isfinite(metres).all()
    valid = ~clean_invalid[0, 2, 20:24]
    assert valid.sum() > 20
    torch.testing.assert_close(metres[0, 2, 20:24][valid], clean[0, 2, 20:24][valid])
    assert not bool(invalid[0, 2, 20:24][valid].any())

    corrupt = mosaic.assemble(rgb, bad)
    out = online.controls(corrupt, batch.state, batch.actions)
    for s, c in out.controls.items():
        assert torch.isfinite(c).all() and c.min() >= 0 and c.max() <= 1, s
    assert 0 < float(out.invalid_fraction[0]) < 1

    # the whole depth row unusable: no scene at all, still no exception and no NaN
    garbage = torch.full_like(colour, 0.5)
    garbage[..., ::2, :] = float("nan")
    out = online.controls(mosaic.assemble(rgb, garbage), batch.state, batch.actions)
    assert float(out.invalid_fraction[0]) == 1.0
    r2s = mosaic.control_views(out.controls["contact_r2s"], len(VIEWS))
    s2g = mosaic.control_views(out.controls["contact_s2g"], len(VIEWS))
    assert float(s2g.abs().max()) == 0.0  # no scene point: nothing painted
    robot = r2s.amax(dim=-3) > 0
    assert robot.any()
    far = torch.tensor([0, 0, 127]) / 255.0  # r2s beyond any cap: nothing within reach
    assert torch.allclose(r2s.permute(0, 1, 2, 4, 5, 3)[robot], far.expand(int(robot.sum()), 3))


def _segment(colour):
    """(3, h, w) colours on the walk -> segment index and fraction (the codec's corners)."""
    from imac_data.core.depth import path_position

    s = path_position(colour, channel_axis=0)
    k = s.floor().clamp(0, 6).long()
    return k, s - k


def _fixed_channel(k):
    """A channel that segment k of the walk black-red-yellow-green-cyan-blue-magenta-white holds fixed."""
    from imac_data.core.depth import CORNERS

    steps = np.abs(np.diff(CORNERS, axis=0))
    fixed = torch.as_tensor([int(np.flatnonzero(steps[j] == 0)[0]) for j in range(7)])
    return fixed[k]


# --------------------------------------------------------------------------- the rollout loss


def _model_and_clip(root, **overrides):
    run, spec, layout = _spec(root, **overrides)
    torch.manual_seed(0)
    model = WorldModel(spec)
    chunks = ChunkDataset("local/rollout_tiny", layout, root=root, episodes=[0], cache="none")
    clips = chunks.clips(2)
    assert clips[0] == (0, 1) and len(clips) == len(chunks.episode_chunks(0)) - 1
    picked = [clips[1], clips[3]]
    clip = [chunks.batch([c[r] for c in picked]) for r in range(2)]
    online = OnlineControls.from_dataset(root, spec)
    return model, clip, online


def test_rollout_loss_is_the_weighted_sum_of_the_chunks(built):
    """R = 2: chunk 2 is trained from the decoded last frame of chunk 1's one-step estimate
    x_tau + (1 - tau) v (detached), with contact images rebuilt from its depth, and the loss is
    (L_1 + L_2) / 2. Calling backward per chunk gives the same gradients as the total's."""
    root, _ = built
    model, clip, online = _model_and_clip(root, **{"flow.prediction": "velocity"})
    B = len(clip[0])
    taus = [torch.tensor([0.3, 0.8]), torch.tensor([0.6, 0.2])]
    noise_shape = lambda b: model.encode_chunk(b.reference, b.future)[1].shape  # noqa: E731
    gen = torch.Generator().manual_seed(1)
    noises = [torch.randn(noise_shape(b), generator=gen) for b in clip]
    out = rollout_loss(model, clip, online, taus=taus, noises=noises)

    # by hand
    first = model(clip[0], tau=taus[0], noise=noises[0])
    x1_hat = first.x_tau + (1 - taus[0]).view(B, 1, 1, 1, 1) * first.velocity
    ref2 = model.decode_future(first.reference_latent, x1_hat.detach())[:, -1].clamp(0, 1)
    torch.testing.assert_close(out.references[1], ref2)
    assert not out.references[1].requires_grad
    rebuilt = online.controls(ref2, clip[1].state, clip[1].actions, streams=("contact_s2g", "contact_r2s"))
    assert torch.equal(out.controls[1]["motion"], clip[1].controls["motion"])  # actions + FK: the stored ones
    for s in ("contact_s2g", "contact_r2s"):
        torch.testing.assert_close(out.controls[1][s], rebuilt.controls[s])
        assert not torch.equal(out.controls[1][s], clip[1].controls[s])  # rebuilt, not the recorded ones
    second = model(replace(clip[1], reference=ref2, controls={**clip[1].controls, **rebuilt.controls}),
                   tau=taus[1], noise=noises[1])
    torch.testing.assert_close(out.chunk_losses[0], first.loss.detach())
    torch.testing.assert_close(out.chunk_losses[1], second.loss.detach())
    torch.testing.assert_close(out.loss, (first.loss + second.loss) / 2)
    assert not torch.allclose(first.loss, second.loss)

    # gradients: one backward of the total = backward per chunk (what the trainer does)
    model.zero_grad()
    out.loss.backward()
    whole = {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}
    model.zero_grad()
    again = rollout_loss(model, clip, online, taus=taus, noises=noises, backward=lambda loss: loss.backward())
    torch.testing.assert_close(again.loss, out.loss.detach())
    assert whole.keys() == {k for k, p in model.named_parameters() if p.grad is not None}
    for k, p in model.named_parameters():
        if k in whole:
            torch.testing.assert_close(p.grad, whole[k], rtol=1e-4, atol=1e-6)


def test_an_exact_estimate_hands_on_the_recorded_frame(built):
    """At tau = 1 the one-step estimate is the clean latent itself, so chunk 2's reference is
    its recorded reference (chunk 1's last recorded frame) and its depth decodes as recorded."""
    root, _ = built
    model, clip, online = _model_and_clip(root)
    ones = torch.ones(len(clip[0]))
    out = rollout_loss(model, clip, online, taus=[ones, torch.full_like(ones, 0.5)])
    torch.testing.assert_close(out.references[1], clip[1].reference, atol=2e-6, rtol=0)
    _, recorded_invalid = online.reference_depth(clip[1].reference)  # black: near-plane pixels of the wrists
    assert out.invalid_depth[0] == pytest.approx(float(recorded_invalid.float().mean()), abs=1e-3)
    # with a random tau it is not (the test above is not vacuous)
    out = rollout_loss(model, clip, online, taus=[ones * 0.1, ones * 0.5])
    assert not torch.allclose(out.references[1], clip[1].reference, atol=1e-2)


def test_the_scene_warp_is_derived_for_training_and_rebuilt_online_alike(built):
    """``conditioning.scene_warp``: the dataset stores no such stream, so the chunks derive it from
    their recorded reference, state and actions, and a training-time rollout rebuilds it from the
    model's own frame through the same function. The oracle is MuJoCo's own frame: where the warp of
    a moving wrist camera lands scene, it is closer to the recorded future frame than the reference
    view left in place is."""
    root, _ = built
    model, clip, online = _model_and_clip(root, **{"conditioning.scene_warp": True})
    spec = model.spec
    assert spec.conditioning.streams[-1] == "scene_warp"
    for batch in clip:
        assert batch.controls["scene_warp"].shape == batch.controls["motion"].shape
        again = online.controls(batch.reference, batch.state, batch.actions, streams=("scene_warp",))
        torch.testing.assert_close(again.controls["scene_warp"], batch.controls["scene_warp"], atol=0.5 / 255, rtol=0)

    ds = ChunkDataset("local/rollout_tiny", _spec(root, **{"conditioning.scene_warp": True})[2], root=root,
                      episodes=[0, 1], cache="none")
    V, errors = len(spec.views), []
    for i in range(len(ds)):
        item = ds[i]
        q_future = online.configurations(item["state"][None], item["actions"][None])[0]
        robot = online.rig.robot_views(torch.cat([item["state"][None], q_future]), resolution=online.view_hw,
                                       gripper=False).mask
        robot = dilate_mask(robot[0] | robot[-1], 2)  # the robot where it was and where it goes: not scene
        warp, _ = mosaic.split(item["control.scene_warp"][-1:].float() / 255, V)  # step H
        recorded, _ = mosaic.split(item["future"][-1:].float() / 255, V)
        reference, _ = mosaic.split(item["reference"][None].float() / 255, V)
        for v, name in enumerate(spec.views):
            scene = (warp[0, v].amax(0) > 0) & ~robot[v]
            kept = float((reference[0, v] - recorded[0, v]).abs().mean(0)[scene].mean())
            if "wrist" in name and scene.sum() > 20 and kept > 0.03:  # a wrist view that changes
                errors.append((float((warp[0, v] - recorded[0, v]).abs().mean(0)[scene].mean()), kept))
    moved, kept = np.mean(errors, axis=0)  # measured: 0.055 against 0.082 over 10 wrist views
    assert len(errors) >= 5 and moved < 0.8 * kept, errors

    out = rollout_loss(model, clip, online, taus=[torch.full((2,), 0.3), torch.full((2,), 0.6)])
    rebuilt = online.controls(out.references[1], clip[1].state, clip[1].actions, streams=("scene_warp",))
    torch.testing.assert_close(out.controls[1]["scene_warp"], rebuilt.controls["scene_warp"])
    assert not torch.equal(out.controls[1]["scene_warp"], clip[1].controls["scene_warp"])  # from the model's frame


# --------------------------------------------------------------------------- config, trainer and sampler


def test_online_controls_warn_about_a_camera_out_of_step():
    """A dataset whose camera has a time offset had that camera's controls drawn at the image's own time; a
    rollout has no joint states before its reference or past its chunk, so the online controls draw it at the
    joint states' time (the same images as without the offset) and say so, naming the camera and its offset.
    Without an offset nothing is said."""
    cameras = sim_rig.camera_calibration(sim_rig.load_mujoco_model("transfer_cube"), HW[1], HW[0])
    late = {c: replace(cam, time_offset_s=-0.04) if c == "cam_left_wrist" else cam for c, cam in cameras.items()}
    codec = DepthCodec.preset()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning at all without an offset
        plain = OnlineControls(Rig.from_platform("aloha_sim", cameras), codec, VIEWS, (32, 40), HW)
    with pytest.warns(UserWarning, match=r"camera time offsets \{'cam_left_wrist': -0.04\} s: online motion and "
                                         r"contact images draw every camera at the joint states' time"):
        shifted = OnlineControls(Rig.from_platform("aloha_sim", late), codec, VIEWS, (32, 40), HW)
    q = torch.zeros(1, 2, 14)
    q[0, 1, [1, 8]] = 0.4  # both shoulders raised in the second frame
    assert torch.equal(shifted.motion(q), plain.motion(q))


def test_rollout_config_is_typed_validated_and_round_trips(tmp_path):
    run = RunConfig().replace(**{"rollout.chunks": 4, "rollout.warmup_epochs": 1.5, "rollout.stage_one_epochs": 0.5,
                                 "rollout.resolution": "dataset", "rollout.reference_state": "commanded"})
    save_config(run, tmp_path / "run.yaml")
    assert load_run_config(tmp_path / "run.yaml") == run
    assert parse(RolloutConfig, to_dict(run.rollout), "rollout") == run.rollout
    for bad, message in ((("rollout.chunks", 0), "rollout.chunks: must be a positive integer"),
                         (("rollout.warmup_epochs", -1), "rollout.warmup_epochs: must be >= 0"),
                         (("rollout.max_walk_distance", 0), "rollout.max_walk_distance: must be in (0, 1]"),
                         (("rollout.resolution", "full"), "rollout.resolution: must be one of"),
                         (("rollout.chunk", 2), "rollout: unknown field(s) ['chunk']")):
        with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")
                           .replace("[", r"\[").replace("]", r"\]")):
            RunConfig().replace(**{bad[0]: bad[1]})
    with pytest.raises(InputError, match="stage one .* needs conditioning.mode motion\\+contact"):
        RunConfig().replace(**{"rollout.stage_one_epochs": 1, "conditioning.mode": "motion"})


def test_rollout_training_and_long_sampling_clis(built, tmp_path, capsys):
    import av

    root, _ = built
    out = tmp_path / "run"
    sets = [f"{k}={json.dumps(v)}" for k, v in {**TINY, "train.max_steps": 3, "train.eval_every": 3,
                                                  "rollout.chunks": 2, "rollout.warmup_epochs": 0.1,
                                                  "train.checkpoint_every": 3}.items()]
    args = ["--dataset", "local/rollout_tiny", "--root", str(root), "--output-dir", str(out), "--no-progress"]
    assert model_main(["train", *args, *[a for s in sets for a in ("--set", s)]]) == 0
    rows = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [r.get("phase") for r in rows[1:]] == ["warmup", "rollout", "rollout"]
    assert all(len(r["chunk_losses"]) == 2 and 0 <= r["invalid_depth"] <= 1 for r in rows[2:])
    assert load_run_config(out / "config.yaml").rollout.chunks == 2

    video, png = tmp_path / "long.mp4", tmp_path / "long.png"
    capsys.readouterr()
    assert model_main(["sample", "--checkpoint", str(out), "--episode", "1", "--chunk", "1", "--chunks", "2",
                            "--out", str(video), "--png", str(png), "--steps", "2", "--scale", "1"]) == 0
    printed = capsys.readouterr().out
    assert "2 chunks" in printed and "per chunk 1:" in printed and "2:" in printed
    with av.open(str(video)) as f:
        frames = [fr.to_ndarray(format="rgb24") for fr in f.decode(video=0)]
    assert len(frames) == 2 * CHUNK and png.is_file()
    assert model_main(["sample", "--checkpoint", str(out), "--episode", "1", "--chunk", "5", "--chunks", "2"]) == 2
    assert "--chunk 5 --chunks 2: episode 1 has chunks 0..5" in capsys.readouterr().err


# --------------------------------------------------------------------------- the workspace crop


def test_online_rebuild_crops_to_the_datasets_workspace(built, stored):
    """The online rebuild takes the dataset's workspace (``imac.workspace``, the crop the build
    applied) and applies it to decoded depth: a reference whose depth holds uint16-saturated
    values (65.535 m, through the colour codec) gives exactly the contact images of one with
    invalid depth there; a far background (8 m) leaves the caps within the workspace; with the
    crop switched off the s2g cap is tens of metres."""
    root, _ = built
    _, _, ep = stored
    _, spec, _ = _spec(root, **{"data.view_height": HW[0]})
    online = OnlineControls.from_dataset(root, spec)
    info = dataset_info(root)
    ws = online.rig.workspace
    assert ws is not None and ws.to_dict() == info["imac"]["workspace"]
    ref, future = 4, [5, 6, 7, 8]
    q_ref = torch.as_tensor(ep.qpos[ref], dtype=torch.float32)[None]
    q_future = online.configurations(q_ref, torch.as_tensor(ep.action[[f - 1 for f in future]],
                                                            dtype=torch.float32)[None])
    depth = torch.stack([torch.as_tensor(depth_from_millimetres(ep.depth_mm[v][ref])) for v in VIEWS])
    hit = torch.as_tensor(np.random.default_rng(0).random(depth.shape) < 0.03)

    def through_codec(d):  # what the world model's depth row decodes to
        colour = torch.as_tensor(online.codec.encode_uint8(d.numpy())).permute(0, 3, 1, 2).float() / 255
        return decode_depth(colour, online.codec)[0]

    saturated, invalid = depth.clone(), depth.clone()
    saturated[hit], invalid[hit] = 65.535, 0.0
    a = online.contact(through_codec(saturated)[None], q_ref, q_future)
    b = online.contact(through_codec(invalid)[None], q_ref, q_future)
    assert torch.equal(a.caps, b.caps), (a.caps, b.caps)
    assert torch.equal(a.r2s, b.r2s) and torch.equal(a.s2g, b.s2g)
    far = depth.clone()
    far[0, : HW[0] // 3] = 8.0  # the head camera's upper third: a wall
    c = online.contact(through_codec(far)[None], q_ref, q_future)
    assert bool((c.caps <= ws.diagonal).all())
    uncropped = OnlineControls(online.rig, online.codec, VIEWS, HW, HW,
                               contact={**online.contact_options, "workspace": None})
    assert float(uncropped.contact(saturated[None], q_ref, q_future).caps[0, 1]) > 10

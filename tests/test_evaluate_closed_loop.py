"""Closed-loop policy evaluation in the world model, end to end on the CPU, and its CLI.

Real parts only: a dataset built by ``imac_data.build.hdf5`` (the rollout tests' fixture), the small
DiT (untrained, its zero-initialised layers randomised so that the controls change its output: the
test checks the plumbing, not quality), LeRobot's own ACT policy saved with ``save_pretrained`` and
its processors, LeRobot's writer and loader, and ``lerobot-dataset-viz``'s own function.

Oracles: a policy that replays the recorded actions must reproduce, bit for bit, the open-loop
long rollout of those actions (:func:`imac_model.pipelines.rollout.sample_rollout`, written before this
module); the LeRobot adapter must return what ACT's own ``predict_action_chunk`` and
post-processor return; the written dataset's actions, states and first frame against the source
dataset and the controller map.
"""

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from test_model_rollout import built  # noqa: F401  (the rollout tests' built dataset fixture)
from test_simulator import BEYOND, aloha_command_bounds, beyond_the_range_policy

from imac_data.errors import InputError
from imac_data.metadata import dataset_info
from imac_model.cli import main as model_main
from imac_model.config import RunConfig
from imac_model.data import mosaic
from imac_model.data.batch import ChunkBatch
from imac_model.data.chunks import open_metadata
from imac_model.evaluate.closed_loop import (
    ClosedLoopConfig,
    GeneratedDatasetWriter,
    episode_starts,
    rollout_episode,
    run_closed_loop,
)
from imac_model.evaluate.policies import ActionQueue, LeRobotPolicy, recorded_actions_policy
from imac_model.evaluate.results import write_json
from imac_model.evaluate.success import CallableJudge
from imac_model.models.checkpoint import load_world_model, save_checkpoint
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.rollout import sample_rollout
from imac_model.pipelines.sampling import open_chunks

REPO = "local/rollout_tiny"
VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
TINY = {"backbone.small.dim": 32, "backbone.small.depth": 1, "backbone.small.heads": 2, "data.view_height": 32,
        "flow.sample_steps": 2, "data.held_out_episodes": [1]}


def _checkpoint(root, out: Path, mode: str, **changes) -> Path:
    from imac_model.models.world_model import WorldModel
    from imac_model.training.dataset_source import model_spec

    run = RunConfig().replace(**{"data.dataset": REPO, "data.root": str(root), "conditioning.mode": mode, **TINY,
                                 **changes})
    spec, _ = model_spec(run, open_metadata(run.data))
    torch.manual_seed(0)
    model = WorldModel(spec)
    for p in model.parameters():  # zero-initialised layers (controls, output, gates): randomise, so that the
        if not p.detach().any():  # frames depend on the reference, the controls and the actions
            torch.nn.init.normal_(p, std=0.05)
    return save_checkpoint(out, model=model, spec=spec, run=run)


@pytest.fixture(scope="module")
def world(built, tmp_path_factory):  # noqa: F811
    root, _ = built
    ckpt = _checkpoint(root, tmp_path_factory.mktemp("wm") / "ckpt", "motion+contact")
    model, spec = load_world_model(ckpt)
    chunks = open_chunks(spec, REPO, str(root))
    online = OnlineControls.from_dataset(root, spec, info=chunks.lerobot.meta)
    return root, ckpt, model, spec, chunks, online


def test_replaying_the_recorded_actions_is_the_open_loop_rollout(world):
    """Closed loop with a replay policy == sample_rollout of the same actions (same seeds, controls
    rebuilt online from the generated depth, state = last command): the chain is the rollout's."""
    root, _, model, spec, chunks, online = world
    start = episode_starts(chunks, [0], seed=3, horizon_chunks=2)[0]
    assert start.frame == 0 and start.seed == 3 and start.chunks == 2
    records = list(rollout_episode(model, online, recorded_actions_policy(start.recorded_actions), start))
    H = spec.chunk
    actions = start.recorded_actions[:2 * H].reshape(1, 2, H, -1)
    first = ChunkBatch(reference=start.reference[None], actions=actions[:, 0], state=start.state[None])
    ref = sample_rollout(model, first, actions, online, q0=start.state[None], seed=3, first_controls="online",
                         include_reference_step=True)
    for n, rec in enumerate(records):
        assert torch.equal(rec.actions, actions[0, n])
        assert torch.equal(rec.frames, ref.frames[0, n].clamp(0, 1))
        for s in spec.conditioning.streams:
            assert torch.equal(rec.controls[s], mosaic.control_views(ref.controls[n][s][0], len(VIEWS)))
    # the second chunk starts at the first chunk's last commanded configuration
    assert torch.allclose(records[1].state, online.configurations(start.state[None], actions[:, 0])[0, -1])
    # not vacuous: other actions (hold still) give other frames
    hold = list(rollout_episode(model, online, lambda obs: obs["observation.state"][None], start))
    assert not torch.equal(hold[0].frames, records[0].frames)


def test_a_command_beyond_the_actuators_reaches_the_next_state_saturated_in_the_world_model_too(world):
    """The closed loop gives the policy, and draws, the command saturated at gym-aloha's actuator ranges (read
    from its XML), as the MuJoCo runner does (``test_simulator``): a policy meets the same state in both."""
    root, _, model, spec, chunks, online = world
    start = episode_starts(chunks, [0], seed=3, horizon_chunks=2)[0]
    records = list(rollout_episode(model, online, beyond_the_range_policy, start))
    lo, hi = aloha_command_bounds()
    command = start.state.double().numpy().copy()
    for i, value in BEYOND.items():
        command[i] = value
    expected = np.clip(command, lo, hi)
    assert not np.allclose(expected, command)  # the case saturates
    np.testing.assert_allclose(records[1].state.double().numpy(), expected, atol=1e-6)
    assert float(records[0].actions[0, 13]) == np.float32(-4.2)  # the record keeps the command


def test_a_closed_loop_keeps_its_start_frame_for_a_model_conditioned_on_the_first_frame(world, tmp_path):
    """``conditioning.first_frame``: every chunk of a closed loop is the rollout with the start frame as
    the episode's first frame, and another first frame gives other frames (the model reads it)."""
    root, _, _, spec, chunks, online = world
    model, spec = load_world_model(_checkpoint(root, tmp_path / "ckpt", "motion+contact",
                                               **{"conditioning.first_frame": True}))
    start = episode_starts(chunks, [0], seed=3, horizon_chunks=2)[0]
    records = list(rollout_episode(model, online, recorded_actions_policy(start.recorded_actions), start))
    H = spec.chunk
    actions = start.recorded_actions[:2 * H].reshape(1, 2, H, -1)

    def rollout(first_frame):
        first = ChunkBatch(reference=start.reference[None], actions=actions[:, 0], state=start.state[None],
                           first_frame=first_frame)
        return sample_rollout(model, first, actions, online, q0=start.state[None], seed=3, first_controls="online",
                              include_reference_step=True).frames[0]

    ref = rollout(start.reference[None])
    for n, rec in enumerate(records):
        assert torch.equal(rec.frames, ref[n].clamp(0, 1))
    later = chunks.batch([chunks.episode_chunks(0)[-1]]).reference  # a frame other than the start
    assert not torch.equal(rollout(later)[1], ref[1])


def test_a_scene_frame_replaces_the_reference_only_in_the_contact_images(world):
    """``scene(n)`` (the gate's diagnosis): chunk n's contact images are the ones rebuilt from that
    frame's depth (OnlineControls called on it directly), its motion images and reference stay."""
    root, ckpt, model, spec, chunks, online = world
    start = episode_starts(chunks, [0], seed=3, horizon_chunks=2)[0]
    items = chunks.episode_chunks(0)
    recorded = [chunks.batch([i]).reference for i in items[:2]]
    policy = recorded_actions_policy(start.recorded_actions)
    plain = list(rollout_episode(model, online, policy, start))
    records = list(rollout_episode(model, online, recorded_actions_policy(start.recorded_actions), start,
                                   scene=lambda n: recorded[n][0]))
    assert torch.equal(records[0].frames, plain[0].frames)  # chunk 1's reference is the recorded frame anyway
    rec = records[1]
    assert not torch.equal(rec.reference, recorded[1][0])  # the model went on from its own frame
    want = online.controls(recorded[1], rec.state[None], rec.actions[None], streams=("contact_s2g", "contact_r2s"))
    for s in ("contact_s2g", "contact_r2s"):
        assert torch.equal(rec.controls[s], mosaic.control_views(want.controls[s][0], len(spec.views)))
    assert torch.equal(rec.controls["motion"], plain[1].controls["motion"])


def test_closed_loop_cli_writes_a_lerobot_dataset_of_generated_episodes(world, tmp_path, capsys):
    root, ckpt, model, spec, chunks, online = world
    out = tmp_path / "generated"
    assert model_main(["evaluate", "closed-loop", "--checkpoint", str(ckpt), "--mode", "motion+contact", "--policy", "recorded",
                     "--output", str(out), "--episodes", "0", "1", "--horizon-chunks", "2", "--seed", "3",
                     "--no-progress"]) == 0
    assert "wrote 2 generated episodes" in capsys.readouterr().out
    ds = LeRobotDataset("local/generated", root=out)
    T = 1 + 2 * spec.chunk
    assert ds.meta.total_episodes == 2 and len(ds) == 2 * T
    for stream in ("observation.images", "observation.depth", "control.motion", "control.contact_s2g",
                   "control.contact_r2s"):
        for v in VIEWS:
            assert ds.meta.features[f"{stream}.{v}"]["dtype"] == "video"
    src = LeRobotDataset(REPO, root=root)
    eps = ds.meta.episodes
    assert list(eps["imac/source"]) == ["world_model"] * 2 and list(eps["imac/start_episode"]) == [0, 1]
    assert list(eps["imac/seed"]) == [3, 4] and list(eps["imac/success"]) == [None, None]
    for e in (0, 1):
        lo = int(src.meta.episodes["dataset_from_index"][e])
        rec = torch.stack([src.hf_dataset[lo + t]["action"] for t in range(T - 1)])
        gen = torch.stack([ds.hf_dataset[e * T + t]["action"] for t in range(T)])
        assert torch.equal(gen[:-1], rec) and torch.equal(gen[-1], rec[-1])  # executed, then held
        state = torch.stack([ds.hf_dataset[e * T + t]["observation.state"] for t in range(T)])
        assert torch.equal(state[0], src.hf_dataset[lo]["observation.state"])
        phi = online.configurations(state[:1], rec[None])[0]
        assert torch.allclose(state[1:], phi)
        # frame 0 is the recorded start frame at the model's size (through a lossy video codec)
        first = ds[e * T]["observation.images.cam_high"]
        recorded = torch.nn.functional.interpolate(src[lo]["observation.images.cam_high"][None], size=first.shape[-2:],
                                                   mode="bilinear", antialias=True, align_corners=False)[0]
        assert (first - recorded).abs().mean() < 0.03
        assert float(ds[e * T]["control.motion.cam_high"].max()) < 0.05  # no control at the reference frame
        assert float(ds[e * T + 1]["control.motion.cam_high"].max()) > 0.2  # the robot, drawn
    result = json.loads((out / "closed_loop.json").read_text())
    p = result["protocol"]
    assert p["frames_per_episode"] == [T, T] and p["views"] == list(VIEWS) and p["samples"] == 2
    assert p["sampler_steps"] == 2 and p["seed"] == 3 and p["resolution"]["view"] == [32, 40]
    assert [e["policy_calls"] for e in result["episodes"]] == [2 * spec.chunk] * 2  # one action per call
    assert dataset_info(out)["imac"]["closed_loop"]["policy"] == "recorded"
    # lerobot-dataset-viz opens it (its own function, saving a .rrd instead of spawning a viewer)
    from lerobot.scripts.lerobot_dataset_viz import visualize_dataset

    rrd = visualize_dataset(LeRobotDataset("local/generated", root=out, episodes=[1]), 1, save=True,
                            output_dir=tmp_path / "viz")
    assert rrd is not None and Path(rrd).stat().st_size > 10_000
    # labels scored by people go into the dataset; a CSV naming other episodes is refused
    labels = tmp_path / "labels.csv"
    labels.write_text("episode_index,success\n0,1\n1,0\n")
    assert model_main(["evaluate", "label", "--dataset", str(out), "--labels", str(labels)]) == 0
    assert list(LeRobotDataset("local/generated", root=out).meta.episodes["imac/success"]) == [True, False]
    labels.write_text("episode_index,success\n0,1\n7,0\n")
    assert model_main(["evaluate", "label", "--dataset", str(out), "--labels", str(labels)]) == 2
    assert "names episodes the dataset does not have: [7]" in capsys.readouterr().err
    assert model_main(["evaluate", "label", "--dataset", str(root), "--labels", str(labels)]) == 2
    assert "a recorded dataset is never modified" in capsys.readouterr().err


def test_a_judge_decides_each_episode_from_its_last_generated_frames(world, tmp_path):
    root, ckpt, model, spec, chunks, online = world
    seen = []

    def fn(ep):
        seen.append({k: tuple(v.shape) for k, v in ep.frames.items()})
        return ep.episode_index == 0

    result = run_closed_loop(model, chunks, online, "recorded", tmp_path / "judged", repo_id="local/judged",
                             config=ClosedLoopConfig(episodes=(1, 0), horizon_chunks=1, judge_frames=3),
                             judge=CallableJudge(fn, name="first-is-success"), progress=False)
    assert seen == [{f"observation.images.{v}": (3, 3, 32, 40) for v in VIEWS}] * 2
    assert [e["success"] for e in result.episodes] == [True, False] and result.to_dict()["success_rate"] == 0.5
    assert list(LeRobotDataset("local/judged", root=tmp_path / "judged").meta.episodes["imac/success"]) == [True, False]


# --------------------------------------------------------------------------- a real LeRobot policy


def _save_act(directory: Path, stats, *, image_keys=("observation.images.cam_high",), action_dim=14,
              image_hw=(64, 80)) -> Path:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (14,))}
    inputs |= {k: PolicyFeature(FeatureType.VISUAL, (3, *image_hw)) for k in image_keys}
    cfg = ACTConfig(input_features=inputs, output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))},
                    chunk_size=6, n_action_steps=6, dim_model=32, n_heads=2, dim_feedforward=64, n_encoder_layers=1,
                    n_decoder_layers=1, use_vae=False, pretrained_backbone_weights=None, device="cpu")
    torch.manual_seed(0)
    policy = ACTPolicy(cfg)
    stats = {k: {s: torch.as_tensor(np.asarray(v)).float() for s, v in st.items()} for k, st in stats.items()
             if k in ("observation.state", "action", "observation.images.cam_high")}
    stats |= {k: stats["observation.images.cam_high"] for k in image_keys}
    if action_dim != 14:
        stats["action"] = {s: v[:action_dim] for s, v in stats["action"].items()}
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(directory)
    return directory


@pytest.fixture(scope="module")
def act_dir(world, tmp_path_factory):
    _, _, _, _, chunks, _ = world
    return _save_act(tmp_path_factory.mktemp("act") / "act", chunks.lerobot.meta.stats)


def test_lerobot_policy_adapter_acts_like_the_policy_itself(world, act_dir):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    _, _, model, spec, chunks, online = world
    adapter = LeRobotPolicy.from_pretrained(act_dir)
    adapter.check(views=spec.views, action_dim=14, state_dim=14)
    start = episode_starts(chunks, [0], horizon_chunks=2)[0]
    # at the policy's own resolution the adapter passes the frame through unchanged
    lerobot_frame = chunks.lerobot[int(chunks.lerobot.meta.episodes["dataset_from_index"][0])]
    img = lerobot_frame["observation.images.cam_high"][0]
    obs = {"observation.images.cam_high": img, "observation.state": start.state, "task": start.task}
    cfg = PreTrainedConfig.from_pretrained(act_dir)
    own = ACTPolicy.from_pretrained(act_dir, config=cfg)
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(act_dir))
    expected = post(own.predict_action_chunk(pre(dict(obs))))[0]
    adapter.reset()
    got = adapter(obs)
    assert got.shape == (6, 14)
    torch.testing.assert_close(got, expected)
    # in the world model: 6 actions per call, chunks of 4: two calls for two chunks (LeRobot's queue)
    queue = ActionQueue(adapter, 14)
    records = list(rollout_episode(model, online, queue, start))
    assert queue.calls == 2 and len(queue.queue) == 4
    first_call = adapter.__class__.from_pretrained(act_dir)
    first_call.reset()
    from imac_model.evaluate.closed_loop import observation_of

    expected = first_call(observation_of(start.reference, start.state, VIEWS, start.task))
    torch.testing.assert_close(torch.cat([records[0].actions, records[1].actions[:2]]), expected)


def test_a_policy_that_does_not_fit_the_world_model_is_refused(world, act_dir, tmp_path, capsys):
    root, ckpt, model, spec, chunks, online = world
    stats = chunks.lerobot.meta.stats
    seven = _save_act(tmp_path / "act7", stats, action_dim=7)
    with pytest.raises(InputError, match="outputs 7-dimensional actions, but the world model's dataset has 14"):
        LeRobotPolicy.from_pretrained(seven).check(views=VIEWS, action_dim=14, state_dim=14)
    top = _save_act(tmp_path / "top", stats, image_keys=("observation.images.top",))
    with pytest.raises(InputError, match=r"camera keys \['observation.images.top'\] do not match"):
        LeRobotPolicy.from_pretrained(top).check(views=VIEWS, action_dim=14, state_dim=14)
    LeRobotPolicy.from_pretrained(top, camera_map={"observation.images.top": "cam_high"}).check(
        views=VIEWS, action_dim=14, state_dim=14)
    out = tmp_path / "never"
    args = ["closed-loop", "--checkpoint", str(ckpt), "--output", str(out), "--episodes", "0", "--horizon-chunks", "1",
            "--no-progress"]
    assert model_main(["evaluate", *args, "--policy", f"lerobot:{top}"]) == 2
    assert "do not match the world model's views" in capsys.readouterr().err
    assert model_main(["evaluate", *args, "--policy", f"lerobot:{seven}"]) == 2
    assert "7-dimensional actions" in capsys.readouterr().err
    # a plain callable with the wrong action size is refused at its first answer; nothing is left behind
    with pytest.raises(InputError, match="returned 3-dimensional actions"):
        run_closed_loop(model, chunks, online, lambda obs: torch.zeros(4, 3), out,
                        config=ClosedLoopConfig(episodes=(0,), horizon_chunks=1), progress=False)
    # a checkpoint trained with another conditioning mode than asked
    assert model_main(["evaluate", *args, "--policy", "hold", "--mode", "motion"]) == 2
    assert "trained with conditioning mode 'motion+contact', not 'motion'" in capsys.readouterr().err
    assert not out.exists() and not list(tmp_path.glob(".never*"))


def test_the_output_of_a_user_and_a_staging_path_not_ours_are_refused_before_any_work(world, tmp_path, capsys):
    """``--output DIR --overwrite`` where DIR is a user's directory (not a dataset), and a
    ``.DIR.staging`` next to the output that we did not make: both refused before the checkpoint
    is even read (a missing checkpoint gives the same answer), and nothing is deleted."""
    _, ckpt, model, spec, chunks, online = world
    mine = tmp_path / "my_results"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's file\n")
    staged = tmp_path / ".generated.staging"
    staged.mkdir()
    (staged / "thesis.tex").write_text("not ours\n")
    for out, what in ((mine, "is a directory but not a LeRobot dataset"), (tmp_path / "generated", "was not made by imac_data")):
        for checkpoint in (str(ckpt), str(tmp_path / "no_such_checkpoint")):
            assert model_main(["evaluate", "closed-loop", "--checkpoint", checkpoint, "--policy", "recorded",
                               "--output", str(out), "--overwrite", "--episodes", "0", "--horizon-chunks", "1",
                               "--no-progress"]) == 2
            assert what in capsys.readouterr().err
    # the writer itself refuses the same (its own check, under the output's lock)
    with pytest.raises(InputError, match="not a LeRobot dataset"):
        GeneratedDatasetWriter(mine, "local/mine", spec, overwrite=True)
    with pytest.raises(InputError, match="was not made by imac_data"):
        run_closed_loop(model, chunks, online, "recorded", tmp_path / "generated", overwrite=True,
                        config=ClosedLoopConfig(episodes=(0,), horizon_chunks=1), progress=False)
    assert (mine / "notes.txt").read_text() == "a user's file\n" and sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    assert (staged / "thesis.tex").read_text() == "not ours\n" and sorted(p.name for p in staged.iterdir()) == ["thesis.tex"]
    assert not (tmp_path / "generated").exists() and not list(tmp_path.glob(".*.lock"))
    # guidance on a model trained without conditioning.dropout: refused, naming the field, and nothing written
    assert model_main(["evaluate", "closed-loop", "--checkpoint", str(ckpt), "--policy", "recorded", "--guidance", "2",
                       "--output", str(tmp_path / "guided"), "--episodes", "0", "--no-progress"]) == 2
    assert "conditioning.guidance: 2.0 needs a model trained with conditioning.dropout" in capsys.readouterr().err
    assert not (tmp_path / "guided").exists()


def test_overwrite_replaces_a_generated_dataset_through_the_staged_flow(world, tmp_path):
    """A dataset of generated episodes is ours: --overwrite replaces it (swapped into place, no
    sibling left behind); an aborted run leaves the previous one as it was."""
    _, _, model, spec, chunks, online = world
    out = tmp_path / "gen"
    config = ClosedLoopConfig(episodes=(0,), horizon_chunks=1)
    run_closed_loop(model, chunks, online, "recorded", out, config=config, progress=False)
    with pytest.raises(InputError, match="already exists"):
        run_closed_loop(model, chunks, online, "recorded", out, config=config, progress=False)
    before = (out / "meta" / "info.json").read_bytes()
    with pytest.raises(InputError, match="returned 3-dimensional actions"):
        run_closed_loop(model, chunks, online, lambda obs: torch.zeros(4, 3), out, config=config, overwrite=True,
                        progress=False)
    assert (out / "meta" / "info.json").read_bytes() == before
    run_closed_loop(model, chunks, online, "recorded", out, config=config, overwrite=True, progress=False)
    assert LeRobotDataset("local/gen", root=out).meta.total_episodes == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gen"]


# --------------------------------------------------------------------------- metrics, statistics, JSON


def test_video_metrics_cli_writes_the_protocol(world, tmp_path):
    _, ckpt, *_ = world
    out = tmp_path / "metrics.json"
    assert model_main(["evaluate", "video-metrics", "--checkpoint", str(ckpt), "--episodes", "1", "--chunks", "2", "--json", str(out),
                     "--no-progress"]) == 0
    result = json.loads(out.read_text())
    p = result["protocol"]
    assert p["frames"] == 8 and p["views"] == list(VIEWS) and p["sampler_steps"] == 2 and p["seed"] == 0
    assert p["resolution"]["cam_high"] == [32, 40] and p["num_samples"] == 2  # 21 frames: two 2-chunk rollouts
    for key in (*VIEWS, "mosaic"):
        assert 0 < result["pooled"][key]["mse"] < 1


def test_strict_json_names_non_finite_values(tmp_path):
    path = write_json(tmp_path / "r.json", {"pooled": {"psnr": float("inf"), "mse": 0.0},
                                                 "per_frame": [1.0, float("nan"), -float("inf")]})

    def refuse(name):
        raise AssertionError(f"non-standard JSON constant {name}")

    data = json.loads(path.read_text(), parse_constant=refuse)
    assert data["pooled"] == {"psnr": None, "mse": 0.0} and data["per_frame"] == [1.0, None, None]
    assert data["nonfinite"] == {"pooled.psnr": "inf", "per_frame[1]": "nan", "per_frame[2]": "-inf"}


def test_correlate_cli_reads_per_episode_successes(tmp_path):
    from scipy.stats import pearsonr

    rng = np.random.default_rng(0)
    rates = {"a": (0.2, 0.3), "b": (0.5, 0.4), "c": (0.9, 0.8)}
    rows, wm_rates, real_rates = [], [], []
    for policy, (w, r) in rates.items():
        for group in ("g1", "g2"):
            ws, rs = rng.random(20) < w, rng.random(20) < r
            rows += [(policy, group, "world_model", int(s)) for s in ws] + [(policy, group, "real", int(s)) for s in rs]
            wm_rates.append(ws.mean())
            real_rates.append(rs.mean())
    path = tmp_path / "outcomes.csv"
    with path.open("w", newline="") as f:
        csv.writer(f).writerows([("policy", "group", "source", "success"), *rows])
    out, png = tmp_path / "corr.json", tmp_path / "corr.png"
    assert model_main(["evaluate", "correlate", "--outcomes", str(path), "--json", str(out), "--png", str(png),
                     "--replicates", "200"]) == 0
    result = json.loads(out.read_text())
    assert result["levels"]["group"]["n_points"] == 6
    assert result["levels"]["group"]["pearson"]["value"] == pytest.approx(pearsonr(wm_rates, real_rates)[0])
    assert png.stat().st_size > 1000
    bad = tmp_path / "bad.csv"
    bad.write_text("policy,source,success\na,simulator,1\n")
    assert model_main(["evaluate", "correlate", "--outcomes", str(bad), "--json", str(out)]) == 2

"""The policy-ranking benchmark (docs/ranking.md): the lift's success against gym-aloha's own
reward, the lift judge against MuJoCo, the two runners' observation contract, interventions,
an outside policy module through both runners, and the whole benchmark at toy size."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tarfile
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from dm_control.mujoco.engine import Physics
from gym_aloha.tasks.sim import TransferCubeTask
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from safetensors.torch import load_file

from benchmarks import ablation, cpu_ablation, gate_diagnosis, outcome_probe
from imac_data.cli import main as imac_main
from imac_data.cli.parser import TASKS as CLI_TASKS
from imac_data.console import scheduling
from imac_data.core.cameras import save_calibration
from imac_data.core.depth import depth_codec_of
from imac_data.core.robot.aloha import SIM_TASKS, mjcf_path
from imac_data.dataset.output import output_lock
from imac_data.errors import InputError
from imac_data.layout import STATE, depth_key, image_key
from imac_data.metadata import dataset_info
from imac_data.sources.hdf5 import read_episode, write_episode
from imac_data.sources.sim.env import SimEnv
from imac_model.cli import main as model_main
from imac_model.cli.parser import build_parser
from imac_model.cli.ranking import _plan, stages_to_run
from imac_model.cli.ranking import _run_stages as run_stages
from imac_model.config import RunConfig
from imac_model.data import mosaic
from imac_model.data.chunks import open_metadata
from imac_model.data.pack import Pack, write_pack
from imac_model.data.scene_warp import SceneWarp
from imac_model.evaluate.closed_loop import episode_starts, rollout_episode
from imac_model.evaluate.policies import lerobot_dir, load_policy
from imac_model.evaluate.simulator import SimRunConfig, SimRunner, run_policy
from imac_model.evaluate.success import episode_frames
from imac_model.experiments.ranking import plan as plan_module
from imac_model.experiments.ranking.benchmark import STAGE_FUNCTIONS
from imac_model.experiments.ranking.evaluation import chunk_end_heights, evaluate_mode, policy_dir
from imac_model.experiments.ranking.gate import measure_gate, read_gates
from imac_model.experiments.ranking.gpu import export_runs, import_gpu_runs, runs_file
from imac_model.experiments.ranking.judge import LiftJudge
from imac_model.experiments.ranking.perception import redness, without_cube
from imac_model.experiments.ranking.plan import (
    CHECKPOINTS,
    EVAL_REPO,
    GATED_MODE,
    POLICY_MODULE,
    TRAIN_REPO,
    TRAIN_SEED0,
    RankingPlan,
    checkpoints_plan,
    command_flags,
    slug,
    toy_plan,
)
from imac_model.experiments.ranking.policies import (
    TRAINING_OFFSETS,
    VIEWS,
    WORKSPACE,
    LiftPolicy,
    closed_loop,
    open_loop,
    training_policy,
)
from imac_model.experiments.ranking.report import _relative, rewrite_report, training_log, write_report
from imac_model.experiments.ranking.report_text import _by_family, budget, parting_chunks, verdict_pairs
from imac_model.experiments.ranking.shipped import sha256
from imac_model.experiments.ranking.simulate import simulate_training_part
from imac_model.experiments.ranking.training import GateStop, stage_train
from imac_model.experiments.stages import REPO_ROOT, mark_trained
from imac_model.models.checkpoint import list_checkpoints, load_world_model, save_checkpoint
from imac_model.models.world_model import WorldModel
from imac_model.modes import CONTROL_STREAMS, MODES, ConditioningMode, streams_of_mode
from imac_model.pipelines.online_controls import OnlineControls
from imac_model.pipelines.packed_contact import PackedContact
from imac_model.pipelines.rollout import last_frame, rollout_loss
from imac_model.pipelines.sampling import open_chunks
from imac_model.training import train as train_cli
from imac_model.training.dataset_source import model_spec
from imac_model.training.pack_source import PackSource
from imac_model.training.runs import RUNS_FILE, RunsFile
from imac_model.training.runs import main as runs_main
from imac_model.training.train import evaluation_items, heldout_loss

REPO = "local/lift_test"
SEED = 200  # closed_loop lifts the cube from this start; a 4.5 cm offset misses it
ROOT = Path(__file__).resolve().parents[1]
TARGET_TOLERANCE = 0.015  # metres: how closely a closed-loop grasp target follows a moved cube


class Recording:
    """Wraps a policy; keeps what it was shown and what it answered."""

    def __init__(self, policy):
        self.policy, self.name = policy, f"recording_{policy.name}"
        self.seen, self.answered = [], []

    def reset(self):
        self.seen.clear()
        self.answered.clear()
        self.policy.reset()

    def __call__(self, observation):
        self.seen.append(observation)
        self.answered.append(self.policy(observation))
        return self.answered[-1]


@pytest.fixture(scope="module")
def runner():
    with SimRunner(SimRunConfig(views=VIEWS)) as r:
        yield r


@pytest.fixture(scope="module")
def lift(runner, tmp_path_factory):
    """Two MuJoCo episodes from the same start (a lift, a miss) built with imac build, and a
    random tiny world model on that dataset."""
    tmp = tmp_path_factory.mktemp("lift")
    src = tmp / "src"
    src.mkdir()
    save_calibration(src / "calibration.json", runner.cameras)
    episodes, final_qpos, recorders = [], [], []
    for i, policy in enumerate((closed_loop(), LiftPolicy("miss", relocalise=None, offset=(0.0, 0.045)))):
        rec = Recording(policy)
        ep = runner.run_episode(rec, SEED)
        write_episode(src / f"episode_{i}.hdf5", ep.raw_episode("lift", policy.name, runner.fps))
        episodes.append(ep)
        final_qpos.append(runner.env.data.qpos.copy())
        recorders.append(rec)
    root = tmp / "dataset"
    before = scheduling()
    assert imac_main(["build", "--repo", REPO, "--recipe", str(ROOT / "recipes" / "aloha_sim_lift.yaml"), "--source",
                      str(src), "--root", str(root), "--episodes", "2", "--workers", "1", "--no-progress"]) == 0
    # the in-process build left this process's scheduling alone (its AV1 encoder would make it real-time,
    # and the toy benchmark's simulations, started from it, would starve each other: docs/building.md)
    assert scheduling() == before
    run = RunConfig().replace(**{"data.dataset": REPO, "data.root": str(root), "conditioning.mode": "motion+contact",
                                 "backbone.small.dim": 32, "backbone.small.depth": 1, "backbone.small.heads": 2,
                                 "data.view_height": 48, "data.views": list(VIEWS),
                                 "flow.sample_steps": 2})
    spec, _ = model_spec(run, open_metadata(run.data))
    torch.manual_seed(0)
    model = WorldModel(spec)
    for p in model.parameters():  # zero-initialised layers: randomise, so the frames depend on the inputs
        if not p.detach().any():
            torch.nn.init.normal_(p, std=0.05)
    ckpt = save_checkpoint(tmp / "ckpt", model=model, spec=spec, run=run)
    model, spec = load_world_model(ckpt)
    chunks = open_chunks(spec, REPO, str(root))
    online = OnlineControls.from_dataset(root, spec, info=dataset_info(chunks.lerobot.meta))
    return {"root": root, "episodes": episodes, "final_qpos": final_qpos, "recorders": recorders, "ckpt": ckpt,
            "model": model, "spec": spec, "chunks": chunks, "online": online}


def test_the_command_line_knows_every_simulated_task():
    assert CLI_TASKS == SIM_TASKS and "lift" in SIM_TASKS


def test_lift_success_agrees_with_gym_aloha_reward(lift):
    """gym-aloha's own TransferCubeTask.get_reward (dm_control physics of its XML, our final
    state): a lift we call a success is its level 2 (right gripper holds the cube off the table),
    a miss is below it."""
    physics = Physics.from_xml_path(str(mjcf_path("transfer_cube")))
    task = TransferCubeTask(random=None)
    rewards = []
    for qpos in lift["final_qpos"]:
        physics.data.qpos[:] = qpos
        physics.forward()
        rewards.append(task.get_reward(physics))
    assert [ep.success for ep in lift["episodes"]] == [True, False]
    assert rewards[0] == 2 and rewards[1] < 2
    assert lift["episodes"][0].max_reward == 2


def test_lift_judge_agrees_with_mujoco_on_real_frames(runner, lift):
    """Read through LeRobot from the built dataset: the judge's cube height against MuJoCo's."""
    ds = LeRobotDataset(REPO, root=lift["root"])
    frames = episode_frames(ds, [0, 1], [image_key(v) for v in VIEWS], 4, geometry=True)
    judge = LiftJudge()
    assert judge.judge(frames).tolist() == [True, False]
    held, missed = (judge.heights(f)[-1] for f in frames)
    cube_z = lift["final_qpos"][0][runner.env.layout.object_qadr["box"] + 2]
    assert cube_z - 0.01 <= held <= cube_z + 0.03  # the visible faces lie up to a half side above the centre
    assert np.isnan(missed)  # the cube lies on the table, far from the lifted gripper
    # with the cube painted out, the held cube is gone and the arm alone says nothing
    painted = [dataclasses.replace(f, frames={c: without_cube(x) for c, x in f.frames.items()}) for f in frames]
    assert judge.judge(painted).tolist() == [False, False]
    assert all((redness(x) <= 0.05).all() for f in painted for x in f.frames.values())


def test_the_cube_read_at_each_chunks_end_is_where_mujoco_has_it(runner, lift):
    """Which chunk a closed loop parts from MuJoCo in is read from the frames at the chunks' ends: there the
    judge's cube height, read through LeRobot from the built dataset, against MuJoCo's box re-simulated from the
    start and the recorded actions."""
    ds = LeRobotDataset(REPO, root=lift["root"])
    judge, chunk = LiftJudge(), runner.config.chunk
    read = chunk_end_heights(judge, ds, [0, 1], chunk, runner.config.chunks)
    env = SimEnv("lift", frame_stride=runner.config.frame_stride, settle_s=runner.config.settle_s)
    lifted = []
    for episode, heights in zip(lift["episodes"], read):
        env.reset(SEED)
        box = []
        for t, action in enumerate(episode.action[:-1], start=1):  # the last frame's action repeats the one before
            env.step(action)
            if t % chunk == 0:
                box.append(env.object_position("box")[2])
        assert len(box) == len(heights) == runner.config.chunks
        seen = ~np.isnan(heights)
        assert (heights[seen] >= np.array(box)[seen] - 0.01).all() and (heights[seen] <= np.array(box)[seen] + 0.03).all()
        held = (np.array(box) >= judge.lifted_z).tolist()
        assert (heights >= judge.lifted_z).tolist() == held  # NaN compares False: a cube not near the gripper
        lifted.append(held)
    assert lifted[0][-1] and not any(lifted[1])  # the lift is held up at the end; the miss never
    assert not lifted[0][0]  # and it starts on the table


def test_both_runners_give_a_policy_the_same_observation(lift):
    """One recording policy in MuJoCo and in the world model from the same start: the same keys,
    shapes and types, queried at the same chunk boundaries, the same first frame, and the state
    rule (measured at the first frame, then phi of the policy's own actions) in both."""
    sim = lift["recorders"][0]
    rec = Recording(closed_loop())
    start = episode_starts(lift["chunks"], [0], horizon_chunks=4)[0]
    list(rollout_episode(lift["model"], lift["online"], rec, start))
    assert len(sim.seen) == len(rec.seen) == 4
    rig = lift["online"].rig
    for seen, answered in ((sim.seen, sim.answered), (rec.seen, rec.answered)):
        assert sorted(seen[0]) == sorted(sim.seen[0])
        for obs in seen:
            for v in VIEWS:
                assert obs[image_key(v)].shape == (3, 48, 64) and obs[image_key(v)].dtype == torch.float32
                assert obs[depth_key(v)].shape == (48, 64) and obs[depth_key(v)].dtype == torch.float32
            assert obs[STATE].shape == (14,) and obs["task"] == "Pick up the cube with the right arm and lift it."
        for n in range(1, 4):
            phi = rig.rollout(seen[n - 1][STATE][None], answered[n - 1][None])[0, -1]
            torch.testing.assert_close(seen[n][STATE], phi.float())
    a, b = sim.seen[0], rec.seen[0]
    torch.testing.assert_close(a[STATE], b[STATE])  # the measured start state (float32 in the dataset)
    for v in VIEWS:
        assert (a[image_key(v)] - b[image_key(v)]).abs().mean() < 0.01  # through the AV1 video and back
        valid_a, valid_b = a[depth_key(v)] > 0, b[depth_key(v)] > 0  # beyond the far plane: unknown in both
        assert (valid_a == valid_b).float().mean() > 0.98
        both = valid_a & valid_b
        assert (a[depth_key(v)] - b[depth_key(v)])[both].abs().median() < 0.005  # metres, through the colour codec


def test_moving_the_cube_moves_a_closed_loop_policys_grasp_target_in_both_runners(runner, lift):
    shift = np.array([0.0, 0.03, 0.0])

    def move(env, n):
        env.move_object("box", env.object_position("box") + shift)

    def targets(policy, intervene=None):
        runner.run_episode(policy, SEED, intervene=intervene)
        return np.array(policy.targets)

    # MuJoCo: the closed-loop policy follows the cube after frame 0; the open-loop one does not. The cube's
    # estimate is pulled towards the camera by the faces it sees (up to a half side from the workspace view, which
    # sees the near face), so a moved cube is followed to within 1.5 cm (docs/ranking.md, "The policies")
    moved = targets(closed_loop(), move)[1] - targets(closed_loop())[1]
    assert np.linalg.norm(moved - shift[:2]) < TARGET_TOLERANCE, moved
    np.testing.assert_allclose(targets(open_loop(), move), targets(open_loop()))

    # the world model: the frame it goes on from after chunk 0 is MuJoCo's, with and without the move
    codec = depth_codec_of(dataset_info(lift["chunks"].lerobot.meta))
    start = episode_starts(lift["chunks"], [0], horizon_chunks=2)[0]

    def wm_targets(with_move: bool) -> np.ndarray:
        policy = Recording(closed_loop())

        def intervene(reference, n):
            runner.env.reset(SEED)
            for action in policy.answered[0]:
                runner.env.step(action.double().numpy())
            if with_move:
                move(runner.env, n)
            return runner.reference(runner.env.render(), codec)[None]

        list(rollout_episode(lift["model"], lift["online"], policy, start, intervene=intervene))
        return np.array(policy.policy.targets)

    moved = wm_targets(True)[1] - wm_targets(False)[1]
    assert np.linalg.norm(moved - shift[:2]) < TARGET_TOLERANCE, moved


OUTSIDE = '''
import torch

from imac_model.experiments.ranking.judge import LiftJudge


class Wave:
    """Lowers the right shoulder by 0.1 rad over each chunk; reads the first view's depth."""

    name = "wave"

    def __init__(self):
        self.calls = 0

    def reset(self):
        self.calls = 0

    def __call__(self, observation):
        self.calls += 1
        depth = next(v for k, v in observation.items() if k.startswith("observation.depth."))
        assert depth.ndim == 2 and float(depth.max()) > 0, "no depth in the observation"
        actions = observation["observation.state"].repeat(8, 1)
        actions[:, 8] -= torch.linspace(0.0125, 0.1, 8)
        return actions


class Held(LiftJudge):
    """The lift judge, written by someone else."""

    name = "held"
'''


def test_an_outside_policy_module_runs_through_both_runners_from_its_folder(lift, tmp_path):
    """The console script, run from the folder that holds the policy and judge module, with no
    PYTHONPATH for it: `python:MODULE:NAME` imports MODULE from the current directory. (PYTHONPATH
    names only this checkout, so that the console script runs the code under test.)"""
    (tmp_path / "outside_policy.py").write_text(textwrap.dedent(OUTSIDE))
    command = str(Path(sys.executable).parent / "imac-model")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    spec = "python:outside_policy:Wave"
    sim = subprocess.run([command, "evaluate", "simulator", "--policy", spec, "--seeds", "3..4",
                          "--chunks", "2", "--output", "sim", "--no-progress"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert sim.returncode == 0, sim.stderr[-2000:]
    assert "python:outside_policy:Wave on lift: success 0/2" in sim.stdout
    outcome = json.loads((tmp_path / "sim" / "outcomes.json").read_text())
    assert [e["seed"] for e in outcome["episodes"]] == [3, 4] and outcome["episodes"][0]["policy_calls"] == 2
    assert (tmp_path / "sim" / "episode_1.hdf5").is_file()
    wm = subprocess.run([command, "evaluate", "closed-loop", "--checkpoint",
                         str(lift["ckpt"]), "--dataset", REPO, "--root", str(lift["root"]), "--policy", spec,
                         "--episodes", "0", "--horizon-chunks", "2", "--steps", "1",
                         "--judge", "python:outside_policy:Held", "--output", "wm", "--no-progress"],
                        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert wm.returncode == 0, wm.stderr[-2000:]
    result = json.loads((tmp_path / "wm" / "closed_loop.json").read_text())
    assert result["protocol"]["policy"] == "wave" and result["episodes"][0]["policy_calls"] == 2
    assert result["episodes"][0]["success"] is False and result["protocol"]["judge"] == "held"


def test_built_episodes_record_their_simulated_start(lift):
    eps = LeRobotDataset(REPO, root=lift["root"]).meta.episodes
    assert list(eps["imac/sim_seed"]) == [SEED, SEED] and list(eps["imac/sim_task"]) == ["lift", "lift"]
    assert eps.features["imac/sim_seed"].dtype == "int64" and list(eps["imac/sim_settle_s"]) == [0.0, 0.0]


class StartRecording(Recording):
    """A :class:`Recording` that takes the start the runner names, and keeps it."""

    takes_start = True

    def __init__(self, policy):
        super().__init__(policy)
        self.starts = []

    def reset(self, start=None):
        self.starts.append(start)
        self.seen.clear()
        self.answered.clear()
        self.policy.reset(start)


def test_both_runners_name_the_simulated_start_to_a_policy_that_takes_it(runner, lift):
    """A policy declaring ``takes_start`` is reset with the start's gym seed: by MuJoCo's runner from the seed it
    runs, by the world model's from the episode's recorded ``imac/sim_seed``. So graded action noise
    (``noisy:STD:SPEC``) draws the same noise from the same start in both: its first chunk less the clean policy's
    answer to the same observation is the same in both runners."""
    noise = {}
    for name, run in (("mujoco", lambda p: runner.run_episode(p, SEED)),
                      ("world model", lambda p: list(rollout_episode(
                          lift["model"], lift["online"], p, episode_starts(lift["chunks"], [0], horizon_chunks=1)[0])))):
        recording = StartRecording(load_policy(f"noisy:0.05:python:{POLICY_MODULE}:closed_loop"))
        run(recording)
        clean = closed_loop()
        clean.reset()
        assert recording.starts == [SEED]
        noise[name] = recording.answered[0] - clean(recording.seen[0])
    torch.testing.assert_close(noise["mujoco"], noise["world model"])
    assert 0.04 < float(noise["mujoco"].std()) < 0.06


def test_a_policy_of_another_task_is_refused_by_the_closed_loop(lift, tmp_path, monkeypatch, capsys):
    (tmp_path / "insert_policy.py").write_text("from imac_model.evaluate.policies import hold_policy\n\n\n"
                                               "def inserter(observation):\n    return hold_policy(observation)\n\n\n"
                                               "inserter.tasks = ('Insert the peg into the socket.',)\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    code = model_main(["evaluate", "closed-loop", "--checkpoint", str(lift["ckpt"]), "--dataset", REPO, "--root",
                       str(lift["root"]), "--policy", "python:insert_policy:inserter", "--episodes", "1",
                       "--output", "wm", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "policy inserter acts on ['Insert the peg into the socket.'] (its tasks), but the task of start " \
           "episode 1 is 'Pick up the cube with the right arm and lift it.'" in err
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "__pycache__") == ["insert_policy.py"]


def test_training_policies_run_their_share_of_the_training_rollouts_from_the_rollouts_own_starts(tmp_path):
    """A plan's training_policies run their share of the world model's training rollouts (0.25: every fourth,
    the specs in turn); the rest stay the scripted mix. Each such rollout is what the policy does from that
    rollout's start when run alone (the same actions); the plan round-trips; bad settings are refused."""
    spec_a, spec_b = f"python:{POLICY_MODULE}:open_loop", f"python:{POLICY_MODULE}:closed_loop_1p5cm"
    plan = dataclasses.replace(toy_plan(tmp_path / "work", tmp_path / "docs"), train_episodes=8, jobs=1,
                               training_policies=(spec_a, spec_b))
    assert [plan.training_policy_of(i) for i in range(8)] == [None, None, None, spec_a, None, None, None, spec_b]
    assert RankingPlan.from_dict(json.loads(json.dumps(plan.to_dict()))) == plan
    assert RankingPlan.from_dict({k: v for k, v in plan.to_dict().items()
                                  if not k.startswith("training_polic")}).training_policy_of(3) is None  # older plans
    simulate_training_part(plan, 0)
    out = plan.work / "sim" / "train" / "part_0"
    rows = {r["index"]: r for r in json.loads((out / "outcomes.json").read_text())}
    assert sorted(rows) == list(range(8))
    assert [rows[i]["policy"] for i in (3, 7)] == [slug(spec_a), slug(spec_b)]
    assert rows[3]["offset"] is None and all(rows[i]["policy"].startswith("mix_") and len(rows[i]["offset"]) == 2
                                             for i in (0, 1, 2, 4, 5, 6))
    alone = run_policy(load_policy(spec_b), [TRAIN_SEED0 + 7], tmp_path / "alone", progress=False,
                       config=SimRunConfig(chunks=plan.chunks, view_height=plan.view_size[0],
                                           view_width=plan.view_size[1], views=plan.views, settle_s=plan.settle_s))
    assert alone[0]["success"] == rows[7]["success"]
    np.testing.assert_array_equal(read_episode(tmp_path / "alone" / "episode_0.hdf5").action,
                                  read_episode(out / "ep_00007" / "episode_0.hdf5").action)
    for bad, match in [({"training_policy_share": 0.0}, "training_policy_share"),
                       ({"training_policies": ("open_loop",)}, "training_policies")]:
        with pytest.raises(InputError, match=match):
            dataclasses.replace(plan, **bad)


@pytest.fixture(scope="module")
def toy_run(tmp_path_factory):
    """make ranking at the CI size: tiny backbone, 2 policies, 4 episodes each, 2 chunks, 2 modes,
    2 sampler steps."""
    tmp = tmp_path_factory.mktemp("toy_ranking")
    work, docs = tmp / "work", tmp / "docs"
    # as a GPU loan is prepared (docs/ranking.md, "The GPU preset"): the pack first, then every other stage
    assert model_main(["ranking", "--toy", "--work", str(work), "--docs", str(docs), "--stages", "pack"]) == 0
    plan = RankingPlan.load(work / "plan.json")
    (tmp / "after_pack.json").write_text(json.dumps({
        "pack_sha256": sha256(plan.pack), "train_dataset": (plan.train_dataset / "meta" / "info.json").is_file(),
        "eval_side": [str(p) for p in (plan.eval_dataset, *map(plan.sim_dir, plan.names)) if p.exists()]}))
    assert model_main(["ranking", "--toy", "--work", str(work), "--docs", str(docs)]) == 0
    return work, docs


def test_ranking_benchmark_end_to_end_at_toy_size(toy_run):
    work, docs = toy_run
    results = json.loads((docs / "results.json").read_text())
    assert set(results["statistics"]) == {"motion+contact", "none"}
    assert results["judges"]["real"]["lift_geometry"]["n"] == 8
    assert results["judges"]["real"]["lift_geometry"]["accuracy"] == 1.0  # two chunks end before any lift
    assert results["judges"]["cube_masked"]["lift_geometry"]["n"] == 8
    assert all(results["evaluations"]["none"]["none_check"]["bit_identical"])
    assert {"simulate", "build", "decode", "train", "judges", "evaluate"} <= set(results["stages"])  # before the report
    assert (docs / "scatter_motion_contact.png").is_file() and "## Time per stage" in (docs / "README.md").read_text()
    # every stage's log says what a user acts on: not the datasets library's warning at each LeRobot parquet load
    assert not [p.name for p in (work / "logs").glob("*.log") if "Cannot enable progress bars" in p.read_text()]
    # the early gate: motion+contact measured on the held-out training rollouts, against the simulator's own outcomes
    plan = RankingPlan.load(work / "plan.json")
    (gate,) = results["gates"]["motion+contact"]  # none has no gate
    simulated = {r["index"]: r["success"] for part in (work / "sim" / "train").glob("part_*")
                 for r in json.loads((part / "outcomes.json").read_text())}
    assert gate["episodes"] == plan.held_out_episodes() and gate["labels"] == [simulated[e] for e in gate["episodes"]]
    offsets = [r["offset"] for part in (work / "sim" / "train").glob("part_*")
               for r in json.loads((part / "outcomes.json").read_text())]
    assert plan.training_offsets == "across" and all(abs(x) <= 0.02 and abs(y) <= 0.05 for x, y in offsets)
    assert gate["budget_minutes"] == plan.cpu_minutes and set(gate["from_chunk"]) == {"0", "1"}
    assert set(gate["cube"]) == set(gate["cube_at_chunk_end"]) == set(plan.views)  # every view the model generates
    assert all([len(c) for c in gate["cube"][v]["recorded"]] == [plan.chunks] * len(gate["episodes"]) for v in plan.views)
    assert all([len(x) for x in c.values()] == [plan.chunks] * 2 for c in gate["cube_at_chunk_end"].values())
    # every replay sampled with each of the gate's seeds, pooled; the diagnosis replays them the same way
    assert gate["seeds"] == plan.gate_seeds == 2
    assert all(c["n"] == 2 * len(gate["episodes"]) and len(c["balanced_accuracy_per_seed"]) == 2
               for c in gate["from_chunk"].values())
    diagnosis = gate_diagnosis.diagnose(plan, "motion_contact", seeds=2, ways=("generated",))
    assert [x for row in diagnosis["generated"]["judged_lifted"] for x in row] == \
        [int(x) for x in gate["from_chunk"]["0"]["predicted"]]
    # the evaluation replays: every episode with each of the gate's seeds (drawn as the gate draws them), pooled
    for rec in results["evaluations"]["motion+contact"]["recorded"].values():
        n = len(rec["episodes"])
        assert rec["seeds"] == plan.gate_seeds and [r["seed"] for r in rec["rows"]] == [0] * n + [1] * n
        assert [r["episode"] for r in rec["rows"]] == rec["episodes"] * 2 and len(rec["labels"]) == n
        per_seed = rec["accuracy_per_seed"]["lift_geometry"]
        assert len(per_seed) == 2 and rec["accuracy"]["lift_geometry"] == pytest.approx(sum(per_seed) / 2)
        assert all(a["mse_per_chunk"] != b["mse_per_chunk"] for a, b in zip(rec["rows"][:n], rec["rows"][n:]))
        # the views are of one size: their errors average to the whole mosaic's
        by_view = np.array(list(rec["mse_per_chunk_by_view"].values()))
        assert by_view.shape == (len(plan.views), plan.chunks)
        np.testing.assert_allclose(by_view.mean(axis=0), rec["mse_per_chunk"], rtol=1e-5)
    report = (docs / "README.md").read_text()
    assert all(f"| motion+contact | {plan.steps} | {v} |" in report for v in (*plan.views, "all views"))
    # start by start: MuJoCo's verdict is the simulator's own at the start's seed, the world model's its episode's
    for name in plan.names:
        simulated = {row["seed"]: row["success"]
                     for row in json.loads((plan.sim_dir(name) / "outcomes.json").read_text())["episodes"]}
        generated = results["evaluations"]["motion+contact"]["policies"][name]["episodes"]
        assert verdict_pairs(plan, results, "motion+contact", name) == [
            (simulated[plan.eval_seeds()[s][1]], row["success"]) for s, row in zip(plan.wm_starts(), generated)]
        assert f"| motion+contact | {name} | {len(generated)} |" in report
        # which chunk: the cube at every chunk's end in both runs, and how far apart their actions were
        assert all(len(row["chunk_held"]) == len(row["real_chunk_held"]) == len(row["action_gap"]) == plan.chunks
                   for row in generated)
        assert not any(x for row in generated for x in row["real_chunk_held"])  # two chunks end before any lift
        assert all(g >= 0 for row in generated for g in row["action_gap"])
        assert parting_chunks(plan, results, "motion+contact", name)["parted"] == sum(a != b for a, b in verdict_pairs(
            plan, results, "motion+contact", name))
    assert "Which chunk:" in report and "| motion+contact | closed_loop | " in report.split("Which chunk:")[1]
    # against a guess: the per-start balanced accuracy over every policy's starts, counted here by hand
    pairs = [p for name in plan.names for p in verdict_pairs(plan, results, "motion+contact", name)]
    recalls = [sum(wm == c for real, wm in pairs if real == c) / n
               for c in (True, False) if (n := sum(real == c for real, _ in pairs))]
    assert f"| motion+contact | {sum(recalls) / len(recalls):.3f} | {len(pairs)} |" in report
    assert "**The best two-level guess**" in report
    assert "## The early gate" in report and "Where the cube goes wrong" in report and (docs / "gate.png").is_file()
    assert f"({sum(rec['labels'])} successes) x 2 seeds" in report
    # a second run finds every stage's outputs and only writes the report again
    stages = json.loads((work / "stages.json").read_text())
    assert model_main(["ranking", "--toy", "--work", str(work), "--docs", str(docs)]) == 0
    again = json.loads((work / "stages.json").read_text())[len(stages):]
    assert all(e["cpu_s"] < 5 for e in again if e["stage"] != "report"), again


def golden_of(work: Path, docs: Path) -> dict:
    """What the trainers' merge must keep of the toy run: held-out losses per logged step, gate verdicts,
    per-start verdicts, replay verdicts and RGB errors (tests/fixtures/toy_ranking_golden.json, from 40b4533)."""
    r = json.loads((docs / "results.json").read_text())
    out = {"heldout_loss": {}, "gate": {}, "per_start": {}, "replays": {}}
    for run in sorted((work / "runs").iterdir()):
        rows = [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines() if x.strip()]
        out["heldout_loss"][run.name] = {str(x["step"]): x["heldout_loss"] for x in rows if "heldout_loss" in x}
    for mode, gates in r["gates"].items():
        out["gate"][mode] = [{"step": g["step"], "labels": g["labels"],
                              "predicted": {c: v["predicted"] for c, v in g["from_chunk"].items()}} for g in gates]
    for mode, ev in r["evaluations"].items():
        out["per_start"][mode] = {p: [e["success"] for e in v["episodes"]] for p, v in ev["policies"].items()}
        out["replays"][mode] = {s: [[row["episode"], row["seed"], row["lift_geometry"], row["mse_per_chunk"]]
                                    for row in rec["rows"]] for s, rec in ev.get("recorded", {}).items()}
    return out


def test_the_toy_run_reproduces_the_golden_values_of_the_code_before_the_trainers_merged(toy_run):
    """The one trainer on the dataset path gives the toy run's held-out losses (to 1e-4 relative), gate verdicts,
    per-start and replay verdicts as the code before the merge gave them (its replays' RGB errors to 1e-2).
    The losses are bit-equal on one kind of CPU; on another, torch's float kernels round otherwise (1.9e-5 relative
    between the machines of 2026-12-01 and 2026-12-02; docs/verification.md, "Across machines")."""
    got = golden_of(*toy_run)
    want = json.loads((ROOT / "tests" / "fixtures" / "toy_ranking_golden.json").read_text())
    assert got["heldout_loss"].keys() == want["heldout_loss"].keys()
    for run, losses in want["heldout_loss"].items():
        assert got["heldout_loss"][run] == pytest.approx(losses, rel=1e-4), run
    assert got["gate"] == want["gate"] and got["per_start"] == want["per_start"]
    for mode, by_steps in want["replays"].items():
        for steps, rows in by_steps.items():
            assert [r[:3] for r in got["replays"][mode][steps]] == [r[:3] for r in rows]
            errors = [x for r in got["replays"][mode][steps] for x in r[3]]
            # the golden errors come from the trainer's float32 EMA weights; the run evaluates the float16 ones it
            # ships since 2026-12-01 (shipped.py), which move them in the third digit
            assert errors == pytest.approx([x for r in rows for x in r[3]], rel=1e-2)


def test_the_evaluate_stage_in_a_process_per_policy_gives_what_one_process_gives(toy_run, tmp_path):
    """The evaluate stage runs each policy's closed loop and each mode's replays in a process of its own; one process
    making all of a mode's in turn (evaluate_mode on a work directory without them) gets the same outcomes, so no
    state passes from one policy's closed loop to the next."""
    work, _ = toy_run
    plan = dataclasses.replace(RankingPlan.load(work / "plan.json"), work=tmp_path / "work", docs=tmp_path / "docs")
    plan.work.mkdir()
    for part in ("datasets", "judges", "runs"):
        (plan.work / part).symlink_to(work / part)
    mode = "motion+contact"
    evaluate_mode(plan, mode)

    def untimed(x):  # times apart, and paths inside either work directory named alike
        if isinstance(x, dict):
            return {k: untimed(v) for k, v in x.items() if k not in ("wall_s", "cpu_s")}
        if isinstance(x, list):
            return [untimed(v) for v in x]
        return x.replace(str(plan.work), "WORK").replace(str(work), "WORK") if isinstance(x, str) else x

    ours = json.loads((plan.wm_dir(mode) / "outcomes.json").read_text())
    stage = json.loads((RankingPlan.load(work / "plan.json").wm_dir(mode) / "outcomes.json").read_text())
    assert untimed(ours["policies"]) == untimed(stage["policies"]) and untimed(ours["recorded"]) == untimed(stage["recorded"])
    assert [p.name for p in sorted((work / "logs").glob("evaluate_motion_contact_*.log"))] == sorted(
        [f"evaluate_motion_contact_{n}.log" for n in plan.names] + ["evaluate_motion_contact_replays.log"])


def test_a_toy_mode_registered_alone_trains_is_gated_evaluated_and_reported(toy_run, tmp_path, monkeypatch):
    """Adding a conditioning mode touches one file: a mode registered in ``imac_model.modes.MODES`` alone (no other
    line of the package changed) is a mode of a ranking plan, trains on the toy run's training rollouts, is gated,
    evaluated and reported beside the toy run's modes. In this process: the stages' own processes would not see
    the registry patched here."""
    work, _ = toy_run
    toy = "motion-toy"
    monkeypatch.setitem(MODES, toy, ConditioningMode(streams=("motion",), label="toy motion"))
    ran = RankingPlan.load(work / "plan.json")
    plan = dataclasses.replace(ran, work=tmp_path / "work", docs=tmp_path / "docs", modes=ran.modes + (toy,))
    plan.work.mkdir()
    for part in ("datasets", "judges", "sim", "stages.json"):
        (plan.work / part).symlink_to(work / part)
    shutil.copytree(work / "chunkcache", plan.work / "chunkcache")  # the toy mode's own cache goes beside the others
    for mode in ran.modes:  # the toy run's trained and evaluated modes, as they are
        for done in (ran.run_dir(mode), ran.wm_dir(mode)):
            (plan.work / done.relative_to(work)).parent.mkdir(parents=True, exist_ok=True)
            (plan.work / done.relative_to(work)).symlink_to(done)
    run = plan.run_config(toy)
    assert run.conditioning.streams == ("motion",) and run.train.max_cpu_minutes == plan.cpu_minutes
    train_cli.train(run, progress=False)
    mark_trained(plan.run_dir(toy))  # as the train stage does
    gate = measure_gate(plan, plan.cpu_budget(toy), toy)
    evaluate_mode(plan, toy)
    write_report(plan)
    results = json.loads((plan.docs / "results.json").read_text())
    assert list(results["statistics"]) == list(plan.modes) and results["gates"][toy] == [gate]
    assert set(results["evaluations"][toy]["policies"]) == set(plan.names)  # it sees the actions: every policy
    assert "none_check" not in results["evaluations"][toy] and results["training"][toy]["finished"]
    report = (plan.docs / "README.md").read_text()
    assert f"| policy | MuJoCo | {' | '.join(plan.modes)} |" in report and f"| {toy} | lift_geometry |" in report
    assert f"| {toy} | {plan.cpu_budget(toy):g} |" in report  # its gate
    assert (plan.docs / f"scatter_{toy}.png").is_file()


def test_a_mode_trained_again_from_another_seed_is_a_run_of_its_own_and_the_goal_reads_their_mean(toy_run, tmp_path):
    """``motion+contact@seed1``: the same mode, data and budget from training seed + 1, through the train, evaluate
    and report stages; the goal's figures are the mean over the seeds (docs/ranking.md, "Seeds")."""
    work, _ = toy_run
    ran = RankingPlan.load(work / "plan.json")
    again = "motion+contact@seed1"
    plan = dataclasses.replace(ran, work=tmp_path / "work", docs=tmp_path / "docs", modes=ran.modes + (again,))
    plan.work.mkdir()
    for part in ("datasets", "judges", "sim", "chunkcache"):
        (plan.work / part).symlink_to(work / part)
    for mode in ran.modes:
        for done in (ran.run_dir(mode), ran.wm_dir(mode)):
            (plan.work / done.relative_to(work)).parent.mkdir(parents=True, exist_ok=True)
            (plan.work / done.relative_to(work)).symlink_to(done)
    (plan.work / "plan.json").write_text(json.dumps(plan.to_dict()))
    run = plan.run_config(again)
    assert (run.conditioning.mode, run.train.seed) == ("motion+contact", ran.seed + 1)
    assert plan.run_dir(again).name == "motion_contact_seed1" and plan.cpu_budget(again) == plan.cpu_minutes
    for stage in ("train", "evaluate", "report"):
        STAGE_FUNCTIONS[stage](plan)
    first, other = (training_log(plan.run_dir(m))["rows"] for m in ("motion+contact", again))
    assert [r["step"] for r in first] == [r["step"] for r in other] and first[-1]["loss"] != other[-1]["loss"]
    results = json.loads((plan.docs / "results.json").read_text())
    assert set(results["evaluations"][again]["policies"]) == set(plan.names)
    pearson = [results["statistics"][m]["lift_geometry"]["levels"]["policy"]["pearson"]["value"]
               for m in ("motion+contact", again)]
    mmrv = [results["statistics"][m]["lift_geometry"]["levels"]["policy"]["mmrv"]["value"]
            for m in ("motion+contact", again)]
    report = (plan.docs / "README.md").read_text()
    assert f"| {again} | lift_geometry | policy |" in report
    expect = f"MMRV {np.mean(mmrv):.3f} over 2 seeds: {mmrv[0]:.3f}, {mmrv[1]:.3f}"
    assert expect in report, report.split("**Goal**")[1][:400]
    assert (None in pearson) or f"Pearson {np.mean(pearson):.3f} over 2 seeds" in report
    with pytest.raises(InputError, match="@seedK"):
        dataclasses.replace(plan, modes=("motion+contact@seedX",))


def test_the_checkpoint_preset_is_its_files_plan_and_its_policy_stages_refuse_a_missing_checkpoint(tmp_path,
                                                                                                  monkeypatch):
    shipped = yaml.safe_load(CHECKPOINTS.read_text())
    names = [slug(p) for p in shipped["policies"]]
    assert len(set(names)) == len(names) >= 10 and "lerobot_020000" in names
    ckpt = tmp_path / "act" / "checkpoints" / "002000" / "pretrained_model"
    ckpt.mkdir(parents=True)
    (ckpt / "config.json").write_text("{}")  # the plan checks that a checkpoint is there; loading it is the runners'
    preset = tmp_path / "preset.yaml"
    scripted = [p for p in shipped["policies"] if p.startswith("python:")]
    relative = ckpt.relative_to(tmp_path)  # the preset's paths are relative to the repository
    monkeypatch.setattr(plan_module, "REPO_ROOT", tmp_path)
    preset.write_text(yaml.safe_dump({**shipped, "policies": [*scripted, f"lerobot:{relative}",
                                                              f"noisy:0.05:lerobot:{relative}"]}))
    plan = checkpoints_plan(tmp_path / "work", tmp_path / "docs", preset)
    assert plan.policies[-2:] == (f"lerobot:{ckpt}", f"noisy:0.05:lerobot:{ckpt}")
    assert plan.names == [slug(p) for p in scripted] + ["lerobot_002000", "lerobot_002000_noise0p05"]
    assert plan.modes == tuple(shipped["modes"])
    assert len(plan.eval_seeds()) == len(plan.wm_starts()) == 100  # the same starts in MuJoCo and the world model
    plan.check_policies()
    (ckpt / "config.json").unlink()
    missing = checkpoints_plan(tmp_path / "work", tmp_path / "docs", preset)  # the world models may train meanwhile
    with pytest.raises(InputError, match=f"no LeRobot checkpoint .* at lerobot:{ckpt}, noisy:0.05:lerobot:{ckpt}; "
                       ".*benchmarks.lerobot_policy"):
        missing.check_policies()
    with pytest.raises(InputError, match="no LeRobot checkpoint"):  # before any stage runs
        run_stages(missing, ["simulate"])
    assert not (tmp_path / "work").exists()
    # the training side needs only the training policies: it may start while the ranked checkpoints train
    other = tmp_path / "act" / "checkpoints" / "004000" / "pretrained_model"
    other.mkdir(parents=True)
    (other / "config.json").write_text("{}")
    mixed = dataclasses.replace(missing, training_policies=(f"lerobot:{other}",))
    mixed.check_policies("training")
    with pytest.raises(InputError, match=f"at lerobot:{ckpt}, noisy"):
        mixed.check_policies()
    (other / "config.json").unlink()
    with pytest.raises(InputError, match=f"no LeRobot checkpoint .* at lerobot:{other};"):
        run_stages(mixed, ["train"])
    with pytest.raises(InputError, match=f"at lerobot:{ckpt}, noisy:0.05:lerobot:{ckpt}; "):  # --from-models's check:
        mixed.check_policies("ranked")  # the ranked ones alone, not the missing training policy
    assert not (tmp_path / "work").exists()
    preset.write_text(yaml.safe_dump({"policy": scripted}))
    with pytest.raises(InputError, match=r"not settings of a ranking plan: \['policy'\]"):
        checkpoints_plan(tmp_path / "work", tmp_path / "docs", preset)


def test_the_shipped_models_rerun_the_reports_closed_loops_bit_for_bit_without_training(toy_run, tmp_path):
    """The report ships its motion+contact model as it evaluated it (float16 EMA weights); --from-models reruns the
    report's first start from that archive alone and gets the same frames, actions and verdicts."""
    work, docs = toy_run
    results = json.loads((docs / "results.json").read_text())
    (archive,) = (docs / "models").iterdir()
    assert results["shipped"] == {"motion_contact": {"mode": "motion+contact", "sha256": sha256(archive),
                                                     "bytes": archive.stat().st_size}}
    weights = load_file(str(work / "shipped" / "motion_contact" / "model.safetensors"))
    assert {v.dtype for v in weights.values() if v.is_floating_point()} == {torch.float16}
    assert model_main(["ranking", "--from-models", str(docs / "models"), "--work", str(tmp_path / "rerun"),
                       "--starts", "1", "--policies", "python:imac_model.experiments.ranking.policies:open_loop"]) == 0
    rerun = RankingPlan.load(tmp_path / "rerun" / "plan.json")
    assert not (rerun.work / "runs").exists() and rerun.modes == ("motion+contact",)  # nothing trained
    assert rerun.names == ["closed_loop", "open_loop"]  # the report's first policy first: its episodes give the starts
    out = json.loads((rerun.docs / "rerun.json").read_text())
    assert out["policies"]["closed_loop"]["real_same_as_report"] == 1 and "real_same_as_report" not in out["policies"]["open_loop"]
    assert out["policies"]["closed_loop"]["modes"]["motion+contact"]["same_as_report"] == 1
    ours = LeRobotDataset("local/closed_loop", root=rerun.wm_dir("motion+contact") / "closed_loop")
    theirs = LeRobotDataset("local/closed_loop", root=work / "wm" / "motion_contact" / "closed_loop")
    n = int(ours.meta.episodes["dataset_to_index"][0])
    assert n > 8 and n == int(theirs.meta.episodes["dataset_to_index"][0])
    for i in range(n):  # the start is the report's first: episode 0 of both
        a, b = ours[i], theirs[i]
        assert torch.equal(a["action"], b["action"]) and torch.equal(a[image_key(WORKSPACE)], b[image_key(WORKSPACE)])
    assert "| closed_loop | " in (rerun.docs / "README.md").read_text()
    assert model_main(["ranking", "--from-models", str(docs / "models"), "--work", str(tmp_path / "x"),
                       "--starts", "9"]) != 0  # more starts than the report ran


def test_a_cpu_trained_run_carried_to_another_work_directory_is_evaluated_as_it_ships(toy_run, tmp_path, capsys):
    """--export-runs / --import-gpu carry a CPU-trained run to a fresh machine: the weights the evaluation loads there
    are those freeze_models shipped here (its EMA in float16, not the raw weights), with its log and early gates."""
    work, docs = toy_run
    plan = RankingPlan.load(work / "plan.json")
    run = plan.run_dir(GATED_MODE)
    assert (list_checkpoints(run)[-1] / "ema.safetensors").is_file() and read_gates(plan)  # what must not be lost
    with output_lock(work, who="a run training on"):  # export reads finished runs only, so it takes no lock
        assert model_main(["ranking", "--toy", "--work", str(work), "--docs", str(docs), "--export-runs",
                           str(tmp_path / "carried"), "--runs", run.name]) == 0
    (archive,) = (tmp_path / "carried").iterdir()
    fresh = dataclasses.replace(plan, work=tmp_path / "fresh")
    assert import_gpu_runs(fresh, archive.parent) == [run.name]
    assert read_gates(fresh) == read_gates(plan)
    assert (fresh.run_dir(GATED_MODE) / "log.jsonl").read_text() == (run / "log.jsonl").read_text()
    carried = load_file(str(list_checkpoints(fresh.run_dir(GATED_MODE))[-1] / "model.safetensors"))
    shipped = load_file(str(plan.evaluated_model(GATED_MODE) / "model.safetensors"))  # freeze_models' unpacked archive
    assert carried.keys() == shipped.keys() and all(torch.equal(carried[k], shipped[k]) for k in shipped)
    raw = load_file(str(list_checkpoints(run)[-1] / "model.safetensors"))
    assert any(not torch.equal(raw[k].half(), shipped[k]) for k in load_file(str(list_checkpoints(run)[-1] / "ema.safetensors")))
    cli = tmp_path / "cli"  # the command line's import leaves a work directory that --status reads
    assert model_main(["ranking", "--toy", "--work", str(cli), "--docs", str(tmp_path / "d"), "--import-gpu",
                       str(archive.parent)]) == 0
    capsys.readouterr()
    assert model_main(["ranking", "--work", str(cli), "--status"]) == 0
    assert "gates (balanced accuracy from chunk" in capsys.readouterr().out
    (fresh.run_dir(GATED_MODE) / "DONE.json").unlink()  # as while it trains: not exported
    with pytest.raises(InputError, match="no trained run"):
        export_runs(fresh, tmp_path / "again", [run.name])


def test_the_committed_model_reruns_the_committed_reports_first_starts(tmp_path, monkeypatch):
    """The repository's own `motion+contact` model (docs/ranking/models, the committed report's) reruns the report's
    first three starts of its first policy and of a graded one from the archive alone: MuJoCo's outcomes, the lift
    judge's verdicts per chunk and the frames drawn equal the report's; the depth's invalid share, the judge's cube
    heights in both runners and the action gap equal them to a machine's rounding. On the CPU that made the report
    they are bit-equal; on another, the model's float kernels round otherwise and the closed loop carries that on
    (measured between the machines of 2026-12-02: cube heights 2.5 mm apart at most, one action gap 1e-5 rad;
    docs/verification.md, "Across machines"). A model that draws other frames moves heights by centimetres."""
    committed = REPO_ROOT / "docs" / "ranking"
    report = json.loads((committed / "results.json").read_text())
    archive = committed / "models" / "motion_contact.tar.xz"
    assert report["shipped"]["motion_contact"]["sha256"] == sha256(archive)
    models = tmp_path / "report" / "models"  # the report with one of its models: the quick check runs that one
    models.mkdir(parents=True)
    shutil.copy(committed / "results.json", models.parent)
    # from a folder without the report's runs/, as a clean clone is: the LeRobot checkpoints that made the models'
    # training data (the plan's training_policies, relative paths) are not there, and need not be
    monkeypatch.chdir(tmp_path)
    assert any(lerobot_dir(p) and not Path(lerobot_dir(p)).exists() for p in report["plan"]["training_policies"])
    (models / archive.name).symlink_to(archive)
    graded = "python:imac_model.experiments.ranking.policies:closed_loop_1p5cm"
    starts = 3  # each start is a 33-frame closed loop in both runners; three give 6 episodes and 198 drawn frames
    assert model_main(["ranking", "--from-models", str(models), "--work", str(tmp_path / "rerun"), "--starts",
                       str(starts), "--policies", graded]) == 0
    rerun = RankingPlan.load(tmp_path / "rerun" / "plan.json")
    out = json.loads((rerun.docs / "rerun.json").read_text())
    assert set(out["policies"]) == {"closed_loop", "closed_loop_1p5cm"} and rerun.modes == ("motion+contact",)
    exact = ("success", "frames", "chunk_held", "real_chunk_held")
    close = {"invalid_depth": 0.01, "chunk_height_m": 0.005, "real_chunk_height_m": 0.005, "action_gap": 0.001}
    for name, row in out["policies"].items():
        assert row["real_same_as_report"] == starts and row["modes"]["motion+contact"]["same_as_report"] == starts, name
        ours = json.loads((policy_dir(rerun, "motion+contact", name) / "closed_loop.json").read_text())["episodes"]
        theirs = report["evaluations"]["motion+contact"]["policies"][name]["episodes"][:starts]
        assert [{k: e[k] for k in exact} for e in ours] == [{k: e[k] for k in exact} for e in theirs], name
        for i, (a, b) in enumerate(zip(ours, theirs)):
            for key, tol in close.items():
                assert np.allclose(np.array(a[key], float), np.array(b[key], float), atol=tol, rtol=0,
                                   equal_nan=True), (name, i, key, a[key], b[key])


def test_the_pack_stage_alone_makes_only_the_training_side_and_the_same_pack(toy_run):
    """--stages pack on a new work directory (a GPU waiting for it; the toy run starts so): the training rollouts
    simulated, built, decoded and packed, none of the evaluation episodes; the other stages then leave the training
    side as it was: the pack made again from it after them is byte-identical."""
    plan = RankingPlan.load(toy_run[0] / "plan.json")
    after_pack = json.loads((toy_run[0].parent / "after_pack.json").read_text())
    assert after_pack["train_dataset"] and after_pack["eval_side"] == []
    first = plan.pack.with_name("pack_alone.npz")
    shutil.move(plan.pack, first)
    assert sha256(first) == after_pack["pack_sha256"]
    assert model_main(["ranking", "--toy", "--work", str(toy_run[0]), "--docs", str(toy_run[1]), "--stages", "pack"]) == 0
    ours, theirs = Pack(first), Pack(plan.pack)
    assert ours.tensors.keys() == theirs.tensors.keys()
    assert all(torch.equal(ours.tensors[k], theirs.tensors[k]) for k in ours.tensors), \
        [k for k in ours.tensors if not torch.equal(ours.tensors[k], theirs.tensors[k])]
    first.unlink()


def test_the_stages_run_by_default_are_those_the_preset_needs(tmp_path):
    """Without --stages: every stage, the GPU's tensor pack only with the GPU preset (it trains from it); the
    command line's list of stages (named without importing the benchmark) is the benchmark's."""
    from imac_model.cli.parser import RANKING_STAGES
    from imac_model.cli.ranking import stages_to_run
    from imac_model.experiments.ranking.plan import STAGES, gpu_plan

    assert RANKING_STAGES == STAGES
    assert stages_to_run(None, RankingPlan(work=tmp_path, docs=tmp_path)) == [s for s in STAGES if s != "pack"]
    assert stages_to_run(None, gpu_plan(tmp_path, tmp_path)) == list(STAGES)
    assert stages_to_run(" evaluate,report", gpu_plan(tmp_path, tmp_path)) == ["evaluate", "report"]
    for bad in ("evaluate,judge", ","):
        with pytest.raises(InputError, match="--stages: unknown"):
            stages_to_run(bad, gpu_plan(tmp_path, tmp_path))


def test_the_views_are_the_plans_choice_checked_before_any_work(tmp_path, capsys):
    """--views sets what the policies, the judge and the world model see (the model's data.views); a
    camera the rig does not record, a repeated one, or a set without the judge's workspace view is refused."""
    plan = RankingPlan(work=tmp_path, docs=tmp_path, views=("cam_workspace",))
    assert plan.run_config("motion+contact").data.views == ("cam_workspace",)
    for bad in (("cam_right_wrist",), ("cam_workspace", "cam_workspace"), ("cam_workspace", "cam_back")):
        with pytest.raises(InputError, match="views .* distinct cameras of the simulated rig"):
            RankingPlan(work=tmp_path, docs=tmp_path, views=bad)
    assert model_main(["ranking", "--work", str(tmp_path / "w"), "--docs", str(tmp_path), "--views", "cam_back",
                       "cam_workspace", "--stages", "report"]) == 2
    assert "cam_back" in capsys.readouterr().err and not (tmp_path / "w").exists()


def test_the_modes_are_the_command_lines_choice_checked_before_any_work(tmp_path, capsys):
    """--modes replaces the preset's modes (a first look at new training data trains one seed, not three); an
    unknown mode is refused naming it, before the work directory exists; --from-models keeps the report's."""
    from imac_model.cli.parser import build_parser
    from imac_model.cli.ranking import _plan

    args = build_parser().parse_args(["ranking", "--preset", "checkpoints", "--work", str(tmp_path / "w"), "--modes",
                                      "motion+contact", "none"])
    plan = _plan(args)
    assert plan.modes == ("motion+contact", "none") and plan.real_per_group == 50  # the rest stays the preset's
    assert _plan(build_parser().parse_args(["ranking", "--work", str(tmp_path / "w")])).modes == RankingPlan(
        work=tmp_path, docs=tmp_path).modes
    assert model_main(["ranking", "--work", str(tmp_path / "w"), "--docs", str(tmp_path), "--modes", "motion+colour",
                       "--stages", "report"]) == 2
    assert "motion+colour" in capsys.readouterr().err and not (tmp_path / "w").exists()
    assert model_main(["ranking", "--from-models", str(tmp_path), "--work", str(tmp_path / "w"), "--modes",
                       "none"]) == 2
    assert "--modes would change it" in capsys.readouterr().err


def test_run_config_fields_set_on_the_command_line_reach_every_trained_mode_checked_before_any_work(tmp_path, capsys):
    """--set FIELD=VALUE goes into the plan's overrides, over the budget the plan sets (a budget in steps on both
    cores: docs/ranking.md, "Training on the ranked family"), and is kept in plan.json; a field or value the run
    config refuses is refused before the work directory exists; --from-models keeps the report's."""
    from imac_model.cli.parser import build_parser
    from imac_model.cli.ranking import _plan

    args = build_parser().parse_args(["ranking", "--preset", "checkpoints", "--work", str(tmp_path / "w"),
                                      "--cpu-minutes", "240", "--set", "train.max_steps=10000",
                                      "--set", "train.cpu_threads=2"])
    plan = _plan(args)
    for mode in plan.modes:
        train = plan.run_config(mode).train
        assert (train.max_steps, train.cpu_threads) == (10000, 2)
        assert train.max_cpu_minutes == (10.0 if mode == "none" else 240.0)
    back = RankingPlan.from_dict(json.loads(json.dumps(plan.to_dict())))  # as plan.json keeps it
    assert back == plan and back.overrides == {"train.max_steps": 10000, "train.cpu_threads": 2}
    for bad, named in (("train.max_step=10", "max_step"), ("train.max_steps=many", "train.max_steps")):
        assert model_main(["ranking", "--work", str(tmp_path / "w2"), "--docs", str(tmp_path), "--set", bad,
                           "--stages", "report"]) == 2
        assert named in capsys.readouterr().err and not (tmp_path / "w2").exists()
    assert model_main(["ranking", "--from-models", str(tmp_path), "--work", str(tmp_path / "w3"), "--set",
                       "train.max_steps=1"]) == 2
    assert "--set would change it" in capsys.readouterr().err


def test_slope_offsets_put_half_the_training_rollouts_where_the_success_rate_falls():
    """The slope offsets: half the draws are across's (uniform over 2 cm along and 5 cm across the fingers), half
    1-3 cm either way across them; so 0.5 + 0.5 * 0.4 = 0.7 of all land 1-3 cm off across, 0.2 beyond 3 cm, the
    two signs alike. A training rollout's policy grasps at its own draw."""
    draws = np.array([TRAINING_OFFSETS["slope"](np.random.default_rng([i, 0x7A11])) for i in range(4000)])
    x, y = draws[:, 0], np.abs(draws[:, 1])
    assert np.abs(x).max() <= 0.02 and y.max() <= 0.05
    assert abs(((y >= 0.01) & (y <= 0.03)).mean() - 0.7) < 0.03 and abs((y > 0.03).mean() - 0.2) < 0.03
    assert abs((draws[:, 1] > 0).mean() - 0.5) < 0.03
    assert training_policy(5, "slope").offset.tolist() == pytest.approx(
        list(TRAINING_OFFSETS["slope"](np.random.default_rng([5, 0x7A11]))))


def test_a_plan_saved_before_the_training_offsets_settle_and_views_settings_loads_as_what_it_ran(tmp_path, capsys):
    saved = RankingPlan(work=tmp_path, docs=tmp_path).to_dict()
    assert saved["settle_s"] == 0.3  # a new plan lets the box settle before the first frame
    assert saved["views"] == ("cam_workspace",)  # and shows the policies and the model the workspace view alone
    del saved["training_offsets"], saved["settle_s"], saved["views"]
    (tmp_path / "plan.json").write_text(json.dumps(saved))
    before = RankingPlan.load(tmp_path / "plan.json")
    assert before.training_offsets == "disc" and before.settle_s == 0.0
    assert before.views == ("cam_workspace", "cam_right_wrist")
    with pytest.raises(InputError, match="training_offsets"):
        RankingPlan(work=tmp_path, docs=tmp_path, training_offsets="ring")
    # such a work directory is refused with today's defaults, naming the settings to give
    assert model_main(["ranking", "--work", str(tmp_path), "--docs", str(tmp_path), "--stages", "report"]) == 2
    err = capsys.readouterr().err
    assert "settle_s: 0.0 there, 0.3 here" in err and "training_offsets: 'disc' there, 'across' here" in err
    assert "views: ('cam_workspace', 'cam_right_wrist') there, ('cam_workspace',) here" in err
    # --plan is the stages' own way to hand their processes the plan: from a user it would be ignored
    assert model_main(["ranking", "--plan", str(tmp_path / "plan.json"), "--stages", "report"]) == 2
    assert "only the benchmark's own processes (--internal) read a plan" in capsys.readouterr().err


def test_a_work_directorys_report_stays_where_its_run_put_it_unless_docs_moves_it(tmp_path):
    """--docs is where the report goes, not a setting of the run: without it, a work directory's report is written
    where its plan says (never over the committed docs/ranking by default); with it, the same run's report goes
    there; a setting that differs is still refused."""
    work, first, second = tmp_path / "w", tmp_path / "first", tmp_path / "second"
    RankingPlan(work=work, docs=first).save()
    assert _plan(build_parser().parse_args(["ranking", "--work", str(work)])).docs == first
    assert _plan(build_parser().parse_args(["ranking", "--work", str(work), "--docs", str(second)])).docs == second
    with pytest.raises(InputError, match="cpu_minutes: 120.0 there, 90.0 here"):
        _plan(build_parser().parse_args(["ranking", "--work", str(work), "--cpu-minutes", "90"]))
    assert _plan(build_parser().parse_args(["ranking", "--work", str(tmp_path / "new")])).docs == \
        Path("docs/ranking").resolve()


def test_the_budget_adds_what_runs_and_closed_loops_logged_beyond_a_resumed_stages_record(tmp_path):
    """Worked by hand: the stage log records an invocation when it ends, so a stage killed and resumed keeps only
    its last part. Train: 1,030 CPU-s logged by the runs against 1,000 recorded (under a minute: not reported).
    Evaluate: closed loops of 400 and 700 CPU-s logged against 500 recorded: 600 s missed, added to the total."""
    plan = RankingPlan(work=tmp_path, docs=tmp_path)
    r = {"stages": {"train": {"cpu_s": 1000.0, "wall_s": 900.0}, "evaluate": {"cpu_s": 500.0, "wall_s": 300.0}},
         "training": {"motion+contact": {"train_s": 1030.0}, "none": {"train_s": None}},
         "evaluations": {"motion+contact": {"policies": {"a": {"cpu_s": 400.0}, "b": {"cpu_s": 700.0}}}}}
    assert budget(plan, r) == (2100.0, 1200.0, {"evaluate": 600.0})
    r["evaluations"]["motion+contact"]["policies"]["b"]["cpu_s"] = 100.0  # all the closed loops within the record
    assert budget(plan, r) == (1500.0, 1200.0, {})


def test_which_chunk_counts_the_first_chunk_end_where_the_cube_is_held_differently(tmp_path):
    """Worked by hand: four starts, MuJoCo lifts in the first two; the world model drops the first lift at chunk 3's end,
    draws the second one to its end, lifts in the third start from chunk 2 on, and agrees on the fourth. The action
    gaps up to the parting chunk: 0.02, 0 (the whole episode), 0.03."""
    plan = RankingPlan(work=tmp_path, docs=tmp_path, policies=("python:m:a", "python:m:b"), groups=1,
                       real_per_group=4, wm_per_group=4, chunks=4)
    held = {"up": [False, False, True, True], "drop": [False, False, False, False], "early": [False, True, True, True]}
    rows = [{"success": False, "chunk_held": held["drop"], "real_chunk_held": held["up"], "action_gap": [0, .01, .02, .5]},
            {"success": True, "chunk_held": held["up"], "real_chunk_held": held["up"], "action_gap": [0, 0, 0, 0]},
            {"success": True, "chunk_held": held["early"], "real_chunk_held": held["drop"], "action_gap": [0, .03, .1, .1]},
            {"success": False, "chunk_held": held["drop"], "real_chunk_held": held["drop"], "action_gap": [0, 0, 0, 0]}]
    rows[1]["success"] = False  # its chunk ends agree: only the judge's majority over the last frames parts
    r = {"real": {"a/g0": [True, True, False, False]}, "evaluations": {"motion+contact": {"policies": {"a": {"episodes": rows}}}}}
    assert parting_chunks(plan, r, "motion+contact", "a") == {"parted": 3, "first_at_chunk": [0, 1, 1, 0],
                                                              "at_no_chunk_end": 1, "action_gap_median": 0.02}
    assert parting_chunks(plan, r, "motion+contact", "b") is None  # not run for b
    for row in rows:
        del row["action_gap"]
    r["evaluations"]["motion+contact"]["policies"]["a"]["episodes"] = [
        {k: v for k, v in row.items() if k == "success"} for row in rows]  # evaluated before the readings existed
    assert parting_chunks(plan, r, "motion+contact", "a") is None


def test_the_status_says_where_a_run_stands_without_taking_its_lock(toy_run, tmp_path, capsys):
    work, docs = toy_run
    plan = RankingPlan.load(work / "plan.json")
    with output_lock(work, who="a benchmark run"):  # one working there: the status answers all the same
        assert model_main(["ranking", "--work", str(work), "--status"]) == 0
    out = capsys.readouterr().out
    assert f"working on it now: a process with PID {os.getpid()}" in out
    assert "stages done: pack (" in out and "simulate (" in out and "report (" in out  # the toy run packed first
    assert "  motion+contact: trained, step 6, " in out and "  none: trained, step 6, " in out
    (gate,) = read_gates(plan)
    assert f"gates (balanced accuracy from chunk 1): 1 min {gate['from_chunk']['0']['balanced_accuracy']:.2f}" in out
    assert "evaluated: 2 of 2 closed loops, the recorded actions' replays" in out and "evaluated: 1 of 1" in out
    assert f"report: {docs / 'README.md'} (written " in out
    assert model_main(["ranking", "--work", str(work), "--status"]) == 0
    assert "working on it now: no process" in capsys.readouterr().out
    assert model_main(["ranking", "--work", str(tmp_path), "--status"]) == 2
    assert "no benchmark run there (no plan.json)" in capsys.readouterr().err


def test_the_diagnosis_oracle_restores_one_recorded_view_at_the_chosen_boundaries(toy_run):
    work, _ = toy_run
    plan = RankingPlan.load(work / "plan.json")
    assert gate_diagnosis.replayed_episodes(plan, "training") == [plan.held_out_episodes()[0] - 1]
    spec = load_world_model(list_checkpoints(plan.run_dir("motion+contact"))[-1], weights="ema")[1]
    chunks = open_chunks(spec, TRAIN_REPO, str(plan.train_dataset), episodes=[0])
    items = chunks.episode_chunks(0)
    reference = chunks[items[1]]["reference"]  # the dataset's own frame at t=H, as the chunk cache keeps it
    assert reference.dtype == torch.uint8
    recorded = reference.float() / 255
    ours = torch.rand(1, *recorded.shape)  # a "generated" frame
    w = spec.view_width
    for v, view in enumerate(spec.views):
        scene, intervene = gate_diagnosis._oracles(f"recorded:{view}", chunks, items, spec, boundaries=(1,))
        out = intervene(ours, 1)
        assert scene is None and torch.equal(out[0, :, :, v * w:(v + 1) * w], recorded[:, :, v * w:(v + 1) * w])
        others = [c for c in range(out.shape[-1]) if not v * w <= c < (v + 1) * w]
        assert torch.equal(out[..., others], ours[..., others]) and torch.equal(intervene(ours, 2), ours)
    scene, intervene = gate_diagnosis._oracles("recorded-scene", chunks, items, spec)
    assert intervene is None and torch.equal(scene(1), recorded)
    with pytest.raises(ValueError, match="views"):
        gate_diagnosis._oracles("recorded:cam_high", chunks, items, spec)
    result = gate_diagnosis.diagnose(plan, "motion_contact", seeds=1, ways=(f"recorded:{spec.views[0]}",),
                                     split="training", boundaries=(1,))
    assert result["episodes"] == gate_diagnosis.replayed_episodes(plan, "training") and result["boundaries"] == [1]
    assert len(result[f"recorded:{spec.views[0]}"]["judged_lifted"][0]) == 1
    cube = result[f"recorded:{spec.views[0]}"]["cube_at_chunk_end"]  # a full replay's cube, in every view
    assert set(cube) == set(spec.views) and all(len(c["kept"]) == plan.chunks for c in cube.values())


def test_a_run_that_misses_the_early_gate_stops_and_reports_it(toy_run, tmp_path):
    """The toy's gated model against a goal it cannot meet: the benchmark stops before the other
    modes train, and writes the report of what the gate showed."""
    work, _ = toy_run
    plan = dataclasses.replace(RankingPlan.load(work / "plan.json"), work=tmp_path / "work", docs=tmp_path / "docs",
                               gate_min=1.01)
    shutil.copytree(work / "runs" / "motion_contact", plan.run_dir("motion+contact"))
    (plan.run_dir("motion+contact") / "DONE.json").unlink()
    for part in ("datasets", "chunkcache"):  # the training side, built (stage_train brings in what is missing)
        (plan.work / part).symlink_to(work / part)
    with pytest.raises(GateStop, match="below 1.01; the benchmark stops here"):
        stage_train(plan)  # the gate at the end of the budget is measured already: nothing trains again
    assert not plan.run_dir("none").exists()
    report = (plan.docs / "README.md").read_text()
    assert "**Stopped at the early gate**" in report and "**Verdict:** stop." in report
    assert (plan.docs / "gate.png").is_file() and (plan.docs / "training_loss.png").is_file()
    (plan.docs / "README.md").unlink()  # written again from its results alone (--rewrite-report)
    assert rewrite_report(plan.docs).read_text() == report


def test_a_report_is_written_again_from_its_results_alone(toy_run, tmp_path):
    """--rewrite-report: a finished run's README from its results.json, with no work directory, is the text the
    report stage wrote (a stopped run's: the test above)."""
    _, docs = toy_run
    finished = tmp_path / "finished"
    shutil.copytree(docs, finished)
    written = (finished / "README.md").read_text()
    (finished / "README.md").unlink()
    assert model_main(["ranking", "--docs", str(finished), "--rewrite-report"]) == 0
    assert (finished / "README.md").read_text() == written
    assert model_main(["ranking", "--docs", str(tmp_path / "none"), "--rewrite-report"]) == 2  # no results.json


def test_a_cpu_ablation_arm_continues_the_gated_run_with_one_change(toy_run, tmp_path, capsys):
    """benchmarks.cpu_ablation on the toy: the arm is the gated run's checkpoint and log up to the
    branch point, trained on with training-time rollout and nothing else changed, to the same CPU
    budget; its gate replays the same held-out rollouts, labelled by the simulator. A first-frame
    arm past the budget starts from the widened checkpoint."""
    work, _ = toy_run
    shutil.copytree(work, tmp_path / "work", ignore=shutil.ignore_patterns("wm"))
    plan = RankingPlan.load(work / "plan.json")
    base = plan.run_dir("motion+contact")
    (from_step,) = [int(p.name.split("_")[1]) for p in (base / "checkpoints").glob("step_*")]
    # the toy stops at max_steps before its CPU budget: the arm may take 2 steps more
    plan = dataclasses.replace(plan, work=tmp_path / "work", docs=tmp_path / "docs",
                               overrides={**plan.overrides, "train.max_steps": from_step + 2})
    (plan.work / "plan.json").write_text(json.dumps(plan.to_dict()))
    base = plan.run_dir("motion+contact")
    assert cpu_ablation.main(["rollout", "--work", str(plan.work), "--from-step", str(from_step),
                              "--json", str(tmp_path / "ablation.json")]) == 0
    result = json.loads((tmp_path / "ablation.json").read_text())
    arm = plan.work / "runs" / "motion_contact_rollout2"
    assert result["arm"]["run"] == arm.name and result["changes"] == {"rollout.chunks": 2}

    def rows(run):
        return [json.loads(x) for x in (run / "log.jsonl").read_text().splitlines() if x.strip()]
    base_rows, arm_rows = rows(base), rows(arm)
    assert arm_rows[:len(base_rows)] == base_rows  # the branch carries the log up to its checkpoint
    later = [r for r in arm_rows if r.get("step", 0) > from_step and "loss" in r]
    assert later and all(r["phase"] == "rollout" and len(r["chunk_losses"]) == 2 for r in later)
    base_config = yaml.safe_load((base / "config.yaml").read_text().replace(str(work), str(plan.work)))
    arm_config = yaml.safe_load((arm / "config.yaml").read_text())
    assert arm_config["rollout"]["chunks"] == 2 and arm_config["train"]["output_dir"] == str(arm)
    for section in ("data", "backbone", "conditioning", "flow"):
        assert arm_config[section] == base_config[section], section
    (gate,) = json.loads((arm / "gates.json").read_text())
    simulated = {r["index"]: r["success"] for part in (plan.work / "sim" / "train").glob("part_*")
                 for r in json.loads((part / "outcomes.json").read_text())}
    assert gate["step"] == from_step + 2 and gate["budget_minutes"] == plan.cpu_minutes
    assert gate["episodes"] == plan.held_out_episodes() and gate["labels"] == [simulated[e] for e in gate["episodes"]]
    assert result["arm"]["chunks"] == (gate["step"] - from_step) * 2 * plan.run_config("motion+contact").train.batch_size
    base_gate = json.loads((base / "gates.json").read_text())[-1]
    assert result["baseline"]["balanced_accuracy_from_chunk"] == {
        k: v["balanced_accuracy"] for k, v in base_gate["from_chunk"].items()}
    # a second call finds the arm trained and measured
    assert cpu_ablation.main(["rollout", "--work", str(plan.work), "--from-step", str(from_step)]) == 0
    assert len(json.loads((arm / "gates.json").read_text())) == 1
    with pytest.raises(InputError, match="--from-step 1: .* does not exist"):
        cpu_ablation.branch(plan, "another_arm", 1)
    # an arm may branch from another arm (--from-run); a field its saved spec predates is added (guidance's dropout)
    _, changes = cpu_ablation.arm_run(plan, "guidance", plan.cpu_minutes)
    guided = cpu_ablation.branch(plan, "guided_arm", from_step + 2, changes, source=arm.name)
    assert json.loads((guided / "branch.json").read_text())["from"] == f"runs/{arm.name}"
    spec = load_world_model(guided)[1]
    assert spec.conditioning.dropout == 0.1 and spec.flow.reference_noise == 0.3

    # past the preset's budget, a first-frame arm: its branch is the widened checkpoint, its baseline another arm
    minutes = plan.cpu_minutes + 1
    argv = ["first-frame", "--work", str(plan.work), "--from-step", str(from_step), "--minutes", f"{minutes:g}",
            "--baseline", "reference-noise"]
    assert cpu_ablation.main(argv) == 0
    assert "its baseline motion_contact_noise03_to" in capsys.readouterr().out  # not trained yet: said, not raised
    arm = plan.work / "runs" / f"motion_contact_first_frame_to{minutes:g}"
    model, spec = load_world_model(arm)
    assert spec.conditioning.first_frame and spec.flow.reference_noise == 0.3 and model.clean_frames == 2
    (gate,) = json.loads((arm / "gates.json").read_text())
    assert gate["budget_minutes"] == minutes and gate["step"] == from_step + 2


def test_the_pack_trainer_rolls_out_on_its_own_references(toy_run, tmp_path, monkeypatch):
    """Training-time rollout as the GPU machine runs it, from the pack with torch alone: the clips
    are the dataset's own, chunk 2 starts from the model's estimate and keeps its recorded contact
    images (rollout.contact recorded); the one trainer trains from the pack with first-frame memory,
    dropout, the scene-warp stream, sampled references, a compiler that fails, and train.init."""
    plan = RankingPlan.load(toy_run[0] / "plan.json")  # the toy run made its pack first
    pack = Pack(plan.pack)
    held = set(plan.held_out_episodes())
    chunks = open_chunks(pack.spec, "local/ranking_train", str(plan.train_dataset),
                         episodes=[e for e in range(plan.train_episodes) if e not in held])
    expected = chunks.clips(2)  # the oracle: what the CPU trainer rolls out over, read through LeRobot
    clips = pack.clips(2)
    assert len(clips) == len(expected) > 0
    for got, want in zip(clips.tolist(), expected):
        for j, i in zip(got, want):
            assert torch.equal(pack.tensors["reference"][j], chunks[i]["reference"])

    streams = streams_of_mode("motion+contact")
    model = WorldModel(pack.spec)
    clip = [pack.batch(clips[:1, r], streams) for r in range(2)]
    result = rollout_loss(model, clip, None, stored_contact=True, generator=torch.Generator().manual_seed(0))
    first = model(clip[0], generator=torch.Generator().manual_seed(0), streams=streams)  # the same draws
    assert torch.equal(result.references[1], last_frame(model, first))
    assert not torch.equal(result.references[1], clip[1].reference)
    for s in ("contact_s2g", "contact_r2s"):
        assert torch.equal(result.controls[1][s], clip[1].controls[s])
    with pytest.raises(InputError, match="needs the dataset's OnlineControls"):
        rollout_loss(model, clip, None)
    # the runs file the pack stage wrote: every run of the plan on the pack, the GPU settings at toy size
    runs = RunsFile.load(plan.pack.parent / RUNS_FILE)
    assert set(runs.runs) == {plan.run_dir(m).name for m in plan.compared_modes}  # none trains on the CPU

    def pack_run(out, **changes):
        base = runs.config("motion_contact", tmp_path).replace(**{
            "train.output_dir": str(tmp_path / out), "train.batch_size": 16, "train.max_steps": 1, "train.log_every": 1,
            "train.eval_every": 1, **changes})
        return train_cli.train(base, progress=False)

    # with the first frame as memory, every chunk of a clip keeps its episode's first frame; with dropout, a share of
    # the samples goes without controls, and the checkpoint can be sampled with guidance; with the scene-warp stream,
    # which the pack carries derived from the recorded chunks (from sampled references, the recorded contact and warp
    # images describe another scene: the trainer says so)
    result = pack_run("first_frame", **{"rollout.chunks": 2, "conditioning.first_frame": True,
                                        "conditioning.dropout": 0.1, "conditioning.scene_warp": True,
                                        "rollout.reference_steps": 2})
    assert result.step == 1 and result.log[-1]["phase"] == "rollout" and len(result.log[-1]["chunk_losses"]) == 2
    spec = load_world_model(tmp_path / "first_frame")[1]
    assert spec.conditioning.first_frame and spec.conditioning.dropout == 0.1 and spec.conditioning.scene_warp

    # a compiler that fails on the GPU machine costs the run its compilation, not the run: it trains eager
    def failing_compile(fn, **kwargs):
        def compiled(*args):
            raise RuntimeError("no compiler here")
        return compiled
    monkeypatch.setattr(torch, "compile", failing_compile)
    result = pack_run("eager", **{"rollout.chunks": 2, "train.compile": True})
    assert result.step == 1 and result.log[-1]["compiled"] is False and (tmp_path / "eager" / "checkpoints").is_dir()
    # a stream added to a trained model (train.init) starts at its zero projection, so the model starts as the
    # checkpoint's; a checkpoint with a stream the run lacks is refused
    result = pack_run("warp_added", **{"conditioning.scene_warp": True, "train.init": str(tmp_path / "eager"),
                                       "train.max_steps": 0})
    added = result.log[0]["init_added"]
    assert added == ["controls.layers.scene_warp.bias", "controls.layers.scene_warp.weight"]
    theirs = load_world_model(tmp_path / "eager")[0].state_dict()  # what train.init loads: the EMA weights
    ours = load_file(str(list_checkpoints(tmp_path / "warp_added")[-1] / "model.safetensors"))
    assert sorted(set(ours) - set(theirs)) == added
    assert all(torch.equal(theirs[k], ours[k]) for k in theirs) and not any(ours[k].any() for k in added)
    with pytest.raises(InputError, match=r"this run lacks: \['controls.layers.scene_warp.bias'"):
        pack_run("warp_dropped", **{"train.init": str(tmp_path / "warp_added")})
    with pytest.raises(InputError, match=r"conditioning.mode is motion\+contact, this run's action-vector"):
        pack_run("other_mode", **{"train.init": str(tmp_path / "eager"), "conditioning.mode": "action-vector"})


def test_the_pack_paints_contact_images_as_the_renderer_does(toy_run, tmp_path):
    """ABLATION=contact: the pack's contact geometry, with torch alone, paints the contact images OnlineControls paints
    with the renderer (both with exact searches) from the same references; in a rollout chunk 2 gets them painted
    from the model's own reference, and the trainer paints them so from the pack (rollout.contact rebuilt, the contact ablation)."""
    work, docs = toy_run
    assert model_main(["ranking", "--toy", "--work", str(work), "--docs", str(docs), "--stages", "pack"]) == 0
    plan = RankingPlan.load(work / "plan.json")
    pack = Pack(plan.pack)
    packed = PackedContact.from_pack(pack)
    online = OnlineControls.from_dataset(plan.train_dataset, pack.spec)
    online.contact_options["tolerance"] = None
    e = int(pack.tensors["episode_index"][pack.train[0]])
    mine = torch.nonzero(pack.tensors["episode_index"] == e).flatten()
    chunks = open_chunks(pack.spec, TRAIN_REPO, str(plan.train_dataset), episodes=[e])
    items = [chunks[i] for i in range(len(chunks))]
    assert len(items) == len(mine) >= 2
    assert all(torch.equal(pack.tensors["reference"][j], it["reference"]) for j, it in zip(mine, items))
    reference = torch.stack([it["reference"] for it in items]).float() / 255.0
    got, invalid = packed.controls(reference, mine)
    want = online.controls(reference, torch.stack([it["state"] for it in items]),
                           torch.stack([it["actions"] for it in items]), streams=("contact_s2g", "contact_r2s"))
    torch.testing.assert_close(invalid, want.invalid_fraction)
    for s in ("contact_s2g", "contact_r2s"):
        assert got[s].shape == want.controls[s].shape == (len(items), *items[0][f"control.{s}"].shape)
        difference = (got[s] - want.controls[s]).abs()
        assert difference.max() <= 1.5 / 255 and (difference > 0).float().mean() < 1e-3  # a colour level at ties
        assert got[s].amax() > 0  # painted, not black

    streams = streams_of_mode("motion+contact")
    model = WorldModel(pack.spec)
    clips = pack.clips(2)[:2]
    clip = [pack.batch(clips[:, r], streams) for r in range(2)]
    result = rollout_loss(model, clip, None, generator=torch.Generator().manual_seed(0),
                          rebuild=lambda r, ref: packed.controls(ref, clips[:, r]))
    assert not torch.equal(result.references[1], clip[1].reference)
    painted, _ = packed.controls(result.references[1], clips[:, 1])
    for s in ("contact_s2g", "contact_r2s"):
        assert torch.equal(result.controls[1][s], painted[s]) and not torch.equal(painted[s], clip[1].controls[s])
    assert torch.equal(result.controls[1]["motion"], clip[1].controls["motion"])
    damaged = {**pack.tensors, "geometry.pose": pack.tensors["geometry.pose"][:-1]}
    with pytest.raises(InputError, match="the pack is damaged"):
        PackedContact(damaged, pack.geometry)
    runs = RunsFile.load(plan.pack.parent / RUNS_FILE)
    run = runs.config("motion_contact", tmp_path).replace(**{
        "train.batch_size": 4, "train.max_steps": 1, "train.log_every": 1, "train.eval_every": 1,
        "rollout.chunks": 2, "rollout.contact": "rebuilt"})
    result = train_cli.train(run, progress=False)
    assert 0.0 <= result.log[-1]["invalid_depth"] <= 1.0  # chunk 2's contact images painted from its reference
    geometry = {k: v for k, v in np.load(plan.pack).items() if not k.startswith("geometry")}
    old_pack = tmp_path / "old_pack.npz"  # a pack written before the geometry travelled with it
    write_pack(geometry, old_pack)
    with pytest.raises(InputError, match="carries no contact geometry"):
        train_cli.train(run.replace(**{"data.pack": str(old_pack), "train.output_dir": str(tmp_path / "old")}),
                        progress=False)


def test_the_gpu_preset_trains_from_the_pack_and_comes_back(toy_run, tmp_path):
    """The GPU preset's path on the CPU: the tensor pack holds what LeRobot reads; scripts/gpu_train.py trains
    every run of its runs file (an ablation's arm too) with torch, numpy and the wheels alone (every other library
    refused at import), and the imported checkpoints are the models that were trained (their held-out loss, measured
    again here, is the log's), replacing the CPU-trained toy runs of the same name whole."""
    work, docs = toy_run
    assert model_main(["ranking", "--toy", "--work", str(work), "--docs", str(docs), "--stages", "pack"]) == 0
    plan = RankingPlan.load(work / "plan.json")
    pack = Pack(plan.pack)
    run = plan.run_config("motion+contact")
    chunks = open_chunks(pack.spec, "local/ranking_train", run.data.root, episodes=None)
    for i in (0, len(chunks) - 1):  # the oracle: the dataset read through LeRobot
        item = chunks[i]
        assert int(pack.tensors["episode_index"][i]) == int(item["episode_index"])
        for key in ("reference", "future"):
            assert torch.equal(pack.tensors[key][i], item[key])
        h = pack.spec.view_height
        for s in CONTROL_STREAMS:
            assert torch.equal(pack.tensors[f"control.{s}"][i], item[f"control.{s}"][:, :, :h])
        warp = SceneWarp.from_dataset(chunks.lerobot.meta, run.data.root, pack.spec.views,
                                      (h, pack.spec.view_width)).images(item["reference"][None] / 255.0,
                                                                         item["state"][None], item["actions"][None])
        derived = (mosaic.controls(warp[0]) * 255).round().to(torch.uint8)[:, :, :h]
        assert torch.equal(pack.tensors["control.scene_warp"][i], derived)
    # a chunk's reference is stored only where the previous chunk does not end on it; every one comes back
    with np.load(plan.pack) as stored:
        assert len(stored["reference"]) == len(set(pack.tensors["episode_index"].tolist())) < len(chunks)
    assert all(torch.equal(pack.tensors["reference"][i], chunks[i]["reference"]) for i in range(len(chunks)))
    assert sorted(pack.tensors["episode_index"][pack.heldout].unique().tolist()) == list(run.data.held_out_episodes)
    some = [1, len(chunks) // 2, len(chunks) - 1]  # each chunk's episode's first frame, as the CPU trainer's batch
    assert torch.equal(pack.batch(torch.tensor(some), ()).first_frame, chunks.batch(some).first_frame)
    # the probe's evaluation episodes, decoded in memory: the chunks LeRobot reads, MuJoCo's rate per policy
    evaluation = outcome_probe.evaluation_pack(plan)
    eval_chunks = open_chunks(pack.spec, EVAL_REPO, str(plan.eval_dataset), episodes=None)
    assert len(evaluation.tensors["reference"]) == len(eval_chunks) and len(evaluation.heldout) == len(eval_chunks)
    for i in (0, len(eval_chunks) - 1):
        assert torch.equal(evaluation.tensors["reference"][i], eval_chunks[i]["reference"])
    probed = outcome_probe.measure_on_evaluation(plan, ["reference"], [1], steps=2, seeds=[0])
    row = probed["probes"]["reference"]["1"]
    simulated = {json.loads((plan.sim_dir(n) / "outcomes.json").read_text())["success_rate"] for n in plan.names}
    assert row["n"] == len(plan.names) * len(plan.eval_seeds())
    assert {p["mujoco"] for p in row["policies"].values()} == simulated

    # the runs file, with the focus ablation's arm, at toy size; no EMA, so the archived weights are the trained ones
    runs = runs_file(dataclasses.replace(plan, gpu_ablations=("focus",)))
    runs = dataclasses.replace(runs, base={**runs.base, "train": {**runs.base["train"], "batch_size": 16, "max_steps": 2,
                                                                   "log_every": 1, "eval_every": 1, "ema_decay": 0.0,
                                                                   "compile": False}})
    assert runs.runs["motion_contact_uniform"] == {"conditioning.mode": "motion+contact", "flow.focus_weight": 0.0}
    assert "none" not in runs.runs  # the blind harness check trains on the CPU (stage_train), not on GPU minutes
    file = runs.to_yaml(plan.pack.parent / "toy_runs.yaml")
    out = tmp_path / "gpu_out"
    blocked = ("lerobot", "mujoco", "open3d", "diffusers", "accelerate", "scipy", "trimesh", "cv2", "av", "pandas",
               "datasets", "torchcodec", "pytorch_kinematics", "h5py", "transformers", "tqdm")
    # what the GPU machine lacks is refused at import; PyYAML and safetensors travel as wheels there
    bootstrap = ("import sys, runpy, importlib.machinery\n"
                 "class Refuse:\n"  # found (torch probes for some), but refused when imported
                 "    def find_spec(self, name, path=None, target=None):\n"
                 f"        if name.split('.')[0] in {blocked!r}: return importlib.machinery.ModuleSpec(name, self)\n"
                 "    def create_module(self, spec):\n"
                 "        raise ImportError('not on the GPU machine: ' + spec.name)\n"
                 "    def exec_module(self, module):\n"
                 "        pass\n"
                 "sys.meta_path.insert(0, Refuse())\n"
                 f"sys.argv = ['gpu_train.py', {str(file)!r}, {str(out)!r}]\n"
                 f"runpy.run_path({str(ROOT / 'scripts' / 'gpu_train.py')!r}, run_name='__main__')\n")
    done = subprocess.run([sys.executable, "-c", bootstrap], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    assert sorted(p.name for p in out.iterdir()) == ["motion_contact.tar", "motion_contact_uniform.tar"]
    assert (work / "wm" / "motion_contact" / "replays.json").is_file()  # the CPU-trained toy model's
    assert sorted(import_gpu_runs(plan, out)) == ["motion_contact", "motion_contact_uniform"]
    assert not (work / "wm" / "motion_contact").exists()  # evaluations of the replaced model are dropped
    source = PackSource(runs.config("motion_contact", tmp_path))
    items = evaluation_items(source.n_held, runs.config("motion_contact", tmp_path).train.eval_batches * 16)
    for name, mode, focus in (("motion_contact", "motion+contact", 5.0), ("motion_contact_uniform", "motion+contact", 0.0)):
        model, spec = load_world_model(work / "runs" / name, weights="ema")
        assert spec.conditioning.mode == mode and spec.flow.focus_weight == focus
        log = [json.loads(line) for line in (work / "runs" / name / "log.jsonl").read_text().splitlines()]
        assert log[-1]["step"] == 2 and json.loads((work / "runs" / name / "DONE.json").read_text()) == log[-1]
        source.streams = spec.conditioning.streams
        again = heldout_loss(model.float(), source, items, 16, "cpu", contextlib.nullcontext)
        assert again == pytest.approx(log[-1]["heldout_loss"], rel=1e-3)  # float16 weights
    # a run archive carries a run to another machine whole: imported back, its weights and its whole log are the run's
    kept_log = (work / "runs" / "motion_contact" / "log.jsonl").read_text()
    kept_weights = (list_checkpoints(work / "runs" / "motion_contact")[-1] / "model.safetensors").read_bytes()
    (archive,) = export_runs(plan, tmp_path / "carried", ["motion_contact"])
    shutil.rmtree(work / "runs" / "motion_contact")  # as on a fresh machine
    assert import_gpu_runs(plan, archive.parent) == ["motion_contact"]
    assert (work / "runs" / "motion_contact" / "log.jsonl").read_text() == kept_log
    assert (list_checkpoints(work / "runs" / "motion_contact")[-1] / "model.safetensors").read_bytes() == kept_weights
    # the loss-weighting ablation's figures on the imported runs: the gate measured for each, the replays
    assert ablation.main(["focus", "--work", str(work), "--json", str(tmp_path / "focus.json")]) == 0
    figures = json.loads((tmp_path / "focus.json").read_text())
    assert [figures[k]["focus_weight"] for k in ("baseline", "arm")] == [5.0, 0.0]
    assert all(set(f["gate_balanced_accuracy_from_chunk"]) == {"0", "1"} and f["seeds"] == plan.gate_seeds
               and f["replays"] == plan.recorded * plan.gate_seeds for f in figures.values())
    with pytest.raises(InputError, match="not a run archive"):
        bad = tmp_path / "bad"
        bad.mkdir()
        with tarfile.open(bad / "x.tar", "w") as archive:
            archive.add(plan.pack, arcname="pack.npz")
        import_gpu_runs(plan, bad)
    # a runs file naming a run it does not have is refused before any training
    assert runs_main([str(file), str(tmp_path / "none"), "--runs", "motion_kontact"]) == 2
    assert not list((tmp_path / "none").iterdir())
    bad = dataclasses.replace(runs, runs={**runs.runs, "typo": {"flow.focus_wieght": 0.0}}).to_yaml(tmp_path / "b.yaml")
    shutil.copy(plan.pack, tmp_path / Path(runs.pack).name)
    with pytest.raises(InputError, match=r"b.yaml: run typo: .*focus_wieght"):
        RunsFile.load(bad)


def test_the_report_records_paths_inside_the_repository_relative_to_it():
    """results.json is committed: a path inside the repository, at any depth of what it holds, is written
    relative to it; other paths and plain strings are left as they are."""
    inside = REPO_ROOT / "runs" / "ranking_gpu" / "datasets" / "eval"
    got = _relative({"root": str(inside), "runs": [inside, {"elsewhere": "/data/x", "n": 3}], "plain": "a/b"})
    assert got == {"root": "runs/ranking_gpu/datasets/eval",
                   "runs": ["runs/ranking_gpu/datasets/eval", {"elsewhere": "/data/x", "n": 3}], "plain": "a/b"}


def test_the_offset_curve_runs_the_benchmarks_own_policies():
    """benchmarks.offset_curve at two offsets and two starts: at 0 and 3 cm its open-loop planner is the benchmark's
    open_loop and open_loop_3cm, start by start (MuJoCo's outcomes of the same starts and protocol)."""
    from benchmarks import offset_curve
    from imac_model.evaluate.simulator import SimRunConfig, SimRunner, run_policy
    from imac_model.experiments.ranking import policies
    from imac_model.experiments.ranking.plan import EVAL_SEED0

    got = offset_curve.curve("open_loop", [0.0, 3.0], 2)
    plan = RankingPlan(work=Path("unused"), docs=Path("unused"))
    config = SimRunConfig(chunks=plan.chunks, view_height=plan.view_size[0], view_width=plan.view_size[1],
                          views=plan.views, settle_s=plan.settle_s)
    with SimRunner(config) as runner:
        want = {cm: float(np.mean([r["success"] for r in run_policy(make(), [EVAL_SEED0, EVAL_SEED0 + 1],
                                                                      runner=runner, progress=False)]))
                for cm, make in (("0", policies.open_loop), ("3", policies.open_loop_3cm))}
    assert got == want


def test_each_family_alone_is_ranked_as_scipy_ranks_it(tmp_path):
    """The report's scripted-alone and LeRobot-alone rows: Pearson and Spearman as scipy computes them, MMRV as the
    brute-force definition (every pair, the worst real gap each policy is ordered against)."""
    from scipy.stats import pearsonr, spearmanr

    scripted = [f"python:{POLICY_MODULE}:{p}" for p in ("closed_loop", "open_loop", "open_loop_3cm")]
    learned = [f"lerobot:{tmp_path}/act/checkpoints/{s:06d}/pretrained_model" for s in (2000, 4000, 6000)]
    learned.append(f"noisy:0.02:{learned[-1]}")  # a checkpoint under action noise is a LeRobot policy too
    plan = RankingPlan(work=tmp_path, docs=tmp_path, policies=tuple(scripted + learned), groups=1, real_per_group=10,
                       wm_per_group=10, modes=("motion+contact",))
    real = dict(zip(plan.names, [0.9, 0.5, 0.1, 0.0, 0.3, 0.6, 0.7]))
    wm = dict(zip(plan.names, [0.8, 0.6, 0.0, 0.1, 0.2, 0.8, 0.6]))
    r = {"real": {f"{n}/g0": [i < round(10 * real[n]) for i in range(10)] for n in plan.names},
         "statistics": {"motion+contact": {"lift_geometry": {"points": [
             {"policy": n, "world_model": wm[n], "n_world_model": 10} for n in plan.names]}}}}
    rows = {line.split(" | ")[0].lstrip("| "): line.strip(" |").split(" | ") for line in _by_family(plan, r)
            if line.startswith("| scripted") or line.startswith("| LeRobot")}
    assert set(rows) == {"scripted", "LeRobot"}
    for family, names in (("scripted", plan.names[:3]), ("LeRobot", plan.names[3:])):
        x, y = [wm[n] for n in names], [real[n] for n in names]
        worst = [max([abs(y[i] - y[j]) for j in range(len(y)) if (x[i] > x[j]) != (y[i] > y[j])], default=0.0)
                 for i in range(len(y))]
        assert rows[family][1:6] == [str(len(names)), "motion+contact", f"{pearsonr(x, y)[0]:.3f}",
                                     f"{spearmanr(x, y)[0]:.3f}", f"{np.mean(worst):.3f}"]


def test_any_preset_trains_on_a_gpu_with_gpu_minutes(tmp_path):
    """--gpu-minutes turns a preset's training into the GPU preset's (the pack, scripts/gpu_train.py,
    --import-gpu): the checkpoint preset's policies and modes, each compared mode trained that long, no
    CPU-hourly early gate; the pack stage then runs by default."""
    plan = _plan(build_parser().parse_args(["ranking", "--preset", "checkpoints", "--work", str(tmp_path / "w"),
                                            "--gpu-minutes", "1.9"]))
    assert plan.on_gpu and plan.gpu_minutes == 1.9 and plan.gate_every is None and plan.real_per_group == 50
    assert "pack" in stages_to_run(None, plan)
    runs = runs_file(plan)
    assert runs.base["train"]["max_minutes"] == 1.9 and runs.base["train"]["max_cpu_minutes"] is None
    assert runs.runs["motion_contact_seed2"] == {"conditioning.mode": "motion+contact", "train.seed": 2}
    assert "none" not in runs.runs  # trained on the CPU, its own 10 CPU-minutes


def test_a_reports_command_line_makes_its_plan_again(tmp_path):
    """The report names the preset and flags that make its plan (plan.command_flags); the command line itself
    is the oracle: parsed, those flags give the same plan, for each preset and for a plan changed by flags."""
    work, docs = tmp_path / "w", tmp_path / "d"
    given = [[], ["--preset", "gpu"], ["--preset", "checkpoints"], ["--toy"],
             ["--preset", "checkpoints", "--modes", "motion+contact", "none", "--training-offsets", "slope",
              "--training-policies", "python:imac_model.experiments.ranking.policies:closed_loop", "--gpu-minutes",
              "1.9", "--settle", "0.5", "--views", "cam_workspace", "cam_right_wrist"],
             ["--cpu-minutes", "180", "--steps", "20", "--set", "train.max_steps=10207", "--set", "train.cpu_threads=2"]]
    for flags in given:
        plan = _plan(build_parser().parse_args(["ranking", "--work", str(work), "--docs", str(docs), *flags]))
        shown, by_hand = command_flags(plan)
        again = _plan(build_parser().parse_args(["ranking", "--work", str(work), "--docs", str(docs), *shown]))
        assert again == plan and by_hand == [], (flags, shown)
    edited = dataclasses.replace(RankingPlan(work=work, docs=docs), groups=3)
    assert command_flags(edited) == ([], ["groups"])


def test_the_gpu_presets_none_trains_on_the_cpu_before_it_asks_for_the_gpu(toy_run, tmp_path):
    """`none` is the harness check with its own CPU budget: a GPU plan trains it here, then, on a machine with no
    GPU, says how to train the compared modes on one (scripts/gpu_train.py, --import-gpu)."""
    work, _ = toy_run
    plan = dataclasses.replace(RankingPlan.load(work / "plan.json"), work=tmp_path / "work", docs=tmp_path / "docs",
                               gpu_minutes=1.0, gate_every=None, overrides={"train.max_steps": 2})
    for part in ("datasets", "chunkcache", "sim"):  # the training side, built
        (plan.work / part).parent.mkdir(parents=True, exist_ok=True)
        (plan.work / part).symlink_to(work / part)
    with pytest.raises(InputError, match="the GPU preset trains on a GPU"):
        stage_train(plan)
    assert (plan.run_dir("none") / "DONE.json").is_file() and not plan.run_dir("motion+contact").exists()
